"""MCAP reading (foxglove + ROS 2), writing, write-back and bad logs, on tiny logs built here
(batchpose.io.mcap_read, mcap_write, mcap_poses and the modules they use)."""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import importlib
import io
import json
import logging
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import register_schema
from mcap_ros1.decoder import dynamic as ros1_dynamic
from mcap_ros1.writer import Writer as Ros1Writer
from mcap_ros2.writer import Writer as Ros2Writer
from PIL import Image
from scipy.spatial.transform import Rotation

from batchpose.core.frames import Camera, Frame, ObjectPose, decode_image
from batchpose.errors import CameraError, ConfigError, DataError, ImageError
from batchpose.io.gltf import mesh_to_glb
from batchpose.io.mcap_poses import write_poses_mcap
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_topics import (
    ANNOTATIONS_TOPIC,
    DEPTH_TOPIC,
    GT_TOPIC,
    IMAGE_TOPIC,
    SCENE_TOPIC_PREFIX,
    STATUS_TOPIC,
    TF_TOPIC,
)
from batchpose.io.mcap_write import write_frames_mcap

W, H = 64, 48
K1 = np.array([[80.0, 0.0, 31.5], [0.0, 82.0, 23.5], [0.0, 0.0, 1.0]])
K2 = np.array([[90.0, 0.0, 30.0], [0.0, 91.0, 22.0], [0.0, 0.0, 1.0]])
T0 = 1_700_000_000_000_000_000
DT = 50_000_000


def _img(rng: np.random.Generator) -> np.ndarray:
    # Smooth colour blobs so that JPEG keeps them recognisable; a few per image, all distinct.
    img = cv2.resize(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)
    return img


def _enc(img: np.ndarray, ext: str = ".png") -> bytes:
    return cv2.imencode(ext, img)[1].tobytes()


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    T[:3, 3] = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 1.0)]
    return T


