"""MCAP in and out: the only module that imports ``mcap`` (and its protobuf / ROS 1 / ROS 2 support).

Reading (:class:`McapFrameSource`): images from ``foxglove.CompressedImage`` (jpeg, png),
``foxglove.RawImage`` (the encodings of :data:`batchpose.core.frames.RAW_ENCODINGS`: rgb8, bgr8, rgba8, bgra8,
mono8, mono16, Bayer mosaics, 4:2:2 YUV), ``sensor_msgs/msg/Image`` and ``sensor_msgs/msg/CompressedImage``
(ROS 2 cdr) or ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` (ROS 1, as ``mcap convert`` writes
a bag; big-endian 16-bit images are byte-swapped), or ``foxglove.CompressedVideo`` (h264, h265, vp9, av1;
decoded in log order with FFmpeg through PyAV, one frame a message); calibration from
``foxglove.CameraCalibration``, ``sensor_msgs/msg/CameraInfo`` or ``sensor_msgs/CameraInfo``; foxglove
schemas in protobuf or in Foxglove's JSON encoding (bytes as base64, times as ``{sec, nsec}``). Each image
uses the latest calibration logged at or before it (images logged before the first calibration use the
first one, with a warning). Image bytes are never decoded here (a big-endian 16-bit image is only
byte-swapped; video is decoded, as no frame of it can be decoded alone, and its frames are rgb8):
``Frame.image_format`` is the compressed format or the raw encoding, ``Frame.raw_step`` the row
stride. With a ``depth_topic``, each image gets the depth image (16UC1 / mono16 in mm, 32FC1 in m, or a
16-bit PNG in mm) whose header stamp is nearest its own, within :data:`DEPTH_MAX_GAP_NS`. An image
message that does not parse, or a raw image of another size than its calibration, is still a frame: one
that fails (``Frame.error``, status ``bad_image``) while the others are estimated.

Writing: :func:`write_frames_mcap` turns frames into a log; :func:`write_poses_mcap` copies every input
message byte for byte and adds the estimates. Topics written by batchpose:

================================  ==============================  ===========================================
topic                             schema                          content
================================  ==============================  ===========================================
``/camera/image``                 foxglove.CompressedImage        PNG/JPEG bytes as stored (RawImage for raw)
``/camera/calibration``           foxglove.CameraCalibration      K, R = I, P = [K | 0], D, model, size
``/camera/depth``                 foxglove.RawImage               16UC1 depth in mm registered to the image
                                                                  (``batchpose convert`` of data with depth)
``/ground_truth/poses``           batchpose.GroundTruthPoses      JSON, see :data:`GT_JSON_SCHEMA`
``/batchpose/scene``              foxglove.SceneUpdate            one message at the start: each object's
                                                                  mesh (binary glTF) locked to
                                                                  ``object/<name>``, lifetime forever
``/batchpose/tf``                 foxglove.FrameTransform         camera frame -> ``object/<name>``, metres
``/batchpose/poses/<name>``       foxglove.PosesInFrame           the object's pose in the camera frame
``/batchpose/annotations``        foxglove.ImageAnnotations       projected 3D box, inlier points, labels
``/batchpose/status``             batchpose.FrameStatus           JSON, see :data:`STATUS_JSON_SCHEMA`
================================  ==============================  ===========================================

All batchpose messages of one image are logged at the image's log time; in-message timestamps equal the
image's own header stamp, so Foxglove's Image panel can match annotations to the image. Within one log
time the calibration and ground truth are written before the image.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import io
import json
import logging
import os
import re
import struct
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _dist_version
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.ModelPrimitive_pb2 import ModelPrimitive
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.message import DecodeError
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_protobuf.schema import register_schema
from mcap_ros1.decoder import DecoderFactory as Ros1DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory
from scipy.spatial.transform import Rotation

from batchpose.core.frames import (
    RAW_ENCODINGS,
    Camera,
    Frame,
    FrameSource,
    ObjectPose,
    decode_depth,
    distortion_problem,
    image_size,
)
from batchpose.core.poses import row_cam_from_model
from batchpose.errors import BatchposeError, CameraError, ConfigError, DataError, ImageError
from batchpose.io.files import one_line

try:  # zstd is how chunks are usually compressed; its errors mean a corrupt chunk
    from zstandard import ZstdError
except ImportError:  # pragma: no cover - zstandard ships with mcap's recommended extras
    ZstdError = McapError  # type: ignore[assignment,misc]

try:  # the ROS 1 decoder uses a ROS installation's genpy when there is one, else the copy it ships
    from genpy.message import DeserializationError as _Ros1DecodeError
except ImportError:
    from mcap_ros1._vendor.genpy.message import DeserializationError as _Ros1DecodeError

log = logging.getLogger("batchpose")

try:
    __version__ = _dist_version("batchpose")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "unknown"

MCAP_MAGIC = b"\x89MCAP0\r\n"
IMAGE_TOPIC = "/camera/image"
CALIBRATION_TOPIC = "/camera/calibration"
GT_TOPIC = "/ground_truth/poses"
DEPTH_TOPIC = "/camera/depth"
#: Depth images are paired with the colour image whose header stamp is nearest, within this.
DEPTH_MAX_GAP_NS = 20_000_000
#: Metres per unit of a depth encoding (REP 118: 16-bit depth in millimetres, float depth in metres).
DEPTH_UNITS_M = {
    "16UC1": 0.001,
    "mono16": 0.001,
    "png": 0.001,
    "32FC1": 1.0,
    "compressedDepth png 16UC1": 0.001,
    "compressedDepth png mono16": 0.001,
    "compressedDepth png 32FC1": 1.0,
}
CAMERA_FRAME_ID = "camera"
OUTPUT_PREFIX = "/batchpose/"
SCENE_TOPIC = "/batchpose/scene"
TF_TOPIC = "/batchpose/tf"
POSES_TOPIC_PREFIX = "/batchpose/poses/"
ANNOTATIONS_TOPIC = "/batchpose/annotations"
STATUS_TOPIC = "/batchpose/status"
METADATA_NAME = "batchpose"

#: Image schema name -> "compressed" | "raw".
IMAGE_SCHEMAS = {
    "foxglove.CompressedImage": "compressed",
    "foxglove.RawImage": "raw",
    "sensor_msgs/msg/CompressedImage": "compressed",
    "sensor_msgs/msg/Image": "raw",
    "sensor_msgs/CompressedImage": "compressed",
    "sensor_msgs/Image": "raw",
    "foxglove.CompressedVideo": "video",
}
#: foxglove.CompressedVideo formats and the FFmpeg (PyAV) decoder of each; AV1 through dav1d, FFmpeg's own
#: AV1 decoder needing hardware.
VIDEO_DECODERS = {"h264": "h264", "h265": "hevc", "vp9": "vp9", "av1": "libdav1d"}
CALIBRATION_SCHEMAS = ("foxglove.CameraCalibration", "sensor_msgs/msg/CameraInfo", "sensor_msgs/CameraInfo")

GT_SCHEMA_NAME = "batchpose.GroundTruthPoses"
#: ``/ground_truth/poses``: one JSON message per image, logged at the image's log time (before it).
GT_JSON_SCHEMA = {
    "title": GT_SCHEMA_NAME,
    "description": "Ground-truth object poses of one image (model->camera, metres).",
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer", "description": "log time of the image, ns"},
        "frame_id": {"type": "string", "description": "coordinate frame of the poses (the image's)"},
        "source_frame_id": {"type": "string", "description": "frame id in the source data set"},
        "scene_id": {"type": "integer", "description": "BOP scene id in the source data set"},
        "im_id": {"type": "integer", "description": "BOP image id in the source data set"},
        "objects": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "obj_name": {"type": "string"},
                    "obj_id": {"type": "integer", "description": "data set object id, 0 if unknown"},
                    "cam_from_model": {
                        "type": "array",
                        "items": {"type": "number"},
                        "description": "4x4 rigid transform, row-major, 16 numbers, metres",
                    },
                },
            },
        },
    },
}
STATUS_SCHEMA_NAME = "batchpose.FrameStatus"
#: ``/batchpose/status``: one JSON message per image with the per-object outcome.
STATUS_JSON_SCHEMA = {
    "title": STATUS_SCHEMA_NAME,
    "description": "batchpose estimate status of every target object in one image.",
    "type": "object",
    "properties": {
        "frame_id": {"type": "string"},
        "stamp_ns": {"type": "integer"},
        "n_ok": {"type": "integer"},
        "objects": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "obj_name": {"type": "string"},
                    "status": {"type": "string"},
                    "reason": {"type": "string"},
                    "confidence": {"type": "number"},
                    "n_inliers": {"type": "integer"},
                    "tracked": {"type": "boolean", "description": "followed from the previous frame"},
                },
            },
        },
    },
}

# Foxglove turns every glTF model from glTF's Y-up to its Z-up convention (a +90 deg rotation about x);
# this model pose (-90 deg about x) cancels it so the mesh sits exactly in its model frame.
_GLTF_UNDO_Y_UP = Quaternion(x=-np.sqrt(0.5), y=0.0, z=0.0, w=np.sqrt(0.5))
_BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])
_PALETTE = [
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.4, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
]
#: Errors the mcap reader raises on bad bytes (CRCValidationError is a ValueError).
_READ_ERRORS = (McapError, ValueError, struct.error, ZstdError, RuntimeError)
#: Errors of a decoded message without a field we need, or with one of the wrong type.
_FIELD_ERRORS = (KeyError, TypeError, ValueError, AttributeError, binascii.Error)
_MISSING = object()
#: What was said of a log once a process: (log, image topic) taken as rectified by its name, (log, "") the
#: image topic chosen among several.
_ANNOUNCED: set[tuple[str, str]] = set()


class _BadMessage(DataError):
    """One message that does not parse or lacks a field: an image message's frame fails, not the batch."""


