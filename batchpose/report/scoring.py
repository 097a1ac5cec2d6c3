"""The report's tables: a run's estimates scored against its ground truth (``summary.csv``, ``frames.csv``),
detection summaries without ground truth, the verdict's counts of (frame, object) pairs, per-stage timings,
and any BOP results file scored against a run.

The metrics themselves (ADD, ADD-S, AUC, recalls) are in :mod:`batchpose.report.metrics`; this module picks
the rows and columns the report shows, and adds the paper's reported numbers beside ours.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.core.poses import STAGES, STATUSES
from batchpose.errors import DataError
from batchpose.io.bop_csv import bop_to_poses, read_bop_csv
from batchpose.report import bop_scoring, metrics, precision
from batchpose.report.runs import RunData

log = logging.getLogger("batchpose")

#: GNC-Pose's per-object (ADD-S AUC, ADD AUC) as reported in the paper's YCB table (SPEC §7).
PAPER_GNC_POSE: dict[str, tuple[float, float]] = {
    "002_master_chef_can": (92.1, 51.3),
    "003_cracker_box": (75.0, 68.9),
    "004_sugar_box": (69.2, 50.0),
    "005_tomato_soup_can": (93.7, 87.1),
    "006_mustard_bottle": (96.4, 93.6),
    "007_tuna_fish_can": (83.2, 70.4),
    "008_pudding_box": (83.2, 72.8),
    "009_gelatin_box": (86.6, 78.4),
    "010_potted_meat_can": (90.8, 80.7),
    "021_bleach_cleanser": (94.1, 87.3),
    "035_power_drill": (84.2, 61.9),
    "040_large_marker": (80.0, 64.3),
    "mean": (85.7, 72.2),
}
#: Mean (ADD-S AUC, ADD AUC) of every method in the paper's YCB table (SPEC §7).
PAPER_MEANS: dict[str, tuple[float, float]] = {
    "GNC-Pose": (85.7, 72.2),
    "PoseCNN": (80.4, 62.4),
    "LoFTR": (63.3, 36.8),
    "DeepIM": (92.0, 83.9),
    "FoundationPose": (97.8, 91.8),
    "template upper bound": (64.3, 23.1),
}
PAPER_NOTE = (
    "reported by the paper on a different test set (its own 120 random images per object, top-down "
    "views excluded); shown for orientation, not a like-for-like comparison"
)
#: Columns of ``frames.csv`` without ground truth (those the run has), in this order.
DETECTION_COLUMNS = (
    "frame_id",
    "scene_id",
    "im_id",
    "stamp_ns",
    "obj_name",
    "obj_id",
    "status",
    "reason",
    "confidence",
    "n_matches",
    "n_inliers",
    "median_residual_px",
    "time_total_s",
)


#: Readable names of the pair statuses (:data:`batchpose.core.poses.STATUSES` and ``missing``).
STATUS_LABELS: dict[str, str] = {
    "ok": "ok",
    "absent": "absent",
    "too_few_matches": "too few matches",
    "pnp_failed": "PnP failed",
    "low_confidence": "low confidence",
    "conflict": "region conflict",
    "hidden": "hidden",
    "bad_image": "unreadable image",
    "bad_camera": "bad camera",
    "error": "error",
    metrics.MISSING: "no estimate",
}
#: The not-ok statuses grouped by what they mean to a reader of the verdict, in the order shown.
STATUS_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("absent", ("absent",)),
    ("not found", ("too_few_matches", "pnp_failed")),
    ("rejected", ("low_confidence", "conflict")),
    ("hidden", ("hidden",)),
    ("bad input", ("bad_image", "bad_camera")),
    ("errors", ("error",)),
)
#: Counts of (frame, object) pairs added to both ``summary.csv`` tables (the verdict's numbers per object).
PAIR_COLUMNS = ("n_pairs", "n_pairs_ok", "n_ok_wrong", "n_pairs_failed")
#: An ok pose is wrong when its ADD-S exceeds this fraction of the object's diameter (the 0.1 d rule).
WRONG_FRACTION = 0.1


def status_label(status: str) -> str:
    """A status as a reader reads it: ``too_few_matches`` -> "too few matches"."""
    return STATUS_LABELS.get(status, status.replace("_", " "))


def score_run(run: RunData) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Score a run with ground truth: ``(per_instance, summary)`` of :func:`metrics.score`, with the BOP
    errors and average recalls (:func:`bop_scoring.with_bop_columns`), the precision and recall of ok
    (:func:`precision.trust_columns`) and the paper's numbers beside ours (``paper_adds_auc``,
    ``paper_add_auc``)."""
    assert run.gt is not None  # a run with ground truth
    points, diameters = run.model_points(run.gt["obj_name"])
    per_instance, summary = metrics.score(run.poses, run.gt, points, diameters)
    per_instance, summary = bop_scoring.with_bop_columns(run, per_instance, summary)
    poses = precision.pose_table(run.poses, run.gt, points, diameters)
    summary = precision.trust_columns(summary, poses, precision.absent_pairs(run.poses, run.gt))
    return per_instance, _paper_columns(summary)


