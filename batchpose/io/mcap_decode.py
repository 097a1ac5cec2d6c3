"""MCAP message decoding: one message's bytes to a calibration, an image (pixel bytes untouched) or ground truth.

Messages are decoded with the schema embedded in the log: foxglove schemas in protobuf or in Foxglove's JSON
encoding (bytes as base64, times as ``{sec, nsec}``), ROS 2 (cdr) and ROS 1 messages. The field helpers
accept all of them: foxglove names fields ``K``/``D``/``P``, ROS 2 ``k``/``d``/``p``, and a JSON-encoded
message is a dict.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros1.decoder import DecoderFactory as Ros1DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from batchpose.core.frames import RAW_ENCODINGS, Camera, ObjectPose, image_size
from batchpose.errors import DataError
from batchpose.io.files import one_line
from batchpose.io.mcap_topics import GT_SCHEMA_NAME, IMAGE_SCHEMAS

try:  # the ROS 1 decoder uses a ROS installation's genpy when there is one, else the copy it ships
    from genpy.message import DeserializationError as _Ros1DecodeError
except ImportError:
    from mcap_ros1._vendor.genpy.message import DeserializationError as _Ros1DecodeError

#: Errors of a decoded message without a field we need, or with one of the wrong type.
_FIELD_ERRORS = (KeyError, TypeError, ValueError, AttributeError, binascii.Error)
_MISSING = object()


class BadMessage(DataError):
    """One message that does not parse or lacks a field: an image message's frame fails, not the batch."""


@dataclass(frozen=True)
class Calib:
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

    def rectified(self) -> Calib | None:
        """The camera of the rectified image: ``P``'s left 3x3 as K, no distortion; None without a ``P``."""
        K = self.P[:, :3]
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1):
            return None
        return dataclasses.replace(self, K=K.copy(), dist=np.zeros(0), model="")


@dataclass(frozen=True)
class ImageMsg:
    """A decoded image message (bytes untouched)."""

    fmt: str
    data: bytes
    width: int
    height: int
    step: int
    frame_id: str
    stamp_ns: int
    raw: bool


@dataclass(frozen=True)
class GroundTruth:
    """A decoded ``/ground_truth/poses`` message (:data:`batchpose.io.mcap_topics.GT_JSON_SCHEMA`)."""

    scene_id: int | None
    im_id: int | None
    poses: tuple[ObjectPose, ...]
    obj_ids: dict[str, int]


# ------------------------------------------------------------------------------------------- fields


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
    """The message's header stamp, ns (ROS header.stamp, Foxglove's timestamp)."""
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


# ------------------------------------------------------------------------------------------ messages


def to_calib(msg: Any) -> Calib:
    """A decoded calibration message (foxglove.CameraCalibration, CameraInfo) as :class:`Calib`.

    Raises:
        KeyError, TypeError, ValueError, AttributeError: a field is missing or malformed.
    """
    K = np.asarray(list(_field(msg, "K", "k")), dtype=np.float64)
    # A malformed K becomes NaN so that the frame fails as bad_camera instead of stopping the batch.
    K = K.reshape(3, 3) if K.size == 9 else np.full((3, 3), np.nan)
    dist = np.asarray(list(_field(msg, "D", "d", default=[])), dtype=np.float64).reshape(-1)
    P = np.asarray(list(_field(msg, "P", "p", default=[])), dtype=np.float64)
    return Calib(
        K=K,
        width=int(_field(msg, "width", default=0)),
        height=int(_field(msg, "height", default=0)),
        dist=dist,
        model=str(_field(msg, "distortion_model", default="")),
        P=P.reshape(3, 4) if P.size == 12 else np.zeros((3, 4)),
        frame_id=_frame_id_of(msg, default=""),
    )


