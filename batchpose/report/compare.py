"""Runs side by side (``batchpose compare``): one row per run with its detection rate, accuracy and time
per pair, and each run's pooled accuracy curves."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from batchpose.errors import DataError
from batchpose.report import metrics
from batchpose.report.figures import Curve, colors
from batchpose.report.runs import RunData, load_run
from batchpose.report.scoring import score_run


@dataclass
class Comparison:
    """What ``compare.csv`` and the comparison page show."""

    table: pd.DataFrame
    """One row per run: counts, detection rate, accuracy (with ground truth) and time per pair."""
    curves: dict[str, list[Curve]]
    """``adds_m`` / ``add_m`` -> one pooled accuracy curve per run with ground truth."""
    notes: list[str]
    """Warnings for the page (a run without ground truth)."""


def run_labels(run_dirs: list[Path]) -> list[str]:
    """Folder names, or the last two path parts where names collide (``a/run``, ``b/run``)."""
    paths = [p.resolve() for p in run_dirs]
    names = [p.name for p in paths]
    labels = [f"{p.parent.name}/{p.name}" if names.count(p.name) > 1 else p.name for p in paths]
    for i, label in enumerate(labels):
        while label in labels[:i]:
            label += "'"
        labels[i] = label
    return labels


def compare_runs(run_dirs: list[Path]) -> Comparison:
    """Load and score each run (labelled by folder name; duplicates get a suffix).

    Raises:
        DataError: no run directories, or a run that :func:`batchpose.report.runs.load_run` refuses.
    """
    if not run_dirs:
        raise DataError("compare: no run directories given")
    rows, notes = [], []
    curves: dict[str, list[Curve]] = {"adds_m": [], "add_m": []}
    labels = run_labels([Path(p) for p in run_dirs])
    for run_dir, label, color in zip(run_dirs, labels, colors(len(run_dirs)), strict=True):
        run = load_run(Path(run_dir))
        row = _counts_row(run, label)
        if run.has_gt:
            per_instance, summary = score_run(run)
            row.update(_accuracy_columns(summary))
            for col, lines in curves.items():
                d = per_instance[col].to_numpy(float)
                lines.append((f"{label} (AUC {metrics.vocap_auc(d):.1f}, n={len(d)})", d, {"color": color, "lw": 1.8}))
        else:
            notes.append(f"{label}: no ground truth, so no accuracy and no curve")
        rows.append(row)
    return Comparison(pd.DataFrame(rows), curves, notes)


def _counts_row(run: RunData, label: str) -> dict[str, Any]:
    """A run's counts, detection rate and mean time per (frame, object) pair."""
    ok = run.poses["status"] == "ok"
    return {
        "run": label,
        "run_dir": str(run.run_dir.resolve()),
        "n_frames": run.n_frames,
        "n_pairs": len(run.poses),
        "n_ok": int(ok.sum()),
        "detection_rate_pct": float(ok.mean() * 100.0) if len(ok) else np.nan,
        "time_per_pair_s": float(run.poses["time_total_s"].mean())
        if "time_total_s" in run.poses.columns and len(run.poses)
        else np.nan,
    }


def _accuracy_columns(summary: pd.DataFrame) -> dict[str, Any]:
    """A scored run's mean and pooled AUCs, pooled recalls and median errors, BOP AR and the precision and
    recall of ok (pooled), and each object's AUCs."""
    s = summary.set_index("obj_name")
    out = {
        "n_instances": int(s.loc["pooled", "n"]),
        "adds_auc_mean": s.loc["mean", "adds_auc"],
        "add_auc_mean": s.loc["mean", "add_auc"],
        "adds_auc_pooled": s.loc["pooled", "adds_auc"],
        "add_auc_pooled": s.loc["pooled", "add_auc"],
        "adds_recall_01d": s.loc["pooled", "adds_recall_01d"],
        "add_recall_01d": s.loc["pooled", "add_recall_01d"],
        "median_rot_err_deg": s.loc["pooled", "median_rot_err_deg"],
        "median_trans_err_mm": s.loc["pooled", "median_trans_err_mm"],
        "ar_pooled": s.loc["pooled"].get("ar", np.nan),
        "ok_precision": s.loc["pooled"].get("ok_precision", np.nan),
        "ok_recall": s.loc["pooled"].get("ok_recall", np.nan),
    }
    for obj in s.index.drop(["mean", "pooled"]):
        out[f"adds_auc[{obj}]"] = s.loc[obj, "adds_auc"]
        out[f"add_auc[{obj}]"] = s.loc[obj, "add_auc"]
    return out
