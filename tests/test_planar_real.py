"""The planar ambiguity on a real YCB-Video frame (``planar_score_margin``): video 0049's potted meat can, its
printed face seen from about 0.9 m. The face's points fit two poses, the true one and one that shows the
face from below, with the can's bottom where the frame shows its lid; colour and edges where the two renders
differ do not both prefer the true one, the verification score does."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.core.frames import decode_image
from batchpose.core.geometry import rotation_error_deg
from batchpose.io.mesh import load_mesh
from batchpose.method.features import to_gray
from batchpose.method.gnc_pnp import planar_alternative, reprojection_errors
from batchpose.method.hypotheses import frame_prefers, score_prefers
from batchpose.method.render import get_renderer
from batchpose.method.shot import LazyLab
from tests.conftest import DATA, ycbv_dev_frame

NAME = "010_potted_meat_can"


@pytest.fixture(scope="module")
def scene(cache_dir):
    frame = ycbv_dev_frame("0049/000001")
    model = load_mesh(DATA / "ycb_models" / NAME / "textured.obj", cache_dir=cache_dir)
    truth = next(g.cam_from_model for g in frame.gt if g.obj_name == NAME)
    return frame, decode_image(frame), model, truth


def _face_points(model, truth: np.ndarray) -> np.ndarray:
    """The model's vertices on its flat face turned most towards the camera at ``truth``, moved onto their
    plane: of the six sides across its principal axes, those whose vertices within 4 mm of the extreme lie
    about on one plane (the printed faces, not the rounded lid and ends)."""
    verts = np.asarray(model.mesh.vertices)
    c = verts.mean(axis=0)
    view = -(truth[:3, :3].T @ truth[:3, 3]) - c  # the camera centre in the model frame, from the centre
    faces = []
    for a in np.linalg.eigh(np.cov((verts - c).T))[1].T:
        for side in (a, -a):
            along = (verts - c) @ side
            on = verts[along > along.max() - 4e-3]
            s = np.linalg.svd(on - on.mean(axis=0), compute_uv=False)
            if s[2] < 0.05 * s[1]:
                faces.append((side @ view, on))
    on = max(faces, key=lambda f: f[0])[1]
    normal = np.linalg.svd(on - on.mean(axis=0))[2][2]
    return on - np.outer((on - on.mean(axis=0)) @ normal, normal)  # on the plane: the scan's noise taken off


def test_the_verification_score_tells_a_planar_face_s_two_poses_apart(scene):
    frame, rgb, model, truth = scene
    K, dist = frame.camera.K, frame.camera.dist
    X = _face_points(model, truth)
    assert len(X) >= 20
    rvec = cv2.Rodrigues(truth[:3, :3])[0]
    x = cv2.projectPoints(X, rvec, truth[:3, 3], K, dist)[0].reshape(-1, 2)
    other = planar_alternative(x, X, truth, K, dist, 0.05)
    assert other is not None
    mirror, residuals = other
    assert np.median(residuals) < 1.0  # the face's points fit it about as well ...
    assert rotation_error_deg(truth[:3, :3], mirror[:3, :3]) > 30.0  # ... and it is far from the truth
    assert float(np.median(reprojection_errors(X, x, rvec, truth[:3, 3], K, dist))) < 1e-6
    renderer = get_renderer()
    w, h = frame.camera.width, frame.camera.height
    right, wrong = (renderer.render(model.content_hash, model.mesh, T, K, w, h) for T in (truth, mirror))
    lab = LazyLab(rgb, to_gray(rgb))
    assert frame_prefers(lab, wrong, right, 1.1) is None  # colour and edges alone keep the wrong pose
    assert score_prefers(lab, wrong, right, 0.02) is not None
    assert score_prefers(lab, right, wrong, 0.02) is None
