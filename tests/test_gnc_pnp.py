"""GNC-PnP under random and clustered outliers (SPEC §4), seeded."""

from __future__ import annotations

import cv2
import numpy as np

from batchpose.config import GncConfig
from batchpose.method.gnc_pnp import PnpResult, solve_pose, to_matrix
from batchpose.method.weights import geom_weights
from tests.conftest import K_SYN


def rot_err_deg(R1, R2):
    return float(np.degrees(np.arccos(np.clip((np.trace(R1 @ R2.T) - 1) / 2, -1, 1))))


def random_scene(rng, n_in: int):
    """Points on a 20 cm box in front of the camera and their exact projections."""
    X = rng.uniform(-0.1, 0.1, (n_in, 3))
    rvec = rng.normal(0, 0.5, 3)
    tvec = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.6, 1.0)])
    x, _ = cv2.projectPoints(X, rvec, tvec, K_SYN, None)
    return X, x.reshape(-1, 2), to_matrix(rvec, tvec)


def test_random_outliers_60_percent():
    for seed in range(10):
        rng = np.random.default_rng(seed)
        X_in, x_in, T = random_scene(rng, 80)
        n_out = 120  # 60 % of 200
        X_out = rng.uniform(-0.1, 0.1, (n_out, 3))
        x_out = rng.uniform([0, 0], [640, 480], (n_out, 2))
        X, x = np.vstack([X_in, X_out]), np.vstack([x_in, x_out])
        res = solve_pose(x, X, K_SYN, w_geom=geom_weights(X), seed=seed)
        assert res.status == "ok", res.reason
        assert rot_err_deg(res.cam_from_model[:3, :3], T[:3, :3]) < 2.0
        assert np.linalg.norm(res.cam_from_model[:3, 3] - T[:3, 3]) < 0.01


def test_clustered_outliers_full_at_least_as_good_as_ransac_only():
    full_err, ransac_err = [], []
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        X_in, x_in, T = random_scene(rng, 60)
        x_in = x_in + rng.normal(0, 1.0, x_in.shape)  # pixel noise on true matches
        # 40 % wrong matches, dense and consistent with a wrong pose (e.g. a repeated texture patch).
        n_c = 40
        X_c = rng.normal(0, 0.01, (n_c, 3)) + rng.uniform(-0.08, 0.08, 3)
        T_wrong = T.copy()
        T_wrong[:3, :3] = cv2.Rodrigues(rng.normal(0, 0.4, 3))[0] @ T[:3, :3]
        T_wrong[:3, 3] += rng.normal(0, 0.03, 3)
        x_c, _ = cv2.projectPoints(X_c, cv2.Rodrigues(T_wrong[:3, :3])[0], T_wrong[:3, 3], K_SYN, None)
        X, x = np.vstack([X_in, X_c]), np.vstack([x_in, x_c.reshape(-1, 2)])
        w = geom_weights(X)
        for conf, out in ((GncConfig(), full_err), (GncConfig(enabled=False), ransac_err)):
            res = solve_pose(x, X, K_SYN, w_geom=w, conf=conf, seed=seed)
            assert res.status == "ok", res.reason
            out.append(np.linalg.norm(res.cam_from_model[:3, 3] - T[:3, 3]))
    full_err, ransac_err = np.array(full_err), np.array(ransac_err)
    print(
        "translation error mm full",
        np.round(full_err * 1000, 2),
        "ransac_only",
        np.round(ransac_err * 1000, 2),
    )
    assert full_err.mean() <= ransac_err.mean() + 1e-4
    assert np.all(full_err < 0.01)


def test_too_few_matches_is_a_status_not_an_exception():
    res = solve_pose(np.zeros((3, 2)), np.zeros((3, 3)), K_SYN)
    assert res.status == "too_few_matches" and "3 correspondences" in res.reason


def test_pure_noise_fails_or_reports_few_inliers():
    rng = np.random.default_rng(7)
    res = solve_pose(rng.uniform(0, 640, (50, 2)), rng.uniform(-0.1, 0.1, (50, 3)), K_SYN)
    assert res.status in ("pnp_failed", "ok")
    if res.status == "ok":
        assert res.n_inliers < 25


def test_support_counts_pairs_within_the_threshold():
    res = PnpResult(
        "ok",
        cam_from_model=np.eye(4),
        inliers=np.array([True, True, True, False, False]),
        residuals_px=np.array([0.1, 1.5, 6.0, 1.0, 9.0]),
    )
    assert res.support() == 3  # 0: the inlier count
    assert res.support(2.0) == 3  # 0.1, 1.5 and the outlier at 1.0
    assert res.support(0.5) == 1
    assert PnpResult("pnp_failed", residuals_px=np.zeros(4)).support(2.0) == 0
