"""One image region belongs to one object (batchpose/method/region.py): real YCB meshes at ground-truth
poses of real ycbv_dev frames, rendered; records built by hand, so no estimate runs."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from batchpose.config import EstimatorConfig, RegionConfig
from batchpose.core.frames import decode_image
from batchpose.core.poses import STATUSES, PoseRecord
from batchpose.method.objects import Objects
from batchpose.method.region import claim_regions
from batchpose.method.sequence import Sequence
from batchpose.method.track import Track
from tests.conftest import SHARED_DATA

#: The shared data (``../shared/data`` beside the repository, or ``$BATCHPOSE_SHARED_DATA``).
DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", SHARED_DATA))
pytestmark = pytest.mark.skipif(not (DATA / "ycbv_dev").is_dir(), reason=f"shared ycbv_dev data not at {DATA}")


def _frame(frame_id: str):
    from batchpose.io.sources import open_frames  # noqa: PLC0415

    source = open_frames({"format": "ycbv", "root": str(DATA / "ycbv_dev")}, DATA)
    return next(f for f in source if f.frame_id == frame_id)


def _objects(models: dict, **region) -> Objects:
    """The objects of ``models`` (name -> ObjectModel) under the default config, ``region`` overridden."""
    from batchpose.method.render import get_renderer  # noqa: PLC0415

    conf = dataclasses.replace(EstimatorConfig(), region=RegionConfig(**region))
    return Objects(conf, {}, models=models, renderer=get_renderer())


def _evidence(depth: np.ndarray, step: int = 6) -> np.ndarray:
    """(N, 2) pixels on a grid over where ``depth`` > 0: keypoints on what a render shows."""
    ys, xs = np.nonzero(depth > 0)
    keep = (xs % step == 0) & (ys % step == 0)
    return np.stack([xs[keep], ys[keep]], axis=1).astype(float)


def _record(frame, name: str, pose: np.ndarray, evidence: np.ndarray, confidence: float, tracked=False):
    return PoseRecord(
        frame.frame_id,
        name,
        "ok",
        cam_from_model=pose.copy(),
        confidence=confidence,
        n_inliers=len(evidence),
        inliers_px=evidence,
        tracked=tracked,
    )


@pytest.fixture(scope="module")
def boxes(cache_dir):
    """data_syn/000005: the cracker box in front of the sugar box (0.71 and 0.93 m away; the two silhouettes
    share 41 % of the sugar box's), the frame's RGB, its ground truth, the two meshes."""
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415

    frame = _frame("data_syn/000005")
    gt = {p.obj_name: p.cam_from_model for p in frame.gt}
    names = ("003_cracker_box", "004_sugar_box")
    models = {n: load_mesh(DATA / "ycb_models" / n / "textured.obj", cache_dir=cache_dir) for n in names}
    return frame, decode_image(frame), gt, models


def test_a_pose_laid_on_another_objects_pixels_loses_to_the_one_that_looks_like_them(boxes):
    """The sugar box put at the cracker box's true pose, claiming the cracker box's keypoints, and more
    confident: the verification keeps the cracker box, the sugar box is ``conflict``, naming it, and leaves
    the sequence (its track and last pose)."""
    frame, rgb, gt, models = boxes
    objects = _objects(models)
    cracker = gt["003_cracker_box"]
    _, depth = objects.render("003_cracker_box", cracker, frame.camera)
    seen = _evidence(depth)
    right = _record(frame, "003_cracker_box", cracker, seen, 0.6)
    wrong = _record(frame, "004_sugar_box", cracker, seen[::2], 0.8, tracked=True)
    sequence = Sequence()
    sequence.tracks["004_sugar_box"] = Track(seen, np.zeros((len(seen), 3)), cracker, len(seen), 0.8)
    sequence.last["004_sugar_box"] = wrong.cam_from_model
    records = [right, wrong]
    claim_regions(objects, frame, rgb, records, sequence)
    assert right.status == "ok" and right.reason == ""
    assert wrong.status == "conflict" and "conflict" in STATUSES
    assert wrong.reason.startswith("claims the pixels of 003_cracker_box")
    assert "004_sugar_box" not in sequence.tracks and "004_sugar_box" not in sequence.last
    # Swapped in the list and in confidence: the same verdict (the render decides, not the order or confidence)
    right.status, wrong.status, right.confidence, wrong.confidence = "ok", "ok", 0.9, 0.4
    claim_regions(objects, frame, rgb, [wrong, right], Sequence())
    assert (right.status, wrong.status) == ("ok", "conflict")
    # Off: both stay ok
    wrong.status = "ok"
    claim_regions(_objects(models, max_overlap=0), frame, rgb, records, sequence)
    assert right.ok and wrong.ok


def test_a_real_occlusion_keeps_both_poses(boxes):
    """The true poses, the sugar box's evidence on its pixels the cracker box does not hide: both stay ok, even
    with ``max_overlap`` below their 41 %. The same sugar box with its evidence under the cracker box (the
    cracker box's own pixels) cannot be behind it and seen: a conflict, which the cracker box wins."""
    frame, rgb, gt, models = boxes
    names = ["003_cracker_box", "004_sugar_box"]
    objects = _objects(models, max_overlap=0.3)
    front, back = (objects.render(n, gt[n], frame.camera)[1] for n in names)
    visible_back = np.where((front > 0) & (front < back), 0.0, back)
    cracker = _record(frame, names[0], gt[names[0]], _evidence(front), 0.5)
    sugar = _record(frame, names[1], gt[names[1]], _evidence(visible_back), 0.9)
    claim_regions(objects, frame, rgb, [cracker, sugar], Sequence())
    assert cracker.ok and sugar.ok
    hidden_back = np.where((front > 0) & (back > 0), back, 0.0)
    sugar.inliers_px = _evidence(hidden_back)
    claim_regions(objects, frame, rgb, [cracker, sugar], Sequence())
    assert cracker.ok and sugar.status == "conflict"


def test_objects_apart_are_not_rendered(boxes):
    """Poses whose projected hulls do not meet: no render (no time recorded), both ok."""
    frame, rgb, gt, models = boxes
    objects = _objects(models)
    aside = gt["004_sugar_box"].copy()
    aside[0, 3] += 0.5  # half a metre to the side: off the cracker box
    a = _record(frame, "003_cracker_box", gt["003_cracker_box"], np.zeros((0, 2)), 0.9)
    b = _record(frame, "004_sugar_box", aside, np.zeros((0, 2)), 0.9)
    claim_regions(objects, frame, rgb, [a, b], Sequence())
    assert a.ok and b.ok and "refine" not in a.timings and "refine" not in b.timings
