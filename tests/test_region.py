"""One image region belongs to one object (batchpose/method/region.py): real YCB meshes at ground-truth
poses of real YCB-Video frames (the bundled demo's, and ycbv_dev's where ../shared/data is there), rendered;
the records are built by hand, so no estimate runs."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from batchpose.config import EstimatorConfig, RegionConfig
from batchpose.core.frames import decode_image
from batchpose.core.poses import STATUSES, PoseRecord
from batchpose.io.mesh import load_mesh
from batchpose.io.sources import open_frames
from batchpose.method.objects import Objects
from batchpose.method.region import claim_regions
from batchpose.method.render import get_renderer
from batchpose.method.sequence import Sequence
from batchpose.method.track import Track
from tests.conftest import DEMO, GELATIN, SHARED_DATA

#: The shared data (``../shared/data`` beside the repository, or ``$BATCHPOSE_SHARED_DATA``).
DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", SHARED_DATA))
CRACKER, BOX = "003_cracker_box", "009_gelatin_box"


def _frame(root: Path, frame_id: str):
    return next(iter(open_frames({"format": "ycbv", "root": str(root), "frame_ids": [frame_id]}, root)))


def _objects(models: dict, **region) -> Objects:
    """The objects of ``models`` (name -> ObjectModel) under the default config, ``region`` overridden."""
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


def _along_ray(pose: np.ndarray, factor: float) -> np.ndarray:
    """``pose`` moved along the line of sight to ``factor`` times its distance (same place in the image)."""
    out = pose.copy()
    out[:3, 3] *= factor
    return out


@pytest.fixture(scope="module")
def demo(cracker_model):
    """The demo's frame 0001/000001 (the cracker box 1.08 m away), its RGB, the cracker box's true pose, and
    the cracker and gelatin box meshes."""
    frame = _frame(DEMO / "ycbv", "0001/000001")
    truth = next(p.cam_from_model for p in frame.gt if p.obj_name == CRACKER)
    return frame, decode_image(frame), truth, {CRACKER: cracker_model, BOX: load_mesh(GELATIN)}


def test_a_pose_laid_on_another_objects_pixels_loses_to_the_one_that_looks_like_them(demo):
    """The gelatin box (the same brand's print as other boxes) put on the cracker box's true pose, claiming
    the cracker box's keypoints, tracked and more confident: the verification keeps the cracker box; the
    gelatin box is ``conflict``, naming it, and leaves the sequence (its track and last pose)."""
    frame, rgb, truth, models = demo
    objects = _objects(models)
    _, depth = objects.render(CRACKER, truth, frame.camera)
    seen = _evidence(depth)
    right = _record(frame, CRACKER, truth, seen, 0.6)
    wrong = _record(frame, BOX, truth, seen[::2], 0.8, tracked=True)
    sequence = Sequence()
    sequence.tracks[BOX] = Track(seen, np.zeros((len(seen), 3)), truth, len(seen), 0.8)
    sequence.last[BOX] = wrong.cam_from_model
    claim_regions(objects, frame, rgb, [right, wrong], sequence)
    assert right.status == "ok" and right.reason == ""
    assert wrong.status == "conflict" and "conflict" in STATUSES
    assert wrong.reason.startswith(f"claims the pixels of {CRACKER}")
    assert BOX not in sequence.tracks and BOX not in sequence.last
    assert right.timings["refine"] > 0  # the renders' time is the pair's
    # Swapped in the list and in confidence: the same verdict (the render decides, not the order or confidence)
    right.confidence, wrong.status, wrong.confidence = 0.4, "ok", 0.9
    claim_regions(objects, frame, rgb, [wrong, right], Sequence())
    assert (right.status, wrong.status) == ("ok", "conflict")
    wrong.status = "ok"  # off: both stay ok
    claim_regions(_objects(models, max_overlap=0), frame, rgb, [right, wrong], Sequence())
    assert right.ok and wrong.ok


def test_an_object_in_front_of_another_keeps_both_unless_one_could_not_be_seen(demo):
    """The gelatin box halfway between the camera and the cracker box hides part of it: with the cracker box's
    keypoints on what the gelatin box leaves visible, both stay ok. With the cracker box's keypoints under the
    gelatin box instead (pixels that show the gelatin box if it is there), the two cannot both be right and
    the frame there is the cracker box's. And the gelatin box behind the cracker box, its keypoints on the
    cracker box's pixels: it could be seen there only in front, a conflict too."""
    frame, rgb, truth, models = demo
    objects = _objects(models)
    near = _along_ray(truth, 0.5)
    _, back = objects.render(CRACKER, truth, frame.camera)
    _, front = objects.render(BOX, near, frame.camera)
    box = _record(frame, BOX, near, _evidence(front), 0.9)
    cracker = _record(frame, CRACKER, truth, _evidence(np.where(front > 0, 0.0, back)), 0.5)
    claim_regions(objects, frame, rgb, [box, cracker], Sequence())
    assert box.ok and cracker.ok
    cracker.inliers_px = _evidence(np.where(front > 0, back, 0.0))
    claim_regions(objects, frame, rgb, [box, cracker], Sequence())
    assert cracker.ok and box.status == "conflict"
    far = _along_ray(truth, 1.3)
    _, behind = objects.render(BOX, far, frame.camera)
    hidden = _record(frame, BOX, far, _evidence(behind), 0.9)
    cracker.inliers_px = _evidence(np.where(behind > 0, 0.0, back))  # the cracker box's evidence: not under it
    claim_regions(objects, frame, rgb, [hidden, cracker], Sequence())
    assert cracker.ok and hidden.status == "conflict"


def test_objects_apart_are_not_rendered(demo):
    """Poses whose projected hulls do not meet: no render (no time recorded), both ok."""
    frame, rgb, truth, models = demo
    aside = truth.copy()
    aside[0, 3] += 0.5  # half a metre to the side of the cracker box
    a = _record(frame, CRACKER, truth, np.zeros((0, 2)), 0.9)
    b = _record(frame, BOX, aside, np.zeros((0, 2)), 0.9)
    claim_regions(_objects(models), frame, rgb, [a, b], Sequence())
    assert a.ok and b.ok and "refine" not in a.timings and "refine" not in b.timings


@pytest.mark.skipif(not (DATA / "ycbv_dev").is_dir(), reason=f"shared ycbv_dev data not at {DATA}")
def test_a_real_occlusion_keeps_both_poses(cracker_model):
    """ycbv_dev's data_syn/000005: the cracker box in front of the sugar box (0.71 and 0.93 m away), their
    silhouettes sharing 41 % of the sugar box's. The true poses, the sugar box's keypoints on its pixels the
    cracker box does not hide: both stay ok, even with ``max_overlap`` below the 41 %."""
    frame = _frame(DATA / "ycbv_dev", "data_syn/000005")
    truth = {p.obj_name: p.cam_from_model for p in frame.gt}
    sugar = "004_sugar_box"
    models = {CRACKER: cracker_model, sugar: load_mesh(DATA / "ycb_models" / sugar / "textured.obj")}
    objects = _objects(models, max_overlap=0.3)
    front, back = (objects.render(n, truth[n], frame.camera)[1] for n in (CRACKER, sugar))
    records = [
        _record(frame, CRACKER, truth[CRACKER], _evidence(front), 0.5),
        _record(frame, sugar, truth[sugar], _evidence(np.where(front > 0, 0.0, back)), 0.9),
    ]
    claim_regions(objects, frame, decode_image(frame), records, Sequence())
    assert all(r.ok for r in records)
    assert (front > 0).sum() > 0 and ((front > 0) & (back > 0)).sum() > 0.3 * (back > 0).sum()


def test_renders_that_match_alike_leave_it_to_the_confidence(demo):
    """Two objects with the same mesh at the same pose: their renders match the frame exactly alike, so the
    more confident pose is kept, whichever comes first."""
    frame, rgb, truth, models = demo
    objects = _objects({"a": models[BOX], "b": models[BOX]})
    _, depth = objects.render("a", truth, frame.camera)
    for first, second in ((0.9, 0.5), (0.5, 0.9)):
        a = _record(frame, "a", truth, _evidence(depth), first)
        b = _record(frame, "b", truth, _evidence(depth), second)
        claim_regions(objects, frame, rgb, [a, b], Sequence())
        kept, lost = (a, b) if first > second else (b, a)
        assert kept.ok and lost.status == "conflict" and "the more confident pose kept" in lost.reason
