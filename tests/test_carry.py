"""The carry stage (batchpose/stages/carry.py, batchpose/method/carry.py) on four consecutive real YCB-Video
frames (video 0000, the gelatin box): poses carried backwards (two frames, chained) and forwards into frames
where the estimate found none come within a few millimetres of the truth; a carry that fails its checks
leaves the pair as the estimate made it; the stage skips what it has done."""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from batchpose.config import EstimatorConfig
from batchpose.core.poses import PoseRecord, row_cam_from_model
from batchpose.io.folders import YcbvFrameSource
from batchpose.io.mesh import load_mesh
from batchpose.method.objects import Objects
from batchpose.report.metrics import adds
from batchpose.report.precision import pose_table, trust
from batchpose.stages import carry as carry_stage
from tests.conftest import SHARED_DATA

DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", SHARED_DATA))
NAME = "009_gelatin_box"


@pytest.fixture(scope="module")
def frames():
    root = DATA / "ycbv_dev"
    if not root.is_dir():
        pytest.skip(f"shared YCB-Video dev data not at {root} (set BATCHPOSE_SHARED_DATA)")
    source = YcbvFrameSource(root)
    return [f for f, _ in zip(source, range(4), strict=False)], next(f for f in source if f.frame_id == "0049/000001")


@pytest.fixture(scope="module")
def objects(cache_dir):
    from batchpose.method.render import get_renderer

    model = load_mesh(DATA / "ycb_models" / NAME / "textured.obj", cache_dir=cache_dir)
    return Objects(EstimatorConfig(), {}, {NAME: 9}, {NAME: model}, get_renderer())


def _truth(frame) -> np.ndarray:
    return next(g.cam_from_model for g in frame.gt if g.obj_name == NAME)


def _estimated(frames, missing: set[str]) -> pd.DataFrame:
    """The estimate's rows: the true pose, 0.9 confident, in every frame but ``missing`` (too_few_matches)."""
    rows = []
    for f in frames:
        if f.frame_id in missing:
            rec = PoseRecord(f.frame_id, NAME, "too_few_matches", "3 matches", f.scene_id, f.im_id, f.stamp_ns, 9)
        else:
            rec = PoseRecord(f.frame_id, NAME, "ok", "", f.scene_id, f.im_id, f.stamp_ns, 9, _truth(f), 0.9)
        rec.timings = {"sift": 0.5}
        rows.append(rec.to_row())
    return pd.DataFrame(rows)


def _adds_mm(objects, frame, row) -> float:
    est = row_cam_from_model(row)
    true = _truth(frame)
    pts = objects.models[NAME].mesh.vertices
    return 1000 * adds(est[:3, :3], est[:3, 3], true[:3, :3], true[:3, 3], pts)


def test_poses_carried_backwards_and_forwards_come_back_to_the_truth(frames, objects):
    """Frames 1 and 2 missing (carried backwards from 3, chained) and frame 4 (forwards from 3): all three
    within 1 cm ADD-S (0.1 of the box's 10.8 cm diameter), marked carried and tracked, reason naming the
    source, the estimate's time kept in the row's."""
    seq, _ = frames
    ids = [f.frame_id for f in seq]
    estimated = _estimated(seq, {ids[0], ids[1], ids[3]})
    conf = objects.conf
    gaps = carry_stage.plan(conf, estimated, carry_stage.sequences(iter(seq), conf.track.max_gap_s))
    assert [(g.forward, g.backward) for g in gaps] == [
        ([], [ids[2], ids[1], ids[0]]),
        ([ids[2], ids[3]], []),
    ]
    carried = pd.DataFrame(carry_stage.carry_gaps(objects, gaps, {f.frame_id: f for f in seq}))
    df = carry_stage.overlay(estimated, carried)
    assert df["carried"].tolist() == [True, True, False, True]
    assert (df["status"] == "ok").all() and df.loc[df["carried"], "tracked"].all()
    by_id = {r["frame_id"]: r for r in df.to_dict("records")}
    assert by_id[ids[0]]["reason"].startswith(f"carried backwards from {ids[2]} (2 frames); the estimate: too_few")
    assert by_id[ids[3]]["reason"].startswith(f"carried forwards from {ids[2]} (1 frame)")
    errors = [_adds_mm(objects, f, by_id[f.frame_id]) for f in (seq[0], seq[1], seq[3])]
    assert max(errors) < 10, errors
    assert all(by_id[i]["time_sift_s"] == 0.5 and by_id[i]["time_track_s"] > 0 for i in (ids[0], ids[1], ids[3]))
    assert 0.5 <= by_id[ids[0]]["confidence"] <= 0.9
    # summary.csv's n_carried, n_carried_correct (ADD-S < 0.2 d)
    gt = pd.DataFrame(
        [
            {"frame_id": f.frame_id, "obj_name": NAME, "R": _truth(f)[:3, :3].ravel(), "t_m": _truth(f)[:3, 3]}
            for f in seq
        ]
    )
    model = objects.models[NAME]
    table = pose_table(df, gt, {NAME: model.mesh.vertices}, {NAME: model.diameter_m})
    t = trust(table, table.iloc[:0].assign(ok=False), len(gt))
    assert (t.n_carried, t.n_carried_correct, t.ok_recall) == (3, 3, 1.0)


