"""The plane search on a real YCB-Video frame with one found object: video 0001's mustard bottle, its plain back
to the camera (no SIFT pose), on the table under the sugar box alone (``plane.one_object_tilt_deg``), and a
placement followed from the previous frame set down on this frame's plane first."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from batchpose.config import PlaneConfig
from batchpose.core.frames import Camera, decode_image
from batchpose.io.mesh import load_mesh
from batchpose.method.appearance import N_BINS, colour_bins
from batchpose.method.plane import Target, search_plane
from batchpose.method.render import get_renderer
from batchpose.method.support import one_object_plane, resting_faces, stable_faces
from batchpose.method.views import fibonacci_directions, look_at
from tests.conftest import DATA, ycbv_dev_frame

FOUND, LOST = "004_sugar_box", "006_mustard_bottle"


def _target(model, renderer, K: np.ndarray) -> Target:
    """What the search needs of the mustard bottle: its colours from 16 views, as its library's would be."""
    hist = np.zeros(N_BINS)
    d = 2.5 * model.diameter_m
    for v in fibonacci_directions(16):
        rgb, depth = renderer.render(
            model.content_hash, model.mesh, look_at(d * v, np.zeros(3), np.array([0, 0, 1.0])), K, 640, 480
        )
        hist += np.bincount(colour_bins(rgb)[depth > 0], minlength=N_BINS)
    faces = resting_faces(stable_faces(model.mesh), PlaneConfig().min_stable)
    hull = np.asarray(model.mesh.convex_hull.vertices)
    return Target(hull, np.asarray(model.mesh.bounding_box.centroid), model.diameter_m, tuple(faces), hist / hist.sum())


@pytest.fixture(scope="module")
def scene(cache_dir):
    frame = ycbv_dev_frame("0001/000005")
    models = {n: load_mesh(DATA / "ycb_models" / n / "textured.obj", cache_dir=cache_dir) for n in (FOUND, LOST)}
    truth = {g.obj_name: g.cam_from_model for g in frame.gt}
    return frame, decode_image(frame), models, truth


def _adds_m(model, T: np.ndarray, truth: np.ndarray) -> float:
    pts = np.asarray(model.mesh.vertices)[::10]
    return float(cKDTree(pts @ truth[:3, :3].T + truth[:3, 3]).query(pts @ T[:3, :3].T + T[:3, 3])[0].mean())


def test_one_found_object_gives_the_table_the_plane_search_needs(scene):
    frame, rgb, models, truth = scene
    renderer = get_renderer()
    K = frame.camera.K
    sugar = models[FOUND]
    plane = one_object_plane(
        FOUND, truth[FOUND], sugar.mesh.convex_hull, resting_faces(stable_faces(sugar.mesh), 0.02), PlaneConfig()
    )
    assert plane is not None and plane.objects == (FOUND,)
    depth = renderer.render(sugar.content_hash, sugar.mesh, truth[FOUND], K, frame.camera.width, frame.camera.height)[1]
    covered, nearest = depth > 0, np.where(depth > 0, depth, np.inf).astype(np.float32)
    mustard = models[LOST]
    target = _target(mustard, renderer, K)

    def render(T, K_, w, h):
        return renderer.render(mustard.content_hash, mustard.mesh, T, Camera(K_, w, h).K, w, h)

    placed = search_plane(rgb, K, plane, target, covered, nearest, render, PlaneConfig())
    assert placed is not None and not placed.followed
    assert _adds_m(mustard, placed.cam_from_model, truth[LOST]) < 0.2 * mustard.diameter_m
    # Followed into the next frame from 3 cm above the table: set down on it, then refined.
    lifted = placed.cam_from_model.copy()
    lifted[:3, 3] += 0.03 * plane.normal
    followed = search_plane(rgb, K, plane, target, covered, nearest, render, PlaneConfig(), previous=lifted)
    assert followed is not None and followed.followed
    T = followed.cam_from_model
    lowest = ((target.hull @ T[:3, :3].T + T[:3, 3]) @ plane.normal).min()
    assert lowest == pytest.approx(plane.offset, abs=1e-3)
    assert _adds_m(mustard, T, truth[LOST]) < 0.2 * mustard.diameter_m