def _frames(n: int, ext: str = ".png", seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    cam = Camera(K=K1, width=W, height=H, dist=np.array([0.01, -0.002, 0.0, 0.0, 0.0]), distortion_model="plumb_bob")
    return [
        Frame(
            frame_id=f"0001/{i:06d}",
            scene_id=1,
            im_id=i,
            stamp_ns=T0 + i * DT,
            camera=cam,
            image_format="png" if ext == ".png" else "jpeg",
            image_data=_enc(_img(rng), ext),
            gt=(ObjectPose("003_cracker_box", _pose(rng)), ObjectPose("004_sugar_box", _pose(rng))),
            source=f"f{i}",
        )
        for i in range(n)
    ]


class Log:
    """A small MCAP written with the plain mcap writer (so tests control chunking and compression)."""

    def __init__(
        self, path: Path, chunk_size: int = 1 << 20, summary: bool = True, profile: str = "", library: str = "test"
    ) -> None:
        self.f = open(path, "wb")  # noqa: SIM115 - closed in close()
        kw = (
            {}
            if summary
            else {
                "index_types": IndexType.NONE,
                "repeat_channels": False,
                "repeat_schemas": False,
                "use_statistics": False,
                "use_summary_offsets": False,
            }
        )
        self.w = Writer(self.f, chunk_size=chunk_size, compression=CompressionType.NONE, **kw)
        self.w.start(profile=profile, library=library)
        self.channels: dict[str, int] = {}

    def proto(self, topic: str, msg, t: int, seq: int = 0) -> None:
        if topic not in self.channels:
            sid = register_schema(self.w, type(msg))
            self.channels[topic] = self.w.register_channel(topic, "protobuf", sid)
        self.w.add_message(
            self.channels[topic], log_time=t, data=msg.SerializeToString(), publish_time=t + 7, sequence=seq
        )

    def json(self, topic: str, obj, t: int, schema: str = "test.Thing") -> None:
        if topic not in self.channels:
            sid = self.w.register_schema(schema, "jsonschema", b'{"type":"object"}')
            self.channels[topic] = self.w.register_channel(topic, "json", sid, {"unit": "m/s2"})
        self.w.add_message(self.channels[topic], log_time=t, data=json.dumps(obj).encode(), publish_time=t)

    def close(self) -> None:
        self.w.finish()
        self.f.close()


def _calib(t: int, K: np.ndarray = K1, frame_id: str = "cam_optical", w: int = W, h: int = H) -> CameraCalibration:
    c = CameraCalibration(
        frame_id=frame_id,
        width=w,
        height=h,
        distortion_model="plumb_bob",
        D=[0.1, 0.0, 0.0, 0.0, 0.0],
        K=K.reshape(-1).tolist(),
        P=np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist(),
    )
    c.timestamp.FromNanoseconds(t)
    return c


def _cimg(t: int, data: bytes, fmt: str = "jpeg", frame_id: str = "cam_optical") -> CompressedImage:
    m = CompressedImage(frame_id=frame_id, format=fmt, data=data)
    m.timestamp.FromNanoseconds(t)
    return m


def _simple_log(path: Path, n: int = 4, seed: int = 0, **kw) -> list[bytes]:
    rng = np.random.default_rng(seed)
    datas = [_enc(_img(rng), ".jpg") for _ in range(n)]
    log_ = Log(path, **kw)
    for i, d in enumerate(datas):
        t = T0 + i * DT
        log_.proto("/cam/calibration", _calib(t), t)
        log_.proto("/cam/image", _cimg(t, d), t, seq=i)
    log_.close()
    return datas


# ------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_convert_then_ingest_identical_pixels_and_K(tmp_path, ext):
    frames = _frames(3, ext)
    out = tmp_path / "log.mcap"
    assert write_frames_mcap(iter(frames), out, obj_ids={"003_cracker_box": 2, "004_sugar_box": 3}) == 3
    assert not (tmp_path / "log.mcap.tmp").exists()
    src = McapFrameSource(out)
    assert (src.image_topic, src.calibration_topic, src.gt_topic, src.count()) == (
        "/camera/image",
        "/camera/calibration",
        "/ground_truth/poses",
        3,
    )
    back = list(src)
    for a, b in zip(frames, back, strict=True):
        assert b.image_data == a.image_data  # bytes copied, never re-encoded
        np.testing.assert_array_equal(decode_image(b), decode_image(a))
        np.testing.assert_array_equal(b.camera.K, a.camera.K)
        np.testing.assert_array_equal(b.camera.dist, a.camera.dist)
        assert (b.camera.width, b.camera.height, b.camera.distortion_model) == (W, H, "plumb_bob")
        assert (b.stamp_ns, b.scene_id, b.im_id, b.frame_id) == (a.stamp_ns, 1, a.im_id, f"mcap:{a.stamp_ns}")
        assert [g.obj_name for g in b.gt] == [g.obj_name for g in a.gt]
        for ga, gb in zip(a.gt, b.gt, strict=True):
            np.testing.assert_array_equal(gb.cam_from_model, ga.cam_from_model)
    assert src.obj_id("004_sugar_box") == 3 and src.obj_id("nope") == 0


def test_raw_frames_written_as_raw_image(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    step = W * 3 + 8  # padded rows
    data = np.zeros((H, step), np.uint8)
    data[:, : W * 3] = rgb.reshape(H, -1)
    f = Frame("a", 0, 0, T0, Camera(K1, W, H), "rgb8", data.tobytes(), raw_step=step)
    write_frames_mcap([f], tmp_path / "raw.mcap")
    (b,) = McapFrameSource(tmp_path / "raw.mcap")
    assert (b.image_format, b.raw_step) == ("rgb8", step)
    np.testing.assert_array_equal(decode_image(b), rgb)


ROS_HEADER = """std_msgs/Header header
"""
ROS_DEPS = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
ROS_ROI = """================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
"""
ROS_IMAGE = (
    ROS_HEADER
    + """uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
"""
    + ROS_DEPS
)
ROS_COMPRESSED = ROS_HEADER + "string format\nuint8[] data\n" + ROS_DEPS
ROS_CAMERA_INFO = (
    ROS_HEADER
    + """uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
"""
    + ROS_DEPS
    + ROS_ROI
)


def _header(t: int) -> dict:
    return {"stamp": {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}, "frame_id": "camera_optical"}


def test_ros2_image_and_camera_info(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "ros2.mcap"
    dist = [0.1, -0.05, 0.001, 0.002, 0.01, 0.0, 0.0, 0.0]
    imgs = []
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        s_img = w.register_msgdef("sensor_msgs/msg/Image", ROS_IMAGE)
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", ROS_CAMERA_INFO)
        for i in range(3):
            t = T0 + i * DT
            w.write_message(
                "/robot/camera/camera_info",
                s_info,
                {
                    "header": _header(t),
                    "height": H,
                    "width": W,
                    "distortion_model": "rational_polynomial",
                    "d": dist,
                    "k": K2.reshape(-1).tolist(),
                    "r": np.eye(3).reshape(-1).tolist(),
                    "p": np.hstack([K2, np.zeros((3, 1))]).reshape(-1).tolist(),
                    "binning_x": 0,
                    "binning_y": 0,
                    "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
                },
                log_time=t,
            )
            bgr = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            imgs.append(bgr)
            w.write_message(
                "/robot/camera/image_raw",
                s_img,
                {
                    "header": _header(t),
                    "height": H,
                    "width": W,
                    "encoding": "bgr8",
                    "is_bigendian": 0,
                    "step": W * 3,
                    "data": bgr.tobytes(),
                },
                log_time=t + 1000,
            )
        w.finish()
    src = McapFrameSource(path)
    assert (src.image_topic, src.calibration_topic, src.count()) == (
        "/robot/camera/image_raw",
        "/robot/camera/camera_info",
        3,
    )
    frames = list(src)
    for i, fr in enumerate(frames):
        assert (fr.image_format, fr.raw_step, fr.stamp_ns, fr.im_id) == ("bgr8", W * 3, T0 + i * DT + 1000, i)
        np.testing.assert_array_equal(decode_image(fr), imgs[i][:, :, ::-1])
        np.testing.assert_array_equal(fr.camera.K, K2)
        np.testing.assert_array_equal(fr.camera.dist, dist)
        assert (fr.camera.distortion_model, fr.camera.width, fr.camera.height) == (
            "rational_polynomial",
            W,
            H,
        )


def test_ros2_compressed_image(tmp_path):
    rng = np.random.default_rng(3)
    path = tmp_path / "ros2c.mcap"
    img = _img(rng)
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        s_img = w.register_msgdef("sensor_msgs/msg/CompressedImage", ROS_COMPRESSED)
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", ROS_CAMERA_INFO)
        w.write_message(
            "/cam/camera_info",
            s_info,
            {
                "header": _header(T0),
                "height": H,
                "width": W,
                "distortion_model": "plumb_bob",
                "d": [0.0] * 5,
                "k": K1.reshape(-1).tolist(),
            },
            log_time=T0,
        )
        w.write_message(
            "/cam/image/compressed",
            s_img,
            {"header": _header(T0), "format": "bgr8; png compressed bgr8", "data": _enc(img)},
            log_time=T0,
        )
        w.finish()
    (fr,) = McapFrameSource(path)
    assert fr.image_format == "png"
    np.testing.assert_array_equal(decode_image(fr), img[:, :, ::-1])
    np.testing.assert_array_equal(fr.camera.K, K1)


ROS1_DEPS = """================================================================================
MSG: std_msgs/Header
uint32 seq
time stamp
string frame_id
"""
ROS1_IMAGE = (
    "Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"
)
ROS1_CAMERA_INFO = """Header header
uint32 height
uint32 width
string distortion_model
float64[] D
float64[9] K
float64[9] R
float64[12] P
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
"""
#: ROS 1 message classes generated from their definitions, as ``mcap convert`` of a bag stores them.
ROS1 = {
    name: cls
    for name, text in (
        ("sensor_msgs/Image", ROS1_IMAGE),
        ("sensor_msgs/CompressedImage", "Header header\nstring format\nuint8[] data\n"),
        ("sensor_msgs/CameraInfo", ROS1_CAMERA_INFO + ROS_ROI),
    )
    for name, cls in ros1_dynamic.generate_dynamic(name, text + ROS1_DEPS).items()
}
ros1_genpy = importlib.import_module(ros1_dynamic.__package__)  # genpy: Time


def ros1_header(t: int, seq: int = 0):
    stamp = ros1_genpy.Time(t // 1_000_000_000, t % 1_000_000_000)
    return ROS1["std_msgs/Header"](seq=seq, stamp=stamp, frame_id="cam")


def ros1_image(t: int, px: np.ndarray, encoding: str, seq: int = 0, bigendian: bool = False):
    """A ROS 1 sensor_msgs/Image of the (H, W[, C]) array ``px``, rows as they lie in memory."""
    data = px.astype(px.dtype.newbyteorder(">")).tobytes() if bigendian else px.tobytes()
    return ROS1["sensor_msgs/Image"](
        header=ros1_header(t, seq),
        height=px.shape[0],
        width=px.shape[1],
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=px.strides[0],
        data=data,
    )


def ros1_camera_info(t: int, K: np.ndarray = K1, w: int = W, h: int = H, dist=(0.1, -0.05, 0.001, 0.002, 0.01)):
    return ROS1["sensor_msgs/CameraInfo"](
        header=ros1_header(t),
        height=h,
        width=w,
        distortion_model="plumb_bob",
        D=list(dist),
        K=K.reshape(-1).tolist(),
        R=np.eye(3).reshape(-1).tolist(),
        P=np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist(),
    )


def test_ros1_image_compressed_image_and_camera_info(tmp_path):
    # A ROS 1 bag converted to MCAP (`mcap convert`): ros1msg schemas, uppercase CameraInfo fields,
    # stamps in secs / nsecs, a Bayer camera and a big-endian 16-bit one.
    rng = np.random.default_rng(21)
    rgb = cv2.resize(rng.integers(0, 256, (3, 4, 3), np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)
    mono = rng.integers(0, 65535, (H, W), dtype=np.uint16)
    jpg = _enc(_img(rng), ".jpg")
    path = tmp_path / "ros1.mcap"
    with Ros1Writer(str(path)) as w:
        for i in range(3):
            t = T0 + i * DT
            w.write_message("/camera/camera_info", ros1_camera_info(t), log_time=t)
            w.write_message(
                "/camera/compressed",
                ROS1["sensor_msgs/CompressedImage"](header=ros1_header(t), format="jpeg", data=jpg),
                log_time=t,
            )
            bayer = ros1_image(t + 7, _mosaic(rgb, "rggb"), "bayer_rggb8", seq=i)
            w.write_message("/camera/image_raw", bayer, log_time=t + 1000)
            w.write_message("/ir/image_raw", ros1_image(t, mono, "mono16", bigendian=True), log_time=t)
    src = McapFrameSource(path, image_topic="/camera/image_raw")
    assert (src.calibration_topic, src.count()) == ("/camera/camera_info", 3)
    frames = list(src)
    assert [f.stamp_ns for f in frames] == [T0 + i * DT + 1000 for i in range(3)]
    for fr in frames:
        assert (fr.image_format, fr.raw_step, fr.camera.width, fr.camera.height) == ("bayer_rggb8", W, W, H)
        np.testing.assert_array_equal(fr.camera.K, K1)
        np.testing.assert_array_equal(fr.camera.dist, [0.1, -0.05, 0.001, 0.002, 0.01])
        assert np.abs(decode_image(fr).astype(int) - rgb)[2:-2, 2:-2].mean() < 3
    (c,) = list(McapFrameSource(path, image_topic="/camera/compressed"))[:1]
    np.testing.assert_array_equal(
        decode_image(c), cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    )
    (ir, *_) = McapFrameSource(path, image_topic="/ir/image_raw", calibration_topic="/camera/camera_info")
    np.testing.assert_array_equal(decode_image(ir)[:, :, 0], (mono / 257).astype(np.uint8))


@pytest.mark.parametrize(
    ("topic", "rectified", "expect"),
    [
        ("/stereo/left/image_rect_color", None, "P"),
        ("/stereo/left/image_rect/compressed", None, "P"),
        ("/stereo/left/image_raw", None, "K"),
        ("/stereo/left/image_raw", True, "P"),
        ("/stereo/left/image_rect_color", False, "K"),
    ],
)
def test_rectified_images_take_the_projection_matrix(tmp_path, topic, rectified, expect):
    # ROS's CameraInfo: K and D describe the raw image; a rectified image (image_proc's image_rect*) has
    # no distortion left and its camera is P's left 3x3, which differs from K.
    P = np.array([[70.0, 0.0, 33.0, -7.0], [0.0, 70.0, 22.5, 0.0], [0.0, 0.0, 1.0, 0.0]])
    info = ros1_camera_info(T0)
    info.P = P.reshape(-1).tolist()
    img = ros1_image(T0, np.zeros((H, W), np.uint8), "mono8")
    ros1_log(tmp_path / "rect.mcap", [ros1_record("/stereo/left/camera_info", info, T0), ros1_record(topic, img, T0)])
    src = McapFrameSource(tmp_path / "rect.mcap", rectified=rectified)
    (fr,) = src
    assert src.rectified == (expect == "P")
    if expect == "P":
        np.testing.assert_array_equal(fr.camera.K, P[:, :3])
        assert fr.camera.dist.size == 0
    else:
        np.testing.assert_array_equal(fr.camera.K, K1)
        np.testing.assert_array_equal(fr.camera.dist, [0.1, -0.05, 0.001, 0.002, 0.01])


@pytest.mark.parametrize(
    ("model", "dist", "topic", "match"),
    [
        (
            "equidistant",
            [0.1, 0.01, -0.002, 0.0003],
            "/cam/image_raw",
            "distortion model 'equidistant' is not supported",
        ),
        ("plumb_bob", [0.1, 0.01, 0.0], "/cam/image_raw", "3 distortion coefficients; OpenCV's model takes 4, 5,"),
        ("equidistant", [0.1, 0.01, -0.002, 0.0003], "/cam/image_rect", None),  # rectified: P, no distortion
        ("equidistant", [0.0, 0.0, 0.0, 0.0], "/cam/image_raw", None),  # no distortion to misread
    ],
)
def test_a_distortion_opencv_cannot_apply_is_refused(tmp_path, model, dist, topic, match):
    # A fisheye camera's four equidistant coefficients read as plumb_bob's k1, k2, p1, p2 would give poses
    # that look fine and are wrong.
    info = ros1_camera_info(T0, dist=dist)
    info.distortion_model = model
    records = [
        ros1_record("/cam/camera_info", info, T0),
        ros1_record(topic, ros1_image(T0, np.zeros((H, W), np.uint8), "mono8"), T0),
    ]
    ros1_log(tmp_path / "fisheye.mcap", records)
    if match is None:
        (fr,) = McapFrameSource(tmp_path / "fisheye.mcap")
        assert fr.camera.validate() is fr.camera
    else:
        with pytest.raises(CameraError, match=rf"fisheye.mcap:/cam/camera_info: calibration at log time {T0}: {match}"):
            list(McapFrameSource(tmp_path / "fisheye.mcap"))


def test_rectified_images_without_a_projection_matrix_are_refused(tmp_path):
    img = ros1_image(T0, np.zeros((H, W), np.uint8), "mono8")
    info = ros1_camera_info(T0)
    info.P = [0.0] * 12  # an uncalibrated driver's CameraInfo
    ros1_log(
        tmp_path / "rect.mcap", [ros1_record("/cam/camera_info", info, T0), ros1_record("/cam/image_rect", img, T0)]
    )
    with pytest.raises(CameraError, match=r"the images on /cam/image_rect are rectified but the calibration at log "):
        list(McapFrameSource(tmp_path / "rect.mcap"))
    # Told they are not rectified, the run reads them with K and D, and so does the write-back.
    assert len(list(McapFrameSource(tmp_path / "rect.mcap", rectified=False))) == 1
    out = write_poses_mcap(
        tmp_path / "poses.mcap", _rows([T0], np.random.default_rng(0), fail=set()), {"box": _box_glb()},
        input_mcap=tmp_path / "rect.mcap", rectified=False,
    ).path  # fmt: skip
    with open(out, "rb") as f:
        r = make_reader(f)
        assert r.get_header().profile == ""  # ROS 1's profile allows ros1 channels only; poses are protobuf
        assert "/batchpose/annotations" in {c.topic for c in r.get_summary().channels.values()}


def ros1_record(topic: str, msg, t: int) -> tuple[str, str, bytes, bytes, int]:
    """One message of :func:`ros1_log`: topic, type, definition, serialized bytes, log time."""
    buf = io.BytesIO()
    msg.serialize(buf)
    return topic, msg._type, msg._full_text.encode(), buf.getvalue(), t


def ros1_log(path: Path, records: list[tuple[str, str, bytes, bytes, int]]) -> None:
    """A log laid out as `mcap convert` writes a ROS 1 bag, from :func:`ros1_record` tuples (any bytes).
    Its chunks are LZ4-compressed (:class:`Log` writes them plain, the ROS writers zstd)."""
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.LZ4)
        w.start(profile="ros1", library="test")
        channels = {}
        for topic, type_, definition, data, t in records:
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "ros1", w.register_schema(type_, "ros1msg", definition))
            w.add_message(channels[topic], log_time=t, data=data, publish_time=t)
        w.finish()


def test_a_realsense_log_is_read_from_its_colour_camera(tmp_path):
    # The infrared topics come first in the file; depth is never the image topic.
    records = []
    for cam, enc in (("infra1", "mono8"), ("depth", "mono16"), ("aligned_depth_to_color", "mono16"), ("color", "rgb8")):
        px = np.zeros((H, W, 3) if enc == "rgb8" else (H, W), np.uint16 if enc == "mono16" else np.uint8)
        rect = "image_rect_raw" if cam != "color" else "image_raw"
        records += [
            ros1_record(f"/camera/{cam}/camera_info", ros1_camera_info(T0), T0),
            ros1_record(f"/camera/{cam}/{rect}", ros1_image(T0, px, enc), T0),
        ]
    ros1_log(tmp_path / "d435.mcap", records)
    src = McapFrameSource(tmp_path / "d435.mcap")
    assert (src.image_topic, src.calibration_topic) == ("/camera/color/image_raw", "/camera/color/camera_info")


def test_ros1_image_message_cut_short_fails_only_its_frame(tmp_path):
    img = ros1_image(T0, np.zeros((H, W), np.uint8), "mono8")
    records = []
    for t in (T0, T0 + DT):
        records += [ros1_record("/cam/camera_info", ros1_camera_info(t), t), ros1_record("/cam/image", img, t)]
    records[-1] = records[-1][:3] + (records[-1][3][:10], T0 + DT)  # the second image stops inside its header
    ros1_log(tmp_path / "ros1bad.mcap", records)
    a, b = McapFrameSource(tmp_path / "ros1bad.mcap")
    assert a.error is None and decode_image(a).shape == (H, W, 3)
    with pytest.raises(ImageError, match=rf"ros1bad.mcap:/cam/image: cannot decode message at log time {T0 + DT} "):
        decode_image(b)


@pytest.mark.parametrize("encoding", ["rgb8", "bgra8", "mono8", "mono16"])
def test_foxglove_raw_image_encodings(tmp_path, encoding):
    rng = np.random.default_rng(4)
    ch = {"rgb8": 3, "bgra8": 4, "mono8": 1, "mono16": 1}[encoding]
    dtype = np.uint16 if encoding == "mono16" else np.uint8
    px = rng.integers(0, np.iinfo(dtype).max, (H, W, ch), dtype=dtype)
    log_ = Log(tmp_path / "raw.mcap")
    log_.proto("/cam/calibration", _calib(T0), T0)
    m = RawImage(frame_id="c", width=W, height=H, encoding=encoding, step=W * ch * px.itemsize, data=px.tobytes())
    log_.proto("/cam/image", m, T0)
    log_.close()
    (fr,) = McapFrameSource(tmp_path / "raw.mcap")
    rgb = decode_image(fr)
    if encoding == "rgb8":
        expected = px
    elif encoding == "bgra8":
        expected = px[:, :, 2::-1]
    else:
        expected = np.repeat((px / 257).astype(np.uint8) if dtype == np.uint16 else px, 3, axis=2)
    np.testing.assert_array_equal(rgb, expected)


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """What a colour-filter camera records: one channel a pixel, in ``pattern``'s 2x2 layout."""
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern, strict=True):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, "rgb".index(c)]
    return out


@pytest.mark.parametrize(
    "encoding", ["bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8", "bayer_rggb16", "uyvy", "yuv422_yuy2"]
)
def test_camera_native_raw_encodings_come_out_as_the_scenes_colours(tmp_path, encoding):
    # A colour-filter mosaic or packed 4:2:2 YUV of a smooth image: what many robot cameras log.
    rgb = cv2.resize(
        np.random.default_rng(9).integers(0, 256, (3, 4, 3), np.uint8), (W, H), interpolation=cv2.INTER_CUBIC
    )
    if encoding.startswith("bayer_"):
        px = _mosaic(rgb, encoding[6:10])
        if encoding.endswith("16"):
            px = px.astype(np.uint16) * 257
    else:
        px = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_UYVY if encoding == "uyvy" else cv2.COLOR_RGB2YUV_YUY2)
    log_ = Log(tmp_path / "raw.mcap")
    log_.proto("/cam/calibration", _calib(T0), T0)
    step = px.strides[0]
    log_.proto(
        "/cam/image", RawImage(frame_id="c", width=W, height=H, encoding=encoding, step=step, data=px.tobytes()), T0
    )
    log_.close()
    (fr,) = McapFrameSource(tmp_path / "raw.mcap")
    out = decode_image(fr).astype(int)
    assert out.shape == (H, W, 3)
    # Inside a 2-px border, where demosaicing has both neighbours: within a few levels of the scene.
    err = np.abs(out - rgb)[2:-2, 2:-2]
    assert err.mean() < 3 and np.percentile(err, 99) < 16, (err.mean(), np.percentile(err, 99))


