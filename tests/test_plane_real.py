"""The plane search on a real YCB-Video frame: video 0001's mustard bottle, its plain back to the camera (no SIFT
pose), on the table under the sugar box alone (``plane.one_object_tilt_deg``); a placement followed from the
previous frame set down on this frame's plane first; and the bottle under the chef can and the cracker box with
the sugar box in front of it not asked for (``plane.occluder_cuts``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from batchpose.config import PlaneConfig
from batchpose.core.frames import Camera, decode_image
from batchpose.io.mesh import load_mesh
from batchpose.method.appearance import N_BINS, colour_bins
from batchpose.method.plane import Target, search_plane
from batchpose.method.render import get_renderer
from batchpose.method.support import one_object_plane, resting_faces, stable_faces, support_plane
from batchpose.method.views import fibonacci_directions, look_at
from tests.conftest import DATA, ycbv_dev_frame

FOUND, LOST = "004_sugar_box", "006_mustard_bottle"
OTHERS = ("002_master_chef_can", "003_cracker_box")  # the video's other two objects, behind the bottle


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


# The chef can's and the cracker box's poses the default estimate gives them in frame 1 (3-4 % farther than
# the ground truth, as the frame shows them): the table under them is the one the search is given in a run.
ESTIMATED = {
    "002_master_chef_can": (
        [[0.99503, -0.08081, 0.05816], [0.00237, -0.56478, -0.82524], [0.09954, 0.82128, -0.56178]],
        [-0.03319, 0.13466, 0.99176],
    ),
    "003_cracker_box": (
        [[-0.68682, -0.72052, 0.09554], [-0.4875, 0.35917, -0.79583], [0.5391, -0.59316, -0.59794]],
        [-0.07748, 0.00611, 1.09668],
    ),
}


def test_an_object_not_asked_for_in_front_does_not_hide_the_bottle(cache_dir):
    """Frame 1, the chef can and the cracker box found, the sugar box in front of the bottle's lower half not
    asked for: nothing explains its pixels. Over the whole silhouette the bottle's colours and texture fail
    the checks; with its lower band left out (``occluder_cuts``) they pass, at the bottle."""
    frame = ycbv_dev_frame("0001/000001")
    rgb, truth = decode_image(frame), {g.obj_name: g.cam_from_model for g in frame.gt}
    models = {n: load_mesh(DATA / "ycb_models" / n / "textured.obj", cache_dir=cache_dir) for n in (LOST, *OTHERS)}
    renderer = get_renderer()
    K, w, h = frame.camera.K, frame.camera.width, frame.camera.height
    poses = {n: np.vstack([np.c_[np.array(R), np.array(t)], [0.0, 0.0, 0.0, 1.0]]) for n, (R, t) in ESTIMATED.items()}
    found = {n: (poses[n], models[n].mesh.convex_hull) for n in OTHERS}
    plane = support_plane(found, PlaneConfig(), {n: stable_faces(models[n].mesh)[0] for n in OTHERS})
    assert plane is not None and set(plane.objects) == set(OTHERS)
    covered, nearest = np.zeros((h, w), bool), np.full((h, w), np.inf, np.float32)
    for n in OTHERS:
        depth = renderer.render(models[n].content_hash, models[n].mesh, poses[n], K, w, h)[1]
        covered |= depth > 0
        nearest = np.where(depth > 0, np.minimum(nearest, depth), nearest)
    mustard = models[LOST]
    target = _target(mustard, renderer, K)

    def render(T, K_, w_, h_):
        return renderer.render(mustard.content_hash, mustard.mesh, T, Camera(K_, w_, h_).K, w_, h_)

    whole = dataclasses.replace(PlaneConfig(), occluder_cuts=())
    assert search_plane(rgb, K, plane, target, covered, nearest, render, whole) is None
    placed = search_plane(rgb, K, plane, target, covered, nearest, render, PlaneConfig())
    assert placed is not None
    assert _adds_m(mustard, placed.cam_from_model, truth[LOST]) < 0.1 * mustard.diameter_m
    assert 0.5 < placed.visible < 0.7  # the band the sugar box hides is left out
