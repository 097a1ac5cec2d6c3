"""What a pose record says of a pose: its confidence, the statuses of an object not found, a failed frame's
records (status from the exception's class), and the records of a frame estimated at a working size."""

from __future__ import annotations

import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.core.poses import PoseRecord
from batchpose.errors import CameraError, ImageError

#: Statuses of an object the frame shows no pose of: the retries, the depth search and the plane search look
#: for it. ``conflict`` (:mod:`batchpose.method.region`): its pose claimed another object's pixels and lost
#: them; the object may still be elsewhere.
NOT_FOUND = ("too_few_matches", "pnp_failed", "low_confidence", "conflict")
#: Statuses an object is searched for in (the depth and the plane search): no SIFT pose, or (``absent``) no SIFT
#: evidence of it at all; an object with little texture can be there all the same.
SEARCHED = (*NOT_FOUND, "absent")
#: Statuses of a frame that could not be used at all (every track ends there).
FAILED = ("bad_image", "bad_camera", "error")

#: id(a retry's record) -> (that record, the ok pose it replaced): the weak-pose check gives the replaced pose
#: back when it rejects the replacement. One image's (or frame's) worth, made per frame.
Replaced = dict[int, tuple[PoseRecord, PoseRecord]]


def confidence(n_inliers: int, median_residual_px: float, conf: EstimatorConfig) -> float:
    """Confidence in [0, 1]: (1 - exp(-n_inliers / c_n)) * exp(-median_residual_px / c_r).

    Grows with the number of inliers (c_n = ``confidence_inliers``, 15 by default: 15 inliers give 0.63)
    and falls with their median reprojection error (c_r = ``confidence_residual_px``, 4 px).
    """
    if n_inliers <= 0 or not np.isfinite(median_residual_px):
        return 0.0
    c = (1.0 - np.exp(-n_inliers / conf.confidence_inliers)) * np.exp(-median_residual_px / conf.confidence_residual_px)
    return float(np.clip(c, 0.0, 1.0))


def pose_of(found) -> np.ndarray:
    """The (4, 4) cam_from_model of a record or solve result that has one (an ok one, or a low-confidence
    record's), for the steps that only ever see those."""
    pose = found.cam_from_model
    assert pose is not None, f"{found} has no pose"
    return pose


def failure_status(error: Exception) -> str:
    """A failed frame's status: ``bad_image`` for an :class:`ImageError`, ``bad_camera`` for a
    :class:`CameraError`, ``error`` for anything else."""
    if isinstance(error, ImageError):
        return "bad_image"
    if isinstance(error, CameraError):
        return "bad_camera"
    return "error"


def to_full_size(records: list[PoseRecord], scale: np.ndarray) -> None:
    """Records of a frame estimated at a working size (``max_image_side_px``, x and y ``scale`` (2,)) in the
    full frame's pixels: inlier pixels (pixel centres at integers) and median residuals."""
    for rec in records:
        rec.inliers_px = (np.asarray(rec.inliers_px, float) + 0.5) / scale - 0.5
        rec.median_residual_px /= float(scale.mean())
