"""Which topic is which: the topics and schemas batchpose reads and writes, and choosing a log's image,
calibration and depth topics.

Topics written by batchpose (:mod:`batchpose.io.mcap_write`, :mod:`batchpose.io.mcap_poses`):

=====================================  ==========================  ==========================================
topic                                  schema                      content
=====================================  ==========================  ==========================================
``/camera/image``                      foxglove.CompressedImage    PNG/JPEG bytes as stored (RawImage for raw)
``/camera/calibration``                foxglove.CameraCalibration  K, R = I, P = [K | 0], D, model, size
``/camera/depth``                      foxglove.RawImage           16UC1 depth in mm registered to the image
                                                                   (``batchpose convert`` of data with depth)
``/ground_truth/poses``                batchpose.GroundTruthPoses  JSON, see :data:`GT_JSON_SCHEMA`
``/batchpose/scene/<name>``            foxglove.SceneUpdate        the object's mesh (binary glTF) locked to
                                                                   ``object/<name>`` from the image it is
                                                                   found in; a deletion at the first image it
                                                                   is not (see :mod:`batchpose.io.mcap_poses`)
``/batchpose/tf``                      foxglove.FrameTransform     camera frame -> ``object/<name>``, metres
``/batchpose/poses/<name>``            foxglove.PosesInFrame       the object's pose in the camera frame
``/batchpose/annotations``             foxglove.ImageAnnotations   projected 3D box, inlier points, one
                                                                   status label per object
``/batchpose/status``                  batchpose.FrameStatus       JSON, see :data:`STATUS_JSON_SCHEMA`
``/batchpose/ground_truth/tf``         foxglove.FrameTransform     camera frame -> ``gt/<name>`` (runs with
                                                                   ground truth)
``/batchpose/ground_truth/scene/<n>``  foxglove.SceneUpdate        the mesh, translucent green, at ``gt/<n>``
``/tf``                                tf2_msgs/TFMessage          ROS logs: camera frame ->
                                                                   ``batchpose/<name>``, the log's encoding
=====================================  ==========================  ==========================================

All batchpose messages of one image are logged at the image's log time; in-message timestamps equal the
image's own header stamp, so Foxglove's Image panel can match annotations to the image. Within one log
time the calibration and ground truth are written before the image.

The topic choice here works on a log's topic listing (topic -> schema name, and a message count per
topic), and :func:`foxglove_layout` fills a Foxglove layout with the topics a run used; neither imports an MCAP
library.
"""

from __future__ import annotations

import copy
import logging
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from batchpose.errors import CameraError, DataError

log = logging.getLogger("batchpose")

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
#: One topic per object (its mesh entity or its deletion): each message holds the object's whole state, so the
#: last message before any time (what Foxglove reads after a seek) shows exactly what is found then.
SCENE_TOPIC_PREFIX = "/batchpose/scene/"
TF_TOPIC = "/batchpose/tf"
GT_TF_TOPIC = "/batchpose/ground_truth/tf"
GT_SCENE_TOPIC_PREFIX = "/batchpose/ground_truth/scene/"
#: ROS logs: the estimates as tf2_msgs/TFMessage, where ROS tools read transforms.
ROS_TF_TOPIC = "/tf"
OBJECT_FRAME_PREFIX = "object/"
GT_FRAME_PREFIX = "gt/"
ROS_FRAME_PREFIX = "batchpose/"
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
                    "verification": {
                        "type": ["number", "null"],
                        "description": "the verification score (null: not scored, e.g. a tracked pose)",
                    },
                    "n_inliers": {"type": "integer"},
                    "tracked": {"type": "boolean", "description": "followed from the previous frame"},
                },
            },
        },
    },
}

#: What was said of a log once a process: (log, image topic) taken as rectified by its name, (log, "") the
#: image topic chosen among several.
_ANNOUNCED: set[tuple[str, str]] = set()


def first_time(path: Path, topic: str) -> bool:
    """True the first time this process asks about (``path``, ``topic``): what is said of a log once."""
    key = (str(path), topic)
    if key in _ANNOUNCED:
        return False
    _ANNOUNCED.add(key)
    return True


def looks_rectified(topic: str) -> bool:
    """True for an image topic ROS's image_proc names rectified: ``.../image_rect``, ``image_rect_color``
    (also under an image_transport subtopic: ``.../image_rect_color/compressed``)."""
    return any(part.startswith("image_rect") for part in topic.split("/"))


