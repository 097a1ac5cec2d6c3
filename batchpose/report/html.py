"""The report page and the comparison page, rendered from the Jinja2 templates in ``report/templates/``.

The pages are self-contained (plots inline as base64 PNG, overlays as base64 JPEG thumbnails that open full
size in a CSS ``:target`` lightbox; no scripts, no external CSS), so they open offline from disk. The report
opens with its verdict (pairs, ok, ok but wrong, failed by kind, AUCs), then with ground truth the paper-style
table beside the paper's reported numbers; each object's status along the run's time axis and its ADD-S (or
confidence) in one small panel per object; accuracy-threshold curves, error distributions, confidence vs
error; overlays of the worst, failed and best cases. Without ground truth: detections, confidence and
overlays of estimates. The run's provenance (objects, versions, manifest, config) sits in collapsed sections.
Every label is readable text (``too few matches``, not ``n_too_few_matches``). This module only builds
strings: the report stage (:mod:`batchpose.stages.report`) writes them.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import jinja2
import numpy as np
import pandas as pd
import yaml

from batchpose.core.poses import STATUSES
from batchpose.report import figures, metrics, precision
from batchpose.report.figures import Curve
from batchpose.report.overlays import COLOR_EST, COLOR_GT
from batchpose.report.runs import RunData
from batchpose.report.scoring import PAPER_MEANS, PAPER_NOTE, Verdict, status_label, timing_table

#: Columns of the comparison table shown on its page (those present), and their headers.
COMPARE_SHOWN = (
    "run",
    "n_frames",
    "n_pairs",
    "n_ok",
    "detection_rate_pct",
    "adds_auc_mean",
    "add_auc_mean",
    "adds_auc_pooled",
    "add_auc_pooled",
    "adds_recall_01d",
    "add_recall_01d",
    "median_rot_err_deg",
    "median_trans_err_mm",
    "ar_pooled",
    "ok_precision",
    "ok_recall",
    "time_per_pair_s",
)
COMPARE_HEADERS = {
    "detection_rate_pct": "detection (%)",
    "adds_auc_mean": "ADD-S AUC (mean)",
    "add_auc_mean": "ADD AUC (mean)",
    "adds_auc_pooled": "ADD-S AUC (pooled)",
    "add_auc_pooled": "ADD AUC (pooled)",
    "adds_recall_01d": "ADD-S < 0.1d (%)",
    "add_recall_01d": "ADD < 0.1d (%)",
    "median_rot_err_deg": "median rot (°)",
    "median_trans_err_mm": "median trans (mm)",
    "ar_pooled": "BOP AR (pooled)",
    "ok_precision": "ok precision",
    "ok_recall": "ok recall",
    "time_per_pair_s": "s / (frame, object)",
    "run": "run",
    "n_frames": "frames",
    "n_pairs": "pairs",
    "n_ok": "ok",
}
_TIMING_HEADERS = {
    "total_s": "total (s)",
    "mean_ms": "mean (ms)",
    "median_ms": "median (ms)",
    "p95_ms": "p95 (ms)",
    "share_pct": "share (%)",
}
_DETECTION_HEADERS = {
    "obj_name": "Object",
    "n": "pairs",
    "n_ok": "ok",
    "detection_rate_pct": "detection rate (%)",
    "median_confidence": "median confidence (ok)",
    **{f"n_{s}": status_label(s) for s in STATUSES[1:]},
}


@dataclass(frozen=True)
class Table:
    """A plain table as the template's ``table`` macro draws it; cells go through the ``fmt`` filter."""

    id: str
    header: list[str]
    rows: list[tuple[Any, ...]]
    digits: int = 1


def _table(df: pd.DataFrame, id_: str, headers: Mapping[str, str] | None = None, digits: int = 1) -> Table:
    headers = headers or {}
    return Table(id_, [headers.get(c, c) for c in df.columns], list(df.itertuples(index=False)), digits)