def test_a_weak_source_is_carried_only_past_the_weak_pose_check(frames, objects):
    """With ``carry.min_confidence`` 0.3, a 0.4-confident source is carried, and its carried pose (never more
    confident than its source, so under ``verify_below``) must pass the weak-pose check too: the true pose
    does (within 1 cm)."""
    seq, _ = frames
    conf = dataclasses.replace(objects.conf, carry=dataclasses.replace(objects.conf.carry, min_confidence=0.3))
    weak = Objects(conf, {}, objects.obj_ids, objects.models, objects.renderer)
    estimated = _estimated(seq[:2], {seq[1].frame_id}).assign(confidence=lambda d: d["confidence"] * 0.4 / 0.9)
    gaps = carry_stage.plan(conf, estimated, carry_stage.sequences(iter(seq[:2]), conf.track.max_gap_s))
    rows = carry_stage.carry_gaps(weak, gaps, {f.frame_id: f for f in seq[:2]})
    assert len(rows) == 1 and rows[0]["confidence"] <= 0.4 < conf.verify_below
    assert _adds_mm(weak, seq[1], rows[0]) < 10


def test_a_carry_that_fails_its_checks_leaves_the_pair_unchanged(frames, objects, caplog):
    """Frame 2 holds another video's image (the box is not there): the flow or the check against the mesh
    fails, nothing is carried, and the pair keeps the estimate's row; a source pose under
    ``carry.min_confidence`` starts no carry at all."""
    seq, elsewhere = frames
    ids = [f.frame_id for f in seq]
    swapped = [seq[0], dataclasses.replace(seq[1], image_data=elsewhere.image_data)]
    estimated = _estimated(swapped, {ids[1]})
    conf = objects.conf
    gaps = carry_stage.plan(conf, estimated, carry_stage.sequences(iter(swapped), conf.track.max_gap_s))
    assert len(gaps) == 1
    with caplog.at_level(logging.DEBUG, logger="batchpose"):
        carried = pd.DataFrame(carry_stage.carry_gaps(objects, gaps, {f.frame_id: f for f in swapped}))
    assert carried.empty
    assert f"{NAME} forwards {ids[0]}: {ids[1]}: track lost" in caplog.text  # seeded, then the check failed
    df = carry_stage.overlay(estimated, carried)
    pd.testing.assert_frame_equal(df.drop(columns="carried"), estimated.drop(columns="carried"))
    assert not df["carried"].any()
    weak = estimated.assign(confidence=np.where(estimated["status"] == "ok", 0.4, 0.0))
    unswapped = [seq[0], seq[1]]
    assert carry_stage.plan(conf, weak, carry_stage.sequences(iter(unswapped), conf.track.max_gap_s)) == []


