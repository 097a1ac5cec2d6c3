"""Folder readers (YCB-Video, BOP, plain images) and the ``frames:`` manifest factory, on tiny data sets."""

from __future__ import annotations

import json
import logging
import re
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
import yaml

from batchpose.core.frames import decode_image, image_size
from batchpose.errors import CameraError, ConfigError, DataError, ImageError
from batchpose.io.folders import FRAME_PERIOD_NS, BopFrameSource, ImagesFrameSource, YcbvFrameSource
from batchpose.io.sources import open_frames

SHARED_YCBV = Path(__file__).resolve().parents[2] / "shared" / "data" / "ycbv_dev"
K = np.array([[500.0, 0.0, 15.5], [0.0, 510.0, 11.5], [0.0, 0.0, 1.0]])


def _png(path: Path, rng: np.random.Generator, w: int = 32, h: int = 24) -> np.ndarray:
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)
    return img


def _pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    return np.hstack([q, rng.normal(size=(3, 1)) + [[0], [0], [1]]])


def make_ycbv(root: Path, seed: int = 0) -> dict:
    """Two real frames (video 0001) and one synthetic frame, with their 3x4 poses."""
    rng = np.random.default_rng(seed)
    (root / "classes.txt").parent.mkdir(parents=True, exist_ok=True)
    (root / "classes.txt").write_text("002_master_chef_can\n003_cracker_box\n004_sugar_box\n")
    poses = {}
    for rel, cls in (("data/0001/000001", [1, 3]), ("data/0001/000002", [2, 3]), ("data_syn/000007", [2])):
        _png(root / f"{rel}-color.png", rng)
        P = np.stack([_pose(rng) for _ in cls], axis=2)
        # A real meta.mat also holds a big vertmap: the reader must not need it.
        scipy.io.savemat(
            root / f"{rel}-meta.mat",
            {
                "cls_indexes": np.array(cls, dtype=np.uint8).reshape(-1, 1),
                "poses": P if len(cls) > 1 else P[:, :, 0],  # MATLAB stores one pose as 3x4
                "intrinsic_matrix": K,
                "vertmap": np.zeros((24, 32, 3), np.float32),
            },
        )
        poses[rel] = P
    return poses


def test_ycbv_frames_ids_ground_truth_and_bytes(tmp_path):
    poses = make_ycbv(tmp_path)
    src = YcbvFrameSource(tmp_path)
    assert src.count() == 3 and len(src) == 3
    assert isinstance(iter(src), types.GeneratorType)  # lazy
    frames = list(src)
    assert [f.frame_id for f in frames] == ["0001/000001", "0001/000002", "data_syn/000007"]
    assert [(f.scene_id, f.im_id) for f in frames] == [(1, 1), (1, 2), (10000, 7)]
    assert [f.stamp_ns for f in frames] == [0, FRAME_PERIOD_NS, 2 * FRAME_PERIOD_NS]
    f0 = frames[0]
    assert f0.image_data == (tmp_path / "data/0001/000001-color.png").read_bytes()
    assert f0.image_format == "png" and (f0.camera.width, f0.camera.height) == (32, 24)
    np.testing.assert_array_equal(f0.camera.K, K)
    assert [g.obj_name for g in f0.gt] == ["002_master_chef_can", "004_sugar_box"]
    np.testing.assert_allclose(f0.gt[1].cam_from_model[:3, :], poses["data/0001/000001"][:, :, 1])
    np.testing.assert_array_equal(f0.gt[1].cam_from_model[3], [0, 0, 0, 1])
    assert [g.obj_name for g in frames[2].gt] == ["003_cracker_box"]
    np.testing.assert_allclose(frames[2].gt[0].cam_from_model[:3, :], poses["data_syn/000007"][:, :, 0])
    assert src.obj_id("003_cracker_box") == 2 and src.obj_id("nope") == 0
    assert "3 frames" in src.describe()
    assert decode_image(f0).shape == (24, 32, 3)