def _paper_columns(summary: pd.DataFrame) -> pd.DataFrame:
    """Add the paper's per-object numbers; its mean only when some of our objects are the paper's."""
    known = set(PAPER_GNC_POSE) - {"mean"}
    overlap = bool(known & set(summary["obj_name"]))
    paper = [
        PAPER_GNC_POSE.get(n, (np.nan, np.nan)) if (n != "mean" or overlap) else (np.nan, np.nan)
        for n in summary["obj_name"]
    ]
    return summary.assign(paper_adds_auc=[p[0] for p in paper], paper_add_auc=[p[1] for p in paper])


def instance_table(run: RunData, per_instance: pd.DataFrame) -> pd.DataFrame:
    """frames.csv with ground truth: per-instance errors plus frame ids and estimate diagnostics."""
    table = per_instance.copy()
    if run.frames is not None and {"scene_id", "im_id"} <= set(run.frames.columns):
        ids = run.frames.drop_duplicates("frame_id").set_index("frame_id")
        for c in ("scene_id", "im_id", "stamp_ns"):
            if c in ids.columns and c not in table.columns:
                table[c] = table["frame_id"].map(ids[c])
    diag = [
        c for c in ("reason", "n_matches", "n_inliers", "median_residual_px", "time_total_s") if c in run.poses.columns
    ]
    if diag:
        est = run.poses.assign(_ok=(run.poses["status"] == "ok").astype(int))
        est = est.sort_values(["_ok", "confidence"], ascending=False, kind="stable")
        est = est.drop_duplicates(["frame_id", "obj_name"])[["frame_id", "obj_name", *diag]]
        table = table.merge(est, on=["frame_id", "obj_name"], how="left")
    first = [
        c
        for c in ("frame_id", "scene_id", "im_id", "stamp_ns", "obj_name", "obj_id", "status", "reason")
        if c in table.columns
    ]
    return table[first + [c for c in table.columns if c not in first]]


def detection_summary(poses: pd.DataFrame) -> pd.DataFrame:
    """summary.csv without ground truth: per object and ``all``, detection rate and confidence."""
    rows = []
    groups = [(n, poses[poses["obj_name"] == n]) for n in sorted(set(poses["obj_name"]))]
    for name, g in [*groups, ("all", poses)]:
        ok = g["status"] == "ok"
        row = {
            "obj_name": name,
            "n": len(g),
            "n_ok": int(ok.sum()),
            "detection_rate_pct": float(ok.mean() * 100.0) if len(g) else np.nan,
            "median_confidence": float(g.loc[ok, "confidence"].median()) if ok.any() else np.nan,
            "mean_confidence": float(g.loc[ok, "confidence"].mean()) if ok.any() else np.nan,
        }
        for s in STATUSES[1:]:
            row[f"n_{s}"] = int((g["status"] == s).sum())
        rows.append(row)
    return pd.DataFrame(rows)


def detection_table(poses: pd.DataFrame) -> pd.DataFrame:
    """frames.csv without ground truth: the estimates' :data:`DETECTION_COLUMNS`."""
    return poses[[c for c in DETECTION_COLUMNS if c in poses.columns]]


def timing_table(poses: pd.DataFrame) -> pd.DataFrame:
    """Per stage and ``total``: total seconds, mean / median / p95 milliseconds per (frame, object) and share."""
    rows = []
    total = float(poses["time_total_s"].sum()) if "time_total_s" in poses.columns else np.nan
    for stage in (*STAGES, "total"):
        col = f"time_{stage}_s"
        if col not in poses.columns or len(poses) == 0:
            continue
        v = poses[col].astype(float)
        rows.append(
            {
                "stage": stage,
                "total_s": float(v.sum()),
                "mean_ms": float(v.mean() * 1e3),
                "median_ms": float(v.median() * 1e3),
                "p95_ms": float(v.quantile(0.95) * 1e3),
                "share_pct": float(v.sum() / total * 100.0) if total > 0 else np.nan,
            }
        )
    return pd.DataFrame(rows, columns=["stage", "total_s", "mean_ms", "median_ms", "p95_ms", "share_pct"])