def colour_rank(topic: str) -> int:
    """0 for a topic named as colour (``color``, ``rgb``), 2 for one named as infrared or mono (``infra1``,
    ``ir``, ``mono``, ``thermal``), else 1: SIFT matches a textured mesh in the colour image."""
    words = re.split(r"[/_\-.]+", topic.lower())
    if any(w in ("color", "colour", "rgb", "rgb8") for w in words):
        return 0
    if any(re.fullmatch(r"infra\d*|ir\d*|mono|thermal|nir", w) for w in words):
        return 2
    return 1


def calibration_beside(topics: Mapping[str, str], image_topic: str) -> str | None:
    """The calibration topic in the deepest namespace that contains ``image_topic``.

    Args:
        topics: topic -> schema name, in channel id order.
        image_topic: the image topic.
    """
    best, best_len = None, -1
    for topic, schema in topics.items():
        if schema not in CALIBRATION_SCHEMAS:
            continue
        ns = topic.rsplit("/", 1)[0]
        if image_topic.startswith(ns + "/") and len(ns) > best_len:
            best, best_len = topic, len(ns)
    return best


def image_type_topic(path: Path, topics: Mapping[str, str], wanted: str, what: str) -> str:
    """``wanted`` when it is a topic of an image type.

    Raises:
        DataError: it is not a topic of the log, or not of an image type (naming ``what`` it was meant as).
    """
    if wanted not in topics:
        images = [t for t, s in topics.items() if s in IMAGE_SCHEMAS]
        raise DataError(
            f"{path}: {what} topic {wanted!r} not found "
            f"(image topics: {', '.join(images) or 'none'}; all topics: {', '.join(topics) or 'none'})"
        )
    if topics[wanted] not in IMAGE_SCHEMAS:
        raise DataError(
            f"{path}:{wanted}: schema {topics[wanted]!r} is not an image type "
            f"(expected one of {', '.join(IMAGE_SCHEMAS)})"
        )
    return wanted


def choose_image_topic(
    path: Path,
    topics: Mapping[str, str],
    count: Callable[[str], int | None],
    wanted: str | None,
    depth_topic: str | None,
) -> str:
    """The image topic to read: ``wanted``, or the first image topic with messages whose name does not say
    depth, preferring one with a calibration topic beside it, then one named as colour (:func:`colour_rank`).

    Args:
        path: the log (for messages).
        topics: topic -> schema name, in channel id order.
        count: topic -> its number of messages (None: unknown).
        wanted: the topic asked for, or None to choose.
        depth_topic: the depth topic, never chosen.

    Raises:
        DataError: ``wanted`` is not an image topic, or the log has none.
    """
    if wanted is not None:
        return image_type_topic(path, topics, wanted, "image")
    images = [
        t
        for t, s in topics.items()
        if s in IMAGE_SCHEMAS and count(t) != 0 and t != depth_topic and "depth" not in t.lower()
    ]
    if not images:
        listing = ", ".join(f"{t} ({s or 'no schema'})" for t, s in topics.items())
        raise DataError(
            f"{path}: no image topic (expected messages with schema foxglove.CompressedImage, "
            "foxglove.RawImage, foxglove.CompressedVideo, sensor_msgs/msg/Image or "
            "sensor_msgs/msg/CompressedImage (ROS 1: sensor_msgs/Image, sensor_msgs/CompressedImage); "
            f"topics: {listing or 'none'})"
        )
    # With a calibration beside it first, then colour before infrared (a RealSense log has both).
    chosen = min(images, key=lambda t: (calibration_beside(topics, t) is None, colour_rank(t)))
    if len(images) > 1 and first_time(path, ""):
        log.info(
            "%s: %d image topics (%s); using %s (set image_topic to choose another)",
            path,
            len(images),
            ", ".join(images),
            chosen,
        )
    return chosen


