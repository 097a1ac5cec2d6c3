"""Writing the estimates into an MCAP log for Foxglove (:func:`write_poses_mcap`): the input log copied byte
for byte, or the frames written as by :func:`batchpose.io.mcap_write.write_frames_mcap`, plus the batchpose
topics of :mod:`batchpose.io.mcap_topics` (scenes, tf, poses, annotations, status, ground truth) at each
image's log time.

What Foxglove draws at a time is what the log says of that image: an object's mesh is on its own scene topic
(``/batchpose/scene/<name>``), written when the object is found (``ok``) after an image where it was not, and
deleted at the first image where it is not found (lost, failed, hidden, not estimated). Every message on such a
topic holds the object's whole state, so the last one before a time, which is all Foxglove reads after a seek,
shows exactly the objects found then; and the mesh is embedded once per run of images that find the object,
not once per image. Ground truth is drawn the same way, on ``/batchpose/ground_truth/...``.
"""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
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
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from scipy.spatial.transform import Rotation

from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import row_cam_from_model
from batchpose.errors import BatchposeError, ConfigError, DataError
from batchpose.io.files import atomic_path
from batchpose.io.gltf import glb_bounds, mesh_to_glb
from batchpose.io.mcap_decode import BadMessage, Calib, ImageMsg, camera_of
from batchpose.io.mcap_log import McapLog
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_ros_tf import RosTf
from batchpose.io.mcap_topics import (
    ANNOTATIONS_TOPIC,
    CALIBRATION_TOPIC,
    CAMERA_FRAME_ID,
    GT_FRAME_PREFIX,
    GT_SCENE_TOPIC_PREFIX,
    GT_TF_TOPIC,
    IMAGE_TOPIC,
    METADATA_NAME,
    OBJECT_FRAME_PREFIX,
    OUTPUT_PREFIX,
    POSES_TOPIC_PREFIX,
    SCENE_TOPIC_PREFIX,
    STATUS_JSON_SCHEMA,
    STATUS_TOPIC,
    TF_TOPIC,
)
from batchpose.io.mcap_write import VERSION, LogWriter, set_timestamp, write_frame

log = logging.getLogger("batchpose")

#: Metadata record of ``poses.mcap`` with the export's own options (``ros_tf``: "true" / "false").
EXPORT_METADATA = "batchpose.export"
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
#: Ground-truth meshes: one translucent green, whatever the object, so they never pass for an estimate.
_GT_COLOR = Color(r=0.1, g=0.9, b=0.2, a=0.4)


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


