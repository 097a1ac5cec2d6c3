"""The planar ambiguity: inliers on one face of a box fit two poses; the frame decides (``planar_spread``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig, load_estimator_config
from batchpose.core.frames import Camera
from batchpose.errors import ConfigError
from batchpose.method.estimator import PoseEstimator
from batchpose.method.features import to_gray
from batchpose.method.gnc_pnp import PnpResult, planar_alternative, reprojection_errors
from batchpose.method.hypotheses import planar_mirror
from batchpose.method.render import get_renderer
from batchpose.method.shot import LazyLab
from batchpose.method.views import look_at
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import compose
from tests.test_fine import rot_deg

NO_DIST = np.zeros(5)


def face_view(model, distance_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cracker box seen from ``distance_m`` at 40 degrees to its front face (and 20 above), and a grid
    of points on that face with their pixels (0.3 px noise): (cam_from_model, X, x)."""
    lo, hi = model.mesh.bounds
    c = (lo + hi) / 2
    a, e = np.deg2rad(40.0), np.deg2rad(20.0)
    eye = c + distance_m * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    T = look_at(eye, c, np.array([0.0, 0.0, 1.0]))
    yy, zz = np.meshgrid(np.linspace(lo[1] + 0.01, hi[1] - 0.01, 6), np.linspace(lo[2] + 0.01, hi[2] - 0.01, 8))
    X = np.stack([np.full(yy.size, hi[0]), yy.ravel(), zz.ravel()], axis=1)
    proj, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K_SYN, NO_DIST)
    x = proj.reshape(-1, 2) + np.random.default_rng(0).normal(0, 0.3, (len(X), 2))
    return T, X, x


def looking_at(img: np.ndarray, model, library) -> tuple[PoseEstimator, LazyLab]:
    """A default estimator (with a renderer) and ``img`` as its frame checks look at it, as in ``estimate_image``."""
    est = PoseEstimator(EstimatorConfig(), {model.name: library}, models={model.name: model}, renderer=get_renderer())
    return est, LazyLab(img, to_gray(img))


def as_result(T: np.ndarray, X: np.ndarray, x: np.ndarray) -> PnpResult:
    r = reprojection_errors(X, x, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K_SYN, NO_DIST)
    return PnpResult("ok", cam_from_model=T, inliers=np.ones(len(X), bool), residuals_px=r)


def test_planar_alternative_is_the_other_tilt_of_the_face(cracker_model):
    """From afar a face's points fit a second pose, turned well away, about as well; from that pose the
    first is found again. Points off the plane have no such pose."""
    T, X, x = face_view(cracker_model, 2.0)
    other = planar_alternative(x, X, T, K_SYN, NO_DIST, 0.05)
    assert other is not None
    T_alt, r_alt = other
    assert rot_deg(T_alt, T) > 20
    assert np.median(r_alt) < 1.0
    back, _ = planar_alternative(x, X, T_alt, K_SYN, NO_DIST, 0.05)
    assert rot_deg(back, T) < 1.0
    bumpy = X + np.random.default_rng(1).normal(0, 0.02, X.shape) * [1, 0, 0]
    assert planar_alternative(x, bumpy, T, K_SYN, NO_DIST, 0.05) is None
    assert planar_alternative(x, X, T, K_SYN, NO_DIST, 0.0) is None  # off


@pytest.mark.parametrize("start", ["mirrored", "true"])
def test_the_pose_whose_render_the_frame_shows_is_kept(cracker_model, cracker_library, start):
    """Rendered frame of the box at 2 m: given the face's points at the mirrored pose, the check turns it
    back (rotation within 1 degree of the truth, reason given); given the true pose, it keeps it."""
    T, X, x = face_view(cracker_model, 2.0)
    img = compose(np.random.default_rng(5), cracker_model, T)
    T_alt, _ = planar_alternative(x, X, T, K_SYN, NO_DIST, 0.05)
    est, lab = looking_at(img, cracker_model, cracker_library)
    timings: dict[str, float] = {}
    res = as_result(T_alt if start == "mirrored" else T, X, x)
    out = planar_mirror(est.objects, lab, cracker_model.name, res, x, X, Camera(K_SYN, 640, 480), timings)
    if start == "true":
        assert out is None
    else:
        assert out is not None
        fixed, why = out
        assert rot_deg(fixed.cam_from_model, T) < 1.0
        assert "other pose" in why and "edges" in why
        assert fixed.n_inliers == len(X) and np.median(fixed.residuals_px) < 1.0
    assert timings["refine"] > 0


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("planar_spread", 1.0, "planar_spread must be in \\[0, 1\\)"),
        ("planar_residual_ratio", 0.5, "planar_residual_ratio must be >= 1"),
        ("planar_mismatch_ratio", 0.9, "planar_mismatch_ratio must be >= 1"),
    ],
)
def test_planar_options_are_checked(key, value, message):
    with pytest.raises(ConfigError, match=message):
        load_estimator_config({key: value})


def test_gradient_match_sees_edges_not_their_sign_or_colour():
    """The same outline lighter or darker than its surround matches fully; moved by 6 px it does not."""
    from batchpose.method.appearance import gradient_match

    img = np.full((100, 100), 60, np.uint8)
    cv2.rectangle(img, (30, 30), (70, 60), 200, -1)
    px = np.ones(img.shape, bool)
    assert gradient_match(img, img, px) == pytest.approx(1.0, abs=1e-6)
    assert gradient_match(img, 255 - img, px) == pytest.approx(1.0, abs=1e-6)
    assert gradient_match(img, np.roll(img, 6, axis=1), px) < 0.6
