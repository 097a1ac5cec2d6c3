"""Frames larger than ``max_image_side_px``: estimated resized, reported for the full frame."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from batchpose.config import ConfigError, EstimatorConfig, from_dict, validate
from batchpose.core.frames import Camera, Frame, working_camera
from batchpose.method.estimator import PoseEstimator
from batchpose.method.render import get_renderer
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import add_error, random_pose, textured_background


def test_working_camera_sees_the_resized_image():
    K = np.array([[1210.0, 0.3, 955.2], [0.0, 1205.0, 541.7], [0.0, 0.0, 1.0]])
    cam = Camera(K, 1920, 1080, np.array([0.1, -0.05, 0.001, 0.0, 0.01]), "plumb_bob")
    small, scale = working_camera(cam, 640)
    assert (small.width, small.height) == (640, 360)
    np.testing.assert_allclose(scale, [1 / 3, 1 / 3])
    X = np.random.default_rng(0).uniform([-0.3, -0.2, 0.5], [0.3, 0.2, 2.0], (50, 3))
    full = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    resized = cv2.projectPoints(X, np.zeros(3), np.zeros(3), small.K, small.dist)[0].reshape(-1, 2)
    # Pixel centres at integer coordinates: a full-frame pixel x lands at (x + 0.5) s - 0.5.
    np.testing.assert_allclose(resized, (full + 0.5) * scale - 0.5, atol=1e-9)
    assert working_camera(cam, 0)[0] is cam and working_camera(cam, 1920)[0] is cam


def test_max_image_side_px_is_checked():
    with pytest.raises(ConfigError, match="max_image_side_px must be 0 .* or >= 160, got 100"):
        validate(from_dict(EstimatorConfig, {"max_image_side_px": 100}, "p.yaml"), "p.yaml")


@pytest.mark.slow
def test_an_hd_frame_is_estimated_resized_and_reported_full_size(cracker_model, cracker_library):
    # The cracker box seen by a 1280x960 camera; estimated at 640x480, where the library was rendered.
    rng = np.random.default_rng(32)
    T = random_pose(rng, cracker_model.center_m)
    hd, _ = working_camera(Camera(K_SYN, 640, 480), 640)  # K_SYN itself
    K_hd = K_SYN.copy()
    K_hd[:2] *= 2.0
    K_hd[:2, 2] = 2.0 * (K_SYN[:2, 2] + 0.5) - 0.5
    rgb, depth = get_renderer().render(cracker_model.content_hash, cracker_model.mesh, T, K_hd, 1280, 960, "lit")
    img = textured_background(rng, 1280, 960)
    img[depth > 0] = rgb[depth > 0]
    frame = Frame("hd", 0, 0, 0, Camera(K_hd, 1280, 960), "png", cv2.imencode(".png", img[:, :, ::-1])[1].tobytes())
    conf = dataclasses.replace(EstimatorConfig(), max_image_side_px=640)
    est = PoseEstimator(conf, {cracker_model.name: cracker_library}, models={cracker_model.name: cracker_model},
                        renderer=get_renderer())  # fmt: skip
    assert working_camera(frame.camera, 640)[0].K == pytest.approx(hd.K)
    (rec,) = est.estimate_frame(frame, [cracker_model.name])
    assert rec.ok, rec.reason
    pts = np.asarray(cracker_model.mesh.vertices)[::8]
    assert add_error(rec.cam_from_model, T, pts) < 0.02 * cracker_model.diameter_m
    # The inlier points are the full frame's pixels: on the object there, not in the frame's top-left quarter.
    on_object = cv2.dilate((depth > 0).astype(np.uint8), np.ones((9, 9), np.uint8))
    xy = np.round(rec.inliers_px).astype(int)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < 1280) & (xy[:, 1] >= 0) & (xy[:, 1] < 960)
    assert len(xy) >= 15 and inside.all()
    assert on_object[xy[:, 1], xy[:, 0]].mean() > 0.95
