"""Frames, cameras and ground-truth poses: the records every reader yields and every stage consumes.

Images stay encoded (``image_format`` + ``image_data``) until a worker needs pixels, so a frame is cheap
to pass between processes and PNG/JPEG bytes can be copied into MCAP without re-encoding.
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from batchpose.errors import BatchposeError, CameraError, ImageError

#: Raw encodings understood by :func:`decode_image` (foxglove.RawImage / sensor_msgs/Image names).
RAW_ENCODINGS = {
    "rgb8": (3, np.uint8),
    "bgr8": (3, np.uint8),
    "rgba8": (4, np.uint8),
    "bgra8": (4, np.uint8),
    "mono8": (1, np.uint8),
    "8UC1": (1, np.uint8),
    "8UC3": (3, np.uint8),
    "mono16": (1, np.uint16),
    "16UC1": (1, np.uint16),
    **{f"bayer_{p}8": (1, np.uint8) for p in ("rggb", "bggr", "gbrg", "grbg")},
    **{f"bayer_{p}16": (1, np.uint16) for p in ("rggb", "bggr", "gbrg", "grbg")},
    "uyvy": (2, np.uint8),
    "yuv422": (2, np.uint8),
    "yuyv": (2, np.uint8),
    "yuv422_yuy2": (2, np.uint8),
}
#: Raw encodings OpenCV turns into RGB: colour-filter mosaics and packed 4:2:2 YUV (ROS and Foxglove names:
#: ``yuv422`` is UYVY, ``yuv422_yuy2`` is YUYV). OpenCV names a Bayer pattern by the 2x2 block one pixel
#: down and right of the corner, so ROS's ``rggb`` is OpenCV's ``BG``.
_RAW_TO_RGB = {
    **{
        f"bayer_{p}{bits}": code
        for p, code in (
            ("rggb", cv2.COLOR_BayerBG2RGB),
            ("bggr", cv2.COLOR_BayerRG2RGB),
            ("gbrg", cv2.COLOR_BayerGR2RGB),
            ("grbg", cv2.COLOR_BayerGB2RGB),
        )
        for bits in (8, 16)
    },
    "uyvy": cv2.COLOR_YUV2RGB_UYVY,
    "yuv422": cv2.COLOR_YUV2RGB_UYVY,
    "yuyv": cv2.COLOR_YUV2RGB_YUY2,
    "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUY2,
}
COMPRESSED_FORMATS = ("png", "jpeg")
#: ROS's compressed_depth_image_transport (a ``.../compressedDepth`` topic) with PNG inside: a 12-byte
#: header (int32 format, float32 A, float32 B), then a 16-bit PNG of the depth (16UC1 / mono16, mm), or of
#: quantised inverse depth q for 32FC1 (depth = A / (q - B) metres; q = 0: no reading).
COMPRESSED_DEPTH_FORMATS = ("compressedDepth png 16UC1", "compressedDepth png mono16", "compressedDepth png 32FC1")
#: Encodings of a depth image understood by :func:`decode_depth`: 16-bit PNG, raw 16-bit / 32-bit float, or
#: ROS's compressedDepth (:data:`COMPRESSED_DEPTH_FORMATS`).
DEPTH_ENCODINGS = ("png", "16UC1", "mono16", "32FC1", *COMPRESSED_DEPTH_FORMATS)
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")


#: Distortion models whose coefficients OpenCV's pinhole functions take (ROS CameraInfo's names), and the
#: numbers of coefficients those take. Others (``equidistant``, fisheye ...) are refused unless all zero.
DISTORTION_MODELS = ("", "plumb_bob", "rational_polynomial")
OPENCV_DIST_SIZES = (0, 4, 5, 8, 12, 14)


def distortion_problem(model: str, dist: np.ndarray) -> str | None:
    """Why OpenCV's pinhole model cannot use these coefficients, or None when it can."""
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if model.lower() not in DISTORTION_MODELS and np.any(dist):
        return (
            f"distortion model {model!r} is not supported (plumb_bob or rational_polynomial, OpenCV's pinhole "
            "model); rectify the images first (ROS: image_proc's image_rect topic) and use those"
        )
    if dist.size not in OPENCV_DIST_SIZES:
        return f"{dist.size} distortion coefficients; OpenCV's model takes 4, 5, 8, 12 or 14"
    return None


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with optional distortion.

    Attributes:
        K: (3, 3) float64 intrinsics, OpenCV convention (pixel centres at integer coordinates).
        width: image width in pixels.
        height: image height in pixels.
        dist: (N,) float64 distortion coefficients in OpenCV order (empty: none).
        distortion_model: "" / "plumb_bob" / "rational_polynomial".
    """

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = ""

    def validate(self, where: str = "camera") -> Camera:
        """Raise :class:`CameraError` naming ``where`` unless K is a finite, positive-focal, upper-triangular
        3x3 matrix with the last row (0, 0, 1) and the distortion one OpenCV's pinhole model takes."""
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise CameraError(f"{where}: intrinsics K must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)):
            raise CameraError(f"{where}: intrinsics K contains NaN or inf: {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(f"{where}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9:  # e.g. written transposed
            raise CameraError(
                f"{where}: intrinsics K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (row-major), got {K.tolist()}"
            )
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"{where}: image size must be positive, got {self.width}x{self.height}")
        if self.dist.size and not np.all(np.isfinite(self.dist)):
            raise CameraError(f"{where}: distortion coefficients contain NaN or inf")
        problem = distortion_problem(self.distortion_model, self.dist)
        if problem:
            raise CameraError(f"{where}: {problem}")
        return self


def working_camera(camera: Camera, max_side_px: int) -> tuple[Camera, np.ndarray]:
    """The camera of a frame resized so that its longer side is at most ``max_side_px`` (0: no limit).

    Returns:
        The camera (the same object when no resize is needed: K scaled with OpenCV's pixel-centre convention,
        distortion unchanged, as it acts on normalised coordinates) and (2,) the x and y scale factors.
    """
    w, h = camera.width, camera.height
    if max_side_px <= 0 or max(w, h) <= max_side_px:
        return camera, np.ones(2)
    s = max_side_px / max(w, h)
    w2, h2 = max(1, round(w * s)), max(1, round(h * s))
    scale = np.array([w2 / w, h2 / h])
    K = np.asarray(camera.K, dtype=np.float64).copy()
    K[0, :3] *= scale[0]
    K[1, :3] *= scale[1]
    K[:2, 2] += 0.5 * scale - 0.5  # pixel centres at integer coordinates: (x + 0.5) s - 0.5
    return Camera(K, w2, h2, camera.dist, camera.distortion_model), scale


@dataclass(frozen=True)
class ObjectPose:
    """A (ground-truth) pose of one object in one frame.

    Attributes:
        obj_name: object name, e.g. "003_cracker_box".
        cam_from_model: (4, 4) float64 rigid transform, metres.
    """

    obj_name: str
    cam_from_model: np.ndarray


@dataclass(frozen=True)
class Frame:
    """One camera image with its calibration and, when the data set has it, ground truth.

    Attributes:
        frame_id: unique id within the data set (e.g. "0001/000003" or "mcap:1700000000000000000").
        scene_id: BOP scene id (YCB-Video: video number; data_syn: 10000; logs: 0).
        im_id: BOP image id (YCB-Video: frame number; logs: running index).
        stamp_ns: capture time in integer nanoseconds (log time for MCAP).
        camera: calibration in force at this frame.
        image_format: "png", "jpeg" or a raw encoding from :data:`RAW_ENCODINGS`.
        image_data: encoded bytes (compressed) or raw pixel bytes.
        raw_step: bytes per row for raw encodings (0 for compressed).
        gt: ground-truth poses present in the frame (empty when unknown).
        source: where the frame came from (file path or "file.mcap:/topic"), for error messages.
        depth_format: encoding of a depth image registered to the colour image (one of
            :data:`DEPTH_ENCODINGS`), "" when the frame has none.
        depth_data: the depth image's encoded or raw bytes.
        depth_scale_m: metres per depth unit (YCB-Video: 1e-4; float depth in metres: 1.0).
        depth_step: bytes per row of a raw depth image (0: packed, or compressed).
        im_step: how far this run's previous frame of the sequence is in ``im_id`` (a manifest's
            ``frames.every``: every ``im_step``-th frame is used); tracking follows a pose from that frame.
        error: why the frame cannot be used although the data set lists it (a corrupt ``-meta.mat``, an
            undecodable image message, a raw image of another size than its calibration); None when it
            can. :func:`decode_image` raises it, so the frame fails with it (``bad_image`` for an
            :class:`ImageError`, ``bad_camera`` for a :class:`CameraError`) and the batch goes on.
    """

    frame_id: str
    scene_id: int
    im_id: int
    stamp_ns: int
    camera: Camera
    image_format: str
    image_data: bytes
    raw_step: int = 0
    gt: tuple[ObjectPose, ...] = ()
    source: str = ""
    depth_format: str = ""
    depth_data: bytes = b""
    depth_scale_m: float = 0.0
    depth_step: int = 0
    im_step: int = 1
    error: BatchposeError | None = None

    @property
    def has_depth(self) -> bool:
        return bool(self.depth_format)


def decode_image(frame: Frame) -> np.ndarray:
    """Decode a frame's pixels.

    Returns:
        (H, W, 3) uint8 RGB image (mono is replicated, 16-bit is scaled to 8-bit, alpha dropped, Bayer
        mosaics are demosaiced and 4:2:2 YUV converted by OpenCV).

    Raises:
        ImageError: empty data, undecodable bytes, unsupported encoding or a size that disagrees with
            the calibration.
        BatchposeError: the frame's :attr:`Frame.error`, when it has one.
    """
    if frame.error is not None:  # a fresh copy: the stored one would collect a traceback per raise
        raise type(frame.error)(*frame.error.args) from None
    where = frame.source or frame.frame_id
    if not frame.image_data:
        raise ImageError(f"{where}: image is empty (0 bytes)")
    fmt = frame.image_format.lower()
    if fmt in ("jpg",):
        fmt = "jpeg"
    if fmt in COMPRESSED_FORMATS:
        buf = np.frombuffer(frame.image_data, dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None or img.size == 0:
            raise ImageError(f"{where}: cannot decode {fmt} image ({len(frame.image_data)} bytes)")
        if img.dtype == np.uint16:
            img = (img / 257).astype(np.uint8)
        if img.ndim == 2:
            rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        elif img.shape[2] == 4:
            rgb = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        else:
            rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif frame.image_format in RAW_ENCODINGS:
        channels, dtype = RAW_ENCODINGS[frame.image_format]
        w, h = frame.camera.width, frame.camera.height
        itemsize = np.dtype(dtype).itemsize
        step = frame.raw_step or w * channels * itemsize
        if w <= 0 or h <= 0 or step * h > len(frame.image_data) or step < w * channels * itemsize:
            raise ImageError(
                f"{where}: raw {frame.image_format} image of {w}x{h} (step {step}) needs "
                f"{step * h} bytes, got {len(frame.image_data)}"
            )
        rows = np.frombuffer(frame.image_data[: step * h], dtype=np.uint8).reshape(h, step)
        img = rows[:, : w * channels * itemsize].copy().view(dtype).reshape(h, w, channels)
        if dtype == np.uint16:
            img = (img / 257).astype(np.uint8)
        enc = frame.image_format
        if enc in _RAW_TO_RGB:
            try:
                rgb = cv2.cvtColor(img[:, :, 0] if channels == 1 else img, _RAW_TO_RGB[enc])
            except cv2.error as e:  # e.g. 4:2:2 YUV of an odd width
                msg = str(e).strip().splitlines()[-1]
                raise ImageError(f"{where}: cannot convert the {enc} image of {w}x{h} to RGB ({msg})") from None
        elif channels == 1:
            rgb = np.repeat(img, 3, axis=2)
        elif enc in ("bgr8", "bgra8"):
            rgb = np.ascontiguousarray(img[:, :, 2::-1])
        else:
            rgb = np.ascontiguousarray(img[:, :, :3])
    else:
        raise ImageError(
            f"{where}: unsupported image encoding {frame.image_format!r} "
            f"(expected one of {', '.join(COMPRESSED_FORMATS + tuple(RAW_ENCODINGS))})"
        )
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ImageError(f"{where}: image has zero size {rgb.shape[1]}x{rgb.shape[0]}")
    w, h = frame.camera.width, frame.camera.height
    if w > 0 and h > 0 and rgb.shape[:2] != (h, w):  # K would be wrong for these pixels: no pose from them
        raise ImageError(f"{where}: image is {rgb.shape[1]}x{rgb.shape[0]}, the camera calibration is for {w}x{h}")
    return rgb


def decode_depth(frame: Frame) -> np.ndarray | None:
    """Decode a frame's depth image, registered to its colour image.

    Returns:
        (H, W) float32 depth in metres (z along the optical axis), 0 where the sensor has no reading;
        None when the frame has no depth image.

    Raises:
        ImageError: empty or undecodable data, an encoding not in :data:`DEPTH_ENCODINGS`, a depth scale
            that is not positive, or a size that differs from the colour image's calibration (or a colour
            image of unknown size).
    """
    if not frame.depth_format:
        return None
    where = f"{frame.source or frame.frame_id} (depth)"
    fmt = frame.depth_format
    if fmt not in DEPTH_ENCODINGS:
        raise ImageError(f"{where}: unsupported depth encoding {fmt!r} (expected one of {', '.join(DEPTH_ENCODINGS)})")
    if not frame.depth_data:
        raise ImageError(f"{where}: depth image is empty (0 bytes)")
    if not (np.isfinite(frame.depth_scale_m) and frame.depth_scale_m > 0):
        raise ImageError(
            f"{where}: depth scale must be a positive number of metres per unit, got {frame.depth_scale_m}"
        )
    w, h = frame.camera.width, frame.camera.height
    if w <= 0 or h <= 0:
        raise ImageError(
            f"{where}: the colour image's size is unknown (its header is unreadable), so the depth "
            "image cannot be matched to it"
        )
    if fmt == "png" or fmt in COMPRESSED_DEPTH_FORMATS:
        png = frame.depth_data
        if fmt != "png":
            if len(png) <= _COMPRESSED_DEPTH_HEADER.size:
                raise ImageError(f"{where}: compressedDepth image of {len(png)} bytes has no PNG after its header")
            _, quant_a, quant_b = _COMPRESSED_DEPTH_HEADER.unpack_from(png)
            png = png[_COMPRESSED_DEPTH_HEADER.size :]
        img = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2 or img.dtype != np.uint16:
            got = "undecodable" if img is None else f"{img.dtype} with {1 if img.ndim == 2 else img.shape[2]} channels"
            raise ImageError(f"{where}: depth PNG must be single-channel 16-bit, got {got}")
        if fmt.endswith("32FC1"):  # quantised inverse depth
            q = img.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                img = np.where(img > 0, np.float32(quant_a) / (q - np.float32(quant_b)), np.float32(0.0))
    else:
        dtype = np.float32 if fmt == "32FC1" else np.uint16
        itemsize = np.dtype(dtype).itemsize
        step = frame.depth_step or w * itemsize
        if step < w * itemsize or step * h > len(frame.depth_data):
            raise ImageError(
                f"{where}: raw {fmt} depth of {w}x{h} (step {step}) needs {step * h} bytes, got {len(frame.depth_data)}"
            )
        rows = np.frombuffer(frame.depth_data[: step * h], dtype=np.uint8).reshape(h, step)
        img = rows[:, : w * itemsize].copy().view(dtype).reshape(h, w)
    if img.shape != (h, w):
        raise ImageError(f"{where}: depth image is {img.shape[1]}x{img.shape[0]}, the colour image {w}x{h}")
    depth = img.astype(np.float32) * np.float32(frame.depth_scale_m)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


class FrameSource(ABC):
    """A lazily read sequence of frames. Iterate it to get :class:`Frame` objects in a fixed order."""

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """Yield the frames one by one, reading each from disk only when it is reached."""

    @abstractmethod
    def count(self) -> int:
        """Number of frames, without decoding any image."""

    def obj_id(self, name: str) -> int:
        """Data set object id of ``name`` (YCB-Video: 1-based line of classes.txt; BOP: obj_id); 0 if unknown."""
        return 0

    @abstractmethod
    def describe(self) -> str:
        """One line saying what this source reads, e.g. "ycbv /data/ycbv_dev (21 frames)"."""

    def __len__(self) -> int:
        return self.count()


def image_size(data: bytes) -> tuple[int, int] | None:
    """Width and height from a PNG or JPEG header, without decoding pixels.

    Args:
        data: encoded image bytes.

    Returns:
        (width, height) in pixels, or None when the bytes are not a PNG/JPEG header we can read.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xDA)):  # standalone markers carry no length
            i += 2
            continue
        (seg_len,) = struct.unpack(">H", data[i + 2 : i + 4])
        # SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) hold the frame size.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                return None
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(w), int(h)
        i += 2 + seg_len
    return None
