"""Writing MCAP logs: the shared writer (:class:`LogWriter`) and frames as a log (:func:`write_frames_mcap`).

A frame is written as its calibration, its ground truth (when it has some), its image and its depth image
(when it has one), all at its ``stamp_ns``; topics and schemas in :mod:`batchpose.io.mcap_topics`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable, Mapping
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _dist_version
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from batchpose.core.frames import RAW_ENCODINGS, Camera, Frame, decode_depth, image_size
from batchpose.errors import DataError, ImageError
from batchpose.io.files import atomic_path
from batchpose.io.mcap_topics import (
    CALIBRATION_TOPIC,
    CAMERA_FRAME_ID,
    DEPTH_TOPIC,
    GT_JSON_SCHEMA,
    GT_TOPIC,
    IMAGE_TOPIC,
    METADATA_NAME,
)

log = logging.getLogger("batchpose")

try:
    #: batchpose's installed version: in every log's header (library) and ``batchpose`` metadata record.
    VERSION = _dist_version("batchpose")
except PackageNotFoundError:  # running from a source tree that is not installed
    VERSION = "unknown"


def set_timestamp(msg_ts: Any, ns: int) -> None:
    """Set a protobuf ``google.protobuf.Timestamp`` field to ``ns`` nanoseconds."""
    msg_ts.FromNanoseconds(int(ns))


class LogWriter:
    """An MCAP writer (zstd chunks) with protobuf / JSON channels registered on first use.

    Args:
        f: the open binary file to write.
        profile: the header's profile ("" for none).
    """

    def __init__(self, f: Any, profile: str = "") -> None:
        self.w = Writer(f, compression=CompressionType.ZSTD)
        self.w.start(profile=profile, library=f"batchpose {VERSION}")
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self.topics: set[str] = set()

    def proto(self, topic: str, msg: Any, log_time: int, publish_time: int | None = None) -> None:
        """Write a protobuf message on ``topic`` (its channel and schema registered on first use); times in ns."""
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
        """Write ``obj`` as a compact JSON message on ``topic`` with the JSON schema ``schema`` (by its title)."""
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
        """Write the summary and footer."""
        self.w.finish()


# ------------------------------------------------------------------------------------------- frames


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


def _calibration_msg(cam: Camera, t: int) -> CameraCalibration:
    """The camera as foxglove.CameraCalibration: K, R = I, P = [K | 0], D and model, size; stamp ``t`` ns."""
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
    set_timestamp(cal.timestamp, t)
    return cal


def _ground_truth_json(frame: Frame, t: int, obj_ids: Callable[[str], int]) -> dict:
    """The frame's ground truth as a ``/ground_truth/poses`` message (:data:`GT_JSON_SCHEMA`)."""
    return {
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
    }


def _image_msg(frame: Frame, kind: list[str], t: int) -> CompressedImage | RawImage:
    """The frame's image as foxglove.CompressedImage (PNG/JPEG bytes copied) or RawImage; stamp ``t`` ns.

    Args:
        frame: the frame.
        kind: the image type of the log's frames so far ("raw" or "compressed"; empty before the first),
            set by the first frame.
        t: its stamp, ns.

    Raises:
        DataError: the frame's image type differs from the earlier frames'.
    """
    fmt = frame.image_format.lower()
    this_kind = "raw" if frame.image_format in RAW_ENCODINGS else "compressed"
    if not kind:
        kind.append(this_kind)
    elif kind[0] != this_kind:
        raise DataError(
            f"{frame.source or frame.frame_id}: {this_kind} image after {kind[0]} images "
            f"(one topic holds one image type)"
        )
    cam = frame.camera
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
    set_timestamp(img.timestamp, t)
    return img


def _depth_msg(frame: Frame, t: int, strict: bool) -> RawImage | None:
    """The frame's depth image as 16UC1 foxglove.RawImage in mm (None without one); stamp ``t`` ns.

    Raises:
        ImageError: with ``strict``, the depth image cannot be decoded (else a warning, and None).
    """
    try:
        depth = decode_depth(frame)
    except ImageError as e:
        if strict:
            raise
        log.warning("%s; the depth image is left out of the MCAP (the frame and its poses are written)", e)
        depth = None
    if depth is None:
        return None
    mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype("<u2")
    d = RawImage(
        frame_id=CAMERA_FRAME_ID,
        width=int(mm.shape[1]),
        height=int(mm.shape[0]),
        encoding="16UC1",
        step=int(2 * mm.shape[1]),
        data=mm.tobytes(),
    )
    set_timestamp(d.timestamp, t)
    return d


def write_frame(
    out: LogWriter, frame: Frame, obj_ids: Callable[[str], int], kind: list[str], strict: bool = True
) -> bool:
    """Calibration, ground truth and image of one frame, all at ``frame.stamp_ns``; False when the frame is
    left out.

    With ``strict`` off (the poses export after a run, where such frames are already failed rows), a frame
    whose image cannot be used is left out and a depth image that cannot be read is left out of its frame,
    each with a warning; with it on (``convert``), both raise.

    Args:
        out: the log being written.
        frame: the frame.
        obj_ids: object name -> data set id, for the ground-truth message.
        kind: the image type of the frames written so far (see :func:`_image_msg`); updated.
        strict: raise on a frame or depth image that cannot be written, rather than leave it out.

    Raises:
        BatchposeError: with ``strict``, the frame's :attr:`Frame.error`.
        DataError: a raw image after compressed ones, or the other way round.
        ImageError: with ``strict``, a depth image that cannot be decoded.
    """
    if frame.error is not None and strict:
        raise type(frame.error)(*frame.error.args) from None
    problem = "" if strict else _unwritable(frame)
    if problem:
        log.warning("%s; the frame is left out of the MCAP (its status is written)", problem)
        return False
    t = int(frame.stamp_ns)
    out.proto(CALIBRATION_TOPIC, _calibration_msg(frame.camera, t), t)
    if frame.gt:
        out.json(GT_TOPIC, GT_JSON_SCHEMA, _ground_truth_json(frame, t, obj_ids), t)
    out.proto(IMAGE_TOPIC, _image_msg(frame, kind, t), t)
    depth = _depth_msg(frame, t, strict)
    if depth is not None:  # after the image: its channel must not come first (readers take the first image topic)
        out.proto(DEPTH_TOPIC, depth, t)
    return True


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
    if obj_ids is None:
        obj_ids = {}
    lookup = obj_ids if callable(obj_ids) else (lambda name, m=obj_ids: int(m.get(name, 0)))
    seen: set[str] = set() if callable(obj_ids) else set(obj_ids)
    n = 0
    with atomic_path(out_path) as tmp, open(tmp, "wb") as f:
        out = LogWriter(f)
        kind: list[str] = []
        for frame in frames:
            write_frame(out, frame, lookup, kind)
            seen.update(g.obj_name for g in frame.gt)
            n += 1
        meta = {"version": VERSION, **(metadata or {})}
        ids = {name: lookup(name) for name in sorted(seen)}
        if any(ids.values()):
            meta["obj_ids"] = json.dumps(ids, sort_keys=True)
        out.w.add_metadata(METADATA_NAME, meta)
        out.finish()
    log.debug("wrote %d frames to %s", n, out_path)
    return n