def to_image(msg: Any, kind: str) -> ImageMsg:
    """A decoded image message as :class:`ImageMsg`; a big-endian 16-bit raw image is byte-swapped.

    Args:
        msg: the decoded message.
        kind: "compressed", "raw" or "video" (:data:`batchpose.io.mcap_topics.IMAGE_SCHEMAS`).

    Raises:
        KeyError, TypeError, ValueError, AttributeError, binascii.Error: a field is missing or malformed.
    """
    data = _bytes(_field(msg, "data"))
    if kind == "compressed":
        fmt = _compressed_format(str(_field(msg, "format")))
        return ImageMsg(fmt, data, 0, 0, 0, _frame_id_of(msg), _stamp_ns(msg), raw=False)
    if kind == "video":  # one frame of a stream: decoded in log order by batchpose.io.video.VideoDecoder
        fmt = "video/" + str(_field(msg, "format")).lower().strip()
        return ImageMsg(fmt, data, 0, 0, 0, _frame_id_of(msg), _stamp_ns(msg), raw=False)
    encoding = str(_field(msg, "encoding"))
    spec = RAW_ENCODINGS.get(encoding)
    if _field(msg, "is_bigendian", default=0) and spec is not None and np.dtype(spec[1]).itemsize > 1:
        data = np.frombuffer(data[: len(data) // 2 * 2], dtype=">u2").astype("<u2").tobytes()  # as decode_image reads
    return ImageMsg(
        encoding,
        data,
        int(_field(msg, "width")),
        int(_field(msg, "height")),
        int(_field(msg, "step")),
        _frame_id_of(msg),
        _stamp_ns(msg),
        raw=True,
    )


def to_ground_truth(obj: Any) -> GroundTruth:
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
    return GroundTruth(scene_im[0], scene_im[1], tuple(poses), ids)


def camera_of(cal: Calib, img: ImageMsg | None) -> Camera:
    """Camera for one image: raw images carry their size; compressed ones (and an image message that
    does not parse: None) take the calibration's."""
    if img is not None and img.raw:
        w, h = img.width, img.height
    elif (cal.width and cal.height) or img is None:
        w, h = cal.width, cal.height
    else:
        w, h = image_size(img.data) or (0, 0)
    return Camera(K=cal.K, width=w, height=h, dist=cal.dist, distortion_model=cal.model)


# ------------------------------------------------------------------------------------------- decoder


class MessageDecoder:
    """Decodes the messages of one log with their embedded schemas (protobuf, ROS 2 cdr, ROS 1, or JSON),
    one decoder per channel, made on its first message.

    Args:
        path: the log (named in errors).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._decoders: dict[int, Callable[[bytes], Any]] = {}
        self._factories = (ProtobufDecoderFactory(), Ros2DecoderFactory(), Ros1DecoderFactory())

    def decode(self, schema: Schema | None, channel: Channel, message: Message) -> Any:
        """Decode one message.

        Raises:
            DataError: no decoder for the encoding, or its schema text does not parse.
            BadMessage: the message's bytes do not parse.
        """
        dec = self._decoders.get(channel.id)
        if dec is None:
            dec = self._decoders[channel.id] = self._decoder_for(schema, channel)
        try:
            return dec(message.data)
        except (DecodeError, McapError, ValueError, IndexError, TypeError, struct.error, _Ros1DecodeError) as e:
            raise BadMessage(
                f"{self.path}:{channel.topic}: cannot decode message at log time {message.log_time} ({one_line(e)})"
            ) from None

    def _decoder_for(self, schema: Schema | None, channel: Channel) -> Callable[[bytes], Any]:
        if channel.message_encoding == "json":
            return json.loads
        dec = None
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
        return dec

    def _bad_field(self, schema: Schema | None, channel: Channel, message: Message, e: Exception) -> BadMessage:
        what = f"has no field {e.args[0]!r}" if isinstance(e, KeyError) else f"has a malformed field ({one_line(e)})"
        return BadMessage(
            f"{self.path}:{channel.topic}: {channel.message_encoding}-encoded {schema.name if schema else 'a'} "
            f"message at log time {message.log_time} {what}"
        )

    def calibration(self, schema: Schema | None, channel: Channel, message: Message) -> Calib:
        """Decode a calibration message as it is (K, D and P; no check of the distortion).

        Raises:
            DataError: the message does not parse or lacks a field.
        """
        msg = self.decode(schema, channel, message)
        try:
            return to_calib(msg)
        except _FIELD_ERRORS as e:
            raise self._bad_field(schema, channel, message, e) from None

    def image(self, schema: Schema | None, channel: Channel, message: Message) -> ImageMsg:
        """Decode an image message (its pixel bytes stay encoded).

        Raises:
            DataError: the message does not parse or lacks a field.
        """
        kind = IMAGE_SCHEMAS[schema.name if schema else ""]
        msg = self.decode(schema, channel, message)
        try:
            return to_image(msg, kind)
        except _FIELD_ERRORS as e:
            raise self._bad_field(schema, channel, message, e) from None

    def ground_truth(self, schema: Schema | None, channel: Channel, message: Message) -> GroundTruth:
        """Decode a ``/ground_truth/poses`` message.

        Raises:
            DataError: the message does not parse or lacks a field (which one, and its log time).
        """
        try:
            return to_ground_truth(self.decode(schema, channel, message))
        except ValueError as e:
            raise DataError(
                f"{self.path}:{channel.topic}: {GT_SCHEMA_NAME} message at log time {message.log_time}: {e}"
            ) from None