# ----------------------------------------------------------------------------------------- decoding


@dataclass(frozen=True)
class _Calib:
    """A decoded calibration message."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray
    model: str
    #: (3, 4) projection matrix of the rectified image (all zero when the message has none).
    P: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((3, 4)))
    #: the camera frame it describes ("" when the message does not say)
    frame_id: str = ""

    def rectified(self) -> _Calib | None:
        """The camera of the rectified image: ``P``'s left 3x3 as K, no distortion; None without a ``P``."""
        K = self.P[:, :3]
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1):
            return None
        return dataclasses.replace(self, K=K.copy(), dist=np.zeros(0), model="")


@dataclass(frozen=True)
class _Image:
    """A decoded image message (bytes untouched)."""

    fmt: str
    data: bytes
    width: int
    height: int
    step: int
    frame_id: str
    stamp_ns: int
    raw: bool


def _compressed_format(fmt: str) -> str:
    """Normalise a CompressedImage format ("jpeg", "image/png", "bgr8; jpeg compressed bgr8")."""
    f = fmt.lower().strip()
    f = f.removeprefix("image/")
    if "compresseddepth" in f:  # ROS's "16UC1; compressedDepth png": a 12-byte header before the PNG
        encoding = fmt.split(";")[0].strip()
        codec = f.split("compresseddepth", 1)[1].strip() or "png"  # the oldest versions wrote no codec
        return f"compressedDepth {codec} {encoding}"
    if "jpeg" in f or "jpg" in f:
        return "jpeg"
    if "png" in f:
        return "png"
    return f


def _field(msg: Any, *names: str, default: Any = _MISSING) -> Any:
    """First present field: foxglove uses K/D/P, ROS 2 k/d/p; a JSON-encoded message is a dict.

    Raises:
        KeyError: none of ``names`` is present and there is no ``default``.
    """
    for n in names:
        if isinstance(msg, Mapping):
            if n in msg:
                return msg[n]
        elif hasattr(msg, n):
            return getattr(msg, n)
    if default is _MISSING:
        raise KeyError(names[0])
    return default


def _stamp_ns(msg: Any) -> int:
    header = _field(msg, "header", default=None)
    if header is not None:  # ROS 2: header.stamp.sec / nanosec; ROS 1: secs / nsecs
        st = _field(header, "stamp")
        return int(_field(st, "sec", "secs")) * 1_000_000_000 + int(_field(st, "nanosec", "nsecs"))
    ts = _field(msg, "timestamp")  # foxglove: google.protobuf.Timestamp; in JSON {sec, nsec}
    if isinstance(ts, Mapping):
        return int(ts.get("sec", 0)) * 1_000_000_000 + int(ts.get("nsec", 0))
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _frame_id_of(msg: Any, default: Any = _MISSING) -> str:
    """The message's camera frame: ROS's header.frame_id, Foxglove's frame_id ("" when it has none).

    Raises:
        KeyError: a ROS header without frame_id, and no ``default``.
    """
    header = _field(msg, "header", default=None)
    if header is not None:
        return str(_field(header, "frame_id", default=default))
    return str(_field(msg, "frame_id", default=""))


def _bytes(data: Any) -> bytes:
    """A bytes field: Foxglove's JSON encoding holds it as base64 text."""
    if isinstance(data, str):
        return base64.b64decode(data, validate=True)
    return bytes(data)


def _to_calib(msg: Any) -> _Calib:
    K = np.asarray(list(_field(msg, "K", "k")), dtype=np.float64)
    # A malformed K becomes NaN so that the frame fails as bad_camera instead of stopping the batch.
    K = K.reshape(3, 3) if K.size == 9 else np.full((3, 3), np.nan)
    dist = np.asarray(list(_field(msg, "D", "d", default=[])), dtype=np.float64).reshape(-1)
    P = np.asarray(list(_field(msg, "P", "p", default=[])), dtype=np.float64)
    return _Calib(
        K=K,
        width=int(_field(msg, "width", default=0)),
        height=int(_field(msg, "height", default=0)),
        dist=dist,
        model=str(_field(msg, "distortion_model", default="")),
        P=P.reshape(3, 4) if P.size == 12 else np.zeros((3, 4)),
        frame_id=_frame_id_of(msg, default=""),
    )


