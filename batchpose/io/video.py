"""``foxglove.CompressedVideo`` decoding with FFmpeg through PyAV (the only module that imports ``av``)."""

from __future__ import annotations

from typing import Any

from batchpose.io.files import one_line
from batchpose.io.mcap_decode import BadMessage, ImageMsg

#: foxglove.CompressedVideo formats and the FFmpeg (PyAV) decoder of each; AV1 through dav1d, FFmpeg's own
#: AV1 decoder needing hardware.
VIDEO_DECODERS = {"h264": "h264", "h265": "hevc", "vp9": "vp9", "av1": "libdav1d"}


class VideoDecoder:
    """Decodes a ``foxglove.CompressedVideo`` topic message by message, in log order (FFmpeg through PyAV).

    Each message holds one frame (as Foxglove's schema requires; no B-frames), decoded with FFmpeg's low-delay
    flag so that it comes out of its own message. A message that gives no picture (a stream that starts
    between keyframes, or broken data) fails its frame only.

    Args:
        where: the log and topic (``PATH:TOPIC``), named in errors.
    """

    def __init__(self, where: str) -> None:
        self.where = where
        self._ctx: Any = None
        self._fmt = ""

    def decode(self, img: ImageMsg, log_time: int) -> ImageMsg:
        """The message's frame as a raw rgb8 image.

        Args:
            img: the video message (``fmt`` "video/<format>", ``data`` one encoded frame).
            log_time: the message's log time, ns (named in errors).

        Returns:
            The frame: ``fmt`` "rgb8", (H, W, 3) uint8 pixel bytes, step 3 W; frame id and stamp of ``img``.

        Raises:
            BadMessage: an unsupported format, or no picture from this message.
        """
        import av  # noqa: PLC0415 - only logs with video need FFmpeg

        fmt = img.fmt.removeprefix("video/")
        if fmt not in VIDEO_DECODERS:
            raise BadMessage(
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
            raise BadMessage(
                f"{self.where}: no picture from the {fmt} video message at log time {log_time} ({why}; a stream "
                "that starts between keyframes decodes from its first keyframe)"
            )
        rgb = frames[-1].to_ndarray(format="rgb24")
        h, w = rgb.shape[:2]
        return ImageMsg("rgb8", rgb.tobytes(), w, h, 3 * w, img.frame_id, img.stamp_ns, raw=True)
