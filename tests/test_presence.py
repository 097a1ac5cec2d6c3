"""Which objects are in a frame (``match.presence_votes``): an object whose keypoints agree on no location is
``absent`` at once, without the expensive steps, while a present one is estimated as before (issue 44)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
import yaml

from batchpose import run
from batchpose.config import load_estimator_config, load_yaml
from batchpose.core.geometry import rotation_error_deg
from batchpose.io.folders import YcbvFrameSource
from batchpose.io.library import load
from batchpose.io.mesh import load_mesh
from batchpose.method import presence
from batchpose.method.estimator import PoseEstimator
from batchpose.stages.build_templates import build_library
from tests.conftest import CRACKER, DEMO, ROOT

PIPELINE = ROOT / "pipelines" / "gnc_pose.yaml"
#: 0000/000001 shows the gelatin box and not the cracker box; 0001/000001 the cracker box and not the gelatin box.
FRAMES = {"0000/000001": "009_gelatin_box", "0001/000001": "003_cracker_box"}


@pytest.fixture(scope="module")
def gated_run(tmp_path_factory, cache_dir):
    base = tmp_path_factory.mktemp("presence")
    manifest = base / "m.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "name": "presence",
                "frames": {"format": "ycbv", "root": str(DEMO / "ycbv"), "frame_ids": list(FRAMES)},
                "models": {"root": str(DEMO / "models"), "mesh": "{name}/textured.obj"},
                "objects": ["003_cracker_box", "009_gelatin_box"],
                "targets": "all",
            }
        )
    )
    out = base / "run"
    run.main(PIPELINE, manifest, out, cache_dir=cache_dir, jobs=1, report=False)  # the default check
    return pd.read_parquet(out / "poses.parquet")


def test_absent_objects_are_absent_without_the_expensive_steps(gated_run):
    for frame_id, there in FRAMES.items():
        rows = gated_run[gated_run["frame_id"] == frame_id].set_index("obj_name")
        assert rows.loc[there, "status"] == "ok"
        gone = rows.drop(index=there).iloc[0]
        assert gone["status"] == "absent", gone["reason"]
        need = load_estimator_config(load_yaml(PIPELINE)).match.presence_votes
        assert f"keypoints agree on where it would be, need {need} (match.presence_votes)" in gone["reason"]
        assert gone["time_fine_s"] == 0 and gone["time_refine_s"] == 0 and gone["time_plane_s"] == 0
        # One joint query a frame, which (like its SIFT) every pair of the frame records.
        assert rows["time_presence_s"].nunique() == 1 and rows["time_presence_s"].iloc[0] > 0


def test_a_present_object_is_estimated_as_without_the_check(gated_run, cache_dir):
    """The check only adds a record: without ``match.joint_vote`` the present objects' poses are those of an
    estimator without it; with it (the default run), the view vote reads the joint query and the pose is the
    same within a millimetre."""
    conf = load_estimator_config(load_yaml(PIPELINE))
    conf = dataclasses.replace(conf, match=dataclasses.replace(conf.match, presence_votes=0))
    source = YcbvFrameSource(DEMO / "ycbv")
    frames = {f.frame_id: f for f in source if f.frame_id in FRAMES}
    K, w, h = frames["0000/000001"].camera.K, 640, 480
    models = {"003_cracker_box": load_mesh(CRACKER)}
    libs = {n: load(build_library(m, conf, K, w, h, cache_dir)) for n, m in models.items()}
    from batchpose.method.render import get_renderer

    est = PoseEstimator(conf, libs, models=models, renderer=get_renderer())
    checked = dataclasses.replace(conf, match=dataclasses.replace(conf.match, presence_votes=5, joint_vote=False))
    est_checked = PoseEstimator(checked, libs, models=models, renderer=get_renderer())
    for frame_id, there in list(FRAMES.items())[1:]:  # one frame is enough to compare
        (rec,) = est.estimate_frame(frames[frame_id], [there])
        (same,) = est_checked.estimate_frame(frames[frame_id], [there])
        assert rec.ok and same.ok and np.array_equal(same.cam_from_model, rec.cam_from_model)
        row = gated_run[(gated_run["frame_id"] == frame_id) & (gated_run["obj_name"] == there)].iloc[0]
        assert np.linalg.norm(rec.cam_from_model[:3, 3] - row["t_m"]) < 1e-3
        assert rotation_error_deg(rec.cam_from_model[:3, :3], np.asarray(row["R"]).reshape(3, 3)) < 0.5


def test_no_presence_check_where_the_ground_truth_lists_the_objects(tmp_path, cache_dir):
    """Under ``targets: annotations`` the ground truth says the object is there: never ``absent``."""
    out = tmp_path / "annotated"
    manifest = ROOT / "data_manifest" / "demo.yaml"
    run.main(PIPELINE, manifest, out, cache_dir=cache_dir, jobs=1, report=False, limit=1,
             overrides=["match.presence_votes=1000"])  # fmt: skip
    assert pd.read_parquet(out / "poses.parquet")["status"].tolist() == ["ok"]


def test_the_joint_index_is_kept_beside_the_libraries(cache_dir):
    """The presence check's index over all objects is built once and kept, like each library's own: a second
    build loads it and answers the same; a keypoint of one object's template counts for that object."""
    conf = load_estimator_config(load_yaml(PIPELINE)).match
    libs = {n: load(p) for n, p in _demo_libraries(cache_dir).items()}
    first = presence.joint_index(libs, conf)
    assert first is not None
    keep = presence.index_folder(libs)
    assert keep is not None and keep.parent == next(iter(libs.values())).folder.parent
    kept = list(keep.glob("flann-*.idx"))
    assert len(kept) == 1 and kept[0].with_name(kept[0].name + ".sha256").exists()
    again = presence.joint_index(libs, conf)
    assert again is not None
    queries = np.vstack([lib.desc[:50] for lib in libs.values()])
    a, b = presence.joint_nearest(first, queries, conf), presence.joint_nearest(again, queries, conf)
    assert np.array_equal(a.idx, b.idx) and np.allclose(a.dist, b.dist)
    owners = first.owner[a.idx[:, 0]]
    assert (owners == np.repeat(np.arange(len(libs)), 50)).mean() > 0.95


def _demo_libraries(cache_dir) -> dict:
    """The demo objects' template libraries (built into the shared test cache when not there yet)."""
    conf = load_estimator_config(load_yaml(PIPELINE))
    K = next(iter(YcbvFrameSource(DEMO / "ycbv"))).camera.K
    meshes = {"003_cracker_box": CRACKER, "009_gelatin_box": DEMO / "models" / "009_gelatin_box" / "textured.obj"}
    return {n: build_library(load_mesh(m), conf, K, 640, 480, cache_dir) for n, m in meshes.items()}
