"""Writing the estimates into an MCAP log for Foxglove (:func:`write_poses_mcap`): the input log copied byte
for byte, or the frames written as by :func:`batchpose.io.mcap_write.write_frames_mcap`, plus the batchpose
topics of :mod:`batchpose.io.mcap_topics` (scene, tf, poses, annotations, status) at each image's log time.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.ModelPrimitive_pb2 import ModelPrimitive
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from scipy.spatial.transform import Rotation

from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import row_cam_from_model
from batchpose.errors import ConfigError, DataError
from batchpose.io.files import atomic_path
from batchpose.io.gltf import glb_bounds, mesh_to_glb
from batchpose.io.mcap_decode import BadMessage, Calib, ImageMsg, camera_of
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_topics import (
    ANNOTATIONS_TOPIC,
    CAMERA_FRAME_ID,
    METADATA_NAME,
    OUTPUT_PREFIX,
    POSES_TOPIC_PREFIX,
    SCENE_TOPIC,
    STATUS_JSON_SCHEMA,
    STATUS_TOPIC,
    TF_TOPIC,
)
from batchpose.io.mcap_write import VERSION, LogWriter, set_timestamp, write_frame

log = logging.getLogger("batchpose")

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


def _color(i: int, a: float = 1.0) -> Color:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return Color(r=r, g=g, b=b, a=a)


def _pose_msg(T: np.ndarray) -> Pose:
    """A (4, 4) rigid transform (metres) as foxglove.Pose."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    return Pose(
        position=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def _rows(records: Any) -> list[dict]:
    if hasattr(records, "to_dict"):  # a pandas DataFrame read from poses.parquet
        records = records.to_dict("records")
    return [dict(r) for r in records]


def _status_entry(r: Mapping[str, Any]) -> dict:
    """One object's entry of a ``/batchpose/status`` message (:data:`STATUS_JSON_SCHEMA`)."""
    conf = float(r.get("confidence", 0.0) or 0.0)
    conf = conf if np.isfinite(conf) else 0.0  # JSON has no NaN
    return {
        "obj_name": str(r["obj_name"]),
        "status": str(r["status"]),
        "reason": str(r.get("reason", "") or ""),
        "confidence": conf,
        "n_inliers": int(r.get("n_inliers", 0) or 0),
        "tracked": bool(r.get("tracked", False)),
    }


def _add_label(ann: ImageAnnotations, x: float, y: float, text: str, i: int, stamp_ns: int) -> None:
    """A 14 px label at pixel (x, y) in object ``i``'s colour on a dark background."""
    ta = ann.texts.add()
    set_timestamp(ta.timestamp, stamp_ns)
    ta.position.CopyFrom(Point2(x=x, y=y))
    ta.text, ta.font_size = text, 14.0
    ta.text_color.CopyFrom(_color(i))
    ta.background_color.CopyFrom(Color(r=0, g=0, b=0, a=0.6))