def fmt(x: Any, digits: int = 1) -> str:
    """A table cell: integers as is, floats with ``digits`` decimals, NaN as "–", infinity as "∞"."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        return str(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    v = float(x)
    if np.isnan(v):
        return "–"
    if np.isinf(v):
        return "∞"
    return f"{v:.{digits}f}"


@functools.cache
def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("batchpose.report", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters["fmt"] = fmt
    return env


def _render(template: str, **context: Any) -> str:
    return _environment().get_template(template).render(**context)


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")


# ---------------------------------------------------------------------------------------------- report


def report_page(
    run: RunData,
    summary: pd.DataFrame,
    per_instance: pd.DataFrame | None,
    verdict: Verdict,
    overlays: list[dict[str, str]],
    overlay_note: str,
) -> str:
    """The report's ``index.html``.

    Args:
        run: the loaded run.
        summary: ``summary.csv``'s table (:func:`batchpose.report.scoring.score_run`'s with ground truth,
            else :func:`batchpose.report.scoring.detection_summary`'s).
        per_instance: per-instance errors with ground truth, else None.
        verdict: the first line (:func:`batchpose.report.scoring.verdict`).
        overlays, overlay_note: :func:`batchpose.report.overlays.gallery`'s result.
    """
    results = _gt_results(run, summary, per_instance) if per_instance is not None else _detections(run, summary)
    axis = figures.time_axis(run.poses, run.frames)
    return _render(
        "report.html.j2",
        title=run_title(run),
        run_dir=run.run_dir.resolve(),
        n_frames=run.n_frames,
        generated=_now(),
        has_gt=per_instance is not None,
        verdict=verdict,
        failed_text=_failed_text(verdict),
        timeline=_timeline(run.poses, per_instance, axis),
        **results,
        gallery_groups=_groups(overlays),
        gallery_note=overlay_note,
        color_est=COLOR_EST,
        color_gt=COLOR_GT,
        **_run_section(run),
    )


def run_title(run: RunData) -> str:
    """The report's title: the manifest's ``name`` (a manifest without one is named after its file's stem
    when the run is made), else the run folder's name."""
    name = run.manifest.get("name") if isinstance(run.manifest, dict) else None
    return str(name) if name not in (None, "") else run.run_dir.resolve().name


def _failed_text(v: Verdict) -> str:
    """The failed pairs by kind: "not found 3: too few matches 2, PnP failed 1; hidden 1"."""
    parts = []
    for group, n, detail in v.failed:
        parts.append(detail if detail == f"{group} {n}" else f"{group} {n}: {detail}")
    return "; ".join(parts)


def verdict_text(v: Verdict) -> str:
    """The verdict as one line of text (the report stage's log line)."""
    text = f"{v.n_pairs} (frame, object) pairs: {v.n_ok} ok"
    if v.n_wrong is not None:
        text += f" ({v.n_wrong} wrong: ADD-S > 0.1 d)"
    text += f", {v.n_failed} failed" + (f" ({_failed_text(v)})" if v.failed else "")
    if v.n_wrong is not None:
        text += f"; ADD-S AUC {fmt(v.adds_auc)}, ADD AUC {fmt(v.add_auc)} (pooled, {v.n_instances} instances)"
        if np.isfinite(v.ok_precision) or np.isfinite(v.ok_recall):
            text += f"; ok precision {fmt(v.ok_precision, 3)}, recall {fmt(v.ok_recall, 3)} (ADD-S < 0.2 d)"
        if np.isfinite(v.ar):
            text += f"; BOP AR {fmt(v.ar, 3)}"
        if v.n_absent_pairs:
            text += f"; {v.n_ok_absent} ok of {v.n_absent_pairs} pairs of absent objects"
        if v.n_carried:
            text += f"; {v.n_carried} ok carried from a neighbouring frame, {v.n_carried_correct} right (ADD-S < 0.2 d)"
    return text


def _failures_text(row: Mapping[str, Any]) -> str:
    parts = [f"{status_label(s)} {int(row[f'n_{s}'])}" for s in metrics.FAILURE_STATUSES if row.get(f"n_{s}", 0)]
    return ", ".join(parts) or "–"


def _gt_results(run: RunData, summary: pd.DataFrame, per_instance: pd.DataFrame) -> dict[str, Any]:
    """The results table's rows, the paper's numbers, the accuracy plots and the precision-recall curve."""
    labels = {"mean": "mean of objects", "pooled": "pooled (all instances)"}  # the aggregate rows
    rows = [
        {
            **r,
            "agg": r["obj_name"] in ("mean", "pooled"),
            "label": labels.get(r["obj_name"], r["obj_name"]),
            "n": int(r["n"]),
            "n_ok": int(r["n_ok"]),
            "failures": _failures_text(r),
        }
        for r in summary.to_dict("records")
    ]
    plots = {
        "curves": figures.curves_figure(per_instance),  # one panel per object
        "errors": figures.error_figure(per_instance),
        "confidence": figures.confidence_figure(per_instance),  # one panel per object
        "pr": _pr_plot(run, len(per_instance)),
    }
    means = " · ".join(f"{k} {a:.1f} / {b:.1f}" for k, (a, b) in PAPER_MEANS.items())
    bop = [c for c in ("ar_vsd", "ar_mssd", "ar_mspd", "ar") if c in summary.columns]
    return {"results": rows, "paper_note": PAPER_NOTE, "paper_means": means, "plots": plots, "bop_columns": bop}


def _pr_plot(run: RunData, n_instances: int) -> str | None:
    """The precision-recall curves of the run's poses, by confidence and (where the run has it) by the
    verification score (None without ground truth or poses to sweep)."""
    if run.gt is None or not len(run.gt):
        return None
    points, diameters = run.model_points(run.gt["obj_name"])
    table = precision.pose_table(run.poses, run.gt, points, diameters)
    curves = [
        precision.pr_curve(table, n_instances, precision.ok_threshold(run.config_text, f"min_{by}"), by)
        for by in ("confidence", "verification")
    ]
    curves = [c for c in curves if c is not None]
    return figures.pr_figure(curves) if curves else None