def _to_image(msg: Any, kind: str) -> _Image:
    data = _bytes(_field(msg, "data"))
    if kind == "compressed":
        fmt = _compressed_format(str(_field(msg, "format")))
        return _Image(fmt, data, 0, 0, 0, _frame_id_of(msg), _stamp_ns(msg), raw=False)
    if kind == "video":  # one frame of a stream: decoded in log order by _VideoDecoder
        fmt = "video/" + str(_field(msg, "format")).lower().strip()
        return _Image(fmt, data, 0, 0, 0, _frame_id_of(msg), _stamp_ns(msg), raw=False)
    encoding = str(_field(msg, "encoding"))
    spec = RAW_ENCODINGS.get(encoding)
    if _field(msg, "is_bigendian", default=0) and spec is not None and np.dtype(spec[1]).itemsize > 1:
        data = np.frombuffer(data[: len(data) // 2 * 2], dtype=">u2").astype("<u2").tobytes()  # as decode_image reads
    return _Image(
        encoding,
        data,
        int(_field(msg, "width")),
        int(_field(msg, "height")),
        int(_field(msg, "step")),
        _frame_id_of(msg),
        _stamp_ns(msg),
        raw=True,
    )


def _colour_rank(topic: str) -> int:
    """0 for a topic named as colour (``color``, ``rgb``), 2 for one named as infrared or mono (``infra1``,
    ``ir``, ``mono``, ``thermal``), else 1: SIFT matches a textured mesh in the colour image."""
    words = re.split(r"[/_\-.]+", topic.lower())
    if any(w in ("color", "colour", "rgb", "rgb8") for w in words):
        return 0
    if any(re.fullmatch(r"infra\d*|ir\d*|mono|thermal|nir", w) for w in words):
        return 2
    return 1


class _VideoDecoder:
    """Decodes a ``foxglove.CompressedVideo`` topic message by message, in log order (FFmpeg through PyAV).

    Each message holds one frame (as Foxglove's schema requires; no B-frames), decoded with FFmpeg's low-delay
    flag so that it comes out of its own message. A message that gives no picture (a stream that starts
    between keyframes, or broken data) fails its frame only.
    """

    def __init__(self, where: str) -> None:
        self.where = where
        self._ctx: Any = None
        self._fmt = ""

    def decode(self, img: _Image, log_time: int) -> _Image:
        """The message's frame as a raw rgb8 image.

        Raises:
            _BadMessage: an unsupported format, or no picture from this message.
        """
        import av  # noqa: PLC0415 - only logs with video need FFmpeg

        fmt = img.fmt.removeprefix("video/")
        if fmt not in VIDEO_DECODERS:
            raise _BadMessage(
                f"{self.where}: video format {fmt!r} at log time {log_time} is not supported "
                f"(expected one of {', '.join(VIDEO_DECODERS)})"
            )
        if self._ctx is None or fmt != self._fmt:
            self._ctx = av.CodecContext.create(VIDEO_DECODERS[fmt], "r")
            self._ctx.flags |= av.codec.context.Flags.low_delay
            self._fmt = fmt
        try:
            frames = self._ctx.decode(av.Packet(img.data))
        except av.error.FFmpegError as e:
            frames, why = [], one_line(e)
        else:
            why = "a delayed picture: reordered B-frames, which CompressedVideo does not allow" if not frames else ""
        if not frames:
            raise _BadMessage(
                f"{self.where}: no picture from the {fmt} video message at log time {log_time} ({why}; a stream "
                "that starts between keyframes decodes from its first keyframe)"
            )
        rgb = frames[-1].to_ndarray(format="rgb24")
        h, w = rgb.shape[:2]
        return _Image("rgb8", rgb.tobytes(), w, h, 3 * w, img.frame_id, img.stamp_ns, raw=True)


def looks_rectified(topic: str) -> bool:
    """True for an image topic ROS's image_proc names rectified: ``.../image_rect``, ``image_rect_color``
    (also under an image_transport subtopic: ``.../image_rect_color/compressed``)."""
    return any(part.startswith("image_rect") for part in topic.split("/"))


def _camera(cal: _Calib, img: _Image | None) -> Camera:
    """Camera for one image: raw images carry their size; compressed ones (and an image message that
    does not parse: None) take the calibration's."""
    if img is not None and img.raw:
        w, h = img.width, img.height
    elif (cal.width and cal.height) or img is None:
        w, h = cal.width, cal.height
    else:
        w, h = image_size(img.data) or (0, 0)
    return Camera(K=cal.K, width=w, height=h, dist=cal.dist, distortion_model=cal.model)


@dataclass(frozen=True)
class _GroundTruth:
    """A decoded ``/ground_truth/poses`` message (:data:`GT_JSON_SCHEMA`)."""

    scene_id: int | None
    im_id: int | None
    poses: tuple[ObjectPose, ...]
    obj_ids: dict[str, int]


def _to_ground_truth(obj: Any) -> _GroundTruth:
    """Parse a ground-truth message.

    Raises:
        ValueError: saying which field is missing or malformed.
    """
    if not isinstance(obj, Mapping):
        raise ValueError(f"expected a JSON object, got {type(obj).__name__}")
    objects = obj.get("objects", [])
    if not isinstance(objects, list):
        raise ValueError(f"'objects' must be a list, got {type(objects).__name__}")
    poses, ids = [], {}
    for j, o in enumerate(objects):
        if not isinstance(o, Mapping) or "obj_name" not in o:
            raise ValueError(f"object {j} has no obj_name")
        name = str(o["obj_name"])
        if "cam_from_model" not in o:
            raise ValueError(f"object {j} ({name}) has no cam_from_model (16 numbers, row-major 4x4, metres)")
        try:
            T = np.asarray(o["cam_from_model"], dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise ValueError(
                f"object {j} ({name}): cam_from_model must be 16 numbers (row-major 4x4, metres)"
            ) from None
        poses.append(ObjectPose(obj_name=name, cam_from_model=T))
        obj_id = o.get("obj_id", 0)
        if isinstance(obj_id, int) and not isinstance(obj_id, bool) and obj_id > 0:
            ids[name] = obj_id
    scene_im = []
    for key in ("scene_id", "im_id"):
        try:
            scene_im.append(None if obj.get(key) is None else int(obj[key]))
        except (TypeError, ValueError):
            raise ValueError(f"{key} must be an integer, got {obj[key]!r}") from None
    return _GroundTruth(scene_im[0], scene_im[1], tuple(poses), ids)


# ------------------------------------------------------------------------------------------ reading


@dataclass(frozen=True)
class _PendingFrame:
    """A frame waiting for its ground truth or depth image, and its image's header stamp (what depth is
    paired by)."""

    frame: Frame
    stamp_ns_header: int
    #: the image's header frame_id ("" when unknown): a depth image must be in the same camera frame
    header_frame_id: str = ""


class McapFrameSource(FrameSource):
    """Frames of one image topic of an MCAP file, read lazily in log-time order.

    Args:
        path: the MCAP file.
        image_topic: image topic to read; default (logged): the first image topic whose name does not say
            depth, preferring one with a calibration topic beside it, then one named as colour (``color``,
            ``rgb``) over one named as infrared or mono (``infra1``, ``ir``, ``mono``).
        calibration_topic: calibration topic; default: the calibration topic beside the image topic
            (same namespace: ``/cam/image`` <-> ``/cam/calibration`` or ``/cam/camera_info``).
        depth_topic: an image topic of depth registered to the images (optional; see the module docstring).
            An image without a depth image within :data:`DEPTH_MAX_GAP_NS` has none.
        rectified: the images are rectified, so their camera is the calibration's projection matrix P
            without distortion (as ROS defines CameraInfo), not K and D; None: when a part of the image
            topic's name starts with ``image_rect`` (:func:`looks_rectified`).

    Frames: ``frame_id`` "mcap:<log_time_ns>", ``scene_id`` 0, ``im_id`` running index, ``stamp_ns`` =
    log time; when ``/ground_truth/poses`` holds a message at the image's log time (files written by
    ``batchpose convert``), ``gt`` comes from it and ``scene_id`` / ``im_id`` are the source data set's.

    A file without footer/summary (a recording cut short) is read in stream mode: the messages of all
    complete chunks are used and a warning says what was lost. A batchpose log loses its metadata record
    (object ids) with its tail; the ids are then taken from the ground-truth messages that were read.

    Raises:
        DataError: not an MCAP file, truncated with no complete image message, corrupt (CRC mismatch),
            no image topic, or a chosen image topic whose schema is not an image type; when iterating, a
            calibration or ground-truth message that does not parse or lacks a field (naming the topic,
            its encoding and the message's log time). An image message that does not parse only fails
            its frame (:attr:`Frame.error`, with a warning).
        CameraError: no calibration topic for the image topic, or it has no messages.
    """

    def __init__(
        self,
        path: Path,
        image_topic: str | None = None,
        calibration_topic: str | None = None,
        depth_topic: str | None = None,
        rectified: bool | None = None,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: MCAP file does not exist")
        self._size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(16)
            f.seek(max(0, self._size - 8))
            tail = f.read(8)
        if head.startswith(b"#ROSBAG V2.0"):
            raise DataError(f"{self.path}: a ROS 1 bag, not an MCAP file; convert it with `mcap convert BAG OUT.mcap`")
        if head.startswith(b"SQLite format 3"):
            raise DataError(
                f"{self.path}: an SQLite database (a ROS 2 .db3 bag?), not an MCAP file; convert it with "
                "`mcap convert BAG.db3 OUT.mcap` or `ros2 bag convert`"
            )
        if head[:8] != MCAP_MAGIC:
            raise DataError(
                f"{self.path}: not an MCAP file (expected magic {MCAP_MAGIC!r} at the start, got {head[:8]!r})"
            )
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._counts: dict[int, int] | None = None
        self._metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self._library = ""
        #: object name -> obj_id from the ground-truth messages a stream-mode scan read.
        self._gt_obj_ids: dict[str, int] = {}
        self.indexed = False
        self.truncated = False
        self._lost_bytes = 0
        self._n_messages = 0
        #: log time of the log's first message of any topic (where Foxglove's timeline starts); None when
        #: the file says nothing (no statistics record).
        self.start_ns: int | None = None
        if tail == MCAP_MAGIC and self._size > 16 and self._read_summary():
            self.indexed = True
        else:
            self.truncated = tail != MCAP_MAGIC
            self._scan_stream()
        self.depth_topic = None if depth_topic is None else self._image_type_topic(depth_topic, "depth")
        self.image_topic = self._choose_image_topic(image_topic)
        self.calibration_topic = self._choose_calibration_topic(calibration_topic)
        #: Whether the images are rectified (distortion removed): their camera is the calibration's P, not
        #: K and D. None: as ROS's image_proc names them, ``image_rect``, ``image_rect_color``, ...
        self.rectified = looks_rectified(self.image_topic) if rectified is None else bool(rectified)
        if self.rectified and rectified is None and (str(self.path), self.image_topic) not in _ANNOUNCED:
            _ANNOUNCED.add((str(self.path), self.image_topic))
            log.info(
                "%s:%s: rectified images (by the topic's name): using the calibration's P without distortion "
                "(set rectified: false in the manifest's frames if they are not)",
                self.path,
                self.image_topic,
            )
        self.gt_topic = GT_TOPIC if GT_TOPIC in self._topics() else None
        self._decoders: dict[int, Any] = {}
        self._factories = (ProtobufDecoderFactory(), Ros2DecoderFactory(), Ros1DecoderFactory())
        self._count: int | None = None
        self._warned: set[tuple[str, int]] = set()  # (topic, log time) of messages already warned about
        if self.truncated:
            n_img = self._topic_count(self.image_topic)
            ids = ""
            if self._library.startswith("batchpose") and "obj_ids" not in self._metadata.get(METADATA_NAME, {}):
                ids = (
                    "; the metadata record at its end (object ids) was lost too: object ids come from the "
                    "ground-truth messages read"
                    if self._gt_obj_ids
                    else "; the metadata record at its end (object ids) was lost too: obj_id is 0 in poses.csv"
                )
            log.warning(
                "%s: truncated MCAP (no footer/summary): read %d messages (%d images on %s) from complete "
                "chunks; the last %d bytes (an incomplete record) were lost, holding an unknown number of "
                "messages%s",
                self.path,
                self._n_messages,
                n_img,
                self.image_topic,
                self._lost_bytes,
                ids,
            )

    # -- opening

    def _read_summary(self) -> bool:
        """Load schemas, channels and counts from the summary; False when there is no usable index."""
        try:
            with open(self.path, "rb") as f:
                reader = SeekingReader(f, validate_crcs=True)
                self.profile = reader.get_header().profile
                summary = reader.get_summary()
                if summary is None or not summary.chunk_indexes:
                    return False
                self._schemas = dict(summary.schemas)
                self._channels = dict(summary.channels)
                if summary.statistics is not None:
                    self._counts = dict(summary.statistics.channel_message_counts)
                    self._n_messages = summary.statistics.message_count
                    if self._n_messages:
                        self.start_ns = int(summary.statistics.message_start_time)
                for m in reader.iter_metadata():
                    self._metadata[m.name] = dict(m.metadata)
        except _READ_ERRORS as e:
            log.warning("%s: cannot read the MCAP summary (%s); reading the file sequentially", self.path, one_line(e))
            return False
        return True

    def _scan_stream(self) -> None:
        """Walk the file once without an index: channels, per-channel counts and where it breaks off."""
        counts: dict[int, int] = defaultdict(int)
        data_end = False
        with open(self.path, "rb") as f:
            last_ok = 0
            try:
                for rec in StreamReader(f, validate_crcs=True).records:
                    if isinstance(rec, Message):
                        counts[rec.channel_id] += 1
                        if self.start_ns is None or rec.log_time < self.start_ns:
                            self.start_ns = int(rec.log_time)
                        ch = self._channels.get(rec.channel_id)
                        if ch is not None and ch.topic == GT_TOPIC:
                            self._collect_obj_ids(rec.data)
                    elif isinstance(rec, Schema):
                        self._schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        self._channels[rec.id] = rec
                    elif isinstance(rec, Metadata):
                        self._metadata[rec.name] = dict(rec.metadata)
                    elif isinstance(rec, DataEnd):
                        data_end = True
                    elif hasattr(rec, "profile"):
                        self.profile, self._library = rec.profile, str(getattr(rec, "library", ""))
                    last_ok = f.tell()
            except (EndOfFile, struct.error):
                self.truncated = True
            except CRCValidationError as e:
                raise DataError(f"{self.path}: CRC mismatch, the file is corrupt ({one_line(e)})") from None
            except _READ_ERRORS as e:
                if not self.truncated:
                    raise DataError(f"{self.path}: corrupt MCAP record ({one_line(e)})") from None
        self._counts = dict(counts)
        self._n_messages = sum(counts.values())
        self._lost_bytes = 0 if data_end else max(0, self._size - last_ok)
        if self.truncated and not any(
            self._schema_name(ch) in IMAGE_SCHEMAS and counts.get(cid) for cid, ch in self._channels.items()
        ):
            raise DataError(
                f"{self.path}: truncated MCAP (no footer/summary) and no complete chunk holds an image "
                f"message ({self._size} bytes, {self._n_messages} messages recovered)"
            )

    def _collect_obj_ids(self, data: bytes) -> None:
        """Object ids of a ground-truth message (JSON), kept in case the metadata record is lost; a message
        that does not parse is reported when the frames are read, not here."""
        try:
            self._gt_obj_ids.update(_to_ground_truth(json.loads(data)).obj_ids)
        except ValueError:
            pass

    def _schema_name(self, ch: Channel) -> str:
        s = self._schemas.get(ch.schema_id)
        return s.name if s is not None else ""

    def _topics(self) -> dict[str, str]:
        """topic -> schema name, in channel id order."""
        out: dict[str, str] = {}
        for cid in sorted(self._channels):
            ch = self._channels[cid]
            out.setdefault(ch.topic, self._schema_name(ch))
        return out

    def _topic_count(self, topic: str) -> int | None:
        if self._counts is None:
            return None
        return sum(self._counts.get(cid, 0) for cid, ch in self._channels.items() if ch.topic == topic)

    def _calibration_beside(self, image_topic: str) -> str | None:
        """The calibration topic in the deepest namespace that contains ``image_topic``."""
        best, best_len = None, -1
        for topic, schema in self._topics().items():
            if schema not in CALIBRATION_SCHEMAS:
                continue
            ns = topic.rsplit("/", 1)[0]
            if image_topic.startswith(ns + "/") and len(ns) > best_len:
                best, best_len = topic, len(ns)
        return best

    def _image_type_topic(self, wanted: str, what: str) -> str:
        """``wanted`` when it is a topic of an image type, else DataError naming ``what`` it was meant as."""
        topics = self._topics()
        if wanted not in topics:
            images = [t for t, s in topics.items() if s in IMAGE_SCHEMAS]
            raise DataError(
                f"{self.path}: {what} topic {wanted!r} not found "
                f"(image topics: {', '.join(images) or 'none'}; all topics: {', '.join(topics) or 'none'})"
            )
        if topics[wanted] not in IMAGE_SCHEMAS:
            raise DataError(
                f"{self.path}:{wanted}: schema {topics[wanted]!r} is not an image type "
                f"(expected one of {', '.join(IMAGE_SCHEMAS)})"
            )
        return wanted

    def _choose_image_topic(self, wanted: str | None) -> str:
        topics = self._topics()
        if wanted is not None:
            return self._image_type_topic(wanted, "image")
        images = [
            t
            for t, s in topics.items()
            if s in IMAGE_SCHEMAS and self._topic_count(t) != 0 and t != self.depth_topic and "depth" not in t.lower()
        ]
        if not images:
            listing = ", ".join(f"{t} ({s or 'no schema'})" for t, s in topics.items())
            raise DataError(
                f"{self.path}: no image topic (expected messages with schema foxglove.CompressedImage, "
                "foxglove.RawImage, foxglove.CompressedVideo, sensor_msgs/msg/Image or "
                "sensor_msgs/msg/CompressedImage (ROS 1: sensor_msgs/Image, sensor_msgs/CompressedImage); "
                f"topics: {listing or 'none'})"
            )
        # With a calibration beside it first, then colour before infrared (a RealSense log has both).
        chosen = min(images, key=lambda t: (self._calibration_beside(t) is None, _colour_rank(t)))
        if len(images) > 1 and (str(self.path), "") not in _ANNOUNCED:
            _ANNOUNCED.add((str(self.path), ""))
            log.info(
                "%s: %d image topics (%s); using %s (set image_topic to choose another)",
                self.path,
                len(images),
                ", ".join(images),
                chosen,
            )
        return chosen

    def _choose_calibration_topic(self, wanted: str | None) -> str:
        topics = self._topics()
        if wanted is not None:
            if wanted not in topics:
                raise CameraError(f"{self.path}: calibration topic {wanted!r} not found")
            if topics[wanted] not in CALIBRATION_SCHEMAS:
                raise CameraError(
                    f"{self.path}:{wanted}: schema {topics[wanted]!r} is not a calibration type "
                    f"(expected one of {', '.join(CALIBRATION_SCHEMAS)})"
                )
            topic = wanted
        else:
            topic = self._calibration_beside(self.image_topic)
            if topic is None:
                others = [t for t, s in topics.items() if s in CALIBRATION_SCHEMAS]
                ns = self.image_topic.rsplit("/", 1)[0] or "/"
                raise CameraError(
                    f"{self.path}:{self.image_topic}: image topic has no calibration (expected a "
                    f"foxglove.CameraCalibration or sensor_msgs/(msg/)CameraInfo topic under {ns}; "
                    f"calibration topics elsewhere: {', '.join(others) or 'none'}; set calibration_topic)"
                )
        if self._topic_count(topic) == 0:
            raise CameraError(f"{self.path}:{topic}: calibration topic has no messages")
        return topic

    # -- raw access

    def iter_raw(self, topics: Iterable[str] | None = None) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Yield (schema, channel, message) records, undecoded: log-time order when the file is indexed,
        file order otherwise (stopping silently where a truncated file breaks off).

        Raises:
            DataError: a chunk fails its CRC or cannot be decompressed.
        """
        wanted = set(topics) if topics is not None else None
        with open(self.path, "rb") as f:
            if self.indexed:
                it = SeekingReader(f, validate_crcs=True).iter_messages(
                    topics=sorted(wanted) if wanted is not None else None, log_time_order=True
                )
            else:
                it = self._iter_stream(f, wanted)
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    return
                except CRCValidationError as e:
                    raise DataError(f"{self.path}: CRC mismatch, the file is corrupt ({one_line(e)})") from None
                except _READ_ERRORS as e:
                    raise DataError(f"{self.path}: corrupt MCAP data ({type(e).__name__}: {one_line(e)})") from None
                yield item

    def _iter_stream(self, f: Any, wanted: set[str] | None) -> Iterator[tuple[Schema | None, Channel, Message]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id) or self._channels.get(rec.channel_id)
                    if ch is None:
                        raise DataError(f"{self.path}: message on unknown channel id {rec.channel_id}")
                    if wanted is None or ch.topic in wanted:
                        yield schemas.get(ch.schema_id) or self._schemas.get(ch.schema_id), ch, rec
                elif isinstance(rec, Footer):
                    return
        except (EndOfFile, struct.error):
            if not self.truncated:
                raise DataError(f"{self.path}: unexpected end of file") from None

    def iter_attachments(self) -> Iterator[Attachment]:
        """Yield the file's attachment records."""
        with open(self.path, "rb") as f:
            try:
                if self.indexed:
                    yield from SeekingReader(f, validate_crcs=True).iter_attachments()
                    return
                for rec in StreamReader(f, validate_crcs=True).records:
                    if isinstance(rec, Attachment):
                        yield rec
            except (EndOfFile, struct.error):
                if not self.truncated:
                    raise DataError(f"{self.path}: unexpected end of file") from None
            except _READ_ERRORS as e:
                raise DataError(f"{self.path}: corrupt MCAP data ({type(e).__name__}: {one_line(e)})") from None

    @property
    def time_ordered(self) -> bool:
        """True when frames come in log-time order (an indexed file; a stream-read one is in file order)."""
        return self.indexed

    @property
    def channels(self) -> dict[int, Channel]:
        """Channel id -> channel record."""
        return dict(self._channels)

    @property
    def schemas(self) -> dict[int, Schema]:
        """Schema id -> schema record."""
        return dict(self._schemas)

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name."""
        return {k: dict(v) for k, v in self._metadata.items()}

    def decode(self, schema: Schema | None, channel: Channel, message: Message) -> Any:
        """Decode one message with its embedded schema (protobuf, ROS 2 cdr, ROS 1, or JSON).

        Raises:
            DataError: no decoder for the encoding, or the bytes do not parse.
        """
        dec = self._decoders.get(channel.id)
        if dec is None:
            if channel.message_encoding == "json":
                dec = json.loads
            else:
                for factory in self._factories:
                    try:
                        dec = factory.decoder_for(channel.message_encoding, schema)
                    except Exception as e:  # noqa: BLE001 - each factory's parser has its own errors for bad schema text
                        raise DataError(
                            f"{self.path}:{channel.topic}: cannot read its {channel.message_encoding} schema "
                            f"{schema.name if schema else None!r} ({one_line(e)})"
                        ) from None
                    if dec is not None:
                        break
            if dec is None:
                raise DataError(
                    f"{self.path}:{channel.topic}: cannot decode message encoding "
                    f"{channel.message_encoding!r} with schema {schema.name if schema else None!r} "
                    "(expected protobuf, cdr, ros1 or json)"
                )
            self._decoders[channel.id] = dec
        try:
            return dec(message.data)
        except (DecodeError, McapError, ValueError, IndexError, TypeError, struct.error, _Ros1DecodeError) as e:
            raise _BadMessage(
                f"{self.path}:{channel.topic}: cannot decode message at log time {message.log_time} ({one_line(e)})"
            ) from None

    def _bad_field(self, schema: Schema | None, channel: Channel, message: Message, e: Exception) -> _BadMessage:
        what = f"has no field {e.args[0]!r}" if isinstance(e, KeyError) else f"has a malformed field ({one_line(e)})"
        return _BadMessage(
            f"{self.path}:{channel.topic}: {channel.message_encoding}-encoded {schema.name if schema else 'a'} "
            f"message at log time {message.log_time} {what}"
        )

    def calibration(self, schema: Schema | None, channel: Channel, message: Message) -> _Calib:
        """Decode a calibration message: the camera of the image topic, so for rectified images
        (:attr:`rectified`) the projection matrix P without distortion, else K and D.

        Raises:
            DataError: the message does not parse or lacks a field.
            CameraError: the images are rectified and the message has no usable P, or they are not and its
                distortion is not one OpenCV's pinhole model takes (:func:`batchpose.core.frames.distortion_problem`).
        """
        msg = self.decode(schema, channel, message)
        try:
            cal = _to_calib(msg)
        except _FIELD_ERRORS as e:
            raise self._bad_field(schema, channel, message, e) from None
        if not self.rectified:
            problem = distortion_problem(cal.model, cal.dist)
            if problem:
                raise CameraError(f"{self.path}:{channel.topic}: calibration at log time {message.log_time}: {problem}")
            return cal
        rect = cal.rectified()
        if rect is None:
            raise CameraError(
                f"{self.path}:{channel.topic}: the images on {self.image_topic} are rectified but the calibration "
                f"at log time {message.log_time} has no projection matrix P (P = {cal.P.reshape(-1).tolist()}); "
                "set rectified: false in the manifest's frames if the images are not rectified"
            )
        return rect

    def image(self, schema: Schema | None, channel: Channel, message: Message) -> _Image:
        """Decode an image message (its pixel bytes stay encoded).

        Raises:
            DataError: the message does not parse or lacks a field.
        """
        kind = IMAGE_SCHEMAS[schema.name if schema else ""]
        msg = self.decode(schema, channel, message)
        try:
            return _to_image(msg, kind)
        except _FIELD_ERRORS as e:
            raise self._bad_field(schema, channel, message, e) from None

    def ground_truth(self, schema: Schema | None, channel: Channel, message: Message) -> _GroundTruth:
        """Decode a ``/ground_truth/poses`` message.

        Raises:
            DataError: the message does not parse or lacks a field (which one, and its log time).
        """
        try:
            return _to_ground_truth(self.decode(schema, channel, message))
        except ValueError as e:
            raise DataError(
                f"{self.path}:{channel.topic}: {GT_SCHEMA_NAME} message at log time {message.log_time}: {e}"
            ) from None

    def first_calibration(self) -> _Calib:
        """The first calibration message of the calibration topic."""
        for schema, channel, message in self.iter_raw([self.calibration_topic]):
            return self.calibration(schema, channel, message)
        raise CameraError(f"{self.path}:{self.calibration_topic}: calibration topic has no messages")

    # -- FrameSource

    def __iter__(self) -> Iterator[Frame]:
        if self.depth_topic is None:
            yield from self._frames()
            return
        # One frame waits for its depth image: it may be logged just after the colour image.
        pending: _PendingFrame | None = None
        depths: dict[int, _Image] = {}
        for item in self._frames(with_depth=True):
            if isinstance(item, _Image):
                depths[item.stamp_ns] = item
                if pending is not None and item.stamp_ns >= pending.stamp_ns_header:
                    yield self._with_depth(pending, depths)
                    pending = None
                continue
            if pending is not None:
                yield self._with_depth(pending, depths)
            pending = item
            depths = {k: v for k, v in depths.items() if k >= item.stamp_ns_header - DEPTH_MAX_GAP_NS}
        if pending is not None:
            yield self._with_depth(pending, depths)

    def _with_depth(self, pending: _PendingFrame, depths: dict[int, _Image]) -> Frame:
        frame, stamp = pending.frame, pending.stamp_ns_header
        if not depths:
            return frame
        best = min(depths, key=lambda k: abs(k - stamp))
        if abs(best - stamp) > DEPTH_MAX_GAP_NS:
            return frame
        d = depths[best]
        if d.frame_id and pending.header_frame_id and d.frame_id != pending.header_frame_id:
            # e.g. a RealSense's depth/image_rect_raw: the depth camera's own pixels, not the colour camera's
            raise DataError(
                f"{self.path}:{self.depth_topic}: depth images are in frame {d.frame_id!r}, the images on "
                f"{self.image_topic} in {pending.header_frame_id!r}; the depth must be registered to the colour "
                "camera (a RealSense driver's aligned_depth_to_color topic, or depth_image_proc's register)"
            )
        return dataclasses.replace(
            frame, depth_format=d.fmt, depth_data=d.data, depth_scale_m=DEPTH_UNITS_M.get(d.fmt, 1.0), depth_step=d.step
        )

    def _frames(self, with_depth: bool = False) -> Iterator[Any]:
        """Frames in log-time order; with ``with_depth``, :class:`_PendingFrame` s and the depth topic's
        :class:`_Image` s interleaved."""
        first = self.first_calibration()
        topics = [self.image_topic, self.calibration_topic] + ([self.gt_topic] if self.gt_topic else [])
        if with_depth:
            topics.append(self.depth_topic)
        source = f"{self.path}:{self.image_topic}"
        cal: _Calib | None = None
        gts: dict[int, _GroundTruth] = {}
        index, last_t, dup = 0, None, 0
        warned_early = warned_size = warned_frame = False
        video = _VideoDecoder(source) if IMAGE_SCHEMAS.get(self._topics()[self.image_topic]) == "video" else None
        # The last image's frame waits for the next later log time: its ground truth may be logged after it.
        held: _PendingFrame | None = None
        for schema, channel, message in self.iter_raw(topics):
            t = message.log_time
            if held is not None and t > held.frame.stamp_ns:
                yield self._with_ground_truth(held, gts, with_depth)
                held = None
            if channel.topic == self.calibration_topic:
                cal = self.calibration(schema, channel, message)
                continue
            if channel.topic == self.gt_topic:
                gts[t] = self.ground_truth(schema, channel, message)
                continue
            if with_depth and channel.topic == self.depth_topic:
                try:
                    yield self.image(schema, channel, message)
                except _BadMessage as e:  # its colour image keeps its RGB poses
                    self._warn_once(channel.topic, t, f"{e}; no depth image for the frame it belongs to")
                continue
            if cal is None and not warned_early:
                log.warning(
                    "%s: images logged before the first calibration on %s use that first calibration",
                    source,
                    self.calibration_topic,
                )
                warned_early = True
            c = cal or first
            error: BatchposeError | None = None
            img: _Image | None
            try:
                img = self.image(schema, channel, message)
                if video is not None:
                    img = video.decode(img, t)
            except _BadMessage as e:  # one bad message costs its frame (bad_image), not the batch
                self._warn_once(channel.topic, t, f"{e}; that frame fails as bad_image")
                error, img = ImageError(str(e)), None
            if not warned_frame and img is not None and img.frame_id and c.frame_id and img.frame_id != c.frame_id:
                log.warning(
                    "%s: images are in frame %r, the calibration on %s describes frame %r: check that it is this "
                    "camera's (set calibration_topic)",
                    source,
                    img.frame_id,
                    self.calibration_topic,
                    c.frame_id,
                )
                warned_frame = True
            cam = _camera(c, img)
            size = None
            if img is not None and img.raw:
                size = (img.width, img.height) if img.width > 0 and img.height > 0 and img.data else None
            elif img is not None and img.fmt in ("png", "jpeg"):
                size = image_size(img.data)
            if size is not None and c.width and c.height and size != (c.width, c.height):
                if img is not None and img.raw:  # the camera takes a raw image's size: decode_image cannot tell
                    error = ImageError(
                        f"{source}: image is {size[0]}x{size[1]}, the camera calibration on "
                        f"{self.calibration_topic} is for {c.width}x{c.height}"
                    )
                if not warned_size:
                    log.warning(
                        "%s: image is %dx%d but the calibration on %s says %dx%d (frames of another size fail "
                        "as bad_image)",
                        source,
                        *size,
                        self.calibration_topic,
                        c.width,
                        c.height,
                    )
                    warned_size = True
            if held is not None:  # two images at one log time: the first one takes its ground truth
                yield self._with_ground_truth(held, gts, with_depth)
            dup = dup + 1 if t == last_t else 0
            last_t = t
            frame = Frame(
                frame_id=f"mcap:{t}" + (f"#{dup}" if dup else ""),
                scene_id=0,
                im_id=index,
                stamp_ns=t,
                camera=cam,
                image_format=img.fmt if img is not None else "",
                image_data=img.data if img is not None else b"",
                raw_step=img.step if img is not None else 0,
                source=source,
                error=error,
            )
            held = _PendingFrame(frame, img.stamp_ns if img is not None else t, img.frame_id if img is not None else "")
            index += 1
        if held is not None:
            yield self._with_ground_truth(held, gts, with_depth)

    @staticmethod
    def _with_ground_truth(held: _PendingFrame, gts: dict[int, _GroundTruth], with_depth: bool) -> Any:
        """The held frame with the ground truth logged at its log time (taken out of ``gts``), if any."""
        frame = held.frame
        gt = gts.pop(frame.stamp_ns, None)
        if len(gts) > 16:  # ground truth of images that never came: drop what is older than now
            for k in [k for k in gts if k < frame.stamp_ns]:
                del gts[k]
        if gt is not None:
            frame = dataclasses.replace(
                frame,
                scene_id=gt.scene_id if gt.scene_id is not None else 0,
                im_id=gt.im_id if gt.im_id is not None else frame.im_id,
                gt=gt.poses,
            )
        return dataclasses.replace(held, frame=frame) if with_depth else frame

    def _warn_once(self, topic: str, log_time: int, text: str) -> None:
        """Warn about the message at ``log_time`` once per source, however often the frames are read."""
        if (topic, log_time) not in self._warned:
            self._warned.add((topic, log_time))
            log.warning("%s", text)

    def count(self) -> int:
        if self._count is None:
            n = self._topic_count(self.image_topic)
            if n is None:  # no statistics record: count the index entries by reading
                n = sum(1 for _ in self.iter_raw([self.image_topic]))
            self._count = n
        return self._count

    def obj_id(self, name: str) -> int:
        """Object id from the ``batchpose`` metadata record; when a truncated log lost it, from the
        ground-truth messages read (0 if unknown)."""
        ids = self._metadata.get(METADATA_NAME, {}).get("obj_ids")
        if not ids:
            return int(self._gt_obj_ids.get(name, 0))
        try:
            return int(json.loads(ids).get(name, 0))
        except (ValueError, AttributeError):
            return 0

    def describe(self) -> str:
        gt = ", ground truth" if self.gt_topic else ""
        n = self.count()
        return (
            f"mcap {self.path} ({n} frame{'s' if n != 1 else ''} on {self.image_topic}, "
            f"calibration {self.calibration_topic}{gt})"
        )


# ------------------------------------------------------------------------------------------ writing


def _timestamp(msg_ts: Any, ns: int) -> None:
    msg_ts.FromNanoseconds(int(ns))


class _Out:
    """An MCAP writer with protobuf / JSON channels registered on first use."""

    def __init__(self, f: Any, profile: str = "") -> None:
        self.w = Writer(f, compression=CompressionType.ZSTD)
        self.w.start(profile=profile, library=f"batchpose {__version__}")
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self.topics: set[str] = set()

    def proto(self, topic: str, msg: Any, log_time: int, publish_time: int | None = None) -> None:
        cid = self._channel_ids.get(topic)
        if cid is None:
            name = type(msg).DESCRIPTOR.full_name
            sid = self._schema_ids.get(name)
            if sid is None:
                sid = self._schema_ids[name] = register_schema(self.w, type(msg))
            cid = self._channel_ids[topic] = self.w.register_channel(topic, "protobuf", sid)
            self.topics.add(topic)
        self.w.add_message(
            cid,
            log_time=int(log_time),
            data=msg.SerializeToString(),
            publish_time=int(log_time if publish_time is None else publish_time),
        )

    def json(self, topic: str, schema: dict, obj: Any, log_time: int) -> None:
        cid = self._channel_ids.get(topic)
        if cid is None:
            name = schema["title"]
            sid = self._schema_ids.get(name)
            if sid is None:
                sid = self._schema_ids[name] = self.w.register_schema(name, "jsonschema", json.dumps(schema).encode())
            cid = self._channel_ids[topic] = self.w.register_channel(topic, "json", sid)
            self.topics.add(topic)
        self.w.add_message(
            cid,
            log_time=int(log_time),
            data=json.dumps(obj, separators=(",", ":")).encode(),
            publish_time=int(log_time),
        )

    def finish(self) -> None:
        self.w.finish()


def _unwritable(frame: Frame) -> str:
    """Why a frame's image cannot go into a log (its :attr:`Frame.error`, no bytes, or PNG/JPEG bytes
    without a readable header); "" when it can."""
    if frame.error is not None:
        return str(frame.error)
    where = frame.source or frame.frame_id
    if not frame.image_data:
        return f"{where}: image is empty (0 bytes)"
    if frame.image_format not in RAW_ENCODINGS and image_size(frame.image_data) is None:
        return f"{where}: not a readable PNG/JPEG file (cannot read its size from the header)"
    return ""


def _write_frame(out: _Out, frame: Frame, obj_ids: Callable[[str], int], kind: list[str], strict: bool = True) -> bool:
    """Calibration, ground truth and image of one frame, all at ``frame.stamp_ns``; False when the frame is
    left out.

    With ``strict`` off (the poses export after a run, where such frames are already failed rows), a frame
    whose image cannot be used is left out and a depth image that cannot be read is left out of its frame,
    each with a warning; with it on (``convert``), both raise.

    Raises:
        BatchposeError: with ``strict``, the frame's :attr:`Frame.error`.
        ImageError: with ``strict``, a depth image that cannot be decoded.
    """
    if frame.error is not None and strict:
        raise type(frame.error)(*frame.error.args) from None
    problem = "" if strict else _unwritable(frame)
    if problem:
        log.warning("%s; the frame is left out of the MCAP (its status is written)", problem)
        return False
    t = int(frame.stamp_ns)
    cam = frame.camera
    K = np.asarray(cam.K, dtype=np.float64).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))])
    cal = CameraCalibration(
        frame_id=CAMERA_FRAME_ID,
        width=int(cam.width),
        height=int(cam.height),
        distortion_model=cam.distortion_model or ("plumb_bob" if cam.dist.size else ""),
        D=np.asarray(cam.dist, dtype=float).tolist(),
        K=K.reshape(-1).tolist(),
        R=np.eye(3).reshape(-1).tolist(),
        P=P.reshape(-1).tolist(),
    )
    _timestamp(cal.timestamp, t)
    out.proto(CALIBRATION_TOPIC, cal, t)
    if frame.gt:
        out.json(
            GT_TOPIC,
            GT_JSON_SCHEMA,
            {
                "stamp_ns": t,
                "frame_id": CAMERA_FRAME_ID,
                "source_frame_id": frame.frame_id,
                "scene_id": int(frame.scene_id),
                "im_id": int(frame.im_id),
                "objects": [
                    {
                        "obj_name": g.obj_name,
                        "obj_id": int(obj_ids(g.obj_name)),
                        "cam_from_model": np.asarray(g.cam_from_model, dtype=float).reshape(-1).tolist(),
                    }
                    for g in frame.gt
                ],
            },
            t,
        )
    fmt = frame.image_format.lower()
    this_kind = "raw" if frame.image_format in RAW_ENCODINGS else "compressed"
    if not kind:
        kind.append(this_kind)
    elif kind[0] != this_kind:
        raise DataError(
            f"{frame.source or frame.frame_id}: {this_kind} image after {kind[0]} images "
            f"(one topic holds one image type)"
        )
    if this_kind == "compressed":
        img: Any = CompressedImage(
            frame_id=CAMERA_FRAME_ID, data=frame.image_data, format="jpeg" if fmt == "jpg" else fmt
        )
    else:
        img = RawImage(
            frame_id=CAMERA_FRAME_ID,
            width=int(cam.width),
            height=int(cam.height),
            encoding=frame.image_format,
            step=int(frame.raw_step),
            data=frame.image_data,
        )
    _timestamp(img.timestamp, t)
    out.proto(IMAGE_TOPIC, img, t)
    try:
        depth = decode_depth(frame)
    except ImageError as e:
        if strict:
            raise
        log.warning("%s; the depth image is left out of the MCAP (the frame and its poses are written)", e)
        depth = None
    if depth is not None:  # after the image: its channel must not come first (readers take the first image topic)
        mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype("<u2")
        d = RawImage(
            frame_id=CAMERA_FRAME_ID,
            width=int(mm.shape[1]),
            height=int(mm.shape[0]),
            encoding="16UC1",
            step=int(2 * mm.shape[1]),
            data=mm.tobytes(),
        )
        _timestamp(d.timestamp, t)
        out.proto(DEPTH_TOPIC, d, t)
    return True


def _tmp_path(out_path: Path) -> Path:
    """``OUT.mcap`` -> ``OUT.mcap.tmp``: written first, renamed when complete."""
    return out_path.with_name(out_path.name + ".tmp")


def write_frames_mcap(
    frames: Iterable[Frame],
    out_path: Path,
    *,
    obj_ids: Mapping[str, int] | Callable[[str], int] | None = None,
    metadata: Mapping[str, str] | None = None,
) -> int:
    """Write frames as an MCAP log (atomically: ``OUT.mcap.tmp`` then rename).

    Topics: ``/camera/image`` (foxglove.CompressedImage with the PNG/JPEG bytes copied, never
    re-encoded; foxglove.RawImage for raw frames), ``/camera/calibration`` (foxglove.CameraCalibration)
    and, for frames with ground truth, ``/ground_truth/poses`` (JSON, :data:`GT_JSON_SCHEMA`). Log and
    publish time = ``frame.stamp_ns``; image ``frame_id`` "camera".

    Args:
        frames: frames in time order (consumed once, lazily).
        out_path: output ``.mcap`` file.
        obj_ids: object name -> data set id (a mapping, or a function such as
            :meth:`FrameSource.obj_id`), stored in the ground-truth messages and, for every object seen
            there and every key of a mapping, in the ``batchpose`` metadata record (read back by
            :meth:`McapFrameSource.obj_id`).
        metadata: extra string key/values for the ``batchpose`` metadata record.

    Returns:
        Number of frames written.
    """
    out_path = Path(out_path)
    tmp = _tmp_path(out_path)
    if obj_ids is None:
        obj_ids = {}
    lookup = obj_ids if callable(obj_ids) else (lambda name, m=obj_ids: int(m.get(name, 0)))
    seen: set[str] = set() if callable(obj_ids) else set(obj_ids)
    n = 0
    try:
        with open(tmp, "wb") as f:
            out = _Out(f)
            kind: list[str] = []
            for frame in frames:
                _write_frame(out, frame, lookup, kind)
                seen.update(g.obj_name for g in frame.gt)
                n += 1
            meta = {"version": __version__, **(metadata or {})}
            ids = {name: lookup(name) for name in sorted(seen)}
            if any(ids.values()):
                meta["obj_ids"] = json.dumps(ids, sort_keys=True)
            out.w.add_metadata(METADATA_NAME, meta)
            out.finish()
        os.replace(tmp, out_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    log.debug("wrote %d frames to %s", n, out_path)
    return n


# -------------------------------------------------------------------------------------- write-back


def mesh_to_glb(mesh: Any, max_texture_px: int = 1024) -> bytes:
    """Binary glTF of a (textured) trimesh, with its texture downscaled to keep the MCAP small.

    Args:
        mesh: ``trimesh.Trimesh`` (or ``trimesh.Scene``) in metres, model frame.
        max_texture_px: longest texture side after downscaling (the YCB scans ship 4096²).

    Returns:
        GLB bytes; vertices stay in the model frame (glTF's Y-up is undone by the model pose that
        :func:`write_poses_mcap` gives Foxglove).
    """
    import trimesh
    from PIL import Image

    geoms = list(mesh.geometry.values()) if isinstance(mesh, trimesh.Scene) else [mesh]
    out = []
    for g in geoms:
        g = g.copy()
        mat = getattr(g.visual, "material", None)
        for attr in ("image", "baseColorTexture"):
            img = getattr(mat, attr, None)
            if img is None or max(img.size) <= max_texture_px:
                continue
            scale = max_texture_px / max(img.size)
            small = img.resize((max(1, round(img.size[0] * scale)), max(1, round(img.size[1] * scale))), Image.LANCZOS)
            if small.mode == "RGB":  # trimesh embeds JPEG-format images as JPEG (else PNG, 5x larger)
                buf = io.BytesIO()
                small.save(buf, format="JPEG", quality=90)
                small = Image.open(io.BytesIO(buf.getvalue()))
                small.load()
            setattr(mat, attr, small)
        out.append(g)
    scene = trimesh.Scene(out) if len(out) > 1 else out[0]
    return bytes(scene.export(file_type="glb"))


def _glb_bounds(name: str, glb: bytes) -> np.ndarray:
    """(2, 3) min/max corner of a GLB's geometry, metres."""
    import trimesh

    try:
        scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    except (ValueError, KeyError, IndexError, TypeError, OSError, struct.error) as e:
        raise DataError(f"mesh {name!r}: cannot read the glb bytes ({one_line(e)})") from None
    b = np.asarray(scene.bounds, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)):
        raise DataError(f"mesh {name!r}: glb has no geometry")
    return b


def _color(i: int, a: float = 1.0) -> Color:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return Color(r=r, g=g, b=b, a=a)


def _pose_msg(T: np.ndarray) -> Pose:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    return Pose(
        position=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def _rows(records: Any) -> list[dict]:
    if hasattr(records, "to_dict"):  # a pandas DataFrame read from poses.parquet
        records = records.to_dict("records")
    return [dict(r) for r in records]


class _PoseWriter:
    """Writes the per-image batchpose topics."""

    def __init__(self, out: _Out, rows: list[dict], meshes: Mapping[str, Any]) -> None:
        self.out = out
        self.by_stamp: dict[int, list[dict]] = defaultdict(list)
        for r in rows:
            self.by_stamp[int(r["stamp_ns"])].append(r)
        names = sorted({str(r["obj_name"]) for r in rows} | set(meshes))
        self.index = {n: i for i, n in enumerate(names)}
        self.glb: dict[str, bytes] = {}
        for name, m in meshes.items():
            self.glb[name] = m if isinstance(m, (bytes, bytearray)) else mesh_to_glb(m)
        self.bounds = {name: _glb_bounds(name, g) for name, g in self.glb.items()}
        missing = sorted({str(r["obj_name"]) for r in rows} - set(self.glb))
        if missing:
            log.warning("no mesh for %s: no 3D model or box in the MCAP for them", ", ".join(missing))
        self.scene_written = False
        self.n_images = 0

    def scene(self, log_time: int) -> None:
        """One SceneUpdate with every mesh, locked to its object frame, alive for the whole log."""
        if self.scene_written:
            return
        upd = SceneUpdate()
        for name, glb in sorted(self.glb.items()):
            e = upd.entities.add()
            _timestamp(e.timestamp, log_time)
            e.frame_id = f"object/{name}"
            e.id = name
            e.frame_locked = True  # lifetime left 0: forever
            e.models.append(
                ModelPrimitive(
                    pose=Pose(position=Vector3(x=0, y=0, z=0), orientation=_GLTF_UNDO_Y_UP),
                    scale=Vector3(x=1, y=1, z=1),
                    color=_color(self.index[name]),
                    override_color=False,
                    media_type="model/gltf-binary",
                    data=bytes(glb),
                )
            )
        self.out.proto(SCENE_TOPIC, upd, log_time)
        self.scene_written = True

    def image(self, log_time: int, stamp_ns: int, frame_id: str, camera: Camera | None, fid: str) -> None:
        """Pose topics for the image logged at ``log_time`` (header stamp ``stamp_ns``)."""
        rows = self.by_stamp.pop(int(log_time), [])
        self.n_images += 1
        out = self.out
        ann = ImageAnnotations()
        status = []
        n_fail = 0
        for r in sorted(rows, key=lambda r: str(r["obj_name"])):
            name = str(r["obj_name"])
            i = self.index.get(name, 0)
            T = row_cam_from_model(r)
            ok = str(r["status"]) == "ok" and T is not None
            conf = float(r.get("confidence", 0.0) or 0.0)
            conf = conf if np.isfinite(conf) else 0.0  # JSON has no NaN
            status.append(
                {
                    "obj_name": name,
                    "status": str(r["status"]),
                    "reason": str(r.get("reason", "") or ""),
                    "confidence": conf,
                    "n_inliers": int(r.get("n_inliers", 0) or 0),
                    "tracked": bool(r.get("tracked", False)),
                }
            )
            if not ok:
                text = f"{name}: {r['status']}" + (f" ({r.get('reason')})" if r.get("reason") else "")
                ta = ann.texts.add()
                _timestamp(ta.timestamp, stamp_ns)
                ta.position.CopyFrom(Point2(x=8.0, y=20.0 + 18.0 * n_fail))
                ta.text, ta.font_size = text, 14.0
                ta.text_color.CopyFrom(_color(i))
                ta.background_color.CopyFrom(Color(r=0, g=0, b=0, a=0.6))
                n_fail += 1
                continue
            tf = FrameTransform(parent_frame_id=frame_id, child_frame_id=f"object/{name}")
            _timestamp(tf.timestamp, stamp_ns)
            pose = _pose_msg(T)
            tf.translation.CopyFrom(pose.position)
            tf.rotation.CopyFrom(pose.orientation)
            out.proto(TF_TOPIC, tf, log_time)
            pif = PosesInFrame(frame_id=frame_id, poses=[pose])
            _timestamp(pif.timestamp, stamp_ns)
            out.proto(POSES_TOPIC_PREFIX + name, pif, log_time)
            self._annotate(ann, name, i, T, camera, r, conf, stamp_ns)
        out.proto(ANNOTATIONS_TOPIC, ann, log_time)
        out.json(
            STATUS_TOPIC,
            STATUS_JSON_SCHEMA,
            {
                "frame_id": str(rows[0]["frame_id"]) if rows else fid,
                "stamp_ns": int(log_time),
                "n_ok": sum(s["status"] == "ok" for s in status),
                "objects": status,
            },
            log_time,
        )

    def _annotate(
        self,
        ann: ImageAnnotations,
        name: str,
        i: int,
        T: np.ndarray,
        camera: Camera | None,
        r: Mapping[str, Any],
        conf: float,
        stamp_ns: int,
    ) -> None:
        inl = np.asarray(r.get("inliers_px", []) if r.get("inliers_px") is not None else [], dtype=float)
        if inl.size >= 2:
            pa = ann.points.add()
            _timestamp(pa.timestamp, stamp_ns)
            pa.type = PointsAnnotation.POINTS
            pa.points.extend(Point2(x=float(x), y=float(y)) for x, y in inl.reshape(-1, 2))
            pa.outline_color.CopyFrom(_color(i))
            pa.thickness = 3.0
        if camera is None or name not in self.bounds:
            return
        K = np.asarray(camera.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            return
        lo, hi = self.bounds[name]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        cam_pts = corners @ T[:3, :3].T + T[:3, 3]
        if np.any(cam_pts[:, 2] <= 1e-6):  # box reaches behind the camera: a projection would wrap around
            return
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        dist = np.asarray(camera.dist, dtype=np.float64) if camera.dist.size else None
        uv, _ = cv2.projectPoints(corners, rvec, T[:3, 3].astype(np.float64), K, dist)
        uv = uv.reshape(-1, 2)
        pa = ann.points.add()
        _timestamp(pa.timestamp, stamp_ns)
        pa.type = PointsAnnotation.LINE_LIST
        pa.points.extend(Point2(x=float(x), y=float(y)) for x, y in uv[_BOX_EDGES.reshape(-1)])
        pa.outline_color.CopyFrom(_color(i))
        pa.thickness = 2.0
        ta = ann.texts.add()
        _timestamp(ta.timestamp, stamp_ns)
        ta.position.CopyFrom(Point2(x=float(uv[:, 0].min()), y=float(max(uv[:, 1].min() - 4.0, 12.0))))
        tracked = " (tracked)" if bool(r.get("tracked", False)) else ""
        ta.text, ta.font_size = f"{name} {conf:.2f}{tracked}", 14.0
        ta.text_color.CopyFrom(_color(i))
        ta.background_color.CopyFrom(Color(r=0, g=0, b=0, a=0.6))

    def unmatched(self) -> int:
        return sum(len(v) for v in self.by_stamp.values())


def write_poses_mcap(
    out_path: Path,
    records: Iterable[Mapping[str, Any]],
    meshes: Mapping[str, Any],
    input_mcap: Path | None = None,
    frames: Iterable[Frame] | None = None,
    *,
    image_topic: str | None = None,
    calibration_topic: str | None = None,
    rectified: bool | None = None,
) -> Path:
    """Write the estimates as an MCAP for Foxglove (atomically: ``OUT.mcap.tmp`` then rename).

    With ``input_mcap``: every input message is copied unchanged (topic, schema, log and publish
    time, sequence, bytes; plus metadata and attachments) and the batchpose topics (module docstring)
    are added at each image's log time. Without it, ``frames`` are written as by
    :func:`write_frames_mcap` plus the batchpose topics.

    Args:
        out_path: output file; must differ from ``input_mcap``.
        records: ``poses.parquet`` rows (dicts or a DataFrame): ``frame_id``, ``stamp_ns``,
            ``obj_name``, ``status``, ``reason``, ``R`` (9, row-major), ``t_m`` (3, metres),
            ``confidence``, ``n_inliers``, ``inliers_px`` (x0 y0 x1 y1 ..., pixels). A row belongs to the
            image whose log time equals its ``stamp_ns``.
        meshes: object name -> binary glTF bytes (see :func:`mesh_to_glb`; a trimesh is converted).
        input_mcap: the log the frames came from.
        frames: the frames (folder input), when there is no input log.
        image_topic: image topic of ``input_mcap`` the records refer to (default: as
            :class:`McapFrameSource` chooses).
        calibration_topic: its calibration topic (default: the one beside the image topic).
        rectified: whether its images are rectified, as the run read them (see :class:`McapFrameSource`):
            the overlays are projected with the camera the poses were estimated with.

    Returns:
        ``out_path``.
    """
    out_path = Path(out_path)
    if (input_mcap is None) == (frames is None):
        raise ConfigError("write_poses_mcap: pass exactly one of input_mcap and frames")
    if input_mcap is not None and out_path.resolve() == Path(input_mcap).resolve():
        raise ConfigError(f"{out_path}: the output would overwrite the input log")
    rows = _rows(records)
    tmp = _tmp_path(out_path)
    left_out = 0
    try:
        with open(tmp, "wb") as f:
            if input_mcap is not None:
                pw = _copy_with_poses(f, Path(input_mcap), rows, meshes, image_topic, calibration_topic, rectified)
            else:
                out = _Out(f)
                out.w.add_metadata(METADATA_NAME, {"version": __version__})
                pw = _PoseWriter(out, rows, meshes)
                kind: list[str] = []
                for frame in frames or ():
                    pw.scene(frame.stamp_ns)
                    left_out += not _write_frame(out, frame, lambda _name: 0, kind, strict=False)
                    pw.image(frame.stamp_ns, frame.stamp_ns, CAMERA_FRAME_ID, frame.camera, frame.frame_id)
                out.finish()
        os.replace(tmp, out_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if pw.unmatched():
        log.warning("%s: %d pose records match no image log time (stamp_ns)", out_path, pw.unmatched())
    shown = f"{pw.n_images - left_out} images" + (f", {left_out} unreadable frame(s) left out" if left_out else "")
    log.info("wrote %s (%s, %d pose records)", out_path, shown, len(rows))
    return out_path


def _copy_with_poses(
    f: Any,
    input_mcap: Path,
    rows: list[dict],
    meshes: Mapping[str, Any],
    image_topic: str | None,
    calibration_topic: str | None,
    rectified: bool | None,
) -> _PoseWriter:
    src = McapFrameSource(input_mcap, image_topic=image_topic, calibration_topic=calibration_topic, rectified=rectified)
    clash = sorted(ch.topic for ch in src.channels.values() if ch.topic.startswith(OUTPUT_PREFIX))
    if clash:
        raise DataError(
            f"{input_mcap}: already holds batchpose output topics ({', '.join(clash[:3])}); "
            "write back into the original log instead"
        )
    # A ROS profile requires every channel in its encoding; the batchpose topics are protobuf and JSON.
    out = _Out(f, profile="" if src.profile in ("ros1", "ros2") else src.profile)
    schema_ids: dict[int, int] = {}
    for sid, s in sorted(src.schemas.items()):
        schema_ids[sid] = out.w.register_schema(s.name, s.encoding, s.data)
    channel_ids: dict[int, int] = {}
    for cid, ch in sorted(src.channels.items()):
        channel_ids[cid] = out.w.register_channel(
            ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), dict(ch.metadata)
        )
    for name, data in src.metadata.items():
        out.w.add_metadata(name, data)
    for a in src.iter_attachments():
        out.w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
    pw = _PoseWriter(out, rows, meshes)
    cal: _Calib | None = None
    first: _Calib | None = None
    for schema, channel, message in src.iter_raw():
        pw.scene(message.log_time)
        out.w.add_message(
            channel_ids[channel.id],
            log_time=message.log_time,
            data=message.data,
            publish_time=message.publish_time,
            sequence=message.sequence,
        )
        if channel.topic == src.calibration_topic:
            cal = src.calibration(schema, channel, message)
        elif channel.topic == src.image_topic:
            if cal is None and first is None:
                first = src.first_calibration()
            c = cal or first
            try:
                img: _Image | None = src.image(schema, channel, message)
            except _BadMessage:  # its frame is a bad_image row (reading warned); its status still goes in
                img = None
            cam = _camera(c, img) if c is not None else None
            pw.image(
                message.log_time,
                img.stamp_ns if img is not None else message.log_time,
                (img.frame_id if img is not None else "") or CAMERA_FRAME_ID,
                cam,
                f"mcap:{message.log_time}",
            )
    out.finish()
    return pw
