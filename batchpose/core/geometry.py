"""Rigid-transform geometry shared by the method and the report."""

from __future__ import annotations

import numpy as np


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of the relative rotation ``R_est^T R_gt``.

    Args:
        R_est: (3, 3) estimated rotation.
        R_gt: (3, 3) ground-truth rotation.

    Returns:
        Rotation error in degrees, in [0, 180].
    """
    R_est = check_rotation(R_est, "R_est")
    R_gt = check_rotation(R_gt, "R_gt")
    cos = (np.trace(R_est.T @ R_gt) - 1.0) / 2.0
    # Round-off can push the cosine just outside [-1, 1] for (near-)identical rotations.
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def check_rotation(R: np.ndarray, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {R.shape}")
    return R