class _PoseWriter:
    """Writes the per-image batchpose topics.

    Args:
        out: the log being written.
        rows: pose records (see :func:`write_poses_mcap`).
        meshes: object name -> GLB bytes or a trimesh.
    """

    def __init__(self, out: LogWriter, rows: list[dict], meshes: Mapping[str, Any]) -> None:
        self.out = out
        self.by_stamp: dict[int, list[dict]] = defaultdict(list)
        for r in rows:
            self.by_stamp[int(r["stamp_ns"])].append(r)
        names = sorted({str(r["obj_name"]) for r in rows} | set(meshes))
        self.index = {n: i for i, n in enumerate(names)}
        self.glb: dict[str, bytes | bytearray] = {}
        for name, m in meshes.items():
            self.glb[name] = m if isinstance(m, (bytes, bytearray)) else mesh_to_glb(m)
        self.bounds = {name: glb_bounds(name, g) for name, g in self.glb.items()}
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
            set_timestamp(e.timestamp, log_time)
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
        """Pose topics for the image logged at ``log_time`` (header stamp ``stamp_ns``).

        Args:
            log_time: the image's log time, ns: its records are those with this ``stamp_ns``.
            stamp_ns: the image's header stamp, ns (the in-message timestamps).
            frame_id: the image's camera frame (parent of the objects' transforms).
            camera: its camera, for the projected boxes (None: no boxes).
            fid: its ``frame_id`` in ``poses.csv``, for the status of an image without records.
        """
        rows = self.by_stamp.pop(int(log_time), [])
        self.n_images += 1
        ann = ImageAnnotations()
        status = []
        n_fail = 0
        for r in sorted(rows, key=lambda r: str(r["obj_name"])):
            name = str(r["obj_name"])
            i = self.index.get(name, 0)
            T = row_cam_from_model(r)
            entry = _status_entry(r)
            status.append(entry)
            if not (str(r["status"]) == "ok" and T is not None):
                text = f"{name}: {r['status']}" + (f" ({r.get('reason')})" if r.get("reason") else "")
                _add_label(ann, 8.0, 20.0 + 18.0 * n_fail, text, i, stamp_ns)
                n_fail += 1
                continue
            self._pose(log_time, stamp_ns, frame_id, name, T)
            self._annotate(ann, name, i, T, camera, r, entry["confidence"], stamp_ns)
        self.out.proto(ANNOTATIONS_TOPIC, ann, log_time)
        self.out.json(
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

    def _pose(self, log_time: int, stamp_ns: int, frame_id: str, name: str, T: np.ndarray) -> None:
        """The object's transform (``/batchpose/tf``) and pose (``/batchpose/poses/<name>``) in the camera frame."""
        tf = FrameTransform(parent_frame_id=frame_id, child_frame_id=f"object/{name}")
        set_timestamp(tf.timestamp, stamp_ns)
        pose = _pose_msg(T)
        tf.translation.CopyFrom(pose.position)
        tf.rotation.CopyFrom(pose.orientation)
        self.out.proto(TF_TOPIC, tf, log_time)
        pif = PosesInFrame(frame_id=frame_id, poses=[pose])
        set_timestamp(pif.timestamp, stamp_ns)
        self.out.proto(POSES_TOPIC_PREFIX + name, pif, log_time)

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
        """The object's inlier points, and its mesh's bounding box projected with its label (when the box
        is in front of the camera)."""
        inl = np.asarray(r.get("inliers_px", []) if r.get("inliers_px") is not None else [], dtype=float)
        if inl.size >= 2:
            pa = ann.points.add()
            set_timestamp(pa.timestamp, stamp_ns)
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
        set_timestamp(pa.timestamp, stamp_ns)
        pa.type = PointsAnnotation.LINE_LIST
        pa.points.extend(Point2(x=float(x), y=float(y)) for x, y in uv[_BOX_EDGES.reshape(-1)])
        pa.outline_color.CopyFrom(_color(i))
        pa.thickness = 2.0
        tracked = " (tracked)" if bool(r.get("tracked", False)) else ""
        x, y = float(uv[:, 0].min()), float(max(uv[:, 1].min() - 4.0, 12.0))
        _add_label(ann, x, y, f"{name} {conf:.2f}{tracked}", i, stamp_ns)

    def unmatched(self) -> int:
        """Number of records whose ``stamp_ns`` matched no image written so far."""
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
    time, sequence, bytes; plus metadata and attachments) and the batchpose topics (see
    :mod:`batchpose.io.mcap_topics`) are added at each image's log time. Without it, ``frames`` are written
    as by :func:`batchpose.io.mcap_write.write_frames_mcap` plus the batchpose topics.

    Args:
        out_path: output file; must differ from ``input_mcap``.
        records: ``poses.parquet`` rows (dicts or a DataFrame): ``frame_id``, ``stamp_ns``,
            ``obj_name``, ``status``, ``reason``, ``R`` (9, row-major), ``t_m`` (3, metres),
            ``confidence``, ``n_inliers``, ``inliers_px`` (x0 y0 x1 y1 ..., pixels). A row belongs to the
            image whose log time equals its ``stamp_ns``.
        meshes: object name -> binary glTF bytes (see :func:`batchpose.io.gltf.mesh_to_glb`; a trimesh is
            converted).
        input_mcap: the log the frames came from.
        frames: the frames (folder input), when there is no input log.
        image_topic: image topic of ``input_mcap`` the records refer to (default: as
            :class:`McapFrameSource` chooses).
        calibration_topic: its calibration topic (default: the one beside the image topic).
        rectified: whether its images are rectified, as the run read them (see :class:`McapFrameSource`):
            the overlays are projected with the camera the poses were estimated with.

    Returns:
        ``out_path``.

    Raises:
        ConfigError: not exactly one of ``input_mcap`` and ``frames``, or the output is the input.
        DataError: the input log already holds batchpose topics, or cannot be read.
    """
    out_path = Path(out_path)
    if (input_mcap is None) == (frames is None):
        raise ConfigError("write_poses_mcap: pass exactly one of input_mcap and frames")
    if input_mcap is not None and out_path.resolve() == Path(input_mcap).resolve():
        raise ConfigError(f"{out_path}: the output would overwrite the input log")
    rows = _rows(records)
    left_out = 0
    with atomic_path(out_path) as tmp, open(tmp, "wb") as f:
        if input_mcap is not None:
            pw = _copy_with_poses(f, Path(input_mcap), rows, meshes, image_topic, calibration_topic, rectified)
        else:
            out = LogWriter(f)
            out.w.add_metadata(METADATA_NAME, {"version": VERSION})
            pw = _PoseWriter(out, rows, meshes)
            kind: list[str] = []
            for frame in frames or ():
                pw.scene(frame.stamp_ns)
                left_out += not write_frame(out, frame, lambda _name: 0, kind, strict=False)
                pw.image(frame.stamp_ns, frame.stamp_ns, CAMERA_FRAME_ID, frame.camera, frame.frame_id)
            out.finish()
    if pw.unmatched():
        log.warning("%s: %d pose records match no image log time (stamp_ns)", out_path, pw.unmatched())
    shown = f"{pw.n_images - left_out} images" + (f", {left_out} unreadable frame(s) left out" if left_out else "")
    log.info("wrote %s (%s, %d pose records)", out_path, shown, len(rows))
    return out_path


def _copy_header(src: McapFrameSource, out: LogWriter) -> dict[int, int]:
    """Copy the input log's schemas, channels, metadata and attachments; input -> output channel ids."""
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
    return channel_ids


