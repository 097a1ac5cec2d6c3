"""benchmarks/as_shown.py: a frame rendered with its focal lengths scaled by s shows the object where the
ground truth would stand with its distance along the optical axis divided by s; scored against that pose."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from batchpose.io.mesh import load_mesh
from batchpose.method.render import get_renderer
from tests.conftest import CRACKER, K_SYN, load_benchmark


@pytest.fixture(scope="module")
def as_shown():
    return load_benchmark("as_shown")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_the_image_shows_the_truth_farther_by_the_scale(as_shown, tmp_path):
    model = load_mesh(CRACKER)
    renderer = get_renderer()
    R = np.array([[0.8, -0.6, 0.0], [0.3, 0.4, -0.866], [0.52, 0.69, 0.5]])
    R = np.linalg.svd(R)[0] @ np.linalg.svd(R)[2]  # the nearest rotation
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.12, -0.05, 0.9]
    s = 0.963  # the largest default disagreement, 3.7 %
    shown_K = K_SYN.copy()
    shown_K[:2, :2] *= s
    frame = renderer.render(model.content_hash, model.mesh, T, shown_K, 640, 480)[1] > 0

    scene = tmp_path / "000001"
    scene.mkdir()
    (scene / "shown_scale.json").write_text(json.dumps({"4": s}))
    gt = pd.DataFrame({"frame_id": ["000001/000004"], "obj_name": ["cracker"], "R": [R.ravel()], "t_m": [T[:3, 3]]})
    moved = as_shown.shown_truth(tmp_path, gt)
    assert np.allclose(moved["t_m"][0], [0.12, -0.05, 0.9 / s])
    assert np.allclose(gt["t_m"][0], [0.12, -0.05, 0.9])  # the run's ground truth is not touched
    T_shown = T.copy()
    T_shown[:3, 3] = moved["t_m"][0]
    at_shown = renderer.render(model.content_hash, model.mesh, T_shown, K_SYN, 640, 480)[1] > 0
    at_truth = renderer.render(model.content_hash, model.mesh, T, K_SYN, 640, 480)[1] > 0
    assert _iou(frame, at_shown) > 0.98
    assert _iou(frame, at_truth) < 0.94  # the truth itself does not look like the frame


def test_a_data_set_without_scales_is_a_one_line_error(as_shown, tmp_path):
    gt = pd.DataFrame({"frame_id": ["000001/000000"], "obj_name": ["x"], "R": [np.eye(3).ravel()], "t_m": [[0, 0, 1]]})
    with pytest.raises(SystemExit, match=r"000001/shown_scale.json does not exist"):
        as_shown.shown_truth(tmp_path, gt)
