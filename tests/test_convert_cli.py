"""``batchpose convert`` through the CLI: folder -> MCAP -> frames round trip, and one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
import yaml

from batchpose import convert
from batchpose.core.frames import decode_image
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.sources import open_frames

K = np.array([[500.0, 0.0, 15.5], [0.0, 510.0, 11.5], [0.0, 0.0, 1.0]])


def make_ycbv(root: Path, seed: int = 0) -> None:
    """Video 0002 with two frames and one synthetic frame."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    (root / "classes.txt").write_text("002_master_chef_can\n003_cracker_box\n")
    for rel, cls in (("data/0002/000001", [1, 2]), ("data/0002/000002", [2]), ("data_syn/000003", [1])):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / f"{rel}-color.png"), rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
        poses = rng.normal(size=(3, 4, len(cls)))
        scipy.io.savemat(
            root / f"{rel}-meta.mat",
            {
                "cls_indexes": np.array(cls).reshape(-1, 1),
                "poses": poses,
                "intrinsic_matrix": K,
            },
        )


def make_images(root: Path, n: int = 2, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / f"{i:04d}.jpg"), rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
    (root / "intrinsics.yaml").write_text(
        yaml.safe_dump(
            {
                "fx": 500.0,
                "fy": 510.0,
                "cx": 15.5,
                "cy": 11.5,
                "width": 32,
                "height": 24,
                "dist": [0.1, 0, 0, 0, 0],
            }
        )
    )


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "batchpose", *args], capture_output=True, text=True, timeout=120, check=False
    )


def assert_one_line_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("batchpose: error:")]
    assert len(lines) == 1, res.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_convert_ycbv_then_ingest_identical(tmp_path):
    make_ycbv(tmp_path / "ycbv")
    out = tmp_path / "out" / "ycbv.mcap"
    res = run_cli("convert", str(tmp_path / "ycbv"), str(out), "--format", "ycbv")
    assert res.returncode == 0, res.stderr
    assert "converted 3 / 3 frames" in res.stderr
    folder = list(open_frames({"format": "ycbv", "root": str(tmp_path / "ycbv")}, tmp_path))
    src = McapFrameSource(out)
    logged = list(src)
    assert len(logged) == 3 == src.count()
    for a, b in zip(folder, logged, strict=True):
        np.testing.assert_array_equal(decode_image(b), decode_image(a))
        np.testing.assert_array_equal(b.camera.K, a.camera.K)
        assert (b.scene_id, b.im_id) == (a.scene_id, a.im_id)
        assert [g.obj_name for g in b.gt] == [g.obj_name for g in a.gt]
        for ga, gb in zip(a.gt, b.gt, strict=True):
            np.testing.assert_array_equal(gb.cam_from_model, ga.cam_from_model)
    assert src.obj_id("003_cracker_box") == 2


def test_convert_images_and_bop_in_process(tmp_path):
    make_images(tmp_path / "imgs")
    assert convert.main(tmp_path / "imgs", tmp_path / "imgs.mcap", "images") == tmp_path / "imgs.mcap"
    frames = list(McapFrameSource(tmp_path / "imgs.mcap"))
    assert [f.image_data for f in frames] == [p.read_bytes() for p in sorted((tmp_path / "imgs").glob("*.jpg"))]
    np.testing.assert_array_equal(frames[0].camera.dist, [0.1, 0, 0, 0, 0])

    scene = tmp_path / "bop" / "000001"
    (scene / "rgb").mkdir(parents=True)
    cv2.imwrite(str(scene / "rgb" / "000004.png"), np.full((24, 32, 3), 200, np.uint8))
    (scene / "scene_camera.json").write_text(json.dumps({"4": {"cam_K": K.reshape(-1).tolist()}}))
    (scene / "scene_gt.json").write_text(
        json.dumps({"4": [{"obj_id": 7, "cam_R_m2c": np.eye(3).reshape(-1).tolist(), "cam_t_m2c": [10, 20, 800]}]})
    )
    convert.main(tmp_path / "bop", tmp_path / "bop.mcap", "bop")
    src = McapFrameSource(tmp_path / "bop.mcap")
    (f,) = src
    assert (f.scene_id, f.im_id, f.gt[0].obj_name) == (1, 4, "obj_000007")
    np.testing.assert_allclose(f.gt[0].cam_from_model[:3, 3], [0.01, 0.02, 0.8])
    assert src.obj_id("obj_000007") == 7


def test_convert_refuses_to_overwrite(tmp_path):
    make_images(tmp_path / "imgs")
    out = tmp_path / "x.mcap"
    out.write_bytes(b"precious")
    res = run_cli("convert", str(tmp_path / "imgs"), str(out), "--format", "images")
    assert_one_line_error(res, str(out), "already exists", "--overwrite")
    assert out.read_bytes() == b"precious"
    convert.main(tmp_path / "imgs", out, "images", overwrite=True)
    assert McapFrameSource(out).count() == 2
    tmp = tmp_path / "y.mcap.tmp"  # a file of the user's that happens to have the temporary name
    tmp.write_bytes(b"mine too")
    res = run_cli("convert", str(tmp_path / "imgs"), str(tmp_path / "y.mcap"), "--format", "images")
    assert_one_line_error(res, str(tmp), "already exists", "remove or rename it first")
    assert tmp.read_bytes() == b"mine too"


def test_convert_zero_size_image(tmp_path):
    make_images(tmp_path / "imgs")
    (tmp_path / "imgs" / "0001.jpg").write_bytes(b"")
    out = tmp_path / "x.mcap"
    res = run_cli("convert", str(tmp_path / "imgs"), str(out), "--format", "images")
    assert_one_line_error(res, str(tmp_path / "imgs" / "0001.jpg"), "image is empty (0 bytes)")
    assert not out.exists() and not (tmp_path / "x.mcap.tmp").exists()  # atomic: nothing half-written


@pytest.mark.parametrize(
    ("breakage", "needles"),
    [
        ("corrupt", ("0000.jpg", "not a readable PNG/JPEG")),
        ("size", ("0000.jpg", "image is 16x8 but its intrinsics are for 32x24")),
        ("intrinsics", ("intrinsics.yaml", "unknown key 'fov'")),
        ("missing", ("does not exist",)),
    ],
)
def test_convert_bad_input(tmp_path, breakage, needles):
    make_images(tmp_path / "imgs")
    if breakage == "corrupt":
        (tmp_path / "imgs" / "0000.jpg").write_bytes(b"\x00garbage")
    elif breakage == "size":
        cv2.imwrite(str(tmp_path / "imgs" / "0000.jpg"), np.zeros((8, 16, 3), np.uint8))
    elif breakage == "intrinsics":
        spec = yaml.safe_load((tmp_path / "imgs" / "intrinsics.yaml").read_text())
        (tmp_path / "imgs" / "intrinsics.yaml").write_text(yaml.safe_dump({**spec, "fov": 60}))
    src = tmp_path / ("nowhere" if breakage == "missing" else "imgs")
    res = run_cli("convert", str(src), str(tmp_path / "x.mcap"), "--format", "images")
    assert_one_line_error(res, *needles)
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.mcap.tmp").exists()