def test_stage_rewrites_poses_and_skips_what_it_has_done(frames, tmp_path, cache_dir, caplog):
    """``main`` on a run directory holding the estimate's shard: poses.parquet gets the carried pose,
    carry.json its count; a second call skips the stage; without carry.json it reuses the group's file."""
    seq, _ = frames
    ids = [f.frame_id for f in seq]
    estimated = _estimated(seq, {ids[0]})
    (tmp_path / "shards").mkdir()
    estimated.to_parquet(tmp_path / "shards" / "shard-c000000.parquet", index=False)
    conf = EstimatorConfig()
    inputs = carry_stage.CarryInputs(
        YcbvFrameSource(DATA / "ycbv_dev"),
        {NAME: 9},
        {NAME: DATA / "ycb_models" / NAME / "textured.obj"},
        limit=4,
        frame_ids=set(ids),
        mesh_cache=cache_dir,
        jobs=1,
    )
    with caplog.at_level(logging.INFO, logger="batchpose"):
        out = carry_stage.main(conf, inputs, tmp_path)
        df = pd.read_parquet(out)
        assert df["carried"].tolist() == [True, False, False, False]
        assert (
            "carried 1 of the 1 pairs without a pose within carry.max_steps of a confident one (0 forwards, "
            in caplog.text
        )
        caplog.clear()
        carry_stage.main(conf, inputs, tmp_path)
        assert "Skipping carry" in caplog.text
        (tmp_path / "carry.json").unlink()
        caplog.clear()
        carry_stage.main(conf, inputs, tmp_path)
        assert "Resuming carry: 1 of 1 groups" in caplog.text
    pd.testing.assert_frame_equal(pd.read_parquet(out), df)
    assert carry_stage.main(dataclasses.replace(conf, carry=dataclasses.replace(conf.carry, enabled=False)),
                            inputs, tmp_path) == out  # fmt: skip


def test_a_weak_pose_the_neighbours_contradict_gives_way_to_the_carried_one(frames, objects):
    """``carry.over_weak``: frame 2's estimate is a weak ok pose (0.35 confident, untracked) turned half round
    and 10 cm farther than the truth, scored 0.9: the pose carried from frame 1 scores higher, replaces it
    (within 1 cm) and its reason names what the estimate had. Scored 1.0 (no carried pose can beat it), the
    estimate's pose stays; with ``over_weak`` off, or without the verification score, no carry is tried."""
    seq, _ = frames
    first, second = seq[0], seq[1]
    wrong = _truth(second).copy()
    wrong[:3, :3] = wrong[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    wrong[:3, 3] *= (np.linalg.norm(wrong[:3, 3]) + 0.1) / np.linalg.norm(wrong[:3, 3])
    weak = PoseRecord(
        second.frame_id, NAME, "ok", "found with keypoints at contrast 0.01", second.scene_id, second.im_id,
        second.stamp_ns, 9, wrong, 0.35,
    )  # fmt: skip
    weak.verification = 0.9
    estimated = pd.concat([_estimated([first], set()), pd.DataFrame([weak.to_row()])], ignore_index=True)
    conf = objects.conf
    seqs = carry_stage.sequences(iter(seq[:2]), conf.track.max_gap_s)
    gaps = carry_stage.plan(conf, estimated, seqs)
    assert [(g.forward, g.weak) for g in gaps] == [([first.frame_id, second.frame_id], {second.frame_id: 0.9})]
    rows = carry_stage.carry_gaps(objects, gaps, {f.frame_id: f for f in seq[:2]})
    assert len(rows) == 1 and rows[0]["verification"] > 0.9
    assert rows[0]["reason"] == (
        f"carried forwards from {first.frame_id} (1 frame); the estimate: ok: found with keypoints at "
        "contrast 0.01 (confidence 0.35, verification 0.90)"
    )
    assert _adds_mm(objects, second, rows[0]) < 10 < _adds_mm(objects, second, weak.to_row())

    sure = estimated.assign(verification=lambda d: np.where(d["frame_id"] == second.frame_id, 1.0, np.nan))
    gaps = carry_stage.plan(conf, sure, seqs)
    assert carry_stage.carry_gaps(objects, gaps, {f.frame_id: f for f in seq[:2]}) == []
    for off in (
        dataclasses.replace(conf, carry=dataclasses.replace(conf.carry, over_weak=False)),
        dataclasses.replace(conf, min_verification=0.0),
    ):
        assert carry_stage.plan(off, estimated, seqs) == []
