"""``verified_tracks``: a shiny object whose scan renders in colours the frame does not show (the tuna can's
metal lid in YCB-Video's video 0049) starts a track at its true pose when the verification score passes,
though the texture match fails; a pose 3 cm beside it starts none either way."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from batchpose.config import EstimatorConfig
from batchpose.core.frames import decode_image
from batchpose.core.poses import PoseRecord
from batchpose.io.mesh import load_mesh
from batchpose.method.appearance import texture_match
from batchpose.method.features import to_gray
from batchpose.method.objects import Objects
from batchpose.method.render import get_renderer
from batchpose.method.score import FrameEdges, compare
from batchpose.method.tracked import seed_track
from tests.conftest import DATA, ycbv_dev_frame

NAME = "007_tuna_fish_can"


@pytest.fixture(scope="module")
def scene(cache_dir):
    frame = ycbv_dev_frame("0049/000010")
    model = load_mesh(DATA / "ycb_models" / NAME / "textured.obj", cache_dir=cache_dir)
    truth = next(g.cam_from_model for g in frame.gt if g.obj_name == NAME)
    return frame, decode_image(frame), model, truth


def _objects(model, verified: bool) -> Objects:
    conf = dataclasses.replace(EstimatorConfig(), verified_tracks=verified)
    return Objects(conf, {}, {NAME: 6}, {NAME: model}, get_renderer())


def test_a_shiny_can_is_tracked_where_the_score_passes_and_the_texture_fails(scene):
    frame, rgb, model, truth = scene
    look, gray = FrameEdges(rgb), to_gray(rgb)
    beside = truth.copy()
    beside[0, 3] += 0.03
    objects = _objects(model, True)
    ren, depth = objects.render(NAME, truth, frame.camera)
    seen = depth > 0
    assert texture_match(look.lab[seen], ren[seen]) < objects.conf.track.min_match
    found = compare(look, ren, depth, seen)
    assert found is not None and found.score() >= objects.conf.min_verification

    def starts(pose: np.ndarray, verified: bool) -> bool:
        rec = PoseRecord(frame.frame_id, NAME, "ok", cam_from_model=pose, confidence=0.9)
        return seed_track(_objects(model, verified), NAME, gray, rec, frame.camera, (), look) is not None

    assert starts(truth, True)
    assert not starts(truth, False)
    assert not starts(beside, True)
