"""``max_pose_spread``: how loosely a pose's inliers pin it (:func:`batchpose.method.gnc_pnp.pose_spread`), and
the estimator reporting a loosely pinned pose as low_confidence."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig
from batchpose.method.gnc_pnp import pose_spread, to_matrix
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import default_then


def _monte_carlo(T: np.ndarray, X: np.ndarray, points: np.ndarray, trials: int = 400) -> float:
    """RMS displacement of ``points`` over least-squares poses re-solved from the pairs' exact projections
    with 1-px Gaussian noise added."""
    rng = np.random.default_rng(0)
    rvec0, t0 = cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].copy()
    x = cv2.projectPoints(X, rvec0, t0, K_SYN, None)[0].reshape(-1, 2)
    base = points @ T[:3, :3].T + T[:3, 3]
    sq = []
    for _ in range(trials):
        noisy = x + rng.normal(0.0, 1.0, x.shape)
        _, r, t = cv2.solvePnP(X, noisy, K_SYN, None, rvec0.copy(), t0.reshape(3, 1).copy(), True)
        M = to_matrix(r, t)
        moved = points @ M[:3, :3].T + M[:3, 3]
        sq.append(np.mean(np.sum((moved - base) ** 2, axis=1)))
    return float(np.sqrt(np.mean(sq)))


def test_the_spread_is_what_noise_on_the_pairs_does_to_a_least_squares_pose():
    """The covariance's spread agrees with re-solving the pose under 1-px noise, for pairs over a box's
    faces and for pairs along a pen, within 15 %."""
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.06, 0.06, (300, 3))
    T = to_matrix([0.4, -0.3, 0.2], [0.05, -0.03, 0.8])
    box = rng.uniform(-0.06, 0.06, (25, 3))
    pen = np.c_[rng.uniform(-0.06, 0.06, 25), rng.normal(0, 0.003, (25, 2))]
    for X in (box, pen):
        assert pose_spread(T, X, K_SYN, points) == pytest.approx(_monte_carlo(T, X, points), rel=0.15)


def test_pairs_along_a_line_pin_a_pose_far_less_than_pairs_over_the_object():
    """A pen seen side-on (pairs within 3 mm of its axis) leaves its distance and tilt trading off: a spread
    over twice the box's; pairs exactly on one line (or fewer than three) leave it unconstrained."""
    rng = np.random.default_rng(2)
    points = rng.uniform(-0.06, 0.06, (300, 3))
    T = to_matrix([0.1, 0.2, -0.1], [0.0, 0.02, 1.0])
    box = pose_spread(T, rng.uniform(-0.06, 0.06, (20, 3)), K_SYN, points)
    pen = pose_spread(T, np.c_[rng.uniform(-0.06, 0.06, 20), rng.normal(0, 0.003, (20, 2))], K_SYN, points)
    assert pen > 2 * box
    line = np.c_[np.linspace(-0.06, 0.06, 20), np.zeros((20, 2))]
    assert pose_spread(T, line, K_SYN, points) == float("inf")
    assert pose_spread(T, np.eye(3)[:2] * 0.05, K_SYN, points) == float("inf")


def test_a_loosely_pinned_pose_is_low_confidence(cracker_model, cracker_library):
    """The default passes a cracker box found over its printed faces; a ``max_pose_spread`` under that pose's
    spread makes it low_confidence, with a reason naming the spread and the option."""
    assert EstimatorConfig().max_pose_spread == 0.5
    rec, loose = default_then(cracker_model, cracker_library, lambda r: {"max_pose_spread": 1e-4})
    assert rec.ok
    assert loose.status == "low_confidence"
    assert "of the object's diameter per pixel of noise, over estimator.max_pose_spread 0.0001" in loose.reason
    assert loose.n_inliers == rec.n_inliers
