"""Render-and-match refinement pulls a perturbed pose back to the true one (synthetic, seeded)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import FeatureConfig, GncConfig, RefineConfig
from batchpose.method.features import detect, to_gray
from batchpose.method.refine import guided_matches, refine_pose
from batchpose.method.render import get_renderer
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import compose, random_pose


def test_guided_matches_respect_radius_and_mutual_check():
    rng = np.random.default_rng(0)
    desc = rng.uniform(0, 100, (5, 128)).astype(np.float32)
    xy = np.array([[10, 10], [50, 50], [90, 90], [130, 130], [170, 170]], np.float32)
    # Frame: the same keypoints shifted 3 px, plus a copy of descriptor 0 far away (outside the radius).
    xy_q = np.vstack([xy + 3, [[400, 400]]]).astype(np.float32)
    desc_q = np.vstack([desc + rng.normal(0, 1, desc.shape), desc[:1]]).astype(np.float32)
    r_idx, q_idx = guided_matches(xy, desc, xy_q, desc_q, radius_px=8, ratio=0.9)
    np.testing.assert_array_equal(r_idx, np.arange(5))
    np.testing.assert_array_equal(q_idx, np.arange(5))
    r_idx, _ = guided_matches(xy, desc, xy_q, desc_q, radius_px=2, ratio=0.9)
    assert len(r_idx) == 0  # 3 px shift is outside a 2 px radius


@pytest.mark.parametrize("gnc", [True, False])
def test_refine_recovers_perturbed_pose(cracker_model, gnc):
    rng = np.random.default_rng(11)
    renderer = get_renderer()
    T = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T)
    xy_q, desc_q = detect(to_gray(img), FeatureConfig())
    T0 = T.copy()
    T0[:3, :3] = cv2.Rodrigues(np.deg2rad([2.0, -2.0, 1.5]))[0] @ T[:3, :3]
    T0[:3, 3] += [0.004, -0.003, 0.02]

    def render(Tx):
        return renderer.render(cracker_model.content_hash, cracker_model.mesh, Tx, K_SYN, 640, 480)

    conf = RefineConfig(gnc=gnc)
    out = refine_pose(T0, xy_q, desc_q, K_SYN, np.zeros(0), render, conf, FeatureConfig(), GncConfig())
    assert out is not None and out.result.status == "ok"
    Te = out.result.cam_from_model
    rot = np.degrees(np.arccos(np.clip((np.trace(Te[:3, :3] @ T[:3, :3].T) - 1) / 2, -1, 1)))
    assert rot < 0.5, rot
    assert np.linalg.norm(Te[:3, 3] - T[:3, 3]) < 0.005
    assert out.score >= 30
