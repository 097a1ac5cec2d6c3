"""The report's plots (matplotlib, Agg canvas, no pyplot state), each returned as a base64 PNG string.

Accuracy-threshold curves (runs side by side, or one small panel per object), error histograms, confidence
against error (one small panel per object), the confidence histogram of a run without ground truth, each
object's status along the run's time axis (log time for one log, else frame order) and its ADD-S or
confidence along it (one small panel per object), and the precision-recall curve of the poses as the
confidence threshold sweeps.
"""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from batchpose.report import metrics

#: Thresholds of the plotted accuracy curves, metres (the toolbox's 0..0.1 m range).
CURVE_THRESHOLDS = np.linspace(0.0, 0.1, 401)
#: One line of an accuracy plot: (label, (n,) distances in metres, matplotlib line style kwargs).
Curve = tuple[str, np.ndarray, dict[str, Any]]
#: What the timeline shows for a (frame, object) pair, most severe first, with its colour; a column that
#: holds several frames shows the most severe of them.
TIMELINE_KINDS: tuple[tuple[str, str], ...] = (
    ("ok but wrong (ADD-S > 0.1 d)", "#7b2d8e"),
    ("failed", "#c44e52"),
    ("low confidence, region conflict", "#dd8452"),
    ("hidden", "#b0b0b0"),
    ("ok, full estimate", "#2f7d32"),
    ("ok, tracked", "#95d195"),
    ("absent (match.presence_votes)", "#e4e4e4"),
)
#: Most columns a timeline row has: a longer run puts several frames in a column.
TIMELINE_COLUMNS = 1200


def _new_figure(w: float, h: float):
    # The object-oriented API with an Agg canvas: no pyplot global state, no display needed.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100, layout="constrained")  # laid out once, as it is saved
    FigureCanvasAgg(fig)
    return fig


