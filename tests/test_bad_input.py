"""Bad meshes, cameras and images give a BatchposeError naming the problem, or a failed record in a batch."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from batchpose.config import EstimatorConfig, MeshConfig
from batchpose.core.frames import Camera, Frame
from batchpose.errors import CameraError, ImageError, MeshError
from batchpose.io.mesh import load_mesh
from batchpose.method.estimator import PoseEstimator
from tests.conftest import GELATIN, K_SYN

TRI = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n"


def test_missing_mesh(tmp_path):
    with pytest.raises(MeshError, match="mesh file not found"):
        load_mesh(tmp_path / "nope.obj")


def test_corrupt_mesh(tmp_path):
    p = tmp_path / "bad.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01garbage")
    with pytest.raises(MeshError, match="bad.ply"):
        load_mesh(p)


def test_mesh_without_faces(tmp_path):
    p = tmp_path / "points.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="no faces"):
        load_mesh(p)


def test_mesh_without_texture(tmp_path):
    p = tmp_path / "plain.obj"
    p.write_text(TRI)
    with pytest.raises(MeshError, match="no texture or vertex colours"):
        load_mesh(p)


def test_millimetre_mesh_converted_or_refused(tmp_path, caplog):
    # Scale the bundled gelatin box to millimetres.
    src = load_mesh(GELATIN).mesh.copy()
    src.apply_scale(1000.0)
    p = tmp_path / "gelatin_mm.ply"
    src.export(p)
    m = load_mesh(p)
    assert m.scale == 0.001
    assert 0.05 < m.diameter_m < 0.2
    assert "millimetres" in caplog.text
    with pytest.raises(MeshError, match="looks like millimetres"):
        load_mesh(p, MeshConfig(on_millimetres="refuse"))


@pytest.mark.parametrize(
    "K, msg",
    [
        (np.array([[np.nan, 0, 320], [0, 800, 240], [0, 0, 1]]), "NaN"),
        (np.array([[-800.0, 0, 320], [0, 800, 240], [0, 0, 1]]), "focal lengths must be positive"),
        (np.array([[0.0, 0, 320], [0, 800, 240], [0, 0, 1]]), "focal lengths must be positive"),
        (np.array([[800.0, 0, 0], [0, 800, 0], [320, 240, 1]]), r"K must be \[\[fx, s, cx\], \[0, fy, cy\]"),
    ],
)
def test_bad_intrinsics(cracker_library, K, msg):
    est = PoseEstimator(EstimatorConfig(), {cracker_library.obj_name: cracker_library})
    rgb = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    with pytest.raises(CameraError, match=msg):
        est.estimate_image(rgb, Camera(K, 640, 480), [cracker_library.obj_name], frame_id="f1")


@pytest.mark.parametrize(
    "rgb, msg",
    [
        (np.zeros((480, 640, 3), np.uint8), "blank"),
        (np.zeros((0, 0, 3), np.uint8), "expected an"),
    ],
)
def test_empty_or_black_image(cracker_library, rgb, msg):
    est = PoseEstimator(EstimatorConfig(), {cracker_library.obj_name: cracker_library})
    with pytest.raises(ImageError, match=msg):
        est.estimate_image(rgb, Camera(K_SYN, 640, 480), [cracker_library.obj_name])


def test_batch_turns_bad_input_into_failed_records(cracker_library):
    name = cracker_library.obj_name
    est = PoseEstimator(EstimatorConfig(), {name: cracker_library})
    black = cv2.imencode(".png", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    good_cam = Camera(K_SYN, 640, 480)
    frames = [
        Frame("black", 0, 0, 0, good_cam, "png", black, source="black.png"),
        Frame("empty", 0, 1, 1, good_cam, "png", b"", source="empty.png"),
        Frame("garbage", 0, 2, 2, good_cam, "jpeg", b"not a jpeg", source="garbage.jpg"),
        Frame("weird", 0, 3, 3, good_cam, "nv21", b"\x00" * 100, source="log.mcap:/cam"),
        Frame("nan_k", 0, 4, 4, Camera(K_SYN * np.nan, 640, 480), "png", black, source="nan.png"),
    ]
    out = {f.frame_id: est.estimate_frame(f, [name])[0] for f in frames}
    assert out["black"].status == "bad_image" and "blank" in out["black"].reason
    assert out["empty"].status == "bad_image" and "empty" in out["empty"].reason
    assert out["garbage"].status == "bad_image" and "cannot decode" in out["garbage"].reason
    assert out["weird"].status == "bad_image" and "unsupported image encoding 'nv21'" in out["weird"].reason
    assert out["nan_k"].status == "bad_camera" and "NaN" in out["nan_k"].reason


def test_a_full_disk_names_the_output_folders(tmp_path, monkeypatch, capsys):
    """A write that fails for space rarely names its file: the line names the command's folders instead."""
    import errno

    from batchpose import cli
    from batchpose.stages import report as report_stage

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report_stage, "main", full)
    assert cli.main(["report", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"batchpose: error: no space left on device: run dir {tmp_path / 'run'} (")
    assert err[0].endswith("MB free now). Free some space and rerun the same command: finished work is kept")

    from batchpose import convert

    monkeypatch.setattr(convert, "main", lambda src, out, fmt, overwrite=False: full(out))
    out = tmp_path / "log.mcap"
    assert cli.main(["convert", str(tmp_path), str(out), "--format", "images"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"batchpose: error: no space left on device: output {out} ("), err
