"""`batchpose run` on MCAP input: the full job on a converted log, and bad logs from the CLI (issue 3/4)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.schema import build_file_descriptor_set

from batchpose import convert, run
from tests.conftest import ROOT
from tests.test_mcap_io import (
    T0,
    Log,
    _calib,
    _enc,
    _mosaic,
    _simple_log,
    encode_video,
    ros1_camera_info,
    ros1_image,
    ros1_log,
    ros1_record,
)

PIPELINE = ROOT / "pipelines" / "gnc_pose.yaml"
MODELS = ROOT / "demo_data" / "models"


def _manifest(tmp_path, log_path) -> str:
    m = tmp_path / "m.yaml"
    m.write_text(
        f"name: log\nframes: {{format: mcap, path: {log_path}}}\n"
        f"models: {{root: {MODELS}, mesh: '{{name}}/textured.obj', points: '{{name}}/points.xyz'}}\n"
        "objects: [009_gelatin_box]\ntargets: annotations\n"
    )
    return str(m)


def _demo_log(tmp_path) -> Path:
    """The bundled demo frames converted to a log (Foxglove PNG images, calibration, depth, ground truth)."""
    return convert.main(ROOT / "demo_data" / "ycbv", tmp_path / "demo.mcap", fmt="ycbv")


def _rewritten(src: Path, dst: Path, rewrite, profile: str = "") -> Path:
    """A copy of the log ``src`` with each message through ``rewrite(schema, channel, message)``: None drops
    it, else (topic, schema name, schema encoding, schema data, message encoding, message data)."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        w = Writer(g)
        w.start(profile=profile, library="test")
        ids: dict[str, int] = {}
        for schema, ch, m in make_reader(f).iter_messages():
            rec = rewrite(schema, ch, m)
            if rec is None:
                continue
            topic, name, schema_encoding, schema_data, encoding, data = rec
            if topic not in ids:
                ids[topic] = w.register_channel(topic, encoding, w.register_schema(name, schema_encoding, schema_data))
            w.add_message(ids[topic], log_time=m.log_time, data=data, publish_time=m.publish_time)
        w.finish()
    return dst


def _run_keeps_the_log_and_finds_the_gelatin_box(tmp_path, log_path, cache_dir) -> tuple[set[str], set[str]]:
    """The whole job on the log: its messages are in poses.mcap byte for byte and the gelatin box's three
    poses are within 0.1 d. Returns the input's and the output's topics."""
    out = run.main(PIPELINE, _manifest(tmp_path, log_path), tmp_path / "run", cache_dir=cache_dir, jobs=1)
    with open(log_path, "rb") as f:
        inp = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]
    with open(out / "poses.mcap", "rb") as f:
        outp = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f, validate_crcs=True).iter_messages()]
    assert set(inp) <= set(outp)
    frames = pd.read_csv(out / "report" / "frames.csv")
    gel = frames[frames["obj_name"] == "009_gelatin_box"]
    assert len(gel) == 3 and (gel["add_m"] < 0.1 * gel["diameter_m"]).all(), gel[["status", "add_m"]]
    return {t for t, _, _ in inp}, {t for t, _, _ in outp}


def _rgb(m) -> np.ndarray:
    """The RGB pixels of a converted log's /camera/image message."""
    png = CompressedImage.FromString(m.data).data
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]


@pytest.mark.slow
def test_run_on_converted_log_keeps_input_and_adds_poses(tmp_path, cache_dir):
    _, topics = _run_keeps_the_log_and_finds_the_gelatin_box(tmp_path, _demo_log(tmp_path), cache_dir)
    assert {"/camera/image", "/camera/calibration"} <= topics
    assert len(topics) > 3  # pose topics were added


def _as_ros1_bayer(schema, ch, m):
    """A converted demo log's message as a ROS 1 colour-filter camera records it: bayer_rggb8
    sensor_msgs/Image and sensor_msgs/CameraInfo (ros1 encoding), the ground truth kept as it is (JSON), no
    depth (a :func:`_rewritten` rewrite)."""
    t = m.log_time
    if ch.topic == "/camera/depth":
        return None
    if ch.topic == "/camera/calibration":
        cal = CameraCalibration.FromString(m.data)
        info = ros1_camera_info(t, np.reshape(cal.K, (3, 3)), cal.width, cal.height, cal.D)
        topic, name, definition, data, _ = ros1_record("/camera/camera_info", info, t)
    elif ch.topic == "/camera/image":
        img = ros1_image(t, _mosaic(_rgb(m), "rggb"), "bayer_rggb8")
        topic, name, definition, data, _ = ros1_record("/camera/image_raw", img, t)
    else:
        return ch.topic, schema.name, schema.encoding, schema.data, ch.message_encoding, m.data
    return topic, name, "ros1msg", definition, "ros1", data


