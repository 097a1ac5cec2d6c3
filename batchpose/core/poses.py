"""The result record of one (frame, object) estimate, and its table form (``poses.parquet``).

Table columns (one row per (frame, object)):
    frame_id (str), scene_id (int), im_id (int), stamp_ns (int), obj_name (str), obj_id (int),
    status (str, one of :data:`STATUSES`), reason (str: why it failed; for an ok pose "" or a note, e.g. why
    ``depth.enabled`` left the RGB pose as it was),
    R (list of 9 float, row-major, model->camera), t_m (list of 3 float, metres; NaN when failed),
    confidence (float in [0, 1]), n_matches (int), n_inliers (int), median_residual_px (float),
    templates (str, space-separated template view ids), inliers_px (list of float, x0 y0 x1 y1 ...),
    tracked (bool: followed from the previous frame by :mod:`batchpose.method.track`, not estimated afresh),
    carried (bool: found by the carry stage, :mod:`batchpose.method.carry`, from a confident pose in a
    neighbouring frame, forwards or backwards; also ``tracked``; its reason says from where),
    verification (float: :mod:`batchpose.method.score`'s score of an untracked pose, NaN where not scored),
    time_<stage>_s (float) for each stage in :data:`STAGES`, time_total_s (float).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

STATUSES = (
    "ok",
    "absent",
    "too_few_matches",
    "pnp_failed",
    "low_confidence",
    "conflict",
    "hidden",
    "bad_image",
    "bad_camera",
    "error",
)
#: Per-(frame, object) timing stages, in pipeline order.
STAGES = (
    "decode", "track", "sift", "presence", "match", "fine", "weights", "ransac", "gnc", "lm", "refine", "verify",
    "seed", "depth", "plane",
)  # fmt: skip


@dataclass
class PoseRecord:
    """Result of estimating one object's pose in one frame. A failure is a record, never an exception."""

    frame_id: str
    obj_name: str
    status: str
    reason: str = ""
    scene_id: int = 0
    im_id: int = 0
    stamp_ns: int = 0
    obj_id: int = 0
    cam_from_model: np.ndarray | None = None
    confidence: float = 0.0
    n_matches: int = 0
    n_inliers: int = 0
    median_residual_px: float = float("nan")
    templates: tuple[int, ...] = ()
    inliers_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    timings: dict[str, float] = field(default_factory=dict)
    tracked: bool = False
    carried: bool = False
    verification: float = float("nan")

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_row(self) -> dict:
        """Flatten to one ``poses.parquet`` row (see module docstring)."""
        if self.cam_from_model is not None:
            R = np.asarray(self.cam_from_model[:3, :3], dtype=float).reshape(-1).tolist()
            t = np.asarray(self.cam_from_model[:3, 3], dtype=float).tolist()
        else:
            R, t = [float("nan")] * 9, [float("nan")] * 3
        row = {
            "frame_id": self.frame_id,
            "scene_id": int(self.scene_id),
            "im_id": int(self.im_id),
            "stamp_ns": int(self.stamp_ns),
            "obj_name": self.obj_name,
            "obj_id": int(self.obj_id),
            "status": self.status,
            "reason": self.reason,
            "R": R,
            "t_m": t,
            "confidence": float(self.confidence),
            "n_matches": int(self.n_matches),
            "n_inliers": int(self.n_inliers),
            "median_residual_px": float(self.median_residual_px),
            "templates": " ".join(str(int(v)) for v in self.templates),
            "inliers_px": np.asarray(self.inliers_px, dtype=float).reshape(-1).tolist(),
            "tracked": bool(self.tracked),
            "carried": bool(self.carried),
            "verification": float(self.verification),
        }
        for stage in STAGES:
            row[f"time_{stage}_s"] = float(self.timings.get(stage, 0.0))
        row["time_total_s"] = float(sum(self.timings.get(s, 0.0) for s in STAGES))
        return row


def row_cam_from_model(row) -> np.ndarray | None:
    """4x4 model->camera transform of a ``poses.parquet`` row (dict or pandas Series), None when failed."""
    R = np.asarray(row["R"], dtype=float).reshape(3, 3)
    t = np.asarray(row["t_m"], dtype=float).reshape(3)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T
