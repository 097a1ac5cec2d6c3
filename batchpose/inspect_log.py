"""``batchpose inspect``: what a log or an image folder holds, before a run.

For an MCAP log: its topics (schema, encoding, message count, the size of the first image of each image
topic), the time span, the image topic a run reads and why, its calibration (or why there is none), the
frame count, depth topics and ground truth. For a folder: its layout, frame count, image size and
calibration file. The log is read through its summary (index) where it has one, and at most one message per
image topic and one calibration message are decoded, so a log of many gigabytes is described in a second.
The topic choice is the reader's own (:class:`batchpose.io.mcap_read.McapFrameSource`).
"""

from __future__ import annotations

import contextlib
import datetime
from pathlib import Path

import numpy as np

from batchpose.core.frames import Camera, image_size
from batchpose.errors import BatchposeError, CameraError, DataError
from batchpose.io.files import one_line
from batchpose.io.folders import (
    INTRINSICS_NAMES,
    BopFrameSource,
    YcbvFrameSource,
    find_intrinsics,
    folder_format,
    list_images,
    load_intrinsics,
)
from batchpose.io.mcap_decode import Calib, ImageMsg, MessageDecoder
from batchpose.io.mcap_log import McapLog
from batchpose.io.mcap_read import McapFrameSource
from batchpose.io.mcap_topics import (
    CALIBRATION_SCHEMAS,
    DEPTH_UNITS_M,
    GT_TOPIC,
    IMAGE_SCHEMAS,
    calibration_beside,
    choose_image_topic,
    colour_rank,
)
from batchpose.io.video import VideoDecoder


