"""A full estimate's other refined hypotheses, checked against the frame (``alternatives``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import load_estimator_config
from batchpose.core.frames import Camera
from batchpose.errors import ConfigError
from batchpose.method.estimator import PoseEstimator
from batchpose.method.hypotheses import alternative
from batchpose.method.refine import Refined
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import compose
from tests.test_fine import rot_deg
from tests.test_planar import as_result, face_view, looking_at

CAM = Camera(K_SYN, 640, 480)


def turned(T: np.ndarray, deg: float) -> np.ndarray:
    """``T`` turned ``deg`` about the camera's vertical axis through the object's origin."""
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(deg), 0.0]))[0] @ T[:3, :3]
    return out


def hypothesis(T: np.ndarray, X: np.ndarray, x: np.ndarray, score: int) -> Refined:
    """A refined hypothesis at ``T`` whose guided score is ``score`` (its inlier count)."""
    res = as_result(T, X, x)
    res.inliers = np.arange(len(X)) < score
    return Refined(res, x, X)


@pytest.fixture(scope="module")
def scene(cracker_model, cracker_library):
    """The box rendered at 1.2 m over a textured background, an estimator and that frame as its checks see
    it, the true pose and a pose turned 30 degrees away from it."""
    T, X, x = face_view(cracker_model, 1.2)
    img = compose(np.random.default_rng(3), cracker_model, T)
    return looking_at(img, cracker_model, cracker_library), T, turned(T, 30.0), X, x


def test_a_lower_scored_hypothesis_the_frame_shows_replaces_the_pose(scene, cracker_model):
    """The pose chosen is 30 degrees off; the right hypothesis scored a little lower (its guided score
    18 against 20). Rendered beside each other, the frame prefers it by colour and by edges: it replaces the
    pose, with its own pairs, and the reason says why."""
    (est, lab), T, wrong, X, x = scene
    tried = [hypothesis(wrong, X, x, 20), hypothesis(T, X, x, 18)]
    timings: dict[str, float] = {}
    out = alternative(est.objects, lab, cracker_model.name, tried[0].result, tried, CAM, timings)
    assert out is not None
    (res, x_used, X_used), why = out
    assert rot_deg(res.cam_from_model, T) < 1e-6 and res.n_inliers == 18
    assert x_used is x and X_used is X
    assert why.startswith("a 18-inlier alternative fits the frame better") and "edges" in why
    assert timings["refine"] > 0


def test_the_right_pose_is_kept_and_weak_or_equal_hypotheses_are_not_checked(scene, cracker_model):
    """The right pose stays against a higher-scored wrong one; a right hypothesis under
    ``alternatives_score`` of the best score or with fewer than that fraction of the pose's inliers, or one
    within 5 degrees of the pose, is not considered; ``alternatives: 0`` checks nothing."""
    (est, lab), T, wrong, X, x = scene
    name, objects = cracker_model.name, est.objects
    right = hypothesis(T, X, x, 18)
    assert alternative(objects, lab, name, right.result, [right, hypothesis(wrong, X, x, 20)], CAM, {}) is None
    weak = [hypothesis(wrong, X, x, 20), hypothesis(T, X, x, 9)]  # 9 < 0.5 * 20
    assert alternative(objects, lab, name, weak[0].result, weak, CAM, {}) is None
    near = [hypothesis(wrong, X, x, 20), hypothesis(turned(wrong, 3.0), X, x, 19)]
    assert alternative(objects, lab, name, near[0].result, near, CAM, {}) is None
    # a pose 48 pairs support (e.g. the template pairs') is not second-guessed by 18 (< 0.5 * 48)
    outnumbered = [hypothesis(wrong, X, x, 20), hypothesis(T, X, x, 18)]
    assert alternative(objects, lab, name, as_result(wrong, X, x), outnumbered, CAM, {}) is None
    assert alternative(objects, lab, name, hypothesis(wrong, X, x, 36).result, outnumbered, CAM, {}) is not None
    off = PoseEstimator(
        load_estimator_config({"alternatives": 0}),
        objects.libraries,
        models=objects.models,
        renderer=objects.renderer,
    )
    tried = [hypothesis(wrong, X, x, 20), hypothesis(T, X, x, 18)]
    assert alternative(off.objects, lab, name, tried[0].result, tried, CAM, {}) is None


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [("alternatives", -1, "alternatives must be >= 0"), ("alternatives_score", 0, "alternatives_score must be in")],
)
def test_alternatives_options_are_checked(key, value, message):
    with pytest.raises(ConfigError, match=message):
        load_estimator_config({key: value})