@pytest.mark.parametrize("encoding", ["yuv422", "yuyv"])
def test_camera_native_raw_image_that_cannot_be_converted_fails_its_frame(tmp_path, encoding):
    w = 5  # 4:2:2 YUV shares each U, V sample between two pixels: the width must be even
    log_ = Log(tmp_path / "odd.mcap")
    log_.proto("/cam/calibration", _calib(T0, w=w), T0)
    log_.proto(
        "/cam/image",
        RawImage(frame_id="c", width=w, height=H, encoding=encoding, step=w * 2, data=bytes(w * 2 * H)),
        T0,
    )
    log_.close()
    (fr,) = McapFrameSource(tmp_path / "odd.mcap")
    with pytest.raises(ImageError, match=f"cannot convert the {encoding} image of {w}x{H} to RGB"):
        decode_image(fr)


def test_calibration_pairing_and_changes(tmp_path, caplog):
    rng = np.random.default_rng(5)
    log_ = Log(tmp_path / "two.mcap")
    # /left/image's first image comes before its first calibration.
    for i in range(4):
        t = T0 + i * DT
        if i >= 1:
            log_.proto("/left/calibration", _calib(t, K1 if i < 3 else K2), t)
            log_.proto("/right/calibration", _calib(t, K2), t)
        log_.proto("/left/image", _cimg(t, _enc(_img(rng), ".jpg")), t)
        log_.proto("/right/image", _cimg(t, _enc(_img(rng), ".jpg")), t)
    log_.close()
    with caplog.at_level(logging.INFO, logger="batchpose"):
        left = McapFrameSource(tmp_path / "two.mcap")
        ks = [f.camera.K for f in left]
    assert (left.image_topic, left.calibration_topic) == ("/left/image", "/left/calibration")
    assert "2 image topics (/left/image, /right/image); using /left/image" in caplog.text
    assert "before the first calibration" in caplog.text
    for k, want in zip(ks, [K1, K1, K1, K2], strict=True):
        np.testing.assert_array_equal(k, want)
    right = McapFrameSource(tmp_path / "two.mcap", image_topic="/right/image")
    assert right.calibration_topic == "/right/calibration"
    assert all(np.array_equal(f.camera.K, K2) for f in right)