def describe(path: Path) -> str:
    """What the log or folder at ``path`` holds, as text for a person (several lines).

    Args:
        path: an MCAP file or a data set folder (images with a calibration YAML, YCB-Video or BOP).

    Raises:
        DataError: the path does not exist, is not an MCAP file, is a corrupt or truncated log with no image,
            or is a folder with no image and no known data set layout.
    """
    path = Path(path)
    if path.is_dir():
        return _describe_folder(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder (expected an MCAP log or a folder of images)")
    return _describe_log(path)


# ----------------------------------------------------------------------------------------------- logs


def _describe_log(path: Path) -> str:
    mlog = McapLog(path)
    topics = mlog.topics()
    firsts = {t: _first_image(mlog, t) for t, s in topics.items() if s in IMAGE_SCHEMAS}
    kind = (
        "indexed" if mlog.indexed else ("truncated, read to its last complete chunk" if mlog.truncated else "no index")
    )
    lines = [
        f"{path}: MCAP log, {mlog.size / 1e6:.1f} MB, {kind}" + (f", profile {mlog.profile}" if mlog.profile else "")
    ]
    lines.append(_time_span(mlog))
    lines.append(f"topics ({len(topics)}):")
    lines += _topic_rows(mlog, firsts)
    lines.append("")
    lines += _choice(mlog, firsts)
    depth = [t for t, first in firsts.items() if _is_depth(t, first)]
    lines.append(f"depth topics: {', '.join(depth)}" if depth else "depth topics: none")
    n_gt = mlog.topic_count(GT_TOPIC) if GT_TOPIC in topics else 0
    lines.append(
        f"ground truth: {GT_TOPIC} ({n_gt} messages): runs are scored against it"
        if GT_TOPIC in topics
        else "ground truth: none (every object of the manifest is looked for in every frame)"
    )
    return "\n".join(lines)


def _time_span(mlog: McapLog) -> str:
    if mlog.start_ns is None or mlog.end_ns is None:
        return "time span: unknown (no statistics record)"
    start = datetime.datetime.fromtimestamp(mlog.start_ns * 1e-9, tz=datetime.UTC)
    return (
        f"time span: {(mlog.end_ns - mlog.start_ns) * 1e-9:.2f} s from {start:%Y-%m-%d %H:%M:%S} UTC "
        f"(log time {mlog.start_ns} ns), {mlog.n_messages} messages"
    )


def _topic_rows(mlog: McapLog, firsts: dict[str, ImageMsg | str]) -> list[str]:
    """One line per topic, in columns: name, schema (message encoding), message count, its first image."""
    rows = []
    for cid in sorted(mlog.channels):
        ch = mlog.channels[cid]
        n = mlog.topic_count(ch.topic)
        what = ""
        if ch.topic in firsts:
            first = firsts[ch.topic]
            what = _image_text(first) if isinstance(first, ImageMsg) else f"({first})"
        elif mlog.schema_name(ch) in CALIBRATION_SCHEMAS:
            what = "calibration"
        count = "? messages" if n is None else f"{n} message{'s' if n != 1 else ''}"
        rows.append((ch.topic, f"{mlog.schema_name(ch) or 'no schema'} ({ch.message_encoding})", count, what))
    widths = [max((len(r[i]) for r in rows), default=0) for i in range(3)]
    return [f"  {t:<{widths[0]}}  {s:<{widths[1]}}  {c:>{widths[2]}}  {w}".rstrip() for t, s, c, w in rows]


def _first_image(mlog: McapLog, topic: str) -> ImageMsg | str:
    """The first message of an image topic, decoded (a video frame decoded to pixels); else why not."""
    decoder = MessageDecoder(mlog.path)
    with contextlib.closing(mlog.iter_raw([topic])) as records:
        for schema, channel, message in records:
            try:
                img = decoder.image(schema, channel, message)
                if img.fmt.startswith("video/"):
                    img = VideoDecoder(f"{mlog.path}:{topic}").decode(img, message.log_time)
            except BatchposeError as e:
                return f"first message does not decode: {one_line(e)}"
            return img
    return "no messages"


def _image_text(img: ImageMsg) -> str:
    size = (img.width, img.height) if img.raw else image_size(img.data)
    dims = f"{size[0]}x{size[1]}" if size else "size unknown"
    frame = f", frame {img.frame_id}" if img.frame_id else ""
    return f"{img.fmt} {dims}{frame}"


def _is_depth(topic: str, first: ImageMsg | str) -> bool:
    """A depth topic by its name or its first image's encoding (16UC1, 32FC1, compressedDepth)."""
    fmt = first.fmt if isinstance(first, ImageMsg) else ""
    return "depth" in topic.lower() or (fmt in DEPTH_UNITS_M and fmt not in ("mono16", "png"))


def _choice(mlog: McapLog, firsts: dict[str, ImageMsg | str]) -> list[str]:
    """The image and calibration topics a run reads (the reader's choice) and why; the frame count."""
    try:
        src = McapFrameSource(mlog.path)
    except CameraError as e:  # an image topic without calibration: say which, and why
        image_topic = choose_image_topic(mlog.path, mlog.topics(), mlog.topic_count, None, None)
        return [
            f"image topic: {image_topic} ({_why(mlog, image_topic)})",
            f"calibration: MISSING ({e})",
            "a run needs a calibration: name one with frames.calibration_topic in the manifest",
        ]
    except DataError as e:
        return [f"image topic: none, a run cannot read this log ({e})"]
    lines = [f"image topic: {src.image_topic} ({_why(mlog, src.image_topic)})"]
    try:
        cal = src.first_calibration()
    except BatchposeError as e:  # a message that does not parse, or a camera a run refuses
        lines.append(f"calibration: {src.calibration_topic}: UNUSABLE ({e})")
    else:
        lines.append(f"calibration: {src.calibration_topic}: {_calib_text(cal, src.rectified)}")
        first = firsts.get(src.image_topic)
        if isinstance(first, ImageMsg) and first.frame_id and cal.frame_id and first.frame_id != cal.frame_id:
            lines.append(f"  warning: the images are in frame {first.frame_id!r}, the calibration in {cal.frame_id!r}")
    n = src.count()
    rate = ""
    if mlog.start_ns is not None and mlog.end_ns is not None and mlog.end_ns > mlog.start_ns and n > 1:
        rate = f", about {(n - 1) / ((mlog.end_ns - mlog.start_ns) * 1e-9):.3g} per second over the log"
    lines.append(f"frames: {n} image{'s' if n != 1 else ''} on {src.image_topic}{rate}")
    return lines


def _why(mlog: McapLog, chosen: str) -> str:
    """Why the reader chose ``chosen`` (:func:`batchpose.io.mcap_topics.choose_image_topic`), in words."""
    topics = mlog.topics()
    others = [t for t, s in topics.items() if s in IMAGE_SCHEMAS and t != chosen]
    if not others:
        return "the only image topic"
    reasons = []
    for t in others:
        if mlog.topic_count(t) == 0:
            reasons.append(f"{t}: no messages")
        elif "depth" in t.lower():
            reasons.append(f"{t}: named as depth")
        elif calibration_beside(topics, t) is None and calibration_beside(topics, chosen) is not None:
            reasons.append(f"{t}: no calibration beside it")
        elif colour_rank(t) > colour_rank(chosen):
            reasons.append(f"{t}: not named as colour")
        else:
            reasons.append(f"{t}: later in the log")
    return f"chosen over {'; '.join(reasons)}. To read another, set frames.image_topic in the manifest"


def _calib_text(cal: Calib, rectified: bool) -> str:
    K = cal.K
    dist = _dist_text(cal.model, cal.dist)
    rect = " (rectified images: the calibration's P is used)" if rectified else ""
    frame = f", frame {cal.frame_id}" if cal.frame_id else ""
    return (
        f"fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}, {cal.width}x{cal.height}, "
        f"{dist}{frame}{rect}"
    )


# -------------------------------------------------------------------------------------------- folders


def _describe_folder(root: Path) -> str:
    fmt = folder_format(root)
    if fmt != "images":
        source = YcbvFrameSource(root) if fmt == "ycbv" else BopFrameSource(root)
        layout = "YCB-Video" if fmt == "ycbv" else "BOP"
        return (
            f"{root}: {layout} data set ({source.count()} frames; format {fmt} in a manifest)\n"
            "calibration and ground truth: per frame, from the data set's own files"
        )
    images = list_images(root)
    if not images:
        raise DataError(f"{root}: no .png/.jpg images in the folder (and not a YCB-Video or BOP data set)")
    suffixes = sorted({p.suffix.lower() for p in images})
    size = image_size(images[0].read_bytes())
    dims = f"{size[0]}x{size[1]}" if size else "size unknown"
    lines = [
        f"{root}: image folder, {len(images)} image{'s' if len(images) != 1 else ''} ({', '.join(suffixes)}), "
        f"{dims} (first image, {images[0].name})"
    ]
    found = find_intrinsics(root)
    if found is None:
        lines.append(
            f"calibration: MISSING (expected one of {', '.join(INTRINSICS_NAMES)} in the folder, or "
            "frames.intrinsics in the manifest)"
        )
        return "\n".join(lines)
    try:
        cam = load_intrinsics(found)
    except BatchposeError as e:
        lines.append(f"calibration: {found.name} does not load ({e})")
        return "\n".join(lines)
    lines.append(f"calibration: {found.name}: {_camera_text(cam)}")
    if size and size != (cam.width, cam.height):
        lines.append(f"  warning: the images are {dims}, the calibration is for {cam.width}x{cam.height}")
    lines.append("ground truth: none (every object of the manifest is looked for in every frame)")
    return "\n".join(lines)


def _camera_text(cam: Camera) -> str:
    K = cam.K
    dist = _dist_text(cam.distortion_model, cam.dist)
    return f"fx {K[0, 0]:.1f} fy {K[1, 1]:.1f} cx {K[0, 2]:.1f} cy {K[1, 2]:.1f}, {cam.width}x{cam.height}, {dist}"


def _dist_text(model: str, dist: np.ndarray) -> str:
    if not dist.size:
        return "no distortion"
    return f"{model or 'distortion'} ({len(dist)} coefficients{', all zero' if not np.any(dist) else ''})"
