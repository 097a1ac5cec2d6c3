"""Frames from an MCAP log: :class:`McapFrameSource` reads one image topic and pairs each image with its
calibration, ground truth and depth.

Images come from ``foxglove.CompressedImage`` (jpeg, png), ``foxglove.RawImage`` (the encodings of
:data:`batchpose.core.frames.RAW_ENCODINGS`: rgb8, bgr8, rgba8, bgra8, mono8, mono16, Bayer mosaics, 4:2:2
YUV), ``sensor_msgs/msg/Image`` and ``sensor_msgs/msg/CompressedImage`` (ROS 2 cdr) or ``sensor_msgs/Image``
and ``sensor_msgs/CompressedImage`` (ROS 1, as ``mcap convert`` writes a bag; big-endian 16-bit images are
byte-swapped), or ``foxglove.CompressedVideo`` (h264, h265, vp9, av1; decoded in log order with FFmpeg
through PyAV, one frame a message: :mod:`batchpose.io.video`); calibration from
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

The pieces: :class:`~batchpose.io.mcap_log.McapLog` opens the file and yields its records,
:mod:`batchpose.io.mcap_topics` chooses the topics, :class:`~batchpose.io.mcap_decode.MessageDecoder`
decodes messages, and :class:`_FrameAssembler` here turns image messages into frames.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.records import Attachment, Channel, Message, Schema

from batchpose.core.frames import Frame, FrameSource, distortion_problem, image_size
from batchpose.errors import BatchposeError, CameraError, DataError, ImageError
from batchpose.io.mcap_decode import BadMessage, Calib, GroundTruth, ImageMsg, MessageDecoder, camera_of
from batchpose.io.mcap_log import McapLog, RawRecord
from batchpose.io.mcap_topics import (
    CALIBRATION_SCHEMAS,
    DEPTH_MAX_GAP_NS,
    DEPTH_UNITS_M,
    GT_TOPIC,
    IMAGE_SCHEMAS,
    choose_calibration_topic,
    choose_image_topic,
    first_time,
    image_type_topic,
    looks_rectified,
)
from batchpose.io.video import VideoDecoder

log = logging.getLogger("batchpose")


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
            topic's name starts with ``image_rect`` (:func:`~batchpose.io.mcap_topics.looks_rectified`).

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
        self._log = McapLog(path)
        self.path = self._log.path
        topics, count = self._log.topics(), self._log.topic_count
        check_named_topics(self.path, topics, image=image_topic, calibration=calibration_topic, depth=depth_topic)
        self.depth_topic = None if depth_topic is None else image_type_topic(self.path, topics, depth_topic, "depth")
        self.image_topic = choose_image_topic(self.path, topics, count, image_topic, self.depth_topic)
        self.calibration_topic = choose_calibration_topic(self.path, topics, count, calibration_topic, self.image_topic)
        #: Whether the images are rectified (distortion removed): their camera is the calibration's P, not
        #: K and D. None: as ROS's image_proc names them, ``image_rect``, ``image_rect_color``, ...
        self.rectified = looks_rectified(self.image_topic) if rectified is None else bool(rectified)
        if self.rectified and rectified is None and first_time(self.path, self.image_topic):
            log.info(
                "%s:%s: rectified images (by the topic's name): using the calibration's P without distortion "
                "(set rectified: false in the manifest's frames if they are not)",
                self.path,
                self.image_topic,
            )
        self.gt_topic = GT_TOPIC if GT_TOPIC in topics else None
        self._decoder = MessageDecoder(self.path)
        self._count: int | None = None
        self._warned: set[tuple[str, int]] = set()  # (topic, log time) of messages already warned about
        self._log.warn_if_truncated(self.image_topic)

    # -- the log

    @property
    def indexed(self) -> bool:
        """True when the file was read through its summary (index)."""
        return self._log.indexed

    @property
    def truncated(self) -> bool:
        """True when the file has no footer/summary or breaks off inside a record."""
        return self._log.truncated

    @property
    def profile(self) -> str:
        """The header's profile ("ros1", "ros2", ...)."""
        return self._log.profile

    @property
    def start_ns(self) -> int | None:
        """Log time of the log's first message of any topic (where Foxglove's timeline starts); None when
        the file says nothing (no statistics record)."""
        return self._log.start_ns

    @property
    def time_ordered(self) -> bool:
        """True when frames come in log-time order (an indexed file; a stream-read one is in file order)."""
        return self._log.indexed

    @property
    def channels(self) -> dict[int, Channel]:
        """Channel id -> channel record."""
        return dict(self._log.channels)

    @property
    def schemas(self) -> dict[int, Schema]:
        """Schema id -> schema record."""
        return dict(self._log.schemas)

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name."""
        return {k: dict(v) for k, v in self._log.metadata.items()}

    def iter_raw(self, topics: Iterable[str] | None = None) -> Iterator[RawRecord]:
        """Yield (schema, channel, message) records, undecoded (see :meth:`McapLog.iter_raw`)."""
        return self._log.iter_raw(topics)

    def iter_attachments(self) -> Iterator[Attachment]:
        """Yield the file's attachment records."""
        return self._log.iter_attachments()

    # -- messages

    def decode(self, schema: Schema | None, channel: Channel, message: Message) -> Any:
        """Decode one message with its embedded schema (protobuf, ROS 2 cdr, ROS 1, or JSON).

        Raises:
            DataError: no decoder for the encoding, or the bytes do not parse.
        """
        return self._decoder.decode(schema, channel, message)

    def calibration(self, schema: Schema | None, channel: Channel, message: Message) -> Calib:
        """Decode a calibration message: the camera of the image topic, so for rectified images
        (:attr:`rectified`) the projection matrix P without distortion, else K and D.

        Raises:
            DataError: the message does not parse or lacks a field.
            CameraError: the images are rectified and the message has no usable P, or they are not and its
                distortion is not one OpenCV's pinhole model takes (:func:`batchpose.core.frames.distortion_problem`).
        """
        cal = self._decoder.calibration(schema, channel, message)
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

    def image(self, schema: Schema | None, channel: Channel, message: Message) -> ImageMsg:
        """Decode an image message (its pixel bytes stay encoded).

        Raises:
            DataError: the message does not parse or lacks a field.
        """
        return self._decoder.image(schema, channel, message)

    def ground_truth(self, schema: Schema | None, channel: Channel, message: Message) -> GroundTruth:
        """Decode a ``/ground_truth/poses`` message.

        Raises:
            DataError: the message does not parse or lacks a field (which one, and its log time).
        """
        return self._decoder.ground_truth(schema, channel, message)

    def first_calibration(self) -> Calib:
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
        depths: dict[int, ImageMsg] = {}
        for item in self._frames(with_depth=True):
            if isinstance(item, ImageMsg):
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

    def _with_depth(self, pending: _PendingFrame, depths: dict[int, ImageMsg]) -> Frame:
        """The pending frame with the depth image whose header stamp is nearest its own, within
        :data:`DEPTH_MAX_GAP_NS` (else the frame as it is).

        Raises:
            DataError: that depth image is in another camera frame than the image.
        """
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
        :class:`ImageMsg` s interleaved."""
        assembler = _FrameAssembler(self, self.first_calibration())
        topics = [self.image_topic, self.calibration_topic] + ([self.gt_topic] if self.gt_topic else [])
        if with_depth and self.depth_topic is not None:
            topics.append(self.depth_topic)
        gts: dict[int, GroundTruth] = {}
        # The last image's frame waits for the next later log time: its ground truth may be logged after it.
        held: _PendingFrame | None = None
        for schema, channel, message in self.iter_raw(topics):
            t = message.log_time
            if held is not None and t > held.frame.stamp_ns:
                yield _with_ground_truth(held, gts, with_depth)
                held = None
            if channel.topic == self.calibration_topic:
                assembler.cal = self.calibration(schema, channel, message)
            elif channel.topic == self.gt_topic:
                gts[t] = self.ground_truth(schema, channel, message)
            elif with_depth and channel.topic == self.depth_topic:
                try:
                    yield self.image(schema, channel, message)
                except BadMessage as e:  # its colour image keeps its RGB poses
                    self._warn_once(channel.topic, t, f"{e}; no depth image for the frame it belongs to")
            else:
                pending = assembler.frame(schema, channel, message)
                if held is not None:  # two images at one log time: the first one takes its ground truth
                    yield _with_ground_truth(held, gts, with_depth)
                held = pending
        if held is not None:
            yield _with_ground_truth(held, gts, with_depth)

    def _warn_once(self, topic: str, log_time: int, text: str) -> None:
        """Warn about the message at ``log_time`` once per source, however often the frames are read."""
        if (topic, log_time) not in self._warned:
            self._warned.add((topic, log_time))
            log.warning("%s", text)

    def count(self) -> int:
        if self._count is None:
            n = self._log.topic_count(self.image_topic)
            if n is None:  # no statistics record: count the index entries by reading
                n = sum(1 for _ in self.iter_raw([self.image_topic]))
            self._count = n
        return self._count

    def obj_id(self, name: str) -> int:
        """Object id from the ``batchpose`` metadata record; when a truncated log lost it, from the
        ground-truth messages read (0 if unknown)."""
        return self._log.obj_id(name)

    def describe(self) -> str:
        gt = ", ground truth" if self.gt_topic else ""
        n = self.count()
        return (
            f"mcap {self.path} ({n} frame{'s' if n != 1 else ''} on {self.image_topic}, "
            f"calibration {self.calibration_topic}{gt})"
        )


def check_named_topics(path: Path, topics: dict[str, str], **named: str | None) -> None:
    """Check that every topic a manifest or the user named is in the log.

    Args:
        path: the log (named in the error).
        topics: the log's topic -> schema name.
        named: what each topic is meant as (``image``, ``calibration``, ``depth``) -> the topic named, or None.

    Raises:
        CameraError: a calibration topic that is not in the log; DataError: an image or depth topic that is not.
            The message lists the log's image and calibration topics and names the nearest topic (``did you
            mean``; of the same kind when one is close).
    """
    for what, wanted in named.items():
        if wanted is None or wanted in topics:
            continue
        images = [t for t, s in topics.items() if s in IMAGE_SCHEMAS]
        calibrations = [t for t, s in topics.items() if s in CALIBRATION_SCHEMAS]
        same_kind = calibrations if what == "calibration" else images
        near = difflib.get_close_matches(wanted, same_kind, n=1, cutoff=0.5) or difflib.get_close_matches(
            wanted, list(topics), n=1, cutoff=0.5
        )
        error = CameraError if what == "calibration" else DataError
        raise error(
            f"{path}: {what} topic {wanted!r} not found (image topics: {', '.join(images) or 'none'}; "
            f"calibration topics: {', '.join(calibrations) or 'none'})"
            + (f"; did you mean {near[0]!r}?" if near else "")
        )


def _with_ground_truth(held: _PendingFrame, gts: dict[int, GroundTruth], with_depth: bool) -> Any:
    """The held frame with the ground truth logged at its log time (taken out of ``gts``), if any; with
    ``with_depth`` still a :class:`_PendingFrame`."""
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


class _FrameAssembler:
    """Turns the image messages of one read of a source into frames, in log order.

    Each frame gets the latest calibration (:attr:`cal`, set by the reader; before the first one, the first
    calibration of the topic), a running ``im_id``, and a ``frame_id`` made unique among images at one log
    time. Warns once per read about images before the first calibration, in another camera frame than the
    calibration's, or of another size.

    Args:
        src: the source being read.
        first: the first calibration of its calibration topic.
    """

    def __init__(self, src: McapFrameSource, first: Calib) -> None:
        self.src = src
        self.where = f"{src.path}:{src.image_topic}"
        self.first = first
        #: the calibration logged last (None before the first)
        self.cal: Calib | None = None
        is_video = IMAGE_SCHEMAS.get(src._log.topics()[src.image_topic]) == "video"
        self.video = VideoDecoder(self.where) if is_video else None
        self.index, self.dup = 0, 0
        self.last_t: int | None = None
        self.warned_early = self.warned_size = self.warned_frame = False

    def frame(self, schema: Schema | None, channel: Channel, message: Message) -> _PendingFrame:
        """The frame of one image message (failed with :class:`ImageError` when the message does not parse or
        a raw image's size is not its calibration's), waiting for its ground truth and depth."""
        t = message.log_time
        c = self._calibration()
        error: BatchposeError | None = None
        img: ImageMsg | None
        try:
            img = self.src.image(schema, channel, message)
            if self.video is not None:
                img = self.video.decode(img, t)
        except BadMessage as e:  # one bad message costs its frame (bad_image), not the batch
            self.src._warn_once(channel.topic, t, f"{e}; that frame fails as bad_image")
            error, img = ImageError(str(e)), None
        if img is not None:
            self._check_frame_id(img, c)
            error = self._size_error(img, c)
        self.dup = self.dup + 1 if t == self.last_t else 0
        self.last_t = t
        frame = Frame(
            frame_id=f"mcap:{t}" + (f"#{self.dup}" if self.dup else ""),
            scene_id=0,
            im_id=self.index,
            stamp_ns=t,
            camera=camera_of(c, img),
            image_format=img.fmt if img is not None else "",
            image_data=img.data if img is not None else b"",
            raw_step=img.step if img is not None else 0,
            source=self.where,
            error=error,
        )
        self.index += 1
        return _PendingFrame(frame, img.stamp_ns if img is not None else t, img.frame_id if img is not None else "")

    def _calibration(self) -> Calib:
        """The calibration of the next image: the latest, or the first (with a warning, once)."""
        if self.cal is None and not self.warned_early:
            log.warning(
                "%s: images logged before the first calibration on %s use that first calibration",
                self.where,
                self.src.calibration_topic,
            )
            self.warned_early = True
        return self.cal or self.first

    def _check_frame_id(self, img: ImageMsg, c: Calib) -> None:
        """Warn (once) when the image and its calibration name different camera frames."""
        if not self.warned_frame and img.frame_id and c.frame_id and img.frame_id != c.frame_id:
            log.warning(
                "%s: images are in frame %r, the calibration on %s describes frame %r: check that it is this "
                "camera's (set calibration_topic)",
                self.where,
                img.frame_id,
                self.src.calibration_topic,
                c.frame_id,
            )
            self.warned_frame = True

    def _size_error(self, img: ImageMsg, c: Calib) -> ImageError | None:
        """An error for a raw image of another size than its calibration (a compressed one is only warned
        about, once: decode_image checks it)."""
        error = None
        size = None
        if img.raw:
            size = (img.width, img.height) if img.width > 0 and img.height > 0 and img.data else None
        elif img.fmt in ("png", "jpeg"):
            size = image_size(img.data)
        if size is not None and c.width and c.height and size != (c.width, c.height):
            if img.raw:  # the camera takes a raw image's size: decode_image cannot tell
                error = ImageError(
                    f"{self.where}: image is {size[0]}x{size[1]}, the camera calibration on "
                    f"{self.src.calibration_topic} is for {c.width}x{c.height}"
                )
            if not self.warned_size:
                log.warning(
                    "%s: image is %dx%d but the calibration on %s says %dx%d (frames of another size fail "
                    "as bad_image)",
                    self.where,
                    *size,
                    self.src.calibration_topic,
                    c.width,
                    c.height,
                )
                self.warned_size = True
        return error