def test_log_without_summary_is_read_in_stream_mode(tmp_path, caplog):
    datas = _simple_log(tmp_path / "nosum.mcap", summary=False)
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        src = McapFrameSource(tmp_path / "nosum.mcap")
        frames = list(src)
    assert not src.indexed and not src.truncated and caplog.text == ""
    assert src.count() == 4 and [f.image_data for f in frames] == datas


# --------------------------------------------------------------------------------------- write-back


def _box_glb(extents=(0.1, 0.2, 0.05)) -> bytes:
    return mesh_to_glb(trimesh.creation.box(extents=extents))


def _rows(stamps: list[int], rng: np.random.Generator, fail: set[int]) -> list[dict]:
    rows = []
    for i, s in enumerate(stamps):
        T = _pose(rng)
        ok = i not in fail
        rows.append(
            {
                "frame_id": f"mcap:{s}",
                "stamp_ns": s,
                "obj_name": "box",
                "status": "ok" if ok else "too_few_matches",
                "reason": "" if ok else "3 matches",
                "R": T[:3, :3].reshape(-1).tolist() if ok else [np.nan] * 9,
                "t_m": T[:3, 3].tolist() if ok else [np.nan] * 3,
                "confidence": 0.8 if ok else 0.0,
                "verification": 0.9 if ok and i != 1 else np.nan,  # a tracked pose is not scored
                "n_inliers": 12 if ok else 0,
                "inliers_px": [10.0, 12.0, 20.5, 30.0] if ok else [],
                "tracked": i == 1,
            }
        )
    return rows


def _all_messages(path: Path) -> list[tuple]:
    with open(path, "rb") as f:
        r = make_reader(f, validate_crcs=True)
        return [
            (
                ch.topic,
                s.name if s else None,
                s.encoding if s else None,
                s.data if s else None,
                ch.message_encoding,
                dict(ch.metadata),
                m.log_time,
                m.publish_time,
                m.sequence,
                m.data,
            )
            for s, ch, m in r.iter_messages()
        ]


