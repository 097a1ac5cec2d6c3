"""Pose-accuracy metrics (SPEC §6): ADD, ADD-S, rotation / translation error, VOCap AUC, recall.

Pure functions, arrays in and out. Distances are metres unless a name says otherwise. An instance with no
usable estimate has distance ``+inf`` (NaN is treated the same way) and still counts in every ``n``: a
missing estimate is a failure, never a dropped row.

The AUC is the YCB-Video toolbox's (``reference/YCB_Video_toolbox/AUC.md``): the exact area under the
step accuracy curve up to 0.1 m, normalised to 100. :func:`score` turns a ``poses.parquet`` table and a
ground-truth table into per-instance errors and a per-object / mean / pooled summary.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from batchpose.core.geometry import check_rotation, rotation_error_deg
from batchpose.core.poses import STATUSES
from batchpose.errors import DataError

log = logging.getLogger("batchpose")

#: Status of a ground-truth instance that has no row at all in the estimates.
MISSING = "missing"
#: Failure statuses counted in the summary, in column order.
FAILURE_STATUSES = tuple(s for s in STATUSES if s != "ok") + (MISSING,)
#: Columns of the per-instance table returned by :func:`score`.
INSTANCE_COLUMNS = (
    "frame_id",
    "obj_name",
    "status",
    "confidence",
    "diameter_m",
    "add_m",
    "adds_m",
    "rot_err_deg",
    "trans_err_mm",
)
#: Columns of the summary table returned by :func:`score` (before the ``n_<status>`` counts).
SUMMARY_COLUMNS = (
    "obj_name",
    "n",
    "n_ok",
    "adds_auc",
    "add_auc",
    "add_recall_01d",
    "adds_recall_01d",
    "median_rot_err_deg",
    "median_trans_err_mm",
)


def _check_translation(t: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.shape not in ((3,), (3, 1)):
        raise ValueError(f"{name} must have shape (3,) or (3, 1), got {t.shape}")
    return t.reshape(3)


def _check_points(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"pts must have shape (N, 3) with N > 0, got {pts.shape}")
    return pts


def _transform(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ R.T + t


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance between model points under the estimated and the true pose.

    Args:
        R_est: (3, 3) estimated rotation, model -> camera.
        t_est: (3,) estimated translation, metres.
        R_gt: (3, 3) ground-truth rotation, model -> camera.
        t_gt: (3,) ground-truth translation, metres.
        pts: (N, 3) model points, metres, model frame.

    Returns:
        Mean of ``||(R_est x + t_est) - (R_gt x + t_gt)||`` over the points, metres.
    """
    pts = _check_points(pts)
    est = _transform(check_rotation(R_est, "R_est"), _check_translation(t_est, "t_est"), pts)
    gt = _transform(check_rotation(R_gt, "R_gt"), _check_translation(t_gt, "t_gt"), pts)
    return float(np.linalg.norm(est - gt, axis=1).mean())