def test_ycbv_missing_meta_and_bad_class(tmp_path):
    make_ycbv(tmp_path)
    (tmp_path / "data/0001/000002-meta.mat").unlink()
    with pytest.raises(DataError, match="000002-meta.mat: missing"):
        YcbvFrameSource(tmp_path)
    make_ycbv(tmp_path)
    (tmp_path / "classes.txt").write_text("only_one\n")
    with pytest.raises(DataError, match=r"cls_indexes value 3 outside 1..1"):
        list(YcbvFrameSource(tmp_path))


def test_ycbv_missing_classes(tmp_path):
    make_ycbv(tmp_path)
    (tmp_path / "classes.txt").unlink()
    with pytest.raises(DataError, match="classes.txt: missing"):
        YcbvFrameSource(tmp_path)


def make_bop(root: Path, seed: int = 0) -> dict:
    """Scene 000048 with a PNG (im 1, one object) and a JPEG (im 2, no ground truth)."""
    rng = np.random.default_rng(seed)
    scene = root / "000048"
    _png(scene / "rgb" / "000001.png", rng)
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cv2.imwrite(str(scene / "rgb" / "000002.jpg"), img)
    cams = {str(i): {"cam_K": K.reshape(-1).tolist(), "depth_scale": 0.1} for i in (1, 2)}
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    P = _pose(rng)
    gt = {"1": [{"cam_R_m2c": P[:, :3].reshape(-1).tolist(), "cam_t_m2c": (P[:, 3] * 1000).tolist(), "obj_id": 5}]}
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    return {"pose": P}


def test_bop_frames_mm_to_m_and_names(tmp_path):
    truth = make_bop(tmp_path)
    src = BopFrameSource(tmp_path, obj_names={"5": "006_mustard_bottle"})
    frames = list(src)
    assert [f.frame_id for f in frames] == ["000048/000001", "000048/000002"]
    assert [(f.scene_id, f.im_id, f.image_format) for f in frames] == [(48, 1, "png"), (48, 2, "jpeg")]
    np.testing.assert_array_equal(frames[0].camera.K, K)
    assert (frames[1].camera.width, frames[1].camera.height) == (32, 24)  # from the JPEG header
    (g,) = frames[0].gt
    assert g.obj_name == "006_mustard_bottle"
    np.testing.assert_allclose(g.cam_from_model[:3, :], truth["pose"], atol=1e-12)  # mm -> m
    assert frames[1].gt == ()
    assert src.obj_id("006_mustard_bottle") == 5
    default = BopFrameSource(tmp_path)
    assert next(iter(default)).gt[0].obj_name == "obj_000005" and default.obj_id("obj_000005") == 5


def test_bop_missing_image(tmp_path):
    make_bop(tmp_path)
    (tmp_path / "000048/rgb/000002.jpg").unlink()
    with pytest.raises(DataError, match="000002.png: missing"):
        BopFrameSource(tmp_path)


def make_images(root: Path, n: int = 3, seed: int = 0, **intr) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    imgs = [_png(root / f"img_{i:03d}.png", rng) for i in range(n)]
    spec = {"fx": 500.0, "fy": 510.0, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24, **intr}
    (root / "intrinsics.yaml").write_text(yaml.safe_dump(spec))
    return imgs


def test_images_folder_with_distortion(tmp_path):
    imgs = make_images(tmp_path, dist=[0.1, -0.01, 0.0, 0.0, 0.001])
    src = ImagesFrameSource(tmp_path)
    frames = list(src)
    assert [f.frame_id for f in frames] == ["img_000", "img_001", "img_002"]
    np.testing.assert_array_equal(frames[1].camera.K, K)
    assert frames[1].camera.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(frames[1].camera.dist, [0.1, -0.01, 0.0, 0.0, 0.001])
    np.testing.assert_array_equal(decode_image(frames[2]), imgs[2][:, :, ::-1])  # BGR file -> RGB


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        ({"fov": 60}, ConfigError, "unknown key 'fov'"),
        ({"fx": "wide"}, ConfigError, "must be numbers"),
        ({"fx": -1.0}, CameraError, "focal lengths must be positive"),
        ({"fy": True}, ConfigError, "fy must be a number, got True"),  # YAML `yes` / `true` is not 1.0
        ({"dist": [0.1, 0.01, 0.0, 0.0], "distortion_model": "equidistant"}, CameraError, "'equidistant' is not supp"),
    ],
)
def test_images_bad_intrinsics(tmp_path, change, error, match):
    make_images(tmp_path, **change)
    with pytest.raises(error, match=match):
        ImagesFrameSource(tmp_path)


