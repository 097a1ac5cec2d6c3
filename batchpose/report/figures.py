"""The report's plots (matplotlib, Agg canvas, no pyplot state), each returned as a base64 PNG string.

Accuracy-threshold curves, error histograms, confidence against error, the confidence histogram of a run
without ground truth, and the timeline of each object's status over the run's time.
"""

from __future__ import annotations

import base64
import io
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
    ("low confidence", "#dd8452"),
    ("hidden", "#b0b0b0"),
    ("ok, full estimate", "#2f7d32"),
    ("ok, tracked", "#95d195"),
)
#: Most columns a timeline row has: a longer run puts several frames in a column.
TIMELINE_COLUMNS = 1200


def _new_figure(w: float, h: float):
    # The object-oriented API with an Agg canvas: no pyplot global state, no display needed.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
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
    fig.tight_layout()
    return _fig_png(fig)


def object_curves(per_instance: pd.DataFrame, column: str) -> list[Curve]:
    """One curve of ``column`` (``adds_m`` or ``add_m``) per object, and the pooled curve (dashed)."""
    objects = sorted(set(per_instance["obj_name"]))
    curves = []
    for name, color in zip(objects, colors(len(objects)), strict=True):
        d = per_instance.loc[per_instance["obj_name"] == name, column].to_numpy(float)
        curves.append((f"{name} (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": color, "lw": 1.4}))
    d = per_instance[column].to_numpy(float)
    curves.append(
        (f"pooled (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": "black", "lw": 2.2, "ls": "--"})
    )
    return curves


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
    fig.tight_layout()
    return _fig_png(fig)


