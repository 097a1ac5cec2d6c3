"""The day-one path of README.md's "Your data": `batchpose inspect`, `batchpose init` and `batchpose run` on a
ROS 2 log (and on an image folder with ROS's ost.yaml) that has no ground truth, with a millimetre OBJ mesh
(batchpose.inspect_log, batchpose.init_manifest, the topic checks of batchpose.io.mcap_read)."""

from __future__ import annotations

import contextlib
import io
import logging
import re
import shlex
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import trimesh
import yaml
from mcap_ros2.writer import Writer as Ros2Writer

from batchpose import cli, init_manifest, inspect_log
from batchpose.core.frames import decode_image
from batchpose.core.model import diameter
from batchpose.errors import BatchposeError, CameraError, ConfigError, DataError
from batchpose.io.folders import YcbvFrameSource
from batchpose.io.manifest import load_manifest
from batchpose.io.sources import open_frames
from batchpose.report.metrics import add
from tests.conftest import DEMO, GELATIN, ROOT
from tests.test_mcap_io import ROS_CAMERA_INFO, ROS_COMPRESSED

#: The demo frames of the gelatin box (demo_data/ycbv), in the order the logs hold them.
FRAME_IDS = ("0000/000001", "0000/000004")
OBJECT = "009_gelatin_box"
IMAGE_TOPIC = "/camera/color/image_raw/compressed"
INFO_TOPIC = "/camera/color/camera_info"
CAMERA_FRAME = "camera_color_optical_frame"
T0 = 1_700_000_000_000_000_000
#: What README.md's "Your data" block says, used only when the README has no such block.
README_FALLBACK = (
    "batchpose inspect my_log.mcap",
    "batchpose init my_log.mcap --meshes meshes/ --out my_log.yaml",
    "batchpose run --manifest my_log.yaml --out runs/my_log",
)


def readme_commands() -> list[str]:
    """The commands of the first ```sh block under README.md's "## Your data" (the fallback without one)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = re.search(r"^## Your data\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    block = re.search(r"```sh\n(.*?)```", section.group(1), re.S) if section else None
    lines = [ln.strip() for ln in block.group(1).splitlines()] if block else []
    return [ln for ln in lines if ln and not ln.startswith("#")] or list(README_FALLBACK)


def _demo_frames():
    frames = {f.frame_id: f for f in YcbvFrameSource(DEMO / "ycbv")}
    return [frames[i] for i in FRAME_IDS]


def write_ros2_log(path: Path) -> None:
    """The demo frames as a ROS 2 log: JPEG sensor_msgs/CompressedImage and sensor_msgs/CameraInfo in frame
    camera_color_optical_frame, 100 ms apart, no ground truth."""
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        s_img = w.register_msgdef("sensor_msgs/msg/CompressedImage", ROS_COMPRESSED)
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", ROS_CAMERA_INFO)
        for i, frame in enumerate(_demo_frames()):
            t = T0 + i * 100_000_000
            header = {"stamp": {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}, "frame_id": CAMERA_FRAME}
            K, cam = frame.camera.K, frame.camera
            info = {
                "header": header,
                "height": cam.height,
                "width": cam.width,
                "distortion_model": "plumb_bob",
                "d": [0.0] * 5,
                "k": K.reshape(-1).tolist(),
                "r": np.eye(3).reshape(-1).tolist(),
                "p": np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist(),
            }
            w.write_message(INFO_TOPIC, s_info, info, log_time=t)
            jpeg = cv2.imencode(".jpg", decode_image(frame)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
            image = {"header": header, "format": "rgb8; jpeg compressed bgr8", "data": jpeg.tobytes()}
            w.write_message(IMAGE_TOPIC, s_img, image, log_time=t)
        w.finish()


def write_image_folder(root: Path) -> None:
    """The demo frames as an image folder with the ost.yaml ROS's camera_calibration writes."""
    root.mkdir()
    frames = _demo_frames()
    for frame in frames:
        (root / f"{frame.frame_id.replace('/', '_')}.png").write_bytes(frame.image_data)
    cam = frames[0].camera
    ost = {
        "image_width": cam.width,
        "image_height": cam.height,
        "camera_name": "color",
        "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.reshape(-1).tolist()},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).reshape(-1).tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": np.hstack([cam.K, np.zeros((3, 1))]).reshape(-1).tolist()},
    }
    (root / "ost.yaml").write_text(yaml.safe_dump(ost, sort_keys=False))