@pytest.mark.slow
def test_run_on_a_ros1_bayer_log(tmp_path, cache_dir):
    # A ROS 1 bag of a colour-filter camera, converted with `mcap convert`: the whole job reads it, finds
    # the poses and writes them beside the log's own messages.
    log_path = _rewritten(_demo_log(tmp_path), tmp_path / "ros1.mcap", _as_ros1_bayer, profile="ros1")
    inp, outp = _run_keeps_the_log_and_finds_the_gelatin_box(tmp_path, log_path, cache_dir)
    assert inp == {"/camera/image_raw", "/camera/camera_info", "/ground_truth/poses"}
    assert {"/batchpose/tf", "/tf"} <= outp  # a ROS log gets the poses on /tf too
    layout = json.loads((tmp_path / "run" / "foxglove_layout.json").read_text())["configById"]
    assert layout["Image!batchpose"]["imageMode"]["imageTopic"] == "/camera/image_raw"
    assert layout["Image!batchpose"]["imageMode"]["calibrationTopic"] == "/camera/camera_info"
    assert layout["3D!batchpose"]["followTf"] == "cam"  # the ROS 1 header's frame_id


@pytest.mark.slow
def test_run_on_a_foxglove_video_log(tmp_path, cache_dir):
    # The demo frames as Foxglove's CompressedVideo (H.264, as a recorder that saves space writes them).
    fox = _demo_log(tmp_path)
    with open(fox, "rb") as f:
        images = [_rgb(m) for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/camera/image"]
    packets = iter(encode_video(images, gop=30))
    video_schema = build_file_descriptor_set(CompressedVideo).SerializeToString()

    def as_video(schema, ch, m):
        if ch.topic == "/camera/depth":
            return None
        if ch.topic != "/camera/image":
            return ch.topic, schema.name, schema.encoding, schema.data, ch.message_encoding, m.data
        img = CompressedImage.FromString(m.data)
        video = CompressedVideo(frame_id=img.frame_id, format="h264", data=next(packets))
        video.timestamp.CopyFrom(img.timestamp)
        return (
            "/camera/video",
            "foxglove.CompressedVideo",
            "protobuf",
            video_schema,
            "protobuf",
            video.SerializeToString(),
        )

    log_path = _rewritten(fox, tmp_path / "video.mcap", as_video)
    _, outp = _run_keeps_the_log_and_finds_the_gelatin_box(tmp_path, log_path, cache_dir)
    assert "/batchpose/annotations" in outp


def _bad_logs(tmp_path):
    not_mcap = tmp_path / "photo.mcap"
    not_mcap.write_bytes(_enc(np.zeros((4, 4, 3), np.uint8)))
    cut = tmp_path / "cut.mcap"
    _simple_log(cut)
    cut.write_bytes(cut.read_bytes()[:200])
    crc = tmp_path / "crc.mcap"
    datas = _simple_log(crc)
    raw = bytearray(crc.read_bytes())
    raw[raw.find(datas[1]) + 100] ^= 0xFF
    crc.write_bytes(bytes(raw))
    imu = tmp_path / "imu.mcap"
    log_ = Log(imu)
    log_.json("/imu", {"a": 1}, T0)
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.close()
    bad_schema = tmp_path / "ros1.mcap"  # a ROS 1 image topic whose message definition does not parse
    ros1_log(
        bad_schema,
        [
            ros1_record("/cam/camera_info", ros1_camera_info(T0), T0),
            ("/cam/image", "sensor_msgs/Image", b"Header header\n!!\n", bytes(64), T0),
        ],
    )
    fisheye = tmp_path / "fisheye.mcap"  # a calibration OpenCV's pinhole model would misread
    info = ros1_camera_info(T0, dist=[0.1, 0.01, -0.002, 0.0003])
    info.distortion_model = "equidistant"
    img = ros1_image(T0, np.zeros((48, 64), np.uint8), "mono8")
    ros1_log(fisheye, [ros1_record("/cam/camera_info", info, T0), ros1_record("/cam/image_raw", img, T0)])
    return [
        (fisheye, "fisheye.mcap:/cam/camera_info: calibration at log time"),
        (bad_schema, "ros1.mcap:/cam/image: cannot read its ros1 schema 'sensor_msgs/Image'"),
        (not_mcap, "photo.mcap: not an MCAP file"),
        (cut, "cut.mcap: truncated MCAP"),
        (crc, "crc.mcap: CRC mismatch"),
        (imu, "imu.mcap: no image topic"),
    ]


def test_bad_logs_from_the_cli_are_one_line_exit_2(tmp_path):
    for path, expect in _bad_logs(tmp_path):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "batchpose",
                "run",
                str(PIPELINE),
                "--manifest",
                _manifest(tmp_path, path),
                "--out",
                str(tmp_path / f"out-{path.stem}"),
                "--cache",
                str(tmp_path / "cache"),
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("batchpose: error:")]
        assert r.returncode == 2, r.stderr
        assert len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
        assert expect in errors[0], errors[0]