def _by_stamp(rows: Iterable[Mapping[str, Any]]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        out[int(r["stamp_ns"])].append(dict(r))
    return out


def _status_entry(r: Mapping[str, Any]) -> dict:
    """One object's entry of a ``/batchpose/status`` message (:data:`STATUS_JSON_SCHEMA`)."""
    conf = float(r.get("confidence", 0.0) or 0.0)
    conf = conf if np.isfinite(conf) else 0.0  # JSON has no NaN
    score = r.get("verification")
    return {
        "obj_name": str(r["obj_name"]),
        "status": str(r["status"]),
        "reason": str(r.get("reason", "") or ""),
        "confidence": conf,
        "verification": float(score) if score is not None and np.isfinite(score) else None,
        "n_inliers": int(r.get("n_inliers", 0) or 0),
        "tracked": bool(r.get("tracked", False)),
    }


def status_label(entry: Mapping[str, Any]) -> str:
    """The image label of one object's status entry: ``name ok 0.82`` (`` tracked`` when followed from the
    previous frame), or ``name status`` with the reason in brackets."""
    name, status = entry["obj_name"], entry["status"]
    if status == "ok":
        return f"{name} ok {entry['confidence']:.2f}" + (" tracked" if entry["tracked"] else "")
    return f"{name} {status}" + (f" ({entry['reason']})" if entry["reason"] else "")


def _add_label(ann: ImageAnnotations, x: float, y: float, text: str, i: int, stamp_ns: int) -> None:
    """A 14 px label at pixel (x, y) in object ``i``'s colour on a dark background."""
    ta = ann.texts.add()
    set_timestamp(ta.timestamp, stamp_ns)
    ta.position.CopyFrom(Point2(x=x, y=y))
    ta.text, ta.font_size = text, 14.0
    ta.text_color.CopyFrom(_color(i))
    ta.background_color.CopyFrom(Color(r=0, g=0, b=0, a=0.6))


class _Scene:
    """One object's scene topic: its mesh entity from the image it is shown at, a deletion at the first image
    it is not; nothing while it stays as it was.

    Args:
        topic: the SceneUpdate topic (one an object).
        name: the entity id.
        frame_id: the frame the mesh is locked to (``object/<name>``, ``gt/<name>``).
        glb: the mesh, binary glTF.
        color: its colour (used only with ``override``).
        override: draw the mesh in ``color`` instead of its texture.
    """

    def __init__(
        self, topic: str, name: str, frame_id: str, glb: bytes | bytearray, color: Color, override: bool
    ) -> None:
        self.topic, self.name, self.frame_id = topic, name, frame_id
        self.model = ModelPrimitive(
            pose=Pose(position=Vector3(x=0, y=0, z=0), orientation=_GLTF_UNDO_Y_UP),
            scale=Vector3(x=1, y=1, z=1),
            color=color,
            override_color=override,
            media_type="model/gltf-binary",
            data=bytes(glb),
        )
        self.shown_at: int | None = None  # in-message stamp of the entity on screen, ns

    def show(self, out: LogWriter, log_time: int, stamp_ns: int, visible: bool) -> None:
        """Write the entity (``visible`` after not) or its deletion (not ``visible`` after visible)."""
        if visible == (self.shown_at is not None):
            return
        upd = SceneUpdate()
        if visible:
            e = upd.entities.add()
            set_timestamp(e.timestamp, stamp_ns)
            e.frame_id, e.id = self.frame_id, self.name
            e.frame_locked = True  # lifetime 0: until this topic's next message deletes it
            e.models.append(self.model)
            self.shown_at = int(stamp_ns)
        else:
            d = upd.deletions.add()
            # Foxglove deletes the entities stamped earlier than the deletion: later than the entity, always.
            set_timestamp(d.timestamp, max(int(stamp_ns), int(self.shown_at or 0) + 1))
            d.type, d.id = SceneEntityDeletion.MATCHING_ID, self.name
            self.shown_at = None
        out.proto(self.topic, upd, log_time)


class _PoseWriter:
    """Writes the per-image batchpose topics.

    Args:
        out: the log being written.
        rows: pose records (see :func:`write_poses_mcap`).
        meshes: object name -> GLB bytes or a trimesh.
        gt_rows: ground-truth poses (see :func:`write_poses_mcap`).
        ros_tf: the ``/tf`` writer of a ROS log, or None.
    """

    def __init__(
        self,
        out: LogWriter,
        rows: list[dict],
        meshes: Mapping[str, Any],
        gt_rows: list[dict] | None = None,
        ros_tf: RosTf | None = None,
    ) -> None:
        self.out, self.ros_tf = out, ros_tf
        self.by_stamp = _by_stamp(rows)
        self.gt_by_stamp = _by_stamp(gt_rows or [])
        names = sorted({str(r["obj_name"]) for r in rows} | set(meshes))
        self.index = {n: i for i, n in enumerate(names)}
        glb = {name: m if isinstance(m, (bytes, bytearray)) else mesh_to_glb(m) for name, m in meshes.items()}
        self.bounds = {name: glb_bounds(name, g) for name, g in glb.items()}
        missing = sorted({str(r["obj_name"]) for r in rows} - set(glb))
        if missing:
            log.warning("no mesh for %s: no 3D model or box in the MCAP for them", ", ".join(missing))
        self.scenes = {
            n: _Scene(SCENE_TOPIC_PREFIX + n, n, OBJECT_FRAME_PREFIX + n, g, _color(self.index[n]), False)
            for n, g in sorted(glb.items())
        }
        gt_names = {str(r["obj_name"]) for r in gt_rows or []}
        self.gt_scenes = {
            n: _Scene(GT_SCENE_TOPIC_PREFIX + n, n, GT_FRAME_PREFIX + n, g, _GT_COLOR, True)
            for n, g in sorted(glb.items())
            if n in gt_names
        }
        self.camera_frame = ""  # the first image's frame id
        self.n_images = 0

    @property
    def scene_topics(self) -> list[str]:
        """The SceneUpdate topics this log may hold: each object's, then its ground truth's."""
        return [s.topic for s in self.scenes.values()] + [s.topic for s in self.gt_scenes.values()]

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
        self.camera_frame = self.camera_frame or frame_id
        ann = ImageAnnotations()
        status, found, listed = [], [], 0
        for r in sorted(rows, key=lambda r: str(r["obj_name"])):
            name = str(r["obj_name"])
            i = self.index.get(name, 0)
            T = row_cam_from_model(r)
            entry = _status_entry(r)
            status.append(entry)
            drawn = False
            if str(r["status"]) == "ok" and T is not None:
                found.append((name, T))
                self._pose(log_time, stamp_ns, frame_id, name, T)
                drawn = self._annotate(ann, name, i, T, camera, r, status_label(entry), stamp_ns)
            if not drawn:
                _add_label(ann, 8.0, 20.0 + 18.0 * listed, status_label(entry), i, stamp_ns)
                listed += 1
        shown = {name for name, _ in found}
        for name, scene in self.scenes.items():
            scene.show(self.out, log_time, stamp_ns, name in shown)
        self._ground_truth(log_time, stamp_ns, frame_id)
        if self.ros_tf is not None:
            self.ros_tf.write(log_time, stamp_ns, frame_id, found)
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

    def _transform(self, topic: str, log_time: int, stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Pose:
        tf = FrameTransform(parent_frame_id=parent, child_frame_id=child)
        set_timestamp(tf.timestamp, stamp_ns)
        pose = _pose_msg(T)
        tf.translation.CopyFrom(pose.position)
        tf.rotation.CopyFrom(pose.orientation)
        self.out.proto(topic, tf, log_time)
        return pose

    def _pose(self, log_time: int, stamp_ns: int, frame_id: str, name: str, T: np.ndarray) -> None:
        """The object's transform (``/batchpose/tf``) and pose (``/batchpose/poses/<name>``) in the camera frame."""
        pose = self._transform(TF_TOPIC, log_time, stamp_ns, frame_id, OBJECT_FRAME_PREFIX + name, T)
        pif = PosesInFrame(frame_id=frame_id, poses=[pose])
        set_timestamp(pif.timestamp, stamp_ns)
        self.out.proto(POSES_TOPIC_PREFIX + name, pif, log_time)

    def _ground_truth(self, log_time: int, stamp_ns: int, frame_id: str) -> None:
        """The image's ground truth: ``gt/<name>`` transforms and the ground-truth meshes of the objects it lists."""
        listed = set()
        for g in sorted(self.gt_by_stamp.pop(int(log_time), []), key=lambda g: str(g["obj_name"])):
            T = row_cam_from_model(g)
            if T is None:
                continue
            name = str(g["obj_name"])
            self._transform(GT_TF_TOPIC, log_time, stamp_ns, frame_id, GT_FRAME_PREFIX + name, T)
            listed.add(name)
        for name, scene in self.gt_scenes.items():
            scene.show(self.out, log_time, stamp_ns, name in listed)

    def _annotate(
        self,
        ann: ImageAnnotations,
        name: str,
        i: int,
        T: np.ndarray,
        camera: Camera | None,
        r: Mapping[str, Any],
        label: str,
        stamp_ns: int,
    ) -> bool:
        """The object's inlier points, and its mesh's bounding box projected with its ``label`` (when the box
        is in front of the camera). Returns whether the box and label were drawn."""
        inl = np.asarray(r.get("inliers_px", []) if r.get("inliers_px") is not None else [], dtype=float)
        if inl.size >= 2:
            pa = ann.points.add()
            set_timestamp(pa.timestamp, stamp_ns)
            pa.type = PointsAnnotation.POINTS
            pa.points.extend(Point2(x=float(x), y=float(y)) for x, y in inl.reshape(-1, 2))
            pa.outline_color.CopyFrom(_color(i))
            pa.thickness = 3.0
        if camera is None or name not in self.bounds:
            return False
        K = np.asarray(camera.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            return False
        lo, hi = self.bounds[name]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        cam_pts = corners @ T[:3, :3].T + T[:3, 3]
        if np.any(cam_pts[:, 2] <= 1e-6):  # box reaches behind the camera: a projection would wrap around
            return False
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
        x, y = float(uv[:, 0].min()), float(max(uv[:, 1].min() - 4.0, 12.0))
        _add_label(ann, x, y, label, i, stamp_ns)
        return True

    def unmatched(self) -> int:
        """Number of records whose ``stamp_ns`` matched no image written so far."""
        return sum(len(v) for v in self.by_stamp.values())


@dataclass(frozen=True)
class PosesLog:
    """What :func:`write_poses_mcap` wrote, for the Foxglove layout of the run.

    Attributes:
        path: the ``poses.mcap`` written.
        image_topic: the image topic the poses refer to (the input log's own, or ``/camera/image``).
        calibration_topic: its calibration topic.
        camera_frame: the images' ``frame_id`` (the parent of the objects' transforms).
        scene_topics: the SceneUpdate topics (each object's mesh, then each ground-truth mesh).
        n_ros_tf: ``/tf`` messages written (ROS logs).
    """

    path: Path
    image_topic: str
    calibration_topic: str
    camera_frame: str
    scene_topics: tuple[str, ...]
    n_ros_tf: int = 0


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
    ground_truth: Iterable[Mapping[str, Any]] = (),
    obj_ids: Mapping[str, int] | None = None,
    ros_tf: bool = True,
) -> PosesLog:
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
        ground_truth: ground-truth poses (``gt.parquet`` rows with their image's ``stamp_ns``): ``stamp_ns``,
            ``obj_name``, ``R`` (9, row-major), ``t_m`` (3, metres); drawn as ``gt/<name>`` transforms and
            translucent green meshes.
        obj_ids: object name -> data set id, for the ``/ground_truth/poses`` messages of folder frames (0 for
            an object not in it); an input log's own messages are copied as they are.
        ros_tf: for a ROS log (ROS 2 cdr or ROS 1 image messages), also write the ok poses on ``/tf``
            (:class:`batchpose.io.mcap_ros_tf.RosTf`).

    Returns:
        What was written (:class:`PosesLog`).

    Raises:
        ConfigError: not exactly one of ``input_mcap`` and ``frames``, or the output is the input.
        DataError: the input log already holds batchpose topics, or cannot be read.
    """
    out_path = Path(out_path)
    if (input_mcap is None) == (frames is None):
        raise ConfigError("write_poses_mcap: pass exactly one of input_mcap and frames")
    if input_mcap is not None and out_path.resolve() == Path(input_mcap).resolve():
        raise ConfigError(f"{out_path}: the output would overwrite the input log")
    rows, gt = _rows(records), _rows(ground_truth)
    export = {"version": VERSION, "ros_tf": json.dumps(bool(ros_tf))}
    with atomic_path(out_path) as tmp, open(tmp, "wb") as f:
        if input_mcap is not None:
            src = McapFrameSource(
                Path(input_mcap), image_topic=image_topic, calibration_topic=calibration_topic, rectified=rectified
            )
            pw = _copy_with_poses(f, src, rows, meshes, gt, ros_tf, export)
            left_out, topics = 0, (src.image_topic, src.calibration_topic)
        else:
            pw, left_out = _frames_with_poses(f, frames or (), rows, meshes, gt, obj_ids or {}, export)
            topics = (IMAGE_TOPIC, CALIBRATION_TOPIC)
    if pw.unmatched():
        log.warning("%s: %d pose records match no image log time (stamp_ns)", out_path, pw.unmatched())
    shown = f"{pw.n_images - left_out} images" + (f", {left_out} unreadable frame(s) left out" if left_out else "")
    n_tf = pw.ros_tf.n if pw.ros_tf is not None else 0
    log.info("wrote %s (%s, %d pose records)", out_path, shown, len(rows))
    return PosesLog(out_path, *topics, pw.camera_frame or CAMERA_FRAME_ID, tuple(pw.scene_topics), n_tf)


def export_options(path: Path) -> dict[str, str]:
    """The options a ``poses.mcap`` was written with (its :data:`EXPORT_METADATA` record); empty when the
    file cannot be read or has none (written by an earlier version)."""
    try:
        return dict(McapLog(Path(path)).metadata.get(EXPORT_METADATA, {}))
    except BatchposeError:
        return {}


def _frames_with_poses(
    f: Any,
    frames: Iterable[Frame],
    rows: list[dict],
    meshes: Mapping[str, Any],
    gt: list[dict],
    obj_ids: Mapping[str, int],
    export: dict[str, str],
) -> tuple[_PoseWriter, int]:
    """Write the frames as a log into ``f``, each followed by its pose topics; returns the pose writer and
    the number of frames left out (unreadable)."""
    out = LogWriter(f)
    meta = {"version": VERSION}
    if any(obj_ids.values()):
        meta["obj_ids"] = json.dumps({k: int(v) for k, v in obj_ids.items()}, sort_keys=True)
    out.w.add_metadata(METADATA_NAME, meta)
    out.w.add_metadata(EXPORT_METADATA, export)
    pw = _PoseWriter(out, rows, meshes, gt)
    kind: list[str] = []
    left_out = 0
    for frame in frames:
        left_out += not write_frame(out, frame, lambda name: int(obj_ids.get(name, 0)), kind, strict=False)
        pw.image(frame.stamp_ns, frame.stamp_ns, CAMERA_FRAME_ID, frame.camera, frame.frame_id)
    out.finish()
    return pw, left_out


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


def _ros_tf(src: McapFrameSource, out: LogWriter, channel_ids: Mapping[int, int]) -> RosTf | None:
    """The ``/tf`` writer for a ROS log (its image topic in ROS 2 cdr or ROS 1 encoding), else None."""
    encoding = next((ch.message_encoding for ch in src.channels.values() if ch.topic == src.image_topic), "")
    if encoding not in ("cdr", "ros1"):
        return None
    schemas = src.schemas
    existing = {cid: (ch, schemas.get(ch.schema_id)) for cid, ch in src.channels.items()}
    return RosTf(out.w, encoding, existing, channel_ids)


def _copy_with_poses(
    f: Any,
    src: McapFrameSource,
    rows: list[dict],
    meshes: Mapping[str, Any],
    gt: list[dict],
    ros_tf: bool,
    export: dict[str, str],
) -> _PoseWriter:
    """Write the input log's records unchanged into ``f``, and after each image its pose topics.

    Raises:
        DataError: the input already holds batchpose topics (``/batchpose/...``), or cannot be read.
    """
    clash = sorted(ch.topic for ch in src.channels.values() if ch.topic.startswith(OUTPUT_PREFIX))
    if clash:
        raise DataError(
            f"{src.path}: already holds batchpose output topics ({', '.join(clash[:3])}); "
            "write back into the original log instead"
        )
    # A ROS profile requires every channel in its encoding; the batchpose topics are protobuf and JSON.
    out = LogWriter(f, profile="" if src.profile in ("ros1", "ros2") else src.profile)
    channel_ids = _copy_header(src, out)
    out.w.add_metadata(EXPORT_METADATA, export)
    pw = _PoseWriter(out, rows, meshes, gt, _ros_tf(src, out, channel_ids) if ros_tf else None)
    cal: Calib | None = None
    first: Calib | None = None
    for schema, channel, message in src.iter_raw():
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