def choose_calibration_topic(
    path: Path,
    topics: Mapping[str, str],
    count: Callable[[str], int | None],
    wanted: str | None,
    image_topic: str,
) -> str:
    """The calibration topic of ``image_topic``: ``wanted``, or the one beside it (:func:`calibration_beside`).

    Args:
        path: the log (for messages).
        topics: topic -> schema name, in channel id order.
        count: topic -> its number of messages (None: unknown).
        wanted: the topic asked for, or None to choose.
        image_topic: the image topic it calibrates.

    Raises:
        CameraError: ``wanted`` is not a calibration topic, the image topic has none beside it, or it has
            no messages.
    """
    if wanted is not None:
        if wanted not in topics:
            raise CameraError(f"{path}: calibration topic {wanted!r} not found")
        if topics[wanted] not in CALIBRATION_SCHEMAS:
            raise CameraError(
                f"{path}:{wanted}: schema {topics[wanted]!r} is not a calibration type "
                f"(expected one of {', '.join(CALIBRATION_SCHEMAS)})"
            )
        topic = wanted
    else:
        beside = calibration_beside(topics, image_topic)
        if beside is None:
            others = [t for t, s in topics.items() if s in CALIBRATION_SCHEMAS]
            ns = image_topic.rsplit("/", 1)[0] or "/"
            raise CameraError(
                f"{path}:{image_topic}: image topic has no calibration (expected a "
                f"foxglove.CameraCalibration or sensor_msgs/(msg/)CameraInfo topic under {ns}; "
                f"calibration topics elsewhere: {', '.join(others) or 'none'}; set calibration_topic)"
            )
        topic = beside
    if count(topic) == 0:
        raise CameraError(f"{path}:{topic}: calibration topic has no messages")
    return topic


def _panel_topics(
    topics: Mapping[str, dict], template: Mapping[str, str], run: Mapping[str, str], scene_topics: Sequence[str]
) -> dict[str, dict]:
    """A panel's ``topics`` settings for the run: the template's image and calibration entries moved to the
    run's topics (``cameraInfoTopic`` too), its scene entries replaced by ``scene_topics`` (all visible),
    the other entries kept."""
    out: dict[str, dict] = {}
    for topic, settings in topics.items():
        if topic.startswith(OUTPUT_PREFIX + "scene") or topic.startswith(OUTPUT_PREFIX + "ground_truth/scene"):
            continue
        settings = dict(settings)
        if settings.get("cameraInfoTopic") == template["calibration"]:
            settings["cameraInfoTopic"] = run["calibration"]
        if topic == template["image"]:
            topic = run["image"]
        elif topic == template["calibration"]:
            topic = run["calibration"]
        out[topic] = settings
    for topic in scene_topics:
        out[topic] = {"visible": True}
    return out


def foxglove_layout(
    template: Mapping, image_topic: str, calibration_topic: str, camera_frame: str, scene_topics: Sequence[str]
) -> dict:
    """A Foxglove layout for one run, from the template ``foxglove/layout.json``.

    The template is written for ``/camera/image``, ``/camera/calibration`` and frame ``camera``; each panel
    that shows an image (``imageMode.imageTopic``) is pointed at the run's image and calibration topics, each
    panel that follows a frame (``followTf``) at the run's camera frame, and each panel's topic settings list
    the run's image, calibration and scene topics (Foxglove draws a scene topic only when its panel says so).

    Args:
        template: the template layout (parsed JSON).
        image_topic: the image topic the run read (its own, for an input log).
        calibration_topic: that image's calibration topic.
        camera_frame: the images' ``frame_id``.
        scene_topics: the ``foxglove.SceneUpdate`` topics of ``poses.mcap`` (one an object, and its ground
            truth's).

    Returns:
        The layout (JSON-ready); ``template`` is not modified.

    Raises:
        DataError: the template has no panel configurations (``configById``).
    """
    layout = copy.deepcopy(dict(template))
    panels = layout.get("configById")
    if not isinstance(panels, dict) or not panels:
        raise DataError("Foxglove layout template: no panels (expected a configById mapping)")
    modes = [p["imageMode"] for p in panels.values() if isinstance(p.get("imageMode"), dict)]
    named = [m for m in modes if "imageTopic" in m]
    was = {
        "image": named[0]["imageTopic"] if named else IMAGE_TOPIC,
        "calibration": named[0].get("calibrationTopic", CALIBRATION_TOPIC) if named else CALIBRATION_TOPIC,
    }
    run = {"image": image_topic, "calibration": calibration_topic}
    for panel in panels.values():
        if isinstance(panel.get("imageMode"), dict) and "imageTopic" in panel["imageMode"]:
            panel["imageMode"]["imageTopic"] = image_topic
            panel["imageMode"]["calibrationTopic"] = calibration_topic
        if "followTf" in panel:
            panel["followTf"] = camera_frame
        if isinstance(panel.get("topics"), dict):
            panel["topics"] = _panel_topics(panel["topics"], was, run, scene_topics)
    return layout