@pytest.fixture(scope="module")
def mm_meshes(tmp_path_factory) -> Path:
    """meshes/gelatin_box.obj: the bundled gelatin box in millimetres, written by trimesh (with its .mtl and
    texture); written once, copied into each test's folder so both runs share its template library."""
    out = tmp_path_factory.mktemp("mm") / "meshes"
    out.mkdir()
    mesh = trimesh.load(GELATIN, force="mesh", process=False)
    mesh.apply_scale(1000.0)
    mesh.export(out / "gelatin_box.obj")
    return out


def run_commands(work: Path, lines: list[str], cache: Path) -> dict[str, str]:
    """Each command line through ``batchpose.cli.main`` in ``work`` (``run`` with the test's template cache, one
    worker and templates at one distance); returns each command's stdout by its subcommand, and fails on a
    non-zero exit."""
    outputs = {}
    logger = logging.getLogger("batchpose")  # cli.main adds a handler and stops propagation: put them back after
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(logger, "handlers", list(logger.handlers))
        mp.setattr(logger, "propagate", logger.propagate)
        mp.setattr(logger, "level", logger.level)
        mp.chdir(work)
        for line in lines:
            argv = shlex.split(line)[1:]
            if argv[0] == "run":  # one template distance (the box spans about half the image): half the build time
                argv += ["--cache", str(cache), "--jobs", "1", "--set", "render.image_fractions=[0.5]"]
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = cli.main(argv)
            assert code == 0, f"{line}: exit {code}: {err.getvalue()}"
            outputs[argv[0]] = out.getvalue()
    return outputs


def assert_poses_match_the_demo_ground_truth(poses_csv: Path) -> None:
    """poses.csv (one row per frame, in frame order) against the demo frames' ground truth: ADD < 0.1 d."""
    pts = np.loadtxt(DEMO / "models" / OBJECT / "points.xyz")[:, :3]
    d = diameter(pts)
    est = pd.read_csv(poses_csv).sort_values("im_id")
    assert list(est["im_id"]) == [0, 1]
    for (_, row), frame in zip(est.iterrows(), _demo_frames(), strict=True):
        (gt,) = [p.cam_from_model for p in frame.gt if p.obj_name == OBJECT]
        R = np.array(row["R"].split(), dtype=float).reshape(3, 3)
        t_m = np.array(row["t"].split(), dtype=float) / 1000.0
        err = add(R, t_m, gt[:3, :3], gt[:3, 3], pts)
        assert err < 0.1 * d, (frame.frame_id, err, d)
        assert np.linalg.norm(t_m - gt[:3, 3]) < 0.02, (frame.frame_id, t_m, gt[:3, 3])


@pytest.mark.slow
def test_day_one_on_a_ros2_log(tmp_path, mm_meshes, cache_dir):
    write_ros2_log(tmp_path / "my_log.mcap")
    shutil.copytree(mm_meshes, tmp_path / "meshes")
    out = run_commands(tmp_path, readme_commands(), cache_dir)

    said = dict(
        ln.split(": ", 1) for ln in out["inspect"].splitlines() if ln.startswith(("image topic", "calibration"))
    )
    assert said["image topic"].startswith(f"{IMAGE_TOPIC} (the only image topic)")
    assert said["calibration"].startswith(f"{INFO_TOPIC}: fx 1066.8 fy 1067.5")
    assert "2 images" in out["inspect"] and "ground truth: none" in out["inspect"]

    raw = yaml.safe_load((tmp_path / "my_log.yaml").read_text())
    assert raw["frames"] == {
        "format": "mcap",
        "path": "my_log.mcap",
        "image_topic": IMAGE_TOPIC,
        "calibration_topic": INFO_TOPIC,
    }
    assert (raw["name"], raw["targets"], raw["objects"]) == ("my_log", "all", ["gelatin_box"])
    assert "in millimetres" in (tmp_path / "my_log.yaml").read_text()
    assert_poses_match_the_demo_ground_truth(tmp_path / "runs" / "my_log" / "poses.csv")