def test_write_back_keeps_input_byte_identical_and_adds_decodable_topics(tmp_path):
    rng = np.random.default_rng(6)
    inp = tmp_path / "in.mcap"
    log_ = Log(inp, chunk_size=4096, profile="x-test")
    log_.w.add_metadata("robot", {"name": "r2"})
    log_.w.add_attachment(T0, T0, "calib.yaml", "text/yaml", b"fx: 1\n")
    stamps = []
    for i in range(5):
        t = T0 + i * DT
        stamps.append(t)
        log_.json("/imu", {"a": [0.1 * i, 0, 9.8]}, t - 3)
        log_.proto("/cam/calibration", _calib(t), t)
        # header stamp differs from log time: annotations must carry the header stamp
        log_.proto("/cam/image", _cimg(t - 5_000_000, _enc(_img(rng), ".jpg")), t, seq=i)
    log_.close()
    digest = hashlib.sha256(inp.read_bytes()).hexdigest()
    glb = _box_glb()
    rows = _rows(stamps, rng, fail={2})
    out = tmp_path / "poses.mcap"
    assert write_poses_mcap(out, rows, {"box": glb}, input_mcap=inp).path == out
    assert hashlib.sha256(inp.read_bytes()).hexdigest() == digest
    assert not (tmp_path / "poses.mcap.tmp").exists()

    before = _all_messages(inp)
    after = _all_messages(out)
    kept = [m for m in after if not m[0].startswith("/batchpose/")]
    assert kept == before  # every input message: topic, schema, times, sequence and bytes unchanged
    with open(out, "rb") as f:
        r = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        assert r.get_header().profile == "x-test"
        meta = {m.name: m.metadata for m in r.iter_metadata()}
        assert meta.pop("batchpose.export")["ros_tf"] == "true"  # the export's own options, beside the input's
        assert meta == {"robot": {"name": "r2"}}
        assert [(a.name, a.data) for a in r.iter_attachments()] == [("calib.yaml", b"fx: 1\n")]
        new = [
            (ch.topic, m, d)
            for _, ch, m, d in r.iter_decoded_messages(
                topics=[SCENE_TOPIC_PREFIX + "box", TF_TOPIC, ANNOTATIONS_TOPIC, "/batchpose/poses/box"]
            )
        ]
        status = [json.loads(m.data) for _, ch, m in r.iter_messages(topics=[STATUS_TOPIC])]

    # The mesh from the first image, deleted at the failed one, back at the next.
    scene = [(m.log_time, d) for t, m, d in new if t == SCENE_TOPIC_PREFIX + "box"]
    assert [(t, len(d.entities), len(d.deletions)) for t, d in scene] == [
        (stamps[0], 1, 0),
        (stamps[2], 0, 1),
        (stamps[3], 1, 0),
    ]
    ent = scene[0][1].entities[0]
    assert (ent.frame_id, ent.id, ent.frame_locked) == ("object/box", "box", True)
    assert ent.models[0].media_type == "model/gltf-binary" and ent.models[0].data == glb

    tfs = [(m, d) for t, m, d in new if t == TF_TOPIC]
    ok_rows = [r_ for r_ in rows if r_["status"] == "ok"]
    assert len(tfs) == 4 == len([1 for t, _, _ in new if t == "/batchpose/poses/box"])
    for (m, tf), row in zip(tfs, ok_rows, strict=True):
        assert (tf.parent_frame_id, tf.child_frame_id) == ("cam_optical", "object/box")
        assert m.log_time == row["stamp_ns"]
        assert tf.timestamp.ToNanoseconds() == row["stamp_ns"] - 5_000_000
        np.testing.assert_allclose([tf.translation.x, tf.translation.y, tf.translation.z], row["t_m"])
        q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix().reshape(-1), row["R"], atol=1e-12)

    anns = [(m, d) for t, m, d in new if t == ANNOTATIONS_TOPIC]
    assert [m.log_time for m, _ in anns] == stamps
    half = np.array([0.05, 0.1, 0.025])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    for (m, ann), row in zip(anns, rows, strict=True):
        if row["status"] != "ok":
            assert not ann.points and ann.texts[0].text == "box too_few_matches (3 matches)"
            continue
        R = np.reshape(row["R"], (3, 3))
        uv, _ = cv2.projectPoints(
            corners, cv2.Rodrigues(R)[0], np.array(row["t_m"]), K1, np.array([0.1, 0.0, 0.0, 0.0, 0.0])
        )
        box = [p for p in ann.points if p.type == 4]  # LINE_LIST
        (pts,) = [p for p in ann.points if p.type == 1]  # POINTS: inliers
        assert [(q.x, q.y) for q in pts.points] == [(10.0, 12.0), (20.5, 30.0)]
        got = np.array([[q.x, q.y] for q in box[0].points])
        assert got.shape == (24, 2)
        d = np.linalg.norm(got[:, None] - uv.reshape(1, -1, 2), axis=2).min(axis=1)
        assert d.max() < 1e-6
        assert ann.texts[0].timestamp.ToNanoseconds() == m.log_time - 5_000_000
        assert ann.texts[0].text == "box ok 0.80" + (" tracked" if row["tracked"] else "")
    assert [o["tracked"] for st in status for o in st["objects"]] == [False, True, False, False, False]
    assert [s["n_ok"] for s in status] == [1, 1, 0, 1, 1]
    assert [o["verification"] for st in status for o in st["objects"]] == [0.9, None, None, 0.9, 0.9]
    assert status[2]["objects"][0] == {
        "obj_name": "box",
        "status": "too_few_matches",
        "reason": "3 matches",
        "confidence": 0.0,
        "verification": None,
        "n_inliers": 0,
        "tracked": False,
    }


def test_write_back_from_folder_frames(tmp_path):
    frames = _frames(3)
    rows = _rows([f.stamp_ns for f in frames], np.random.default_rng(7), fail=set())
    out = tmp_path / "poses.mcap"
    write_poses_mcap(out, rows, {"box": _box_glb()}, frames=iter(frames))
    back = list(McapFrameSource(out))
    assert [b.image_data for b in back] == [f.image_data for f in frames]
    with open(out, "rb") as f:
        topics = {ch.topic for _, ch, _ in make_reader(f, validate_crcs=True).iter_messages()}
    assert {
        "/camera/image",
        "/camera/calibration",
        "/ground_truth/poses",
        SCENE_TOPIC_PREFIX + "box",
        TF_TOPIC,
        ANNOTATIONS_TOPIC,
        STATUS_TOPIC,
        "/batchpose/poses/box",
    } == topics


def test_write_back_refuses_to_overwrite_input(tmp_path):
    _simple_log(tmp_path / "in.mcap")
    with pytest.raises(ConfigError, match="overwrite the input"):
        write_poses_mcap(tmp_path / "in.mcap", [], {}, input_mcap=tmp_path / "in.mcap")


def test_mesh_to_glb_downscales_texture():
    mesh = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    uv = np.random.default_rng(8).random((len(mesh.vertices), 2))
    tex = Image.fromarray(np.random.default_rng(9).integers(0, 256, (2048, 2048, 3), dtype=np.uint8))
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=tex)
    glb = mesh_to_glb(mesh)
    back = trimesh.load(io.BytesIO(glb), file_type="glb")
    (g,) = back.geometry.values()
    assert max(g.visual.material.baseColorTexture.size) == 1024
    np.testing.assert_allclose(back.bounds, mesh.bounds)  # model frame kept
    assert tex.size == (2048, 2048)  # the caller's mesh is untouched


