"""``refine.polish``: the dense render-and-compare finish pulls a nearly right pose onto the frame (synthetic,
seeded), leaves a pose alone where the frame does not show the mesh, and is off by default."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig, RefineConfig, load_estimator_config
from batchpose.core.frames import Camera
from batchpose.errors import ConfigError
from batchpose.method.estimator import PoseEstimator
from batchpose.method.features import to_gray
from batchpose.method.hypotheses import polish
from batchpose.method.render import get_renderer
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import add_error, compose, random_pose, textured_background


def _estimator(model, library, **refine) -> PoseEstimator:
    conf = EstimatorConfig(refine=RefineConfig(**refine))
    return PoseEstimator(conf, {model.name: library}, models={model.name: model}, renderer=get_renderer())


def _nudged(T: np.ndarray, depth_frac: float, rot_deg: float, lateral_m: float) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.deg2rad([rot_deg, -rot_deg, 0.5 * rot_deg]))[0] @ T[:3, :3]
    out[:3, 3] = T[:3, 3] * (1.0 + depth_frac) + [lateral_m, -lateral_m, 0.0]
    return out


@pytest.mark.parametrize("seed", [3, 4])
def test_polish_pulls_a_nearly_right_pose_onto_the_frame(cracker_model, cracker_library, seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng, cracker_model.center_m)
    gray = to_gray(compose(rng, cracker_model, T))  # lit mesh, textured background, sensor noise
    start = _nudged(T, depth_frac=0.01, rot_deg=0.4, lateral_m=0.001)  # ~1 cm off, as a SIFT pose can be
    est = _estimator(cracker_model, cracker_library, polish=True)
    polished = polish(est.objects, cracker_model.name, gray, start, Camera(K_SYN, 640, 480))
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    before, after = add_error(start, T, pts), add_error(polished, T, pts)
    print(f"ADD {before * 1000:.2f} -> {after * 1000:.2f} mm")
    assert after < 0.25 * before and after < 0.002, (before, after)


def test_polish_leaves_the_pose_where_the_frame_does_not_show_the_mesh(cracker_model, cracker_library):
    rng = np.random.default_rng(5)
    T = random_pose(rng, cracker_model.center_m)
    gray = to_gray(textured_background(rng))  # no cracker box in this frame
    est = _estimator(cracker_model, cracker_library, polish=True)
    out = polish(est.objects, cracker_model.name, gray, T, Camera(K_SYN, 640, 480))
    np.testing.assert_array_equal(out, T)


def test_polish_is_off_by_default_and_its_settings_are_checked():
    assert not EstimatorConfig().refine.polish
    with pytest.raises(ConfigError, match=r"refine.polish_rounds must be >= 1, got 0"):
        load_estimator_config({"refine": {"polish": True, "polish_rounds": 0}})
    with pytest.raises(ConfigError, match=r"refine.polish_search_px must be >= 1, got 0"):
        load_estimator_config({"refine": {"polish_search_px": 0}})


def test_a_full_estimate_is_polished_when_asked(cracker_model, cracker_library):
    """With ``refine.polish`` the estimate is the default's pose polished (and nothing else changes)."""
    rng = np.random.default_rng(7)
    T = random_pose(rng, cracker_model.center_m)
    img, cam, name = compose(rng, cracker_model, T), Camera(K_SYN, 640, 480), cracker_model.name
    plain = _estimator(cracker_model, cracker_library).estimate_image(img, cam, [name])[0]
    est = _estimator(cracker_model, cracker_library, polish=True)
    rec = est.estimate_image(img, cam, [name])[0]
    assert plain.ok and rec.ok and not np.allclose(rec.cam_from_model, plain.cam_from_model, atol=1e-6)
    polished = polish(est.objects, name, to_gray(img), plain.cam_from_model, cam)
    np.testing.assert_allclose(rec.cam_from_model, polished, atol=1e-9)
    assert (rec.n_inliers, rec.confidence) == (plain.n_inliers, plain.confidence)  # the SIFT evidence, as before