@pytest.mark.slow
def test_day_one_on_an_image_folder_with_ost_yaml(tmp_path, mm_meshes, cache_dir):
    write_image_folder(tmp_path / "my_log")
    shutil.copytree(mm_meshes, tmp_path / "meshes")
    lines = [ln.replace("my_log.mcap", "my_log") for ln in readme_commands()]
    out = run_commands(tmp_path, lines, cache_dir)

    assert "image folder, 2 images (.png), 640x480" in out["inspect"]
    assert "calibration: ost.yaml: fx 1066.8 fy 1067.5" in out["inspect"]
    raw = yaml.safe_load((tmp_path / "my_log.yaml").read_text())
    assert raw["frames"] == {"format": "images", "root": "my_log", "intrinsics": "my_log/ost.yaml"}
    assert (raw["name"], raw["targets"], raw["objects"]) == ("my_log", "all", ["gelatin_box"])
    assert_poses_match_the_demo_ground_truth(tmp_path / "runs" / "my_log" / "poses.csv")


# ----------------------------------------------------------------------------- without a pipeline run


@pytest.fixture(scope="module")
def ros2_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("log") / "my_log.mcap"
    write_ros2_log(path)
    return path


def test_a_misspelt_topic_names_the_nearest_one(ros2_log, tmp_path):
    manifest = tmp_path / "m.yaml"
    frames = {"format": "mcap", "path": str(ros2_log), "image_topic": "/camera/color/image_raw/compresed"}
    manifest.write_text(
        yaml.safe_dump({"frames": frames, "objects": [OBJECT], "models": {"root": str(DEMO / "models")}})
    )
    man = load_manifest(manifest)
    with pytest.raises(DataError) as e:
        open_frames(man.frames, tmp_path)
    assert str(e.value) == (
        f"{ros2_log}: image topic '/camera/color/image_raw/compresed' not found (image topics: {IMAGE_TOPIC}; "
        f"calibration topics: {INFO_TOPIC}); did you mean '{IMAGE_TOPIC}'?"
    )
    frames = {"format": "mcap", "path": str(ros2_log), "calibration_topic": "/camera/camera_info"}
    with pytest.raises(CameraError, match=rf"calibration topic '/camera/camera_info' not found .*mean '{INFO_TOPIC}'"):
        open_frames(frames, tmp_path)


def test_init_refuses_to_overwrite_and_takes_each_mesh_layout(ros2_log, tmp_path):
    meshes = tmp_path / "meshes"
    (meshes / "cracker").mkdir(parents=True)
    for f in (DEMO / "models" / "003_cracker_box").glob("textured.*"):
        shutil.copy(f, meshes / "cracker")
    shutil.copy(DEMO / "models" / "003_cracker_box" / "texture_map.jpg", meshes / "cracker")
    (meshes / "untextured.stl").write_bytes(trimesh.creation.box().export(file_type="stl"))
    (meshes / "notes.txt").write_text("not a mesh")
    out = tmp_path / "sub" / "m.yaml"
    assert init_manifest.main(ros2_log, meshes, out) == out
    man = load_manifest(out)
    assert [(o.name, o.mesh) for o in man.objects] == [("cracker", meshes / "cracker" / "textured.obj")]
    assert '# - "untextured"   # left out: mesh has no texture' in out.read_text()
    assert yaml.safe_load(out.read_text())["frames"]["path"] == "../../" + ros2_log.parent.name + "/my_log.mcap"
    with pytest.raises(ConfigError, match=r"m.yaml: already exists; pass --overwrite"):
        init_manifest.main(ros2_log, meshes, out)
    init_manifest.main(ros2_log, meshes, out, overwrite=True)
    with pytest.raises(ConfigError, match=r"no mesh \(expected NAME.obj"):
        init_manifest.main(ros2_log, tmp_path / "sub", tmp_path / "n.yaml")
    assert not (tmp_path / "n.yaml").exists()


def test_inspect_refuses_a_bad_path_or_a_corrupt_log(ros2_log, tmp_path):
    with pytest.raises(DataError, match=r"nope.mcap: no such file or folder"):
        inspect_log.describe(tmp_path / "nope.mcap")
    bad = tmp_path / "bad.mcap"
    data = bytearray(ros2_log.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = bytes(64)  # inside the chunk: its CRC no longer matches
    bad.write_bytes(bytes(data))
    with pytest.raises(BatchposeError) as e:
        inspect_log.describe(bad)
    assert "\n" not in str(e.value) and "bad.mcap" in str(e.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"empty: no .png/.jpg images"):
        inspect_log.describe(tmp_path / "empty")
