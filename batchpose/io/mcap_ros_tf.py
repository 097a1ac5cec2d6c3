"""The estimates as ROS transforms: ``tf2_msgs/TFMessage`` on ``/tf`` in a ROS log's own encoding (ROS 2 CDR or
ROS 1), so ROS tools (rviz, tf2, rosbag readers) see the objects as frames ``batchpose/<name>`` under the camera
frame. Written into ``poses.mcap`` by :mod:`batchpose.io.mcap_poses`.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from mcap.records import Channel, Schema
from mcap_ros2._dynamic import serialize_dynamic
from scipy.spatial.transform import Rotation

from batchpose.io.mcap_topics import ROS_FRAME_PREFIX, ROS_TF_TOPIC

log = logging.getLogger("batchpose")

_SEP = "=" * 80 + "\n"
#: Concatenated message definitions (the form MCAP's ros2msg / ros1msg schemas hold).
ROS2_TF = (
    "geometry_msgs/TransformStamped[] transforms\n"
    f"{_SEP}MSG: geometry_msgs/TransformStamped\n"
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    f"{_SEP}MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    f"{_SEP}MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    f"{_SEP}MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
    f"{_SEP}MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    f"{_SEP}MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
)
ROS1_TF = (
    "geometry_msgs/TransformStamped[] transforms\n"
    f"{_SEP}MSG: geometry_msgs/TransformStamped\nHeader header\nstring child_frame_id\nTransform transform\n"
    f"{_SEP}MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n"
    f"{_SEP}MSG: geometry_msgs/Transform\nVector3 translation\nQuaternion rotation\n"
    f"{_SEP}MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    f"{_SEP}MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
)
#: message encoding -> (schema name, schema encoding, definition).
_SCHEMAS = {
    "cdr": ("tf2_msgs/msg/TFMessage", "ros2msg", ROS2_TF),
    "ros1": ("tf2_msgs/TFMessage", "ros1msg", ROS1_TF),
}


def _ros1_string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _ros1_tf(stamp_ns: int, parent: str, children: Sequence[tuple[str, np.ndarray]]) -> bytes:
    """A ROS 1 TFMessage: a uint32 count, then each TransformStamped (header seq, stamp, frame; child; t, q)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    parts = [struct.pack("<I", len(children))]
    for child, T in children:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        parts += [struct.pack("<III", 0, sec, nsec), _ros1_string(parent), _ros1_string(child)]
        parts.append(struct.pack("<7d", *np.asarray(T[:3, 3], float), *q))
    return b"".join(parts)


def _ros2_msg(stamp_ns: int, parent: str, children: Sequence[tuple[str, np.ndarray]]) -> dict:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    transforms = []
    for child, T in children:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        t = np.asarray(T[:3, 3], float)
        transforms.append(
            {
                "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": parent},
                "child_frame_id": child,
                "transform": {
                    "translation": {"x": t[0], "y": t[1], "z": t[2]},
                    "rotation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]},
                },
            }
        )
    return {"transforms": transforms}


class RosTf:
    """Writes the ok poses of each image as one ``tf2_msgs/TFMessage`` on ``/tf``.

    Args:
        writer: the ``mcap.writer.Writer`` of ``poses.mcap``.
        encoding: the log's message encoding: ``cdr`` (ROS 2) or ``ros1``.
        existing: the log's own channels by id, with their schemas: a ``/tf`` channel of the same type and
            encoding is written on (ROS tools read one ``/tf``); one of another type leaves ``/tf`` out.
        channel_ids: input -> output channel ids of the copied log.
    """

    def __init__(
        self,
        writer: Any,
        encoding: str,
        existing: Mapping[int, tuple[Channel, Schema | None]],
        channel_ids: Mapping[int, int],
    ) -> None:
        name, schema_encoding, definition = _SCHEMAS[encoding]
        self.w, self.encoding, self.n = writer, encoding, 0
        self.channel: int | None = None
        for cid, (ch, schema) in existing.items():
            if ch.topic != ROS_TF_TOPIC:
                continue
            if schema is not None and schema.name == name and ch.message_encoding == encoding:
                self.channel = channel_ids[cid]
            else:
                log.warning(
                    "%s is %s (%s) in the input log, not %s: the poses are not added to it",
                    ROS_TF_TOPIC,
                    schema.name if schema else "schemaless",
                    ch.message_encoding,
                    name,
                )
                self.w = None
            break
        if self.w is not None and self.channel is None:
            sid = writer.register_schema(name, schema_encoding, definition.encode())
            self.channel = writer.register_channel(ROS_TF_TOPIC, encoding, sid)
        self._encode = serialize_dynamic(name, definition)[name] if encoding == "cdr" else None

    def write(self, log_time: int, stamp_ns: int, parent: str, poses: Sequence[tuple[str, np.ndarray]]) -> None:
        """One TFMessage at ``log_time`` (ns): ``parent`` -> ``batchpose/<name>`` for each (name, (4, 4)
        cam_from_model in metres) of ``poses``, header stamp ``stamp_ns``; nothing when ``poses`` is empty."""
        if self.w is None or self.channel is None or not poses:
            return
        children = [(ROS_FRAME_PREFIX + name, T) for name, T in poses]
        if self._encode is not None:
            data = self._encode(_ros2_msg(stamp_ns, parent, children))
        else:
            data = _ros1_tf(stamp_ns, parent, children)
        self.w.add_message(self.channel, log_time=int(log_time), data=bytes(data), publish_time=int(log_time))
        self.n += 1