def _fig_png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def colors(n: int) -> list:
    """``n`` distinct matplotlib colours (tab10, or tab20 beyond ten)."""
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def curve_figure(curves: list[Curve], title: str) -> str:
    """Accuracy vs threshold, one step line per :data:`Curve`."""
    ncol = 1 if len(curves) <= 4 else 2
    legend_rows = -(-len(curves) // ncol)
    fig = _new_figure(5.8, 3.6 + 0.2 * legend_rows)
    ax = fig.add_subplot(1, 1, 1)
    x_cm = CURVE_THRESHOLDS * 100.0
    for label, d, style in curves:
        ax.step(x_cm, metrics.accuracy_curve(d, CURVE_THRESHOLDS), where="post", label=label, **style)
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 101)
    ax.set_xlabel("distance threshold (cm)")
    ax.set_ylabel("accuracy (%)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    # Below the axes: with a dozen objects a legend inside would hide the curves.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=ncol, fontsize=7.5, frameon=False)
    return _fig_png(fig)


def curves_figure(per_instance: pd.DataFrame) -> str:
    """Accuracy vs threshold, one small panel per object after one of all instances pooled: ADD-S (solid)
    and ADD (dashed) in each, the AUCs in its title."""
    objects = sorted(set(per_instance["obj_name"]))
    groups = [("all objects (pooled)", per_instance)] + [
        (n, per_instance[per_instance["obj_name"] == n]) for n in objects
    ]
    fig, axes = _panels(len(groups), ncols=4, w=2.9, h=2.3)
    x_cm = CURVE_THRESHOLDS * 100.0
    for ax, (name, g) in zip(axes, groups, strict=True):
        aucs = []
        for column, label, ls in (("adds_m", "ADD-S", "-"), ("add_m", "ADD", "--")):
            d = g[column].to_numpy(float)
            ax.step(x_cm, metrics.accuracy_curve(d, CURVE_THRESHOLDS), where="post", ls=ls, lw=1.6,
                    color="#4c72b0" if label == "ADD-S" else "#dd8452", label=label)  # fmt: skip
            aucs.append(f"{metrics.vocap_auc(d):.1f}")
        ax.set_title(f"{name} (n={len(g)})\nAUC ADD-S {aucs[0]}, ADD {aucs[1]}", fontsize=8.5)
        ax.set_xlim(0, 10)
        ax.set_ylim(0, 101)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower right", fontsize=7.5, frameon=False)
    axes[0].set_ylabel("accuracy (%)", fontsize=8)
    fig.suptitle("Accuracy vs distance threshold (cm): the share of instances within it", fontsize=9.5)
    return _fig_png(fig)


def error_figure(per_instance: pd.DataFrame) -> str:
    """Histograms of ADD-S, ADD, rotation and translation error of the ok estimates."""
    ok = per_instance[per_instance["status"] == "ok"]
    fig = _new_figure(11.0, 3.4)
    panels = [
        ("adds_m", 1000.0, "ADD-S (mm)"),
        ("add_m", 1000.0, "ADD (mm)"),
        ("rot_err_deg", 1.0, "rotation error (deg)"),
        ("trans_err_mm", 1.0, "translation error (mm)"),
    ]
    for i, (col, scale, label) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        v = ok[col].to_numpy(float) * scale
        v = v[np.isfinite(v)]
        if v.size:
            ax.hist(v, bins=min(30, max(5, v.size)), color="#4c72b0", edgecolor="white")
            ax.axvline(float(np.median(v)), color="black", ls="--", lw=1, label=f"median {np.median(v):.1f}")
            ax.legend(fontsize=8, frameon=False)
        else:
            ax.text(0.5, 0.5, "no ok estimates", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(label)
        ax.set_ylabel("instances" if i == 0 else "")
    fig.suptitle(
        f"Error distributions over {len(ok)} ok estimates ({len(per_instance) - len(ok)} failures not shown)",
        fontsize=10,
    )
    return _fig_png(fig)


def _panels(n: int, ncols: int = 4, w: float = 2.8, h: float = 2.1, top: float = 0.5):
    """A figure of ``n`` small panels (one per object), ``ncols`` a row; unused cells hidden."""
    ncols = max(1, min(ncols, n))
    nrows = -(-n // ncols)
    fig = _new_figure(w * ncols, h * nrows + top)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    return fig, list(axes[:n])


def confidence_figure(per_instance: pd.DataFrame) -> str:
    """Confidence against ADD-S (log) of the ok estimates, one small panel per object (wrong poses, ADD-S >
    0.1 d, in purple above the object's dashed 0.1 d line), with Spearman's rho over all of them."""
    from scipy.stats import spearmanr

    ok = per_instance[(per_instance["status"] == "ok") & np.isfinite(per_instance["adds_m"])]
    objects = sorted(set(per_instance["obj_name"])) or ["(no objects)"]
    fig, axes = _panels(len(objects))
    floor_mm = 1e-2
    top_mm = max([100.0 * float(per_instance["diameter_m"].max() or 0.0), *(ok["adds_m"] * 1000.0), 1.0])
    for ax, name in zip(axes, objects, strict=True):
        g = ok[ok["obj_name"] == name]
        wrong = (g["adds_m"] > 0.1 * g["diameter_m"]).to_numpy()
        y = np.maximum(g["adds_m"].to_numpy(float) * 1000.0, floor_mm)
        conf = g["confidence"].to_numpy(float)
        ax.scatter(conf[~wrong], y[~wrong], s=12, color=TIMELINE_KINDS[4][1], edgecolors="none")
        ax.scatter(conf[wrong], y[wrong], s=16, color=TIMELINE_KINDS[0][1], edgecolors="none")
        d = per_instance.loc[per_instance["obj_name"] == name, "diameter_m"]
        if len(d):
            ax.axhline(100.0 * float(d.iloc[0]), color="black", ls="--", lw=0.8)
        ax.set_yscale("log")
        ax.set_ylim(floor_mm * 0.8, top_mm * 1.5)
        ax.set_xlim(-0.02, 1.02)
        ax.set_title(f"{name}: {int(wrong.sum())} of {len(g)} ok wrong", fontsize=8.5)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("ADD-S (mm, log)", fontsize=8)
    title = "Confidence (x) vs ADD-S (y) of the ok estimates; purple: wrong (above the dashed 0.1 d line)"
    if len(ok) >= 3 and ok["confidence"].nunique() > 1:
        title += f"; Spearman rho = {spearmanr(ok['confidence'], ok['adds_m']).statistic:.2f}"
    fig.suptitle(title, fontsize=9.5)
    return _fig_png(fig)


def confidence_hist_figure(poses: pd.DataFrame) -> str:
    """Stacked histogram of the confidence of ok and failed estimates (a run without ground truth)."""
    fig = _new_figure(7.6, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    bins = np.linspace(0, 1, 21)
    ok = poses["status"] == "ok"
    ax.hist(
        [poses.loc[ok, "confidence"].astype(float), poses.loc[~ok, "confidence"].astype(float)],
        bins=bins,
        stacked=True,
        color=["#4c72b0", "#c44e52"],
        label=[f"ok ({int(ok.sum())})", f"failed ({int((~ok).sum())})"],
        edgecolor="white",
    )
    ax.set_xlabel("confidence")
    ax.set_ylabel("(frame, object) pairs")
    ax.set_title(
        f"Confidence distribution, detection rate {ok.mean() * 100:.1f} % ({int(ok.sum())} / {len(ok)})"
        if len(ok)
        else "Confidence distribution (no estimates)",
        fontsize=10,
    )
    ax.legend(frameon=False, fontsize=8)
    return _fig_png(fig)


# ------------------------------------------------------------------------------------------- time axis


@dataclass(frozen=True)
class TimeAxis:
    """Where each row of the poses table sits on the report's time axis, and how to label it."""

    x: np.ndarray
    """(n,) float per row: seconds since the log's first frame, or the frame's position in the run."""
    label: str
    breaks: list[tuple[float, str]] = field(default_factory=list)
    """(x, name) where another scene starts, for runs of several (none for one log)."""
    n_frames: int = 0
    log_time: bool = False


def time_axis(poses: pd.DataFrame, frames: pd.DataFrame | None) -> TimeAxis | None:
    """The run's time axis: log time when its frames are one log (one ``source`` and one scene, with
    increasing ``stamp_ns``), else the frames' order in the run with each scene's start marked (the stamps
    of frames from unrelated scenes or files are no common clock). None for fewer than 2 frames.

    Args:
        poses: the poses table (frame_id per row).
        frames: ``frames.parquet`` (frame_id; stamp_ns, scene_id, source where present) in run order, or
            None (the poses' frames in order of first appearance).
    """
    order = poses.drop_duplicates("frame_id")
    if frames is not None and "frame_id" in frames.columns:
        known = frames.drop_duplicates("frame_id")
        extra = order[~order["frame_id"].isin(known["frame_id"])]  # estimated frames the index lacks (if any)
        order = pd.concat([known, extra], ignore_index=True) if len(extra) else known
    order = order.reset_index(drop=True)
    if len(order) < 2:
        return None
    scenes = order["scene_id"] if "scene_id" in order.columns else pd.Series([0] * len(order))
    stamps = order["stamp_ns"] if "stamp_ns" in order.columns else pd.Series([np.nan] * len(order))
    one_log = (
        "source" in order.columns
        and order["source"].nunique(dropna=False) == 1
        and scenes.nunique(dropna=False) == 1
        and bool(stamps.notna().all())
        and bool((stamps.astype("int64").diff().iloc[1:] > 0).all())
    )
    if one_log:
        t_s = (stamps.astype("int64") - int(stamps.iloc[0])).to_numpy() * 1e-9
        x = poses["frame_id"].map(pd.Series(t_s, index=order["frame_id"])).to_numpy(float)
        return TimeAxis(x, "log time (s since the first frame)", [], len(order), log_time=True)
    starts = np.flatnonzero(scenes.ne(scenes.shift()).to_numpy())
    names = [int(v) if isinstance(v, float) and v.is_integer() else v for v in scenes.iloc[starts]]
    breaks = [(float(i), f"scene {n}") for i, n in zip(starts, names, strict=True)] if len(starts) > 1 else []
    label = "frame, in run order" + (" (scene starts marked)" if breaks else "")
    position = pd.Series(np.arange(len(order), dtype=float), index=order["frame_id"])
    return TimeAxis(poses["frame_id"].map(position).to_numpy(float), label, breaks, len(order))


def _mark_breaks(ax, axis: TimeAxis, names: bool) -> None:
    """A line where each scene starts (and its name above the axes); whole frames as ticks in frame order."""
    if not axis.log_time:
        from matplotlib.ticker import MaxNLocator

        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    for x, name in axis.breaks:
        if x > 0:  # (the first scene starts where the axis does)
            ax.axvline(x - 0.5, color="black", lw=0.9, alpha=0.7)
        if names:
            ax.text(x - 0.5, 1.01, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="bottom")


# --------------------------------------------------------------------------------------------- timeline


def timeline_kinds(rows: pd.DataFrame, wrong: np.ndarray | None = None) -> np.ndarray:
    """Index into :data:`TIMELINE_KINDS` of each (frame, object) row (``status``, optional ``tracked``);
    ``wrong``: per row, True for an ok pose the ground truth rejects (ADD-S > 0.1 d)."""
    status = rows["status"].astype(str).to_numpy()
    tracked = rows["tracked"].eq(True).to_numpy() if "tracked" in rows.columns else np.zeros(len(rows), bool)
    ok = status == "ok"
    kind = np.full(len(rows), 1)  # failed: every status not named below
    kind[(status == "low_confidence") | (status == "conflict")] = 2
    kind[status == "hidden"] = 3
    kind[status == "absent"] = 6
    kind[ok & ~tracked] = 4
    kind[ok & tracked] = 5
    if wrong is not None:
        kind[ok & wrong] = 0
    return kind


def timeline_grid(x: np.ndarray, obj: np.ndarray, kind: np.ndarray, objects: list[str], columns: int) -> np.ndarray:
    """(len(objects), columns) kind index of each column (-1: no row there): the axis span of ``x`` (seconds
    or frame positions) cut into ``columns`` equal parts, each showing its most severe kind."""
    grid = np.full((len(objects), columns), len(TIMELINE_KINDS))
    span = float(x.max() - x.min()) if len(x) else 0.0
    col = np.zeros(len(x), int)
    if span > 0:
        col = np.minimum(((x - x.min()) / span * columns).astype(int), columns - 1)
    row = np.array([objects.index(o) for o in obj], int)
    np.minimum.at(grid, (row, col), kind)
    grid[grid == len(TIMELINE_KINDS)] = -1
    return grid


def wrong_per_row(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(ADD-S in metres, wrong) per row of ``poses`` from the scored instances; None without ground truth."""
    if per_instance is None:
        return None
    key = per_instance.drop_duplicates(["frame_id", "obj_name"]).set_index(["frame_id", "obj_name"])
    idx = pd.MultiIndex.from_frame(poses[["frame_id", "obj_name"]])
    adds = key["adds_m"].reindex(idx).to_numpy(float)
    diam = key["diameter_m"].reindex(idx).to_numpy(float)
    return adds, (poses["status"] == "ok").to_numpy() & (adds > 0.1 * diam)


def timeline_figure(poses: pd.DataFrame, per_instance: pd.DataFrame | None, axis: TimeAxis | None) -> str | None:
    """Each object's status along the run's :func:`time_axis` (one row per object; ok-but-wrong poses in
    purple with ground truth); None without an axis."""
    if axis is None or not np.isfinite(axis.x).any():
        return None
    objects = sorted(set(poses["obj_name"]))
    scored = wrong_per_row(poses, per_instance)
    kind = timeline_kinds(poses, None if scored is None else scored[1])
    x = np.nan_to_num(axis.x, nan=float(np.nanmin(axis.x)))
    columns = min(TIMELINE_COLUMNS, axis.n_frames)
    grid = timeline_grid(x, poses["obj_name"].to_numpy(), kind, objects, columns)
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    rgb = np.ones((*grid.shape, 3))  # white: no row there
    for k, (_, c) in enumerate(TIMELINE_KINDS):
        rgb[grid == k] = to_rgb(c)
    fig = _new_figure(11.0, 1.3 + 0.3 * len(objects))
    ax = fig.add_subplot(1, 1, 1)
    half = 0.0 if axis.log_time else 0.5
    ax.imshow(
        rgb, aspect="auto", interpolation="nearest", extent=(x.min() - half, x.max() + half, len(objects) - 0.5, -0.5)
    )
    ax.set_yticks(range(len(objects)), objects, fontsize=8)
    ax.set_xlabel(axis.label, fontsize=9)
    _mark_breaks(ax, axis, names=True)
    if columns < axis.n_frames:
        ax.set_title(f"about {axis.n_frames / columns:.0f} frames a column: the most severe shown", fontsize=8)
    ax.legend(
        handles=[Patch(color=TIMELINE_KINDS[k][1], label=TIMELINE_KINDS[k][0]) for k in sorted(set(kind.tolist()))],
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
        frameon=False,
        fontsize=8,
    )
    return _fig_png(fig)


def values_figure(poses: pd.DataFrame, per_instance: pd.DataFrame | None, axis: TimeAxis | None) -> str | None:
    """One small panel per object along the run's :func:`time_axis`: the ADD-S of its ok poses (log, one
    scale for all panels; wrong ones purple above the object's dashed 0.1 d line) with ground truth, else
    their confidence; failed pairs as red ticks at the bottom. None without an axis."""
    if axis is None or not np.isfinite(axis.x).any():
        return None
    objects = sorted(set(poses["obj_name"]))
    scored = wrong_per_row(poses, per_instance)
    ok = (poses["status"] == "ok").to_numpy()
    fig, axes = _panels(len(objects), ncols=3, w=3.7, h=1.9)
    x = axis.x
    for ax, name in zip(axes, objects, strict=True):
        mine = (poses["obj_name"] == name).to_numpy()
        if scored is not None and per_instance is not None:
            diam = per_instance.loc[per_instance["obj_name"] == name, "diameter_m"]
            _adds_panel(ax, x, scored, mine & ok, float(diam.iloc[0]) if len(diam) else np.nan)
        else:
            ax.scatter(x[mine & ok], poses["confidence"].to_numpy(float)[mine & ok], s=7, color=TIMELINE_KINDS[4][1])
            ax.set_ylim(0, 1.05)
        failed = mine & ~ok
        ax.plot(x[failed], np.zeros(int(failed.sum())), "|", color=TIMELINE_KINDS[1][1], ms=8,
                transform=ax.get_xaxis_transform())  # fmt: skip
        _mark_breaks(ax, axis, names=False)
        ax.set_title(name, fontsize=8.5)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    if scored is not None:
        adds_mm = scored[0][ok & np.isfinite(scored[0])] * 1000.0
        top = max([*adds_mm, 100.0 * float(np.nanmax(per_instance["diameter_m"])) if per_instance is not None else 1.0])
        for ax in axes:
            ax.set_ylim(max(1e-2, float(adds_mm.min()) if len(adds_mm) else 1.0) * 0.6, top * 1.6)
        what = "ADD-S of the ok poses (mm, log; purple: wrong, above the dashed 0.1 d line)"
    else:
        what = "confidence of the ok poses"
    lo, hi = float(np.nanmin(x)), float(np.nanmax(x))
    pad = 0.5 if not axis.log_time else 0.02 * (hi - lo)
    for ax in axes:  # one x range for every panel, so their times line up
        ax.set_xlim(lo - pad, hi + pad)
    fig.suptitle(f"{what}; x: {axis.label}; red ticks: failed pairs", fontsize=9.5)
    return _fig_png(fig)


def _adds_panel(ax, x: np.ndarray, scored: tuple[np.ndarray, np.ndarray], sel: np.ndarray, diameter_m: float) -> None:
    """An object's panel of :func:`values_figure` with ground truth: ADD-S (mm, log) of the ``sel`` rows."""
    adds, wrong = scored
    y = np.maximum(adds * 1000.0, 1e-2)
    ax.scatter(x[sel & ~wrong], y[sel & ~wrong], s=7, color=TIMELINE_KINDS[4][1])
    ax.scatter(x[sel & wrong], y[sel & wrong], s=10, color=TIMELINE_KINDS[0][1])
    if np.isfinite(diameter_m):
        ax.axhline(100.0 * diameter_m, color="black", ls="--", lw=0.8)
    ax.set_yscale("log")


def pr_figure(curves) -> str:
    """Precision against recall of the run's poses as a threshold sweeps, one line per
    :class:`batchpose.report.precision.PrCurve` (confidence, verification score), each with the run's own
    threshold marked, and the run's ok poses."""
    fig = _new_figure(4.6, 3.4)
    ax = fig.add_subplot(1, 1, 1)
    for curve, colour in zip(curves, ("#4c72b0", "#c44e52"), strict=False):
        ax.plot(curve.recall, curve.precision, "-", color=colour, lw=1.6, marker=".", ms=3, label=f"{curve.by} ≥ t")
        at = curve.thresholds >= curve.default_threshold if curve.default_threshold is not None else None
        if at is not None and at.any():
            i = int(np.flatnonzero(at)[-1])  # thresholds descend: the poses kept at the run's threshold
            ax.plot(curve.recall[i], curve.precision[i], "o", color=colour, ms=11, mfc="none", mew=1.8,
                    label=f"t = min_{curve.by} {curve.default_threshold:g}")  # fmt: skip
    r, p = curves[0].ok_point
    if np.isfinite(r) and np.isfinite(p):
        ax.plot(r, p, "x", color="#2f7d32", ms=8, mew=2, label="the run's ok poses")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("recall (instances with a correct pose)", fontsize=8.5)
    ax.set_ylabel("precision (correct poses)", fontsize=8.5)
    ax.set_title("Precision vs recall as a threshold t sweeps\ncorrect: ADD-S < 0.2 d", fontsize=9)
    ax.tick_params(labelsize=7.5)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=7.5, frameon=False)
    return _fig_png(fig)