# -------------------------------------------------------------------------------------- bad input


def test_not_an_mcap(tmp_path):
    p = tmp_path / "photo.mcap"
    p.write_bytes(_enc(np.zeros((4, 4, 3), np.uint8)))
    with pytest.raises(DataError, match=r"photo.mcap: not an MCAP file"):
        McapFrameSource(p)


def test_a_bag_given_as_a_log_says_how_to_convert_it(tmp_path):
    ros1 = tmp_path / "drive.bag"  # a ROS 1 bag starts with its version line and a 4096-byte header record
    ros1.write_bytes(b"#ROSBAG V2.0\n" + bytes(4096))
    with pytest.raises(DataError, match=r"drive.bag: a ROS 1 bag, not an MCAP file; convert it with `mcap convert"):
        McapFrameSource(ros1)
    db3 = tmp_path / "drive_0.db3"  # a ROS 2 bag before Iron: an SQLite database
    with sqlite3.connect(db3) as con:
        con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT, type TEXT)")
    with pytest.raises(DataError, match=r"drive_0.db3: an SQLite database \(a ROS 2 .db3 bag\?\), not an MCAP"):
        McapFrameSource(db3)


def test_truncated_without_complete_chunk(tmp_path):
    p = tmp_path / "cut.mcap"
    _simple_log(p)
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(DataError, match=r"cut.mcap: truncated MCAP \(no footer/summary\) and no complete chunk"):
        McapFrameSource(p)


def test_truncated_keeps_complete_chunks_and_warns(tmp_path, caplog):
    p = tmp_path / "cut.mcap"
    datas = _simple_log(p, n=12, chunk_size=2000)
    raw = p.read_bytes()
    cut = int(len(raw) * 0.6)
    # Expected: the images in chunks that end before the cut.
    with open(p, "rb") as f:
        summary = make_reader(f).get_summary()
        image_ch = next(c.id for c in summary.channels.values() if c.topic == "/cam/image")
        expected = 0
        for ci in summary.chunk_indexes:
            if ci.chunk_start_offset + ci.chunk_length <= cut:
                f.seek(ci.chunk_start_offset + 9)
                chunk = Chunk.read(ReadDataStream(f))
                expected += sum(isinstance(r, Message) and r.channel_id == image_ch for r in breakup_chunk(chunk))
    assert 0 < expected < 12
    p.write_bytes(raw[:cut])
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        src = McapFrameSource(p)
        frames = list(src)
    assert src.truncated and len(frames) == expected == src.count()
    assert [f.image_data for f in frames] == datas[:expected]
    assert f"({expected} images on /cam/image)" in caplog.text
    assert "truncated MCAP (no footer/summary)" in caplog.text and "were lost" in caplog.text


def test_crc_mismatch(tmp_path):
    p = tmp_path / "bad.mcap"
    datas = _simple_log(p)
    raw = bytearray(p.read_bytes())
    at = raw.find(datas[1]) + 100  # flip a byte inside the second image, inside its chunk
    raw[at] ^= 0xFF
    p.write_bytes(bytes(raw))
    src = McapFrameSource(p)
    with pytest.raises(DataError, match=r"bad.mcap: CRC mismatch"):
        list(src)


def test_no_image_topic(tmp_path):
    p = tmp_path / "imu.mcap"
    log_ = Log(p)
    log_.json("/imu", {"a": 1}, T0)
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.close()
    with pytest.raises(DataError, match=r"imu.mcap: no image topic .*topics: /imu \(test.Thing\)"):
        McapFrameSource(p)


def test_image_topic_without_calibration(tmp_path):
    p = tmp_path / "nocal.mcap"
    log_ = Log(p)
    log_.proto("/cam/image", _cimg(T0, b"\xff\xd8"), T0)
    log_.proto("/other/calibration", _calib(T0), T0)
    log_.close()
    with pytest.raises(CameraError, match=r"nocal.mcap:/cam/image: image topic has no calibration.*/other/calibration"):
        McapFrameSource(p)
    assert McapFrameSource(p, calibration_topic="/other/calibration").calibration_topic == "/other/calibration"


def test_image_topic_with_non_image_schema(tmp_path):
    p = tmp_path / "x.mcap"
    _simple_log(p)
    with pytest.raises(
        DataError, match=r"x.mcap:/cam/calibration: schema 'foxglove.CameraCalibration' is not an image"
    ):
        McapFrameSource(p, image_topic="/cam/calibration")
    with pytest.raises(DataError, match=r"image topic '/nope' not found \(image topics: /cam/image"):
        McapFrameSource(p, image_topic="/nope")