def score_bop_csv(
    csv_path: Path | str,
    gt: pd.DataFrame,
    points: Mapping[str, np.ndarray],
    diameters: Mapping[str, float],
    obj_names: Mapping[int, str],
    frames: pd.DataFrame | None = None,
    run: RunData | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Score any BOP-format results file against our ground truth (``batchpose score``).

    Args:
        csv_path: BOP results CSV.
        gt: ground-truth table (frame_id, obj_name, R, t_m; see :func:`batchpose.report.metrics.score`) with
            scene_id and im_id columns, or give ``frames``.
        points: obj_name -> (N, 3) model points, metres.
        diameters: obj_name -> diameter, metres.
        obj_names: obj_id -> obj_name (YCB-Video: 1-based line of ``classes.txt``).
        frames: optional table with frame_id, scene_id, im_id (``frames.parquet``) to map BOP image ids to
            frame ids when ``gt`` has no scene_id / im_id.
        run: the run the ground truth is from: with it, the BOP errors and average recalls of the file's
            poses too (:func:`bop_scoring.with_bop_columns`; VSD where the run's frames have depth).

    Returns:
        ``(per_instance, summary)`` as :func:`batchpose.report.metrics.score` returns them.

    Raises:
        DataError: malformed CSV (file and line named), or no way to map images to ground-truth frames.
    """
    csv_path = Path(csv_path)
    table = read_bop_csv(csv_path)
    id_source = gt if {"scene_id", "im_id"} <= set(gt.columns) else frames
    if id_source is None or not {"frame_id", "scene_id", "im_id"} <= set(id_source.columns):
        raise DataError(
            f"{csv_path}: cannot match BOP image ids to ground truth: the ground-truth table has no "
            "scene_id / im_id columns and no frames table (frame_id, scene_id, im_id) was given"
        )
    frame_ids = {
        (int(s), int(i)): f
        for f, s, i in zip(id_source["frame_id"], id_source["scene_id"], id_source["im_id"], strict=True)
    }
    est = bop_to_poses(table, obj_names, frame_ids, where=str(csv_path))
    log.info("%s: %d estimates for %d ground-truth instances", csv_path, len(est), len(gt))
    per_instance, summary = metrics.score(est, gt, points, diameters)
    if run is None:
        return per_instance, summary
    return bop_scoring.with_bop_columns(replace(run, poses=est, notes=[]), per_instance, summary)


# ---------------------------------------------------------------------------------------------- verdict


def pair_table(poses: pd.DataFrame, per_instance: pd.DataFrame | None) -> pd.DataFrame:
    """One row per estimated (frame, object) pair (an ok row first, then the most confident, as scored):
    frame_id, obj_name, status, ``wrong`` (True for an ok pose whose ADD-S exceeds 0.1 d; False without
    ground truth or where the pair has none) and ``checked`` (the pair has ground truth)."""
    pairs = metrics.pick_estimates(poses)[["frame_id", "obj_name", "status"]].reset_index(drop=True)
    pairs["wrong"] = False
    pairs["checked"] = False
    if per_instance is not None and len(per_instance) and len(pairs):
        inst = per_instance.assign(_w=per_instance["adds_m"] > WRONG_FRACTION * per_instance["diameter_m"])
        wrong = inst.groupby(["frame_id", "obj_name"])["_w"].any()
        key = pd.MultiIndex.from_frame(pairs[["frame_id", "obj_name"]])
        pairs["wrong"] = (pairs["status"] == "ok").to_numpy() & wrong.reindex(key, fill_value=False).to_numpy(bool)
        pairs["checked"] = key.isin(wrong.index)
    return pairs


def _pair_counts(pairs: pd.DataFrame) -> dict[str, int]:
    ok = pairs["status"] == "ok"
    return {
        "n_pairs": len(pairs),
        "n_pairs_ok": int(ok.sum()),
        "n_ok_wrong": int(pairs["wrong"].sum()),
        "n_pairs_failed": int((~ok).sum()),
    }


def with_pair_counts(summary: pd.DataFrame, pairs: pd.DataFrame, has_gt: bool) -> pd.DataFrame:
    """``summary`` with :data:`PAIR_COLUMNS` after ``obj_name``: each object's pairs, and all pairs on the
    aggregate rows (``mean``, ``pooled``, ``all``); ``n_ok_wrong`` only with ground truth."""
    rows = []
    for name in summary["obj_name"]:
        sel = pairs if name in ("mean", "pooled", "all") else pairs[pairs["obj_name"] == name]
        rows.append(_pair_counts(sel))
    counts = pd.DataFrame(rows, columns=list(PAIR_COLUMNS), index=summary.index)
    if not has_gt:
        counts = counts.drop(columns="n_ok_wrong")
    rest = summary.drop(columns=[c for c in counts.columns if c in summary.columns])
    return pd.concat([rest[["obj_name"]], counts, rest.drop(columns="obj_name")], axis=1)


@dataclass(frozen=True)
class Verdict:
    """The report's first line: what came out of the run's (frame, object) pairs, and its accuracy."""

    n_frames: int
    n_pairs: int
    n_ok: int
    n_failed: int
    n_wrong: int | None
    """Ok poses with ADD-S > 0.1 d; None without ground truth."""
    failed: list[tuple[str, int, str]] = field(default_factory=list)
    """(group, pairs, "too few matches 3, PnP failed 1") for each :data:`STATUS_GROUPS` entry that occurs."""
    n_no_estimate: int = 0
    """Ground-truth instances without any estimate row (not among the pairs)."""
    n_ok_unchecked: int = 0
    """Ok pairs without ground truth, which therefore cannot be called wrong."""
    n_instances: int = 0
    adds_auc: float = float("nan")
    add_auc: float = float("nan")
    ok_precision: float = float("nan")
    """Share of the ok poses whose ADD-S is below 0.2 d (one of an absent object is wrong)."""
    ok_recall: float = float("nan")
    """Share of the ground-truth instances that got an ok pose with ADD-S below 0.2 d."""
    ar: float = float("nan")
    """BOP average recall, pooled over the instances (mean of AR_VSD, AR_MSSD, AR_MSPD as available)."""
    n_ok_absent: int = 0
    """Ok poses of objects the ground truth says are absent from their frame."""
    n_absent_pairs: int = 0
    """Estimated (frame, object) pairs of absent objects (``targets: all``)."""
    n_carried: int = 0
    """Ok poses the carry stage found ..."""
    n_carried_correct: int = 0
    """... of them with ADD-S below 0.2 d."""


def verdict(pairs: pd.DataFrame, n_frames: int, summary: pd.DataFrame | None = None) -> Verdict:
    """The verdict of a run from :func:`pair_table`'s pairs and, with ground truth, the scored summary (its
    ``pooled`` row: AUCs, instances, ``n_missing``)."""
    counts = _pair_counts(pairs)
    status = pairs.loc[pairs["status"] != "ok", "status"].astype(str).value_counts()
    known = {s for _, group in STATUS_GROUPS for s in group}
    groups = [*STATUS_GROUPS, ("other", tuple(sorted(set(status.index) - known)))]
    failed = []
    for label, members in groups:
        present = [(s, int(status[s])) for s in members if s in status.index]
        if present:
            detail = ", ".join(f"{status_label(s)} {n}" for s, n in present)
            failed.append((label, sum(n for _, n in present), detail))
    base = Verdict(n_frames, counts["n_pairs"], counts["n_pairs_ok"], counts["n_pairs_failed"], None, failed)
    if summary is None:
        return base
    pooled = summary.set_index("obj_name").loc["pooled"]
    return replace(
        base,
        n_wrong=counts["n_ok_wrong"],
        n_ok_unchecked=int(((pairs["status"] == "ok") & ~pairs["checked"]).sum()),
        n_no_estimate=int(pooled.get(f"n_{metrics.MISSING}", 0)),
        n_instances=int(pooled["n"]),
        adds_auc=float(pooled["adds_auc"]),
        add_auc=float(pooled["add_auc"]),
        ok_precision=float(pooled.get("ok_precision", np.nan)),
        ok_recall=float(pooled.get("ok_recall", np.nan)),
        ar=float(pooled.get("ar", np.nan)),
        n_ok_absent=int(pooled.get("n_ok_absent", 0)),
        n_absent_pairs=int(pooled.get("n_absent_pairs", 0)),
        n_carried=int(pooled.get("n_carried", 0)),
        n_carried_correct=int(pooled.get("n_carried_correct", 0)),
    )
