"""How far ``ok`` can be trusted: precision and recall of the ok poses, ok poses on absent objects, and the
precision-recall curve as the confidence threshold sweeps.

A pose is *correct* when its ADD-S to the ground truth is below :data:`CORRECT_FRACTION` of the object's
diameter. In a run with ground truth every frame counts as annotated for the run's objects (ingest keeps the
ground truth of the run's objects in every frame it reads, as :mod:`benchmarks.cycling_log` assumes too), so a
pose of an object the ground truth does not list in its frame is a pose of an absent object, and wrong.

- ok precision: the share of ok poses that are correct;
- ok recall: the share of ground-truth instances that got a correct ok pose;
- absent: ok poses of absent objects, over the (frame, absent object) pairs the run estimated (it asked
  for objects not in the ground truth, ``targets: all``);
- carried: ok poses the carry stage found (``carried``, :mod:`batchpose.stages.carry`), and how many of them
  are correct.

The curves take every pose the run produced with a finite pose and a confidence (ok, and those rejected
for low confidence) and sweep a threshold over them: over the confidence, and over the verification score
(``min_verification``, :mod:`batchpose.method.score`) where the run has one; a pose the score does not
judge (a tracked one) stays in at every threshold of that curve.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd
import yaml

from batchpose.core.poses import row_cam_from_model
from batchpose.report import metrics

#: A pose is correct when its ADD-S is below this fraction of the object's diameter.
CORRECT_FRACTION = 0.2
#: Statuses whose rows carry a pose and a confidence the curve sweeps over.
SCORED_STATUSES = ("ok", "low_confidence")
#: Columns of :func:`pose_table`.
POSE_COLUMNS = (
    "frame_id", "obj_name", "status", "confidence", "verification", "present", "adds_m", "correct", "carried"
)  # fmt: skip


def _gt_keys(gt: pd.DataFrame) -> set[tuple[str, str]]:
    return set(zip(gt["frame_id"], gt["obj_name"], strict=True))


def pose_table(
    poses: pd.DataFrame, gt: pd.DataFrame, points: Mapping[str, np.ndarray], diameters: Mapping[str, float]
) -> pd.DataFrame:
    """One row per (frame, object) pair with a pose among :data:`SCORED_STATUSES` (an ok row before a
    low-confidence one, then the most confident).

    Args:
        poses: ``poses.parquet`` rows (frame_id, obj_name, status, confidence, R, t_m).
        gt: ground truth (frame_id, obj_name, R, t_m).
        points: obj_name -> (N, 3) model points, metres (every object of ``gt``).
        diameters: obj_name -> diameter, metres.

    Returns:
        :data:`POSE_COLUMNS`: ``verification`` (NaN where not scored), ``present`` (the ground truth lists the
        object in that frame), ``adds_m`` (ADD-S to the truth, metres; +inf when absent), ``correct``
        (present and ADD-S < 0.2 d) and ``carried`` (the carry stage's pose; False in runs without the
        column).
    """
    present = _gt_keys(gt)
    rows = metrics.pick_estimates(poses[poses["status"].isin(SCORED_STATUSES)])
    truth = {(g["frame_id"], g["obj_name"]): g for g in gt.to_dict("records")}
    out = []
    for r in rows.to_dict("records"):
        key = (r["frame_id"], r["obj_name"])
        est = row_cam_from_model(r)
        if est is None:
            continue
        adds_m = np.inf
        if key in present:
            true = row_cam_from_model(truth[key])
            if true is not None:
                adds_m = metrics.adds(est[:3, :3], est[:3, 3], true[:3, :3], true[:3, 3], points[key[1]])
        diam = float(diameters.get(key[1], np.nan))
        carried = r.get("carried") in (True, np.True_)  # (NaN, None: a run before the carry stage)
        correct = adds_m < CORRECT_FRACTION * diam
        verification = float(r.get("verification", np.nan))  # (NaN: not scored, or a run before the score)
        out.append((*key, r["status"], float(r["confidence"]), verification, key in present, adds_m, correct, carried))
    return pd.DataFrame(out, columns=list(POSE_COLUMNS))


def absent_pairs(poses: pd.DataFrame, gt: pd.DataFrame) -> pd.DataFrame:
    """The estimated (frame, object) pairs whose object the ground truth does not list in that frame:
    frame_id, obj_name, ``ok`` (the pair's picked row is ok)."""
    present = _gt_keys(gt)
    pairs = metrics.pick_estimates(poses)
    keys = list(zip(pairs["frame_id"], pairs["obj_name"], strict=True))
    absent = pairs[[k not in present for k in keys]]
    return pd.DataFrame(
        {"frame_id": absent["frame_id"], "obj_name": absent["obj_name"], "ok": absent["status"] == "ok"}
    )


@dataclass(frozen=True)
class Trust:
    """Precision and recall of ok for one group of poses (an object, or all of them)."""

    ok_precision: float
    """Correct ok poses / ok poses (NaN without any)."""
    ok_recall: float
    """Ground-truth instances with a correct ok pose / instances (NaN without any)."""
    n_ok_absent: int
    """Ok poses of objects the ground truth says are absent."""
    n_absent_pairs: int
    """Estimated (frame, object) pairs of absent objects."""
    n_carried: int = 0
    """Ok poses the carry stage found."""
    n_carried_correct: int = 0
    """... of them correct."""


def trust(table: pd.DataFrame, absent: pd.DataFrame, n_instances: int) -> Trust:
    """:class:`Trust` from :func:`pose_table`'s and :func:`absent_pairs`' rows of one group and its number of
    ground-truth instances."""
    ok = table[table["status"] == "ok"]
    precision = float(ok["correct"].mean()) if len(ok) else float("nan")
    n_correct = int(ok["correct"].sum()) if len(ok) else 0  # (a group without ok poses may lack the column)
    recall = n_correct / n_instances if n_instances else float("nan")
    carried = ok[ok["carried"]] if "carried" in ok and len(ok) else ok.iloc[:0]
    n_abs = int(absent["ok"].sum())
    return Trust(
        precision, recall, n_abs, len(absent), len(carried), int(carried["correct"].sum()) if len(carried) else 0
    )


def trust_columns(summary: pd.DataFrame, table: pd.DataFrame, absent: pd.DataFrame) -> pd.DataFrame:
    """``summary`` (:func:`batchpose.report.metrics.score`'s) with ok_precision, ok_recall, n_ok_absent,
    n_absent_pairs, n_carried and n_carried_correct: per object over its poses, ``pooled`` over all, ``mean``
    the mean of the objects' precisions and recalls and the sums of their counts."""
    rows = []
    for name, n in zip(summary["obj_name"], summary["n"], strict=True):
        if name in ("mean", "pooled"):
            sel_t, sel_a = table, absent
        else:
            sel_t, sel_a = table[table["obj_name"] == name], absent[absent["obj_name"] == name]
        rows.append(trust(sel_t, sel_a, int(n)).__dict__)
    cols = pd.DataFrame(rows, index=summary.index)
    objects = ~summary["obj_name"].isin(["mean", "pooled"])
    is_mean = summary["obj_name"] == "mean"
    for c in ("ok_precision", "ok_recall"):
        cols.loc[is_mean, c] = float(cols.loc[objects, c].mean()) if objects.any() else np.nan
    return pd.concat([summary, cols], axis=1)


@dataclass(frozen=True)
class PrCurve:
    """Precision and recall of the poses whose ``by`` (confidence or verification) is >= each threshold
    (thresholds descending)."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    default_threshold: float | None
    """The run's ``min_confidence`` or ``min_verification`` (its ok threshold), None when its config does not
    say."""
    ok_point: tuple[float, float]
    """(recall, precision) of the poses the run called ok."""
    by: str = "confidence"
    """The column swept."""


def pr_curve(
    table: pd.DataFrame, n_instances: int, default_threshold: float | None, by: str = "confidence"
) -> PrCurve | None:
    """The precision-recall curve of :func:`pose_table`'s poses as the threshold on ``by`` sweeps (None
    without poses or instances, or, for ``verification``, without a scored pose). A pose without a
    verification score is kept at every threshold of its curve."""
    if table.empty or n_instances == 0 or not np.isfinite(table[by].to_numpy(float)).any():
        return None
    conf = np.nan_to_num(table[by].to_numpy(float), nan=np.inf)
    correct = table["correct"].to_numpy(bool)
    order = np.argsort(-conf, kind="stable")
    conf, correct = conf[order], correct[order]
    last = np.r_[conf[1:] != conf[:-1], True]  # the last pose of each run of equal confidences
    tp = np.cumsum(correct)[last]
    n = (np.arange(len(conf)) + 1)[last]
    everything = trust(table, table.iloc[:0].assign(ok=False), n_instances)
    return PrCurve(
        conf[last], tp / n, tp / n_instances, default_threshold, (everything.ok_recall, everything.ok_precision), by
    )


def ok_threshold(config_text: str, key: str = "min_confidence") -> float | None:
    """An ok threshold a run used (``pipeline.<key>`` of its ``config.yaml``: ``min_confidence`` or
    ``min_verification``), None when absent."""
    try:
        saved = yaml.safe_load(config_text) if config_text else None
    except yaml.YAMLError:
        return None
    pipeline = saved.get("pipeline") if isinstance(saved, dict) else None
    value = pipeline.get(key) if isinstance(pipeline, dict) else None
    return float(value) if isinstance(value, (int, float)) else None
