"""Outputs that keep identity on a user's own data (issue 42): object ids 1..N, ``trajectory.csv`` with log
time and names, TUM files; every object targeted without ground truth; a failed run does not lock its
folder; the run's ``manifest.yaml`` is a manifest again; each warning once."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io
import yaml
from scipy.spatial.transform import Rotation

from batchpose import run
from batchpose.errors import ConfigError
from batchpose.io.manifest import ObjectSpec, load_manifest, object_ids
from batchpose.io.mesh import load_mesh, unit_scale
from tests.conftest import ROOT

PIPELINE = ROOT / "pipelines" / "gnc_pose.yaml"
YCBV = ROOT / "demo_data" / "ycbv" / "data" / "0001"
MODELS = ROOT / "demo_data" / "models"
FRAMES = ("000001", "000003")
K = scipy.io.loadmat(YCBV / "000001-meta.mat")["intrinsic_matrix"]


def _image_folder(root):
    """Two real frames of the cracker box as an image folder with its calibration: no ground truth."""
    root.mkdir()
    for f in FRAMES:
        shutil.copy(YCBV / f"{f}-color.png", root / f"{f}.png")
    calib = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": 640, "height": 480}
    (root / "intrinsics.yaml").write_text(yaml.safe_dump({k: float(v) for k, v in calib.items()}))


def _manifest(path, targets=None, objects=("003_cracker_box", "009_gelatin_box")):
    data = {
        "name": "my_log",
        "frames": {"format": "images", "root": "images"},
        "models": {"root": str(MODELS), "mesh": "{name}/textured.obj"},
        "objects": list(objects),
    }
    if targets:
        data["targets"] = targets
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def own_run(tmp_path_factory, cache_dir):
    """A run on an image folder without ground truth, after a first attempt that failed before estimating."""
    base = tmp_path_factory.mktemp("own")
    _image_folder(base / "images")
    out = base / "run"
    with pytest.raises(ConfigError, match="nothing to estimate"):
        run.main(PIPELINE, _manifest(base / "annotated.yaml", "annotations"), out, cache_dir=cache_dir, jobs=1)
    assert (out / "config.yaml").is_file()  # the failed run claimed the folder ...
    run.main(PIPELINE, _manifest(base / "my_log.yaml"), out, cache_dir=cache_dir, jobs=1, report=False)
    return out  # ... and did not lock it: a run of another manifest took it over


def test_every_object_targeted_with_ids_in_manifest_order(own_run):
    poses = pd.read_parquet(own_run / "poses.parquet")
    pairs = sorted(zip(poses["obj_name"], poses["frame_id"], strict=True))
    assert pairs == [(o, f) for o in ("003_cracker_box", "009_gelatin_box") for f in sorted(poses["frame_id"].unique())]
    assert poses["frame_id"].nunique() == 2
    objects = {k: v["obj_id"] for k, v in json.loads((own_run / "objects.json").read_text()).items()}
    assert objects == {"003_cracker_box": 1, "009_gelatin_box": 2}
    csv = pd.read_csv(own_run / "poses.csv")
    assert set(csv["obj_id"]) <= {1, 2} and (csv["obj_id"] == 1).sum() == 2  # the cracker box, in both frames


def test_trajectory_csv_names_times_and_poses(own_run):
    poses = pd.read_parquet(own_run / "poses.parquet")
    traj = pd.read_csv(own_run / "trajectory.csv", dtype={"frame_id": str})
    assert list(traj.columns) == [
        "stamp_ns", "frame_id", "object", "obj_id", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw",
        "status", "confidence", "verification", "tracked",
    ]  # fmt: skip
    assert len(traj) == len(poses) == 4
    frames = pd.read_parquet(own_run / "frames.parquet").set_index("frame_id")["stamp_ns"]
    assert (traj["stamp_ns"].to_numpy() == frames.loc[traj["frame_id"]].to_numpy()).all()
    cracker = traj[traj["object"] == "003_cracker_box"]
    assert (cracker["status"] == "ok").all() and (cracker["obj_id"] == 1).all()
    for row, (_, p) in zip(cracker.itertuples(), poses[poses["obj_name"] == "003_cracker_box"].iterrows(), strict=True):
        R = Rotation.from_quat([row.qx, row.qy, row.qz, row.qw]).as_matrix()
        assert np.allclose(R, np.asarray(p["R"]).reshape(3, 3), atol=1e-6)
        assert np.allclose([row.x_m, row.y_m, row.z_m], p["t_m"], atol=1e-8)
        assert row.verification == pytest.approx(p["verification"]) and row.verification > 0.5  # scored, passed
    # the pose against the data set's ground truth (the frames' meta.mat, not given to the run)
    for f, row in zip(FRAMES, cracker.itertuples(), strict=True):
        meta = scipy.io.loadmat(YCBV / f"{f}-meta.mat")
        gt = meta["poses"][:, :, list(meta["cls_indexes"].ravel()).index(2)]
        assert np.linalg.norm(gt[:, 3] - [row.x_m, row.y_m, row.z_m]) < 0.04
    not_ok = traj[traj["status"] != "ok"]
    assert not_ok[["x_m", "qw"]].isna().all().all()  # a pose only where there is one


def test_tum_files_read_as_trajectories(own_run):
    tum = np.loadtxt(own_run / "tum" / "003_cracker_box.txt", comments="#")
    assert tum.shape == (2, 8)
    assert np.all(np.diff(tum[:, 0]) > 0)
    assert np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0)


def test_the_runs_manifest_is_a_manifest(own_run, tmp_path):
    saved = load_manifest(own_run / "manifest.yaml")
    original = load_manifest(own_run.parent / "my_log.yaml")
    assert saved.to_dict() == original.to_dict()


def test_object_ids_from_manifest_data_set_or_order():
    specs = tuple(ObjectSpec(n, ROOT, None, i) for n, i in (("a", None), ("b", 3), ("c", None), ("d", None)))
    assert object_ids(specs, {}) == {"a": 1, "b": 3, "c": 2, "d": 4}
    assert object_ids(specs, {"a": 3, "c": 7}) == {"a": 1, "b": 3, "c": 7, "d": 2}  # 3 is taken by b


def test_unknown_object_says_did_you_mean(tmp_path):
    path = _manifest(tmp_path / "m.yaml", objects=["003_craker_box"])
    with pytest.raises(ConfigError, match=r"no mesh at .*; did you mean '003_cracker_box'\?"):
        load_manifest(path)


def test_millimetre_warning_once(tmp_path, caplog):
    src = MODELS / "009_gelatin_box"
    mm = tmp_path / "gelatin_mm"
    shutil.copytree(src, mm)
    lines = (mm / "textured.obj").read_text().splitlines()
    scaled = [
        " ".join(["v", *(f"{float(x) * 1000:.4f}" for x in ln.split()[1:4])]) if ln.startswith("v ") else ln
        for ln in lines
    ]
    (mm / "textured.obj").write_text("\n".join(scaled) + "\n")
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        model = load_mesh(mm / "textured.obj", cache_dir=tmp_path / "cache")
        load_mesh(mm / "textured.obj", cache_dir=tmp_path / "cache")  # a worker's load, from the cache
        assert unit_scale(mm / "textured.obj", model.mesh.bounds * 1000) == 0.001  # the report's
    warned = [r.getMessage() for r in caplog.records if "millimetres" in r.getMessage()]
    assert len(warned) == 1 and "scaling by 0.001" in warned[0], warned
    assert model.diameter_m == pytest.approx(load_mesh(src / "textured.obj").diameter_m, rel=1e-3)


def test_a_later_run_in_the_same_process_keeps_its_own_ids(own_run, tmp_path, cache_dir):
    """The in-process worker's estimator is rebuilt for other ids (it once kept the run before's)."""
    out = tmp_path / "demo"
    run.main(PIPELINE, ROOT / "data_manifest" / "demo.yaml", out, cache_dir=cache_dir, jobs=1, report=False, limit=1)
    assert pd.read_csv(out / "poses.csv")["obj_id"].tolist() == [8]  # the gelatin box's YCB-Video id


def test_objects_json_names_both_template_libraries_with_the_same_views(own_run):
    """The default's second library (``render.retry_shading: lit``) is built and named beside the first; it
    has the very views of the first (a record's template ids mean the same in both), other descriptors."""
    from batchpose.io import library  # noqa: PLC0415

    for name, entry in json.loads((own_run / "objects.json").read_text()).items():
        first, second = library.load(Path(entry["library"])), library.load(Path(entry["retry_library"]))
        assert entry["library"] != entry["retry_library"], name
        assert first.n_views == second.n_views == 320, name
        np.testing.assert_allclose(first.cams_from_model(), second.cams_from_model(), atol=1e-9)
        assert len(first.desc) != len(second.desc) or not np.array_equal(first.desc, second.desc), name