# What ROS's camera_calibration writes (ost.yaml), for the camera make_images draws.
ROS_OST_YAML = """image_width: 32
image_height: 24
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [500.0, 0.0, 15.5, 0.0, 510.0, 11.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.1, -0.01, 0.0, 0.0, 0.001]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [490.0, 0.0, 15.0, 0.0, 0.0, 505.0, 11.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


# OpenCV 4's FileStorage YAML (OpenCV 5 writes "%YAML 1.2" instead of the "%YAML:1.0" PyYAML refuses).
OPENCV4_YAML = """%YAML:1.0
---
image_width: 32
image_height: 24
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 500., 0., 15.5, 0., 510., 11.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ 0.1, -0.01, 0., 0., 0.001 ]
"""


@pytest.mark.parametrize("form", ["ros", "opencv", "opencv4"])
def test_images_with_a_calibration_tools_yaml(tmp_path, form):
    imgs = make_images(tmp_path)
    path = tmp_path / "intrinsics.yaml"
    if form == "ros":
        path.write_text(ROS_OST_YAML)
    elif form == "opencv4":
        path.write_text(OPENCV4_YAML)
    else:  # OpenCV's FileStorage, as its calibration sample writes the result
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 32)
        fs.write("image_height", 24)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", np.array([[0.1, -0.01, 0.0, 0.0, 0.001]]))
        fs.release()
        assert "!!opencv-matrix" in path.read_text()
    frames = list(ImagesFrameSource(tmp_path))
    np.testing.assert_array_equal(frames[0].camera.K, K)
    np.testing.assert_array_equal(frames[0].camera.dist, [0.1, -0.01, 0.0, 0.0, 0.001])
    assert (frames[0].camera.width, frames[0].camera.height, frames[0].camera.distortion_model) == (32, 24, "plumb_bob")
    np.testing.assert_array_equal(decode_image(frames[1]), imgs[1][:, :, ::-1])


@pytest.mark.parametrize(
    ("old", "new", "error", "match"),
    [
        ("camera_name: narrow_stereo", "camera_nme: x", ConfigError, "unknown key 'camera_nme' in a camera-info YAML"),
        ("image_width: 32\n", "", ConfigError, "missing key 'image_width' (a camera-info YAML needs"),
        ("0.0, 0.0, 1.0]\ndist", "0.0]\ndist", ConfigError, "camera_matrix.data must hold 9 numbers"),
        (
            "data: [500.0, 0.0, 15.5,",
            "data: [500.0, 0.0, abc,",
            ConfigError,
            "camera_matrix.data must be a list of numbers",
        ),
        ("image_height: 24", "image_height: 24.5", ConfigError, "image_width and image_height must be whole numbers"),
        ("0.0, 510.0, 11.5, 0.0, 0.0, 1.0]", "0.0, 510.0, 0.0, 15.5, 11.5, 1.0]", CameraError, "K must be"),
    ],
)
def test_images_bad_calibration_tools_yaml(tmp_path, old, new, error, match):
    make_images(tmp_path)
    assert old in ROS_OST_YAML
    (tmp_path / "intrinsics.yaml").write_text(ROS_OST_YAML.replace(old, new, 1))
    with pytest.raises(error, match=re.escape(match)):
        ImagesFrameSource(tmp_path)


def test_images_broken_opencv_yaml(tmp_path):
    make_images(tmp_path)
    (tmp_path / "intrinsics.yaml").write_text(OPENCV4_YAML.replace("0., 0., 1. ]", "0., 0., 1. "))
    with pytest.raises(DataError, match=r"intrinsics.yaml: invalid OpenCV YAML \(\(-212:Parsing error\)"):
        ImagesFrameSource(tmp_path)


def test_images_missing_intrinsics_key(tmp_path):
    make_images(tmp_path)
    spec = yaml.safe_load((tmp_path / "intrinsics.yaml").read_text())
    del spec["height"]
    (tmp_path / "intrinsics.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(ConfigError, match="intrinsics.yaml: missing key 'height'"):
        ImagesFrameSource(tmp_path)


def test_open_frames_resolves_relative_paths(tmp_path):
    make_ycbv(tmp_path / "ds")
    src = open_frames({"format": "ycbv", "root": "ds"}, base_dir=tmp_path)
    assert src.count() == 3
    make_images(tmp_path / "imgs")
    (tmp_path / "imgs" / "intrinsics.yaml").rename(tmp_path / "cam.yaml")
    src = open_frames({"format": "images", "root": "imgs", "intrinsics": "cam.yaml"}, base_dir=tmp_path)
    assert src.count() == 3


@pytest.mark.parametrize(
    ("spec", "error", "match"),
    [
        ({"format": "kitti", "root": "x"}, ConfigError, "frames.format: unknown format 'kitti'"),
        ({"root": "x"}, ConfigError, "frames.format: unknown format None"),
        ({"format": "ycbv"}, ConfigError, "frames.root: missing"),
        ({"format": "ycbv", "root": "x", "intrinsics": "y"}, ConfigError, "frames.intrinsics: unknown key"),
        ({"format": "ycbv", "root": "nowhere"}, DataError, "frames.root: .*nowhere does not exist"),
        ({"format": "mcap", "path": "nowhere.mcap"}, DataError, "frames.path: .*nowhere.mcap does not exist"),
        (
            {"format": "bop", "root": ".", "obj_names": [1]},
            ConfigError,
            "frames.obj_names: expected a mapping",
        ),
        ("ycbv", ConfigError, "frames: expected a mapping"),
    ],
)
def test_open_frames_bad_spec(tmp_path, spec, error, match):
    with pytest.raises(error, match=match):
        open_frames(spec, base_dir=tmp_path)


def test_image_size_png_and_jpeg():
    img = np.zeros((17, 29, 3), np.uint8)
    assert image_size(cv2.imencode(".png", img)[1].tobytes()) == (29, 17)
    assert image_size(cv2.imencode(".jpg", img)[1].tobytes()) == (29, 17)
    assert image_size(b"") is None and image_size(b"GIF89a....") is None


@pytest.mark.skipif(not SHARED_YCBV.is_dir(), reason=f"shared YCB-Video dev data not at {SHARED_YCBV}")
def test_shared_ycbv_dev():
    src = open_frames({"format": "ycbv", "root": str(SHARED_YCBV)}, base_dir=Path.cwd())
    # 20 consecutive real frames of each of videos 0000, 0001 and 0049, and 6 synthetic ones
    frames = list(src)
    assert src.count() == len(frames) == 66
    assert sum(f.frame_id.startswith("data_syn/") for f in frames) == 6
    assert {f.frame_id.split("/")[0] for f in frames} == {"0000", "0001", "0049", "data_syn"}
    f = frames[0]
    assert f.frame_id == "0000/000001" and (f.camera.width, f.camera.height) == (640, 480)
    assert f.camera.K[0, 0] == pytest.approx(1066.778)
    assert "009_gelatin_box" in [g.obj_name for g in f.gt]


# ------------------------------------------------------------------------------ one bad file, bad fields


def test_ycbv_corrupt_meta_fails_only_its_frame(tmp_path, caplog):
    make_ycbv(tmp_path)
    bad = tmp_path / "data/0001/000002-meta.mat"
    bad.write_bytes(b"MATLAB 5.0 MAT-file garbage" + bytes(range(200)))
    src = YcbvFrameSource(tmp_path)
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        frames = list(src)
        list(src)  # read again (ingest, then estimation): warned once
    assert [f.frame_id for f in frames] == ["0001/000001", "0001/000002", "data_syn/000007"]
    assert frames[0].error is None and decode_image(frames[0]).shape == (24, 32, 3)
    assert frames[2].error is None and len(frames[2].gt) == 1
    assert frames[1].gt == () and not frames[1].has_depth
    with pytest.raises(CameraError, match=r"000002-meta.mat: cannot read MATLAB file"):
        decode_image(frames[1])  # estimate_frame turns this into a bad_camera row
    assert caplog.text.count("000002-meta.mat: cannot read MATLAB file") == 1
    assert "frame 0001/000002 is not estimated (bad_camera)" in caplog.text


def test_ycbv_meta_missing_a_variable_fails_only_its_frame(tmp_path):
    make_ycbv(tmp_path)
    scipy.io.savemat(tmp_path / "data/0001/000001-meta.mat", {"cls_indexes": np.array([[1]], np.uint8)})
    f0, f1, _ = YcbvFrameSource(tmp_path)
    with pytest.raises(CameraError, match=r"000001-meta.mat: missing variable 'poses'"):
        decode_image(f0)
    assert f1.error is None and len(f1.gt) == 2


def test_images_of_another_size_than_the_intrinsics_fail_decoding(tmp_path, caplog):
    rng = np.random.default_rng(3)
    make_images(tmp_path)  # 32x24, as the intrinsics say
    _png(tmp_path / "img_001.png", rng, w=40, h=30)
    _png(tmp_path / "img_002.png", rng, w=16, h=12)
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        frames = list(ImagesFrameSource(tmp_path))
    assert decode_image(frames[0]).shape == (24, 32, 3)
    with pytest.raises(ImageError, match=r"img_001.png: image is 40x30, the camera calibration is for 32x24"):
        decode_image(frames[1])
    with pytest.raises(ImageError, match=r"img_002.png: image is 16x12, the camera calibration is for 32x24"):
        decode_image(frames[2])
    assert "img_001.png: image is 40x30 but" in caplog.text and "fail as bad_image" in caplog.text


def test_text_files_that_are_not_utf8(tmp_path):
    make_images(tmp_path / "imgs")
    intr = tmp_path / "imgs" / "intrinsics.yaml"
    intr.write_bytes("# caméra\n".encode("latin-1") + intr.read_bytes())
    with pytest.raises(DataError, match=r"intrinsics.yaml: not UTF-8 text \(byte 0xe9 at offset 5\)"):
        ImagesFrameSource(tmp_path / "imgs")
    make_ycbv(tmp_path / "ycbv")
    (tmp_path / "ycbv" / "classes.txt").write_bytes("002_master_chef_can\n003_crème\n".encode("latin-1"))
    with pytest.raises(DataError, match=r"classes.txt: not UTF-8 text \(byte 0xe8 at offset 26\)"):
        YcbvFrameSource(tmp_path / "ycbv")
    make_bop(tmp_path / "bop")
    (tmp_path / "bop" / "000048" / "scene_gt.json").write_bytes('{"1": [], "é": []}'.encode("latin-1"))
    with pytest.raises(DataError, match=r"scene_gt.json: not UTF-8 text"):
        list(BopFrameSource(tmp_path / "bop"))


@pytest.mark.parametrize(
    ("file", "content", "match"),
    [
        (
            "scene_camera.json",
            {"1": {"cam_K": ["a"] * 9}, "2": {"cam_K": K.reshape(-1).tolist()}},
            r"scene_camera.json: im_id 1: cam_K must be 9 numbers \(row-major 3x3\), got \['a', 'a'",
        ),
        (
            "scene_camera.json",
            {"1": {"cam_K": "123456789"}, "2": {"cam_K": K.reshape(-1).tolist()}},
            r"scene_camera.json: im_id 1: cam_K must be 9 numbers \(row-major 3x3\), got '123456789'",
        ),
        (
            "scene_gt.json",
            [[{"obj_id": 5}]],
            r"scene_gt.json: expected a mapping im_id -> list of object poses, got a list",
        ),
        ("scene_gt.json", {"first": []}, r"scene_gt.json: key 'first' is not an integer im_id"),
        ("scene_gt.json", {"1": {"obj_id": 5}}, r"scene_gt.json: im_id 1: expected a list of object poses, got a dict"),
    ],
)
def test_bop_malformed_fields_name_file_and_field(tmp_path, file, content, match):
    make_bop(tmp_path)
    (tmp_path / "000048" / file).write_text(json.dumps(content))
    with pytest.raises(DataError, match=match):
        list(BopFrameSource(tmp_path))
