"""Shape search (shape.*): edge templates find an object SIFT cannot match, colour refines its pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from batchpose.config import ConfigError, EstimatorConfig, ShapeConfig, load_estimator_config
from batchpose.estimate import PoseEstimator
from batchpose.features import to_gray
from batchpose.frames import Camera
from batchpose.render import get_renderer
from batchpose.shape import ShapeBank, colour_score, edge_image, pose_from, refine_colour, search
from tests.conftest import K_SYN
from tests.test_estimate_synthetic import compose, random_pose

SMALL = ShapeConfig(
    enabled=True, view_step=4, angle_step_deg=30.0, scales_per_octave=2, hypotheses=3, refine_renders=120
)


def adds_m(T, T_gt, pts):
    return float(cKDTree(pts @ T[:3, :3].T + T[:3, 3]).query(pts @ T_gt[:3, :3].T + T_gt[:3, 3])[0].mean())


def render_fn(model, K=K_SYN):
    return lambda T: get_renderer().render(model.content_hash, model.mesh, T, K, 640, 480, "flat")


def test_shape_search_is_off_by_default_and_checks_its_settings():
    assert EstimatorConfig().shape.enabled is False
    with pytest.raises(ConfigError, match="shape.level"):
        load_estimator_config({"shape": {"level": 0}})


def test_edge_templates_find_the_object_and_colour_refines_it(cracker_model, cracker_library):
    rng = np.random.default_rng(11)
    T_gt = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T_gt)
    bank = ShapeBank(
        render_fn(cracker_model, cracker_library.K),
        cracker_library,
        K_SYN[0, 0],
        (640, 480),
        cracker_model.diameter_m,
        SMALL,
    )
    hits = search(bank, edge_image(to_gray(img), SMALL.level), 3)
    centre_gt = K_SYN @ (T_gt[:3, :3] @ cracker_model.center_m + T_gt[:3, 3])
    centre_gt = centre_gt[:2] / centre_gt[2]
    span_gt = K_SYN[0, 0] * cracker_model.diameter_m / centre_gt_depth(T_gt, cracker_model)
    best = hits[0]
    # The best template sits on the object at about its size (the grid is coarse: half octaves, 30 degrees).
    assert np.linalg.norm(best.centre_xy - centre_gt) < 0.25 * span_gt
    assert abs(best.depth_m / centre_gt_depth(T_gt, cracker_model) - 1) < 0.3
    pts = cracker_library.pts3d.astype(float)
    render = render_fn(cracker_model)
    start = pose_from(cracker_library, best, K_SYN)
    refined, score, renders = refine_colour(render, img, start, cracker_model.center_m, SMALL.refine_renders)
    assert renders <= SMALL.refine_renders + 12
    assert score >= colour_score(render, img, start)
    assert colour_score(render, img, T_gt) > 0.3  # the true pose: the frame looks like the mesh inside, not around
    assert adds_m(refined, T_gt, pts) < 0.04


def centre_gt_depth(T, model) -> float:
    return float((T[:3, :3] @ model.center_m + T[:3, 3])[2])


def test_estimator_falls_back_to_the_shape_search_when_sift_finds_nothing(cracker_model, cracker_library):
    """With SIFT's contrast threshold so high that the frame has no keypoints, the default returns
    too_few_matches; with shape.enabled the object is found by its outline and colour."""
    rng = np.random.default_rng(11)
    T_gt = random_pose(rng, cracker_model.center_m)
    img = compose(rng, cracker_model, T_gt)
    blind = dataclasses.replace(EstimatorConfig().features, contrast_threshold=1.0)
    recs = {}
    for enabled in (False, True):
        conf = dataclasses.replace(EstimatorConfig(), features=blind, shape=dataclasses.replace(SMALL, enabled=enabled))
        est = PoseEstimator(
            conf,
            {cracker_model.name: cracker_library},
            models={cracker_model.name: cracker_model},
            renderer=get_renderer(),
        )
        recs[enabled] = est.estimate_image(img, Camera(K_SYN, 640, 480), [cracker_model.name])[0]
    assert recs[False].status == "too_few_matches"
    rec = recs[True]
    assert rec.ok and "shape search" in rec.reason and 0 < rec.confidence < 0.5
    assert rec.timings["shape"] > 0
    assert adds_m(rec.cam_from_model, T_gt, cracker_library.pts3d.astype(float)) < 0.04