def adds(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S: mean over true-pose points of the distance to the nearest estimated-pose point.

    Args:
        R_est: (3, 3) estimated rotation, model -> camera.
        t_est: (3,) estimated translation, metres.
        R_gt: (3, 3) ground-truth rotation, model -> camera.
        t_gt: (3,) ground-truth translation, metres.
        pts: (N, 3) model points, metres, model frame.

    Returns:
        Mean nearest-neighbour distance, metres. The true-pose points are moved into the estimated pose's
        model frame (a rigid motion keeps distances), so one KD-tree over the model points serves every
        pose of an object (kept for the last :data:`_N_TREES` point sets asked about).
    """
    checked = _check_points(pts)
    R_est, t_est = check_rotation(R_est, "R_est"), _check_translation(t_est, "t_est")
    gt = _transform(check_rotation(R_gt, "R_gt"), _check_translation(t_gt, "t_gt"), checked)
    dist, _ = _tree(pts, checked).query((gt - t_est) @ R_est, k=1)
    return float(np.mean(dist))


_N_TREES = 64
_TREES: dict[int, tuple[np.ndarray, cKDTree]] = {}


def _tree(pts: np.ndarray, checked: np.ndarray) -> cKDTree:
    """The KD-tree over ``checked`` (``pts`` as float64), built once per ``pts`` array (held, so its id
    cannot pass to another array while the tree is kept)."""
    hit = _TREES.get(id(pts))
    if hit is not None and hit[0] is pts:
        return hit[1]
    if len(_TREES) >= _N_TREES:
        _TREES.pop(next(iter(_TREES)))
    tree = cKDTree(checked)
    _TREES[id(pts)] = (pts, tree)
    return tree


def translation_error_mm(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Euclidean distance between translations.

    Args:
        t_est: (3,) estimated translation, metres.
        t_gt: (3,) ground-truth translation, metres.

    Returns:
        ``||t_est - t_gt||`` in millimetres.
    """
    t_est = _check_translation(t_est, "t_est")
    t_gt = _check_translation(t_gt, "t_gt")
    return float(np.linalg.norm(t_est - t_gt) * 1000.0)


def _check_distances(distances: np.ndarray) -> np.ndarray:
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 1:
        raise ValueError(f"distances must have shape (n,), got {d.shape}")
    # NaN is a missing estimate, i.e. a failure, exactly like +inf.
    return np.where(np.isnan(d), np.inf, d)


def vocap_auc(distances: np.ndarray, max_distance: float = 0.1) -> float:
    """Area under the accuracy-threshold curve, exactly as the YCB-Video toolbox computes it (VOCap).

    Distances above ``max_distance`` become failures; the accuracy at the k-th smallest distance is k/n;
    the area sums, over the intervals where the distance changes, width x accuracy at the interval's right
    end (after (0, 0) is prepended, (max_distance, a_m) appended and a running maximum taken). With n
    instances this sits about 100/n above the continuous ``mean(max(0, max_distance - d)) / max_distance``.

    Args:
        distances: (n,) ADD or ADD-S per instance, metres; +inf or NaN for a missing estimate.
        max_distance: upper end of the threshold range, metres (0.1 in the toolbox).

    Returns:
        AUC in [0, 100]; NaN when ``n == 0``.
    """
    d = _check_distances(distances)
    if not max_distance > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    n = d.size
    if n == 0:
        return float("nan")
    d = np.sort(np.where(d > max_distance, np.inf, d))
    acc = np.arange(1, n + 1, dtype=np.float64) / n
    finite = np.isfinite(d)
    if not finite.any():
        return 0.0
    rec = np.concatenate(([0.0], d[finite], [max_distance]))
    prec = np.maximum.accumulate(np.concatenate(([0.0], acc[finite], [acc[finite][-1]])))
    i = np.flatnonzero(rec[1:] != rec[:-1]) + 1
    return float(np.sum((rec[i] - rec[i - 1]) * prec[i]) / max_distance * 100.0)


def recall(distances: np.ndarray, threshold: float | np.ndarray) -> float:
    """Percentage of instances whose distance is strictly below the threshold (e.g. ADD < 0.1 d).

    Args:
        distances: (n,) distances, metres; +inf or NaN for a missing estimate (counted as a failure).
        threshold: scalar or (n,) per-instance threshold, metres (per instance for pooled 0.1 d recall).

    Returns:
        Recall in [0, 100]; NaN when ``n == 0``.
    """
    d = _check_distances(distances)
    thr = np.asarray(threshold, dtype=np.float64)
    if thr.ndim != 0 and thr.shape != d.shape:
        raise ValueError(f"threshold must be a scalar or have shape {d.shape}, got {thr.shape}")
    if d.size == 0:
        return float("nan")
    return float(np.mean(d < thr) * 100.0)


def accuracy_curve(distances: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Accuracy-threshold curve: percentage of instances with distance <= each threshold.

    Args:
        distances: (n,) distances, metres; +inf or NaN for a missing estimate.
        thresholds: (T,) thresholds, metres.

    Returns:
        (T,) float64 accuracy in [0, 100] (NaN everywhere when ``n == 0``).
    """
    d = _check_distances(distances)
    thr = np.asarray(thresholds, dtype=np.float64)
    if thr.ndim != 1:
        raise ValueError(f"thresholds must have shape (T,), got {thr.shape}")
    if d.size == 0:
        return np.full(thr.shape, np.nan)
    # searchsorted on the sorted distances counts d <= thr for all thresholds at once.
    return np.searchsorted(np.sort(d), thr, side="right") / d.size * 100.0


def _rt(row, where: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) of a table row, None when any entry is missing or non-finite."""
    try:
        R = np.asarray(row["R"], dtype=np.float64).reshape(3, 3)
        t = np.asarray(row["t_m"], dtype=np.float64).reshape(3)
    except (TypeError, ValueError) as e:
        raise DataError(f"{where}: R must have 9 and t_m 3 numbers ({e})") from None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    return R, t


#: Accepted range of (bounding-box diagonal of an object's model points) / (its diameter). For points on the
#: object the ratio lies between about 1 and sqrt(3); points in millimetres against a diameter in metres
#: (a unit slip that silently zeroes every AUC) put it near 1000.
SPAN_RATIO_RANGE = (0.1, 10.0)


def _check_scale(obj: str, pts: np.ndarray, diameter_m: float) -> None:
    """Refuse model points and a diameter that cannot both be in metres (DataError naming the object)."""
    try:
        pts = _check_points(pts)
    except ValueError as e:
        raise DataError(f"object {obj!r}: model points: {e}") from None
    d = float(diameter_m)
    if not (np.isfinite(d) and d > 0):
        raise DataError(f"object {obj!r}: diameter must be a positive number of metres, got {diameter_m!r}")
    span = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    lo, hi = SPAN_RATIO_RANGE
    if not lo <= span / d <= hi:
        raise DataError(
            f"object {obj!r}: the model points span {span:.4g} but the diameter is {d:.4g} m; both must be in "
            "metres (model points in millimetres?)"
        )


def pick_estimates(est: pd.DataFrame) -> pd.DataFrame:
    """One estimate per (frame_id, obj_name): an ok row before a failed one, then the most confident."""
    if est.empty:
        return est
    ranked = est.assign(_ok=(est["status"] == "ok").astype(int))
    ranked = ranked.sort_values(["_ok", "confidence"], ascending=False, kind="stable")
    picked = ranked.drop_duplicates(["frame_id", "obj_name"], keep="first").drop(columns="_ok")
    if len(picked) < len(est):
        log.debug("score: %d duplicate estimates ignored", len(est) - len(picked))
    return picked


def _summary_row(name: str, inst: pd.DataFrame) -> dict:
    add_d = inst["add_m"].to_numpy(dtype=float)
    adds_d = inst["adds_m"].to_numpy(dtype=float)
    thr = 0.1 * inst["diameter_m"].to_numpy(dtype=float)
    ok = inst["status"] == "ok"
    row = {
        "obj_name": name,
        "n": len(inst),
        "n_ok": int(ok.sum()),
        "adds_auc": vocap_auc(adds_d),
        "add_auc": vocap_auc(add_d),
        "add_recall_01d": recall(add_d, thr),
        "adds_recall_01d": recall(adds_d, thr),
        "median_rot_err_deg": float(np.median(inst.loc[ok, "rot_err_deg"])) if ok.any() else np.nan,
        "median_trans_err_mm": float(np.median(inst.loc[ok, "trans_err_mm"])) if ok.any() else np.nan,
    }
    for status in FAILURE_STATUSES:
        row[f"n_{status}"] = int((inst["status"] == status).sum())
    return row


def score(
    est: pd.DataFrame,
    gt: pd.DataFrame,
    points: Mapping[str, np.ndarray],
    diameters: Mapping[str, float],
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Score estimates against ground truth, one ground-truth instance at a time.

    Args:
        est: estimates in the ``poses.parquet`` format (:mod:`batchpose.core.poses`); needs frame_id, obj_name,
            status, R, t_m, confidence. A ground-truth instance with no row, or a row whose status is not
            ``ok``, gets distance +inf. Estimates without ground truth are ignored.
        gt: one row per ground-truth instance: frame_id, obj_name, R (9 numbers, row-major, model ->
            camera), t_m (3 numbers, metres). Other columns (obj_id, scene_id, ...) are carried over.
        points: obj_name -> (N, 3) model points, metres (the toolbox's ``points.xyz``).
        diameters: obj_name -> object diameter, metres (for the 0.1 d recall).

    Returns:
        ``(per_instance, summary)``. per_instance: one row per gt instance with :data:`INSTANCE_COLUMNS`
        (status ``missing`` when there was no estimate row; add_m/adds_m are +inf and the rotation /
        translation errors NaN for failures). summary: :data:`SUMMARY_COLUMNS` plus ``n_<status>`` for each
        of :data:`FAILURE_STATUSES`; one row per object (sorted), then ``mean`` (mean of the per-object
        AUC / recall / median values, summed counts) and ``pooled`` (all instances in one curve; 0.1 d
        recall with each instance's own diameter). AUCs and recalls are percentages.

    Raises:
        DataError: a required column is missing, an object has no points or diameter, or its points and
            diameter disagree in scale (:data:`SPAN_RATIO_RANGE`; e.g. millimetre points).
    """
    _check_inputs(est, gt, points, diameters)
    rows, extra = _instance_rows(est, gt, points, diameters)
    cols = list(INSTANCE_COLUMNS[:2]) + extra + list(INSTANCE_COLUMNS[2:])
    per_instance = pd.DataFrame(rows, columns=cols)
    summary, pooled = _summary(per_instance)
    objects = sorted(set(per_instance["obj_name"]))
    log.info(
        "scored %d instances of %d objects: ADD-S AUC %.1f, ADD AUC %.1f (pooled), %d failed",
        len(per_instance),
        len(objects),
        pooled["adds_auc"],
        pooled["add_auc"],
        len(per_instance) - pooled["n_ok"],
    )
    return per_instance, summary


def _check_inputs(est: pd.DataFrame, gt: pd.DataFrame, points, diameters) -> None:
    """:func:`score`'s input checks (its ``Raises``)."""
    for name, table, cols in (
        ("estimates", est, ("frame_id", "obj_name", "status", "R", "t_m", "confidence")),
        ("ground truth", gt, ("frame_id", "obj_name", "R", "t_m")),
    ):
        missing_cols = [c for c in cols if c not in table.columns]
        if missing_cols:
            raise DataError(f"{name} table: missing column(s) {', '.join(missing_cols)}")
    for obj in sorted(set(gt["obj_name"])):
        if obj not in points:
            raise DataError(f"ground truth: object {obj!r} has no model points")
        if obj not in diameters:
            raise DataError(f"ground truth: object {obj!r} has no diameter")
        _check_scale(obj, points[obj], diameters[obj])


def _instance_rows(est: pd.DataFrame, gt: pd.DataFrame, points, diameters) -> tuple[list[dict], list[str]]:
    """One row per ground-truth instance (see :func:`score`), and the extra ground-truth columns carried over."""
    picked = pick_estimates(est)
    by_key = {(r["frame_id"], r["obj_name"]): r for r in picked.to_dict("records")}
    extra = [c for c in gt.columns if c not in ("frame_id", "obj_name", "R", "t_m")]
    rows = []
    for g in gt.to_dict("records"):
        where = f"ground truth {g['frame_id']} / {g['obj_name']}"
        gt_pose = _rt(g, where)
        if gt_pose is None:
            raise DataError(f"{where}: pose contains NaN or inf")
        e = by_key.get((g["frame_id"], g["obj_name"]))
        row = {"frame_id": g["frame_id"], "obj_name": g["obj_name"]}
        row.update({c: g[c] for c in extra})
        row.update(
            status=MISSING if e is None else str(e["status"]),
            confidence=np.nan if e is None else float(e["confidence"]),
            diameter_m=float(diameters[g["obj_name"]]),
            add_m=np.inf,
            adds_m=np.inf,
            rot_err_deg=np.nan,
            trans_err_mm=np.nan,
        )
        est_pose = None
        if e is not None and e["status"] == "ok":
            est_pose = _rt(e, f"estimate {g['frame_id']} / {g['obj_name']}")
            if est_pose is None:
                row["status"] = "error"  # "ok" without a finite pose is a pipeline bug; score it as failure
        if est_pose is not None:
            pts = points[g["obj_name"]]
            row.update(
                add_m=add(*est_pose, *gt_pose, pts),
                adds_m=adds(*est_pose, *gt_pose, pts),
                rot_err_deg=rotation_error_deg(est_pose[0], gt_pose[0]),
                trans_err_mm=translation_error_mm(est_pose[1], gt_pose[1]),
            )
        rows.append(row)
    return rows, extra


def _summary(per_instance: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    """The per-object rows, then ``mean`` and ``pooled`` (see :func:`score`); and the pooled row."""
    objects = sorted(set(per_instance["obj_name"]))
    obj_rows = [_summary_row(o, per_instance[per_instance["obj_name"] == o]) for o in objects]
    summary = pd.DataFrame(obj_rows, columns=list(_summary_row("", per_instance.iloc[:0])))
    mean: dict[str, object] = {"obj_name": "mean"}
    for c in summary.columns[1:]:
        if c == "n" or c.startswith("n_"):
            mean[c] = int(summary[c].sum())
        else:
            mean[c] = float(summary[c].mean()) if len(summary) else np.nan
    pooled = _summary_row("pooled", per_instance)
    summary = pd.concat([summary, pd.DataFrame([mean, pooled])], ignore_index=True)
    for c in summary.columns:
        if c == "n" or c.startswith("n_"):
            summary[c] = summary[c].astype(int)
    return summary, pooled