@pytest.mark.parametrize(
    ("msg", "match"),
    [
        (_cimg(T0, b"RIFF....WEBP", fmt="webp"), "unsupported image encoding 'webp'"),
        (
            RawImage(width=W, height=H, encoding="nv21", step=W, data=bytes(W * H * 3 // 2)),
            "unsupported image encoding 'nv21'",
        ),
        (_cimg(T0, b""), r"image is empty \(0 bytes\)"),
        (RawImage(width=0, height=H, encoding="rgb8", step=0, data=b""), r"image is empty \(0 bytes\)"),
        (RawImage(width=0, height=H, encoding="rgb8", step=0, data=b"\x00" * 10), "raw rgb8 image of 0x48"),
    ],
)
def test_bad_image_fails_per_frame_naming_file_and_topic(tmp_path, msg, match):
    p = tmp_path / "enc.mcap"
    log_ = Log(p)
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.proto("/cam/image", msg, T0)
    log_.close()
    (fr,) = McapFrameSource(p)  # reading works; the frame fails when decoded (a bad_image row)
    with pytest.raises(ImageError, match=rf"enc.mcap:/cam/image: {match}"):
        decode_image(fr)


# ---------------------------------------------------------------------- one bad message, bad fields


def _status_times(path: Path) -> list[tuple[int, str]]:
    return [(m[6], json.loads(m[-1])["objects"][0]["status"]) for m in _all_messages(path) if m[0] == STATUS_TOPIC]


def test_image_message_that_does_not_parse_fails_only_its_frame(tmp_path, caplog):
    rng = np.random.default_rng(11)
    datas = [_enc(_img(rng), ".jpg") for _ in range(3)]
    p = tmp_path / "garbage.mcap"
    log_ = Log(p)
    for i, d in enumerate(datas):
        t = T0 + i * DT
        log_.proto("/cam/calibration", _calib(t), t)
        if i == 1:  # the channel exists (first image): this message's bytes are not protobuf
            log_.w.add_message(
                log_.channels["/cam/image"], log_time=t, data=b"\xff\xff\xff\xff garbage", publish_time=t
            )
        else:
            log_.proto("/cam/image", _cimg(t, d), t)
    log_.close()
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        src = McapFrameSource(p)
        frames = list(src)
        list(src)  # read again (ingest, then estimation): warned once
    assert [f.stamp_ns for f in frames] == [T0, T0 + DT, T0 + 2 * DT]
    assert frames[0].error is None and frames[2].image_data == datas[2]
    np.testing.assert_array_equal(frames[1].camera.K, K1)
    with pytest.raises(ImageError, match=rf"garbage.mcap:/cam/image: cannot decode message at log time {T0 + DT} "):
        decode_image(frames[1])  # estimate_frame turns this into a bad_image row
    assert caplog.text.count("cannot decode message") == 1 and "that frame fails as bad_image" in caplog.text
    # The write-back copies the bad message too and writes every image's status.
    out = tmp_path / "poses.mcap"
    rows = _rows([f.stamp_ns for f in frames], rng, fail={1})
    write_poses_mcap(out, rows, {"box": _box_glb()}, input_mcap=p)
    assert _status_times(out) == [(T0, "ok"), (T0 + DT, "too_few_matches"), (T0 + 2 * DT, "ok")]


def encode_video(images: list[np.ndarray], codec: str = "libx264", gop: int = 5) -> list[bytes]:
    """RGB images as a video stream, one packet (one CompressedVideo message) an image, no B-frames."""
    import fractions

    import av

    h, w = images[0].shape[:2]
    enc = av.CodecContext.create(codec, "w")
    enc.width, enc.height, enc.pix_fmt = w, h, "yuv420p"
    enc.time_base, enc.gop_size = fractions.Fraction(1, 30), gop
    enc.options = {  # each encoder's way to no B-frames / no look-ahead, and a high quality
        "libx264": {"tune": "zerolatency", "crf": "12"},
        "libx265": {"tune": "zerolatency", "crf": "12", "x265-params": "log-level=none"},
        "libvpx-vp9": {"lag-in-frames": "0"},
        "libsvtav1": {"svtav1-params": "pred-struct=1", "crf": "12"},
    }[codec]
    packets = []
    for i, img in enumerate([*images, None]):
        frame = None
        if img is not None:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            frame.pts = i
        packets += [bytes(p) for p in enc.encode(frame)]
    assert len(packets) == len(images)
    return packets


def _video_msg(t: int, data: bytes, fmt: str = "h264") -> CompressedVideo:
    m = CompressedVideo(frame_id="cam_optical", format=fmt, data=data)
    m.timestamp.FromNanoseconds(t)
    return m


@pytest.mark.parametrize(
    ("codec", "fmt"), [("libx264", "h264"), ("libx265", "h265"), ("libvpx-vp9", "vp9"), ("libsvtav1", "av1")]
)
def test_foxglove_compressed_video(tmp_path, codec, fmt):
    # Foxglove's CompressedVideo, recorded from the middle of a stream: the frames before the first keyframe
    # fail on their own, every later one decodes to its own image.
    rng = np.random.default_rng(13)
    base = cv2.resize(rng.integers(0, 256, (6, 8, 3), np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)
    images = [np.roll(base, 2 * i, axis=1) for i in range(12)]
    packets = encode_video(images, codec, gop=5)
    log_ = Log(tmp_path / "video.mcap")
    for i in range(2, 12):  # starts two frames into the stream: frames 2-4 precede the keyframe at 5
        t = T0 + i * DT
        log_.proto("/cam/calibration", _calib(t), t)
        log_.proto("/cam/video", _video_msg(t, packets[i], fmt), t)
    log_.close()
    src = McapFrameSource(tmp_path / "video.mcap")
    assert src.image_topic == "/cam/video" and src.count() == 10
    frames = list(src)
    assert [f.error is not None for f in frames] == [True] * 3 + [False] * 7
    with pytest.raises(ImageError, match=rf"video.mcap:/cam/video: no picture from the {fmt} video message at log"):
        decode_image(frames[0])
    for i, fr in zip(range(5, 12), frames[3:], strict=True):
        assert (fr.image_format, fr.camera.width, fr.camera.height, fr.stamp_ns) == ("rgb8", W, H, T0 + i * DT)
        err = [np.abs(decode_image(fr).astype(int) - images[j]).mean() for j in (i, i - 1)]
        assert err[0] < 10 and err[0] < 0.5 * err[1], err  # lossy (4:2:0 colour), but this image, not the last


def test_calibration_of_another_camera_frame_is_warned_about_once(tmp_path, caplog):
    # A calibration_topic set to the wrong camera of the same size: the numbers would look fine.
    rng = np.random.default_rng(12)
    log_ = Log(tmp_path / "two_cams.mcap")
    for i in range(3):
        t = T0 + i * DT
        log_.proto("/left/calibration", _calib(t, frame_id="right_optical"), t)
        log_.proto("/left/image", _cimg(t, _enc(_img(rng)), "png", frame_id="left_optical"), t)
    log_.close()
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        frames = list(McapFrameSource(tmp_path / "two_cams.mcap"))
    assert len(frames) == 3 and all(f.error is None for f in frames)
    assert caplog.text.count("images are in frame 'left_optical', the calibration on /left/calibration describes") == 1


def test_image_size_differs_from_calibration(tmp_path):
    rgb = _img(np.random.default_rng(12))  # 64x48
    p = tmp_path / "size.mcap"
    log_ = Log(p)
    log_.proto("/a/calibration", _calib(T0, w=32, h=24), T0)
    log_.proto("/a/image", _cimg(T0, _enc(rgb), fmt="png"), T0)
    log_.proto("/b/calibration", _calib(T0, w=32, h=24), T0)
    raw = RawImage(width=W, height=H, encoding="bgr8", step=W * 3, data=rgb.tobytes())
    raw.timestamp.FromNanoseconds(T0)
    log_.proto("/b/image", raw, T0)
    log_.close()
    (compressed,) = McapFrameSource(p, image_topic="/a/image")
    with pytest.raises(ImageError, match=r"size.mcap:/a/image: image is 64x48, the camera calibration is for 32x24"):
        decode_image(compressed)
    (rawf,) = McapFrameSource(p, image_topic="/b/image")  # a raw image's camera takes its size
    with pytest.raises(
        ImageError, match=r"size.mcap:/b/image: image is 64x48, the camera calibration on /b/calibration is for 32x24"
    ):
        decode_image(rawf)


def _json_time(t: int) -> dict:
    return {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}


def test_json_encoded_foxglove_image_and_calibration(tmp_path):
    rng = np.random.default_rng(13)
    datas = [_enc(_img(rng), ".png") for _ in range(2)]
    p = tmp_path / "json.mcap"
    log_ = Log(p)
    for i, d in enumerate(datas):
        t = T0 + i * DT
        cal = {"timestamp": _json_time(t), "frame_id": "cam", "width": W, "height": H}
        cal |= {"distortion_model": "plumb_bob", "D": [0.1, 0.0, 0.0, 0.0, 0.0], "K": K1.reshape(-1).tolist()}
        log_.json("/cam/calibration", cal, t, schema="foxglove.CameraCalibration")
        img = {"timestamp": _json_time(t + 5), "frame_id": "cam", "format": "png", "data": base64.b64encode(d).decode()}
        log_.json("/cam/image", img, t, schema="foxglove.CompressedImage")
    log_.close()
    frames = list(McapFrameSource(p))
    assert [f.image_data for f in frames] == datas and all(f.error is None for f in frames)
    for f in frames:
        np.testing.assert_array_equal(f.camera.K, K1)
        np.testing.assert_array_equal(f.camera.dist, [0.1, 0.0, 0.0, 0.0, 0.0])
        assert (f.camera.width, f.camera.height, f.camera.distortion_model) == (W, H, "plumb_bob")
    out = tmp_path / "poses.mcap"
    write_poses_mcap(out, _rows([f.stamp_ns for f in frames], rng, fail=set()), {"box": _box_glb()}, input_mcap=p)
    assert _status_times(out) == [(T0, "ok"), (T0 + DT, "ok")]
    ann = [m for m in _all_messages(out) if m[0] == ANNOTATIONS_TOPIC]
    assert [m[6] for m in ann] == [T0, T0 + DT]  # at the images' log times, stamped with their header stamps


def test_json_message_without_a_field_names_topic_and_encoding(tmp_path):
    d = _enc(_img(np.random.default_rng(14)), ".png")
    p = tmp_path / "json.mcap"
    log_ = Log(p)
    log_.json(
        "/cam/calibration", {"timestamp": _json_time(T0), "width": W, "height": H}, T0, "foxglove.CameraCalibration"
    )
    log_.json("/cam/image", {"timestamp": _json_time(T0), "format": "png", "data": base64.b64encode(d).decode()}, T0,
              "foxglove.CompressedImage")  # fmt: skip
    log_.close()
    with pytest.raises(
        DataError,
        match=rf"json.mcap:/cam/calibration: json-encoded foxglove.CameraCalibration message at log time {T0} "
        r"has no field 'K'",
    ):
        list(McapFrameSource(p))
    p2 = tmp_path / "json2.mcap"
    log_ = Log(p2)
    log_.proto("/cam/calibration", _calib(T0), T0)
    log_.json("/cam/image", {"timestamp": _json_time(T0), "format": "png"}, T0, "foxglove.CompressedImage")
    log_.json("/cam/image", {"timestamp": _json_time(T0), "format": "png", "data": "%%%"}, T0 + DT)
    log_.close()
    f0, f1 = McapFrameSource(p2)  # an image message without its pixels fails its frame only
    with pytest.raises(
        ImageError,
        match=r"json2.mcap:/cam/image: json-encoded foxglove.CompressedImage message at log time \d+ "
        r"has no field 'data'",
    ):
        decode_image(f0)
    with pytest.raises(ImageError, match=r"at log time \d+ has a malformed field \(.*base64"):
        decode_image(f1)


def _gt_msg(t: int, objects: list[dict], **kw) -> dict:
    return {"stamp_ns": t, "objects": objects, **kw}


def test_ground_truth_message_without_pose_names_the_message(tmp_path):
    p = tmp_path / "gt.mcap"
    log_ = Log(p)
    log_.proto("/camera/calibration", _calib(T0), T0)
    log_.json(GT_TOPIC, _gt_msg(T0, [{"obj_name": "box", "obj_id": 2}]), T0)
    log_.proto(IMAGE_TOPIC, _cimg(T0, _enc(_img(np.random.default_rng(15)), ".jpg")), T0)
    log_.close()
    with pytest.raises(
        DataError,
        match=rf"gt.mcap:/ground_truth/poses: batchpose.GroundTruthPoses message at log time {T0}: object 0 \(box\) "
        r"has no cam_from_model \(16 numbers",
    ):
        list(McapFrameSource(p))


def test_ground_truth_logged_after_its_image(tmp_path):
    rng = np.random.default_rng(16)
    poses = [_pose(rng) for _ in range(3)]
    p = tmp_path / "late.mcap"
    log_ = Log(p)
    for i, T in enumerate(poses):
        t = T0 + i * DT
        log_.proto("/camera/calibration", _calib(t), t)
        log_.proto(IMAGE_TOPIC, _cimg(t, _enc(_img(rng), ".jpg")), t)
        log_.json(
            GT_TOPIC, _gt_msg(t, [{"obj_name": "box", "cam_from_model": T.reshape(-1).tolist()}], im_id=10 + i), t
        )
    log_.close()
    frames = list(McapFrameSource(p))
    assert [f.im_id for f in frames] == [10, 11, 12]
    for f, T in zip(frames, poses, strict=True):
        (g,) = f.gt
        np.testing.assert_array_equal(g.cam_from_model, T)


def test_truncated_batchpose_log_keeps_obj_ids_from_ground_truth(tmp_path, caplog):
    rng = np.random.default_rng(17)
    p = tmp_path / "cut.mcap"
    log_ = Log(p, chunk_size=2000, library="batchpose 0.1")
    for i in range(12):
        t = T0 + i * DT
        log_.proto("/camera/calibration", _calib(t), t)
        gt = [{"obj_name": "004_sugar_box", "obj_id": 3, "cam_from_model": _pose(rng).reshape(-1).tolist()}]
        log_.json(GT_TOPIC, _gt_msg(t, gt), t)
        log_.proto(IMAGE_TOPIC, _cimg(t, _enc(_img(rng), ".jpg")), t)
    log_.w.add_metadata("batchpose", {"version": "0.1", "obj_ids": json.dumps({"004_sugar_box": 3})})  # at the end
    log_.close()
    assert McapFrameSource(p).obj_id("004_sugar_box") == 3
    p.write_bytes(p.read_bytes()[: int(p.stat().st_size * 0.6)])
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        src = McapFrameSource(p)
    assert src.truncated and "batchpose" not in src.metadata and len(list(src)) > 0
    assert src.obj_id("004_sugar_box") == 3 and src.obj_id("nope") == 0
    assert (
        "the metadata record at its end (object ids) was lost too: object ids come from the ground-truth" in caplog.text
    )


def test_poses_export_leaves_out_unreadable_frames_and_depth(tmp_path, caplog):
    depth = cv2.imencode(".png", np.full((H, W), 700, np.uint16))[1].tobytes()
    frames = [dataclasses.replace(f, depth_format="png", depth_data=depth, depth_scale_m=0.001) for f in _frames(3)]
    frames[1] = dataclasses.replace(frames[1], depth_data=b"")  # a 0-byte depth PNG
    frames[2] = dataclasses.replace(frames[2], image_data=b"", camera=Camera(K1, 0, 0))  # a 0-byte colour PNG
    t = [f.stamp_ns for f in frames]
    out = tmp_path / "poses.mcap"
    with caplog.at_level(logging.INFO, logger="batchpose"):
        write_poses_mcap(out, _rows(t, np.random.default_rng(18), fail={2}), {"box": _box_glb()}, frames=iter(frames))
    msgs = _all_messages(out)
    assert [m[6] for m in msgs if m[0] == IMAGE_TOPIC] == t[:2]
    assert [m[6] for m in msgs if m[0] == DEPTH_TOPIC] == t[:1]
    assert [s for s, _ in _status_times(out)] == t  # every frame's status is there
    assert len([m for m in msgs if m[0] == "/batchpose/poses/box"]) == 2  # the RGB poses, with or without depth
    assert "f1 (depth): depth image is empty (0 bytes); the depth image is left out of the MCAP" in caplog.text
    assert "f2: image is empty (0 bytes); the frame is left out of the MCAP" in caplog.text
    assert f"wrote {out} (2 images, 1 unreadable frame(s) left out, 3 pose records)" in caplog.text
    # `convert` (write_frames_mcap) still refuses it: a converted log must hold every frame whole.
    with pytest.raises(ImageError, match=r"f1 \(depth\): depth image is empty"):
        write_frames_mcap(iter(frames[:2]), tmp_path / "conv.mcap")
    assert not (tmp_path / "conv.mcap").exists() and not (tmp_path / "conv.mcap.tmp").exists()


def test_poses_export_leaves_out_frames_that_could_not_be_read(tmp_path, caplog):
    frames = _frames(2)
    frames[1] = dataclasses.replace(frames[1], error=CameraError("f1-meta.mat: cannot read MATLAB file"))
    t = [f.stamp_ns for f in frames]
    out = tmp_path / "poses.mcap"
    with caplog.at_level(logging.WARNING, logger="batchpose"):
        write_poses_mcap(out, _rows(t, np.random.default_rng(19), fail={1}), {"box": _box_glb()}, frames=iter(frames))
    assert [m[6] for m in _all_messages(out) if m[0] == IMAGE_TOPIC] == t[:1]
    assert [s for s, _ in _status_times(out)] == t
    assert "f1-meta.mat: cannot read MATLAB file; the frame is left out of the MCAP" in caplog.text
    with pytest.raises(CameraError, match="f1-meta.mat: cannot read MATLAB file"):
        write_frames_mcap(iter(frames), tmp_path / "conv.mcap")
