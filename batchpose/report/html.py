"""The report page and the comparison page, rendered from the Jinja2 templates in ``report/templates/``.

The pages are self-contained (plots and overlays inline as base64 PNG, no scripts, no external CSS), so they
open offline from disk. With ground truth the report shows the paper-style table beside the paper's reported
numbers, accuracy-threshold curves, error distributions, confidence vs error and overlays of the best and
worst cases; without ground truth, the detection rate, confidence distribution and overlays of estimates.
This module only builds strings: the report stage (:mod:`batchpose.stages.report`) writes them.
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
from batchpose.report import figures, metrics
from batchpose.report.figures import Curve
from batchpose.report.overlays import COLOR_EST, COLOR_GT
from batchpose.report.runs import RunData
from batchpose.report.scoring import PAPER_MEANS, PAPER_NOTE, timing_table

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
    "time_per_pair_s": "s / (frame, object)",
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
    "n_ok": "ok",
    "detection_rate_pct": "detection rate (%)",
    "median_confidence": "median confidence (ok)",
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
    overlays: list[dict[str, str]],
    overlay_note: str,
) -> str:
    """The report's ``index.html``.

    Args:
        run: the loaded run.
        summary: ``summary.csv``'s table (:func:`batchpose.report.scoring.score_run`'s with ground truth,
            else :func:`batchpose.report.scoring.detection_summary`'s).
        per_instance: per-instance errors with ground truth, else None.
        overlays, overlay_note: :func:`batchpose.report.overlays.gallery`'s result.
    """
    results = _gt_results(summary, per_instance) if per_instance is not None else _detections(run, summary)
    return _render(
        "report.html.j2",
        title=f"batchpose report: {run.run_dir.resolve().name}",
        run_dir=run.run_dir.resolve(),
        n_frames=run.n_frames,
        n_pairs=len(run.poses),
        n_ok=int((run.poses["status"] == "ok").sum()),
        generated=_now(),
        has_gt=per_instance is not None,
        timeline=_timeline(run.poses, per_instance),
        **results,
        gallery_groups=_groups(overlays),
        gallery_note=overlay_note,
        color_est=COLOR_EST,
        color_gt=COLOR_GT,
        **_run_section(run),
    )


def _failures_text(row: Mapping[str, Any]) -> str:
    parts = [f"{s} {int(row[f'n_{s}'])}" for s in metrics.FAILURE_STATUSES if row.get(f"n_{s}", 0)]
    return ", ".join(parts) or "–"


def _gt_results(summary: pd.DataFrame, per_instance: pd.DataFrame) -> dict[str, Any]:
    """The results table's rows, the paper's numbers and the accuracy plots."""
    labels = {"mean": "mean of objects", "pooled": "pooled (all instances)"}
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
        "curve_adds": figures.curve_figure(figures.object_curves(per_instance, "adds_m"), "ADD-S"),
        "curve_add": figures.curve_figure(figures.object_curves(per_instance, "add_m"), "ADD"),
        "errors": figures.error_figure(per_instance),
        "confidence": figures.confidence_figure(per_instance),
    }
    means = " · ".join(f"{k} {a:.1f} / {b:.1f}" for k, (a, b) in PAPER_MEANS.items())
    return {"results": rows, "paper_note": PAPER_NOTE, "paper_means": means, "plots": plots}


def _detections(run: RunData, summary: pd.DataFrame) -> dict[str, Any]:
    """The detection table and confidence histogram of a run without ground truth."""
    cols = ["obj_name", "n", "n_ok", "detection_rate_pct", "median_confidence", *[f"n_{s}" for s in STATUSES[1:]]]
    return {
        "detections": _table(summary[cols], "results-table", _DETECTION_HEADERS, digits=2),
        "plots": {"confidence": figures.confidence_hist_figure(run.poses)},
    }


def _timeline(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> dict[str, str] | None:
    png = figures.timeline_figure(poses, per_instance)
    if png is None:
        return None
    what = "ADD-S of the ok poses" if per_instance is not None else "confidence of the ok poses"
    return {"png": png, "what": what}


def _groups(items: list[dict[str, str]]) -> list[tuple[str, list[dict[str, str]]]]:
    """Overlays by group, groups in order of first appearance."""
    groups: dict[str, list[dict[str, str]]] = {}
    for it in items:
        groups.setdefault(it["group"], []).append(it)
    return list(groups.items())


def _run_section(run: RunData) -> dict[str, Any]:
    """The "Run" section: status and failure counts, timings, versions, manifest, config and load notes."""
    status = run.poses["status"].value_counts().rename_axis("status").reset_index(name="count")
    reasons = None
    if "reason" in run.poses.columns:
        counts = run.poses.loc[run.poses["status"] != "ok", "reason"].value_counts().head(10)
        if len(counts):
            reasons = _table(counts.rename_axis("reason").reset_index(name="count"), "reasons-table")
    timing = timing_table(run.poses)
    versions = None
    if run.versions:
        vers = pd.DataFrame(
            [(k, v if isinstance(v, str) else json.dumps(v)) for k, v in run.versions.items()],
            columns=["package", "version"],
        )
        versions = _table(vers, "versions-table")
    return {
        "status_table": _table(status, "status-table"),
        "reasons_table": reasons,
        "timing_table": _table(timing, "timing-table", _TIMING_HEADERS, digits=2) if len(timing) else None,
        "versions_table": versions,
        "manifest_yaml": None if run.manifest is None else yaml.safe_dump(run.manifest, sort_keys=False),
        "config_text": run.config_text,
        "notes": run.notes,
    }


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