def confidence_figure(per_instance: pd.DataFrame) -> str:
    """Scatter of confidence against ADD-S (log) of the ok estimates, per object, with Spearman's rho."""
    from scipy.stats import spearmanr

    ok = per_instance[(per_instance["status"] == "ok") & np.isfinite(per_instance["adds_m"])]
    fig = _new_figure(7.6, 4.2)
    ax = fig.add_subplot(1, 1, 1)
    objects = sorted(set(per_instance["obj_name"]))
    for name, color in zip(objects, colors(len(objects)), strict=True):
        g = ok[ok["obj_name"] == name]
        ax.scatter(
            g["confidence"],
            np.maximum(g["adds_m"] * 1000.0, 1e-2),
            s=18,
            color=color,
            label=name,
            alpha=0.8,
            edgecolors="none",
        )
    title = "Confidence vs ADD-S error (ok estimates)"
    if len(ok) >= 3 and ok["confidence"].nunique() > 1:
        rho = spearmanr(ok["confidence"], ok["adds_m"]).statistic
        title += f", Spearman rho = {rho:.2f}"
    ax.set_yscale("log")
    ax.set_xlim(-0.02, 1.02)
    ax.set_xlabel("confidence")
    ax.set_ylabel("ADD-S (mm, log)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    if objects:
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    fig.tight_layout()
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
    fig.tight_layout()
    return _fig_png(fig)


# --------------------------------------------------------------------------------------------- timeline


def timeline_kinds(rows: pd.DataFrame, wrong: np.ndarray | None = None) -> np.ndarray:
    """Index into :data:`TIMELINE_KINDS` of each (frame, object) row (``status``, optional ``tracked``);
    ``wrong``: per row, True for an ok pose the ground truth rejects (ADD-S > 0.1 d)."""
    status = rows["status"].astype(str).to_numpy()
    tracked = rows["tracked"].eq(True).to_numpy() if "tracked" in rows.columns else np.zeros(len(rows), bool)
    ok = status == "ok"
    kind = np.full(len(rows), 1)  # failed: every status not named below
    kind[status == "low_confidence"] = 2
    kind[status == "hidden"] = 3
    kind[ok & ~tracked] = 4
    kind[ok & tracked] = 5
    if wrong is not None:
        kind[ok & wrong] = 0
    return kind


def timeline_grid(t_s: np.ndarray, obj: np.ndarray, kind: np.ndarray, objects: list[str], columns: int) -> np.ndarray:
    """(len(objects), columns) kind index of each column (-1: no row there): the time span cut into
    ``columns`` equal parts, each showing its most severe kind."""
    grid = np.full((len(objects), columns), len(TIMELINE_KINDS))
    span = float(t_s.max() - t_s.min()) if len(t_s) else 0.0
    col = np.zeros(len(t_s), int)
    if span > 0:
        col = np.minimum(((t_s - t_s.min()) / span * columns).astype(int), columns - 1)
    row = np.array([objects.index(o) for o in obj], int)
    np.minimum.at(grid, (row, col), kind)
    grid[grid == len(TIMELINE_KINDS)] = -1
    return grid


def timeline_figure(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> str | None:
    """Status of each object over the run's time (and ADD-S, or confidence without ground truth); None for
    a run of one frame time."""
    if "stamp_ns" not in poses.columns or poses["stamp_ns"].isna().any():
        return None
    stamps = poses["stamp_ns"].astype("int64")
    if stamps.nunique() < 2:
        return None
    objects = sorted(set(poses["obj_name"]))
    t_s = ((stamps - stamps.min()) * 1e-9).to_numpy()
    adds = diam = wrong = None
    if per_instance is not None:
        key = per_instance.set_index(["frame_id", "obj_name"])
        idx = pd.MultiIndex.from_frame(poses[["frame_id", "obj_name"]])
        adds = key["adds_m"].reindex(idx).to_numpy(float)
        diam = key["diameter_m"].reindex(idx).to_numpy(float)
        wrong = adds > 0.1 * diam
    kind = timeline_kinds(poses, wrong)
    columns = min(TIMELINE_COLUMNS, int(stamps.nunique()))
    grid = timeline_grid(t_s, poses["obj_name"].to_numpy(), kind, objects, columns)
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    rgb = np.ones((*grid.shape, 3))  # white: no row there
    for k, (_, c) in enumerate(TIMELINE_KINDS):
        rgb[grid == k] = to_rgb(c)
    fig = _new_figure(10.0, 1.6 + 0.32 * len(objects) + 2.6)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [0.5 + 0.32 * len(objects), 2.6]})
    ax.imshow(rgb, aspect="auto", interpolation="nearest", extent=(0, t_s.max(), len(objects) - 0.5, -0.5))
    ax.set_yticks(range(len(objects)), objects, fontsize=8)
    title = "Status over time"
    if columns < stamps.nunique():
        title += f" (about {stamps.nunique() / columns:.0f} frames a column: the most severe shown)"
    ax.set_title(title, fontsize=10)
    shown = sorted(set(kind.tolist()))
    ax.legend(
        handles=[Patch(color=TIMELINE_KINDS[k][1], label=TIMELINE_KINDS[k][0]) for k in shown],
        loc="upper left",
        bbox_to_anchor=(1.0, 1.0),
        frameon=False,
        fontsize=8,
    )
    _timeline_values(ax2, poses, objects, t_s, adds, diam)
    fig.tight_layout()
    return _fig_png(fig)


def _timeline_values(
    ax, poses: pd.DataFrame, objects: list[str], t_s: np.ndarray, adds: np.ndarray | None, diam: np.ndarray | None
) -> None:
    """The timeline's lower panel: ADD-S of the ok poses (with each object's 0.1 d line) when ``adds`` is
    given, else their confidence."""
    ok = (poses["status"] == "ok").to_numpy()
    for name, c in zip(objects, colors(len(objects)), strict=True):
        sel = ok & (poses["obj_name"] == name).to_numpy()
        if adds is not None and diam is not None:  # (the diameters come with the ADD-S)
            ax.scatter(t_s[sel], np.maximum(adds[sel] * 1000.0, 1e-2), s=6, color=c, label=name)
            d = diam[(poses["obj_name"] == name).to_numpy()]
            if np.isfinite(d).any():  # the 0.1 d line above which an ok pose counts as wrong
                ax.axhline(100.0 * np.nanmax(d), color=c, ls="--", lw=0.8)
        else:
            ax.scatter(t_s[sel], poses["confidence"].to_numpy(float)[sel], s=6, color=c, label=name)
    if adds is not None:
        ax.set_yscale("log")
        ax.set_ylabel("ADD-S of ok poses (mm; dashed: 0.1 d)")
    else:
        ax.set_ylim(0, 1.02)
        ax.set_ylabel("confidence of ok poses")
    ax.set_xlabel("seconds since the run's first frame")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False, fontsize=8, markerscale=2)