def _copy_with_poses(
    f: Any,
    input_mcap: Path,
    rows: list[dict],
    meshes: Mapping[str, Any],
    image_topic: str | None,
    calibration_topic: str | None,
    rectified: bool | None,
) -> _PoseWriter:
    """Write the input log's records unchanged into ``f``, and after each image its pose topics.

    Raises:
        DataError: the input already holds batchpose topics (``/batchpose/...``), or cannot be read.
    """
    src = McapFrameSource(input_mcap, image_topic=image_topic, calibration_topic=calibration_topic, rectified=rectified)
    clash = sorted(ch.topic for ch in src.channels.values() if ch.topic.startswith(OUTPUT_PREFIX))
    if clash:
        raise DataError(
            f"{input_mcap}: already holds batchpose output topics ({', '.join(clash[:3])}); "
            "write back into the original log instead"
        )
    # A ROS profile requires every channel in its encoding; the batchpose topics are protobuf and JSON.
    out = LogWriter(f, profile="" if src.profile in ("ros1", "ros2") else src.profile)
    channel_ids = _copy_header(src, out)
    pw = _PoseWriter(out, rows, meshes)
    cal: Calib | None = None
    first: Calib | None = None
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
                img: ImageMsg | None = src.image(schema, channel, message)
            except BadMessage:  # its frame is a bad_image row (reading warned); its status still goes in
                img = None
            cam = camera_of(c, img) if c is not None else None
            pw.image(
                message.log_time,
                img.stamp_ns if img is not None else message.log_time,
                (img.frame_id if img is not None else "") or CAMERA_FRAME_ID,
                cam,
                f"mcap:{message.log_time}",
            )
    out.finish()
    return pw