def _detections(run: RunData, summary: pd.DataFrame) -> dict[str, Any]:
    """The detection table and confidence histogram of a run without ground truth."""
    cols = ["obj_name", "n", "n_ok", "detection_rate_pct", "median_confidence"]
    cols += [f"n_{s}" for s in STATUSES[1:] if summary[f"n_{s}"].any()]  # the statuses that occur
    shown = summary[cols].replace({"obj_name": {"all": "all objects"}})
    return {
        "detections": _table(shown, "results-table", _DETECTION_HEADERS, digits=2),
        "plots": {"confidence": figures.confidence_hist_figure(run.poses)},
    }


def _timeline(
    poses: pd.DataFrame, per_instance: pd.DataFrame | None, axis: figures.TimeAxis | None
) -> dict[str, str] | None:
    """The "Over time" section: the status strip, the per-object panels and what their axis is."""
    status = figures.timeline_figure(poses, per_instance, axis)
    values = figures.values_figure(poses, per_instance, axis)
    if axis is None or status is None or values is None:
        return None
    what = "ADD-S of its ok poses" if per_instance is not None else "confidence of its ok poses"
    if axis.log_time:
        where = "The frames are one log, so the axis is the log's time."
    else:
        where = "The frames are not one log, so the axis is their order in the run"
        where += ", a line where each scene starts." if axis.breaks else "."
    return {"strip": status, "panels": values, "what": what, "axis": where}


def _groups(items: list[dict[str, str]]) -> list[tuple[str, list[dict[str, str]]]]:
    """Overlays by group, groups in order of first appearance."""
    groups: dict[str, list[dict[str, str]]] = {}
    for it in items:
        groups.setdefault(it["group"], []).append(it)
    return list(groups.items())


def _run_section(run: RunData) -> dict[str, Any]:
    """The "Run" section: failure reasons, then (collapsed) status counts, timings, objects, versions,
    manifest and config; load notes."""
    status = run.poses["status"].astype(str).value_counts()
    status_df = pd.DataFrame({"status": [status_label(s) for s in status.index], "pairs": status.to_numpy()})
    reasons = None
    if "reason" in run.poses.columns:
        counts = run.poses.loc[run.poses["status"] != "ok", "reason"].value_counts().head(10)
        if len(counts):
            reasons = _table(counts.rename_axis("reason").reset_index(name="pairs"), "reasons-table")
    timing = timing_table(run.poses)
    versions = None
    if run.versions:
        vers = pd.DataFrame(
            [(k, v if isinstance(v, str) else json.dumps(v)) for k, v in run.versions.items()],
            columns=["package", "version"],
        )
        versions = _table(vers, "versions-table")
    return {
        "status_table": _table(status_df, "status-table"),
        "reasons_table": reasons,
        "timing_table": _table(timing, "timing-table", _TIMING_HEADERS, digits=2) if len(timing) else None,
        "objects_table": _objects_table(run.objects),
        "versions_table": versions,
        "manifest_yaml": None if run.manifest is None else yaml.safe_dump(run.manifest, sort_keys=False),
        "config_text": run.config_text,
        "notes": run.notes,
    }


def _objects_table(objects: Mapping[str, Mapping[str, Any]]) -> Table | None:
    """The run's objects (``objects.json``): id, diameter, mesh and points files."""
    if not objects:
        return None
    rows = [
        (
            name,
            o.get("obj_id", "–"),
            float(o["diameter_m"]) * 1000.0 if o.get("diameter_m") is not None else float("nan"),
            str(o.get("mesh") or "–"),
            str(o.get("points") or "– (mesh samples)"),
        )
        for name, o in sorted(objects.items())
    ]
    return Table("objects-table", ["object", "id", "diameter (mm)", "mesh", "points"], rows)


# --------------------------------------------------------------------------------------------- compare


def compare_page(table: pd.DataFrame, curves: Mapping[str, list[Curve]], notes: list[str]) -> str:
    """The comparison's ``index.html``: the table of runs (one row each) and their pooled accuracy curves.

    Args:
        table: ``compare.csv``'s table (:func:`batchpose.report.compare.compare_runs`).
        curves: ``adds_m`` / ``add_m`` -> one curve per run with ground truth.
        notes: warnings shown under the table.
    """
    shown = [c for c in COMPARE_SHOWN if c in table.columns]
    plots = None
    if curves["adds_m"]:
        plots = {
            "adds": figures.curve_figure(curves["adds_m"], "ADD-S"),
            "add": figures.curve_figure(curves["add_m"], "ADD"),
        }
    return _render(
        "compare.html.j2",
        title="batchpose: comparison of runs",
        n_runs=len(table),
        generated=_now(),
        table=_table(table[shown], "compare-table", COMPARE_HEADERS, digits=2),
        notes=notes,
        plots=plots,
    )
