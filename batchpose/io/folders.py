"""Folder data set readers: YCB-Video, BOP and plain images (opened by :func:`batchpose.io.sources.open_frames`).

Every reader yields :class:`~batchpose.core.frames.Frame` lazily, one file read per frame: listing the
frames (``count()``) touches only directory entries and small index files, never image pixels.
Images stay encoded (PNG/JPEG bytes as stored on disk).

Layouts:
    ``ycbv``: ``ROOT/classes.txt`` (one object name per line, obj_id = 1-based line),
    ``ROOT/data/<video>/<frame>-color.png`` + ``-meta.mat`` and ``ROOT/data_syn/<frame>-color.png`` +
    ``-meta.mat`` (scene_id 10000). ``meta.mat``: ``cls_indexes`` (1-based into classes.txt),
    ``poses`` (3, 4, N) model->camera in metres, ``intrinsic_matrix`` (3, 3). A ``-meta.mat`` that cannot
    be read (or lacks one of these) fails only its frame: :attr:`Frame.error`, status ``bad_camera``.
    ``bop``: ``ROOT/<scene>/scene_camera.json`` (``cam_K``: 9 floats, row-major, per im_id),
    optional ``scene_gt.json`` (``cam_R_m2c`` row-major, ``cam_t_m2c`` in mm, ``obj_id``) and
    ``rgb/<im_id:06d>.png|jpg``.
    ``images``: a folder of ``.png`` / ``.jpg`` files plus an intrinsics YAML with ``fx, fy, cx, cy,
    width, height`` and optional ``dist`` (OpenCV order) and ``distortion_model``, or the camera-info YAML
    ROS's ``camera_calibration`` writes (``ost.yaml``); found in the folder by the names of
    :data:`INTRINSICS_NAMES` unless the manifest names it.
    ``mcap``: see :mod:`batchpose.io.mcap_read`.

Folder data sets carry no capture times, so ``stamp_ns`` is synthetic: ``index * 33_333_333`` (30 Hz
from 0), in listing order.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io
import yaml
from scipy.io.matlab import MatReadError

from batchpose.core.frames import Camera, Frame, FrameSource, ObjectPose, image_size
from batchpose.errors import CameraError, ConfigError, DataError
from batchpose.io.files import one_line, read_text

log = logging.getLogger("batchpose")

#: Synthetic frame period for data sets without capture times (30 Hz), in nanoseconds.
FRAME_PERIOD_NS = 33_333_333
#: scene_id of YCB-Video's synthetic frames (``data_syn/``), as in the BOP conversion.
YCBV_SYN_SCENE_ID = 10000
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

INTRINSICS_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
#: The calibration files an image folder is searched for, in this order (``ost.yaml``: ROS's camera_calibration).
INTRINSICS_NAMES = ("intrinsics.yaml", "ost.yaml", "camera_info.yaml", "calibration.yaml")


def image_format_of(path: Path) -> str:
    """``"png"`` or ``"jpeg"`` from a file suffix."""
    return "png" if path.suffix.lower() == ".png" else "jpeg"


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise DataError(f"{path}: cannot read image ({e.strerror or e})") from None


def _camera_from_image(K: np.ndarray, data: bytes, path: Path) -> Camera:
    """Camera with the image's own size (0x0 when the header is unreadable: decode_image then reports it)."""
    size = image_size(data)
    if size is None and data:
        log.debug("%s: cannot read the image size from its header", path)
    w, h = size if size is not None else (0, 0)
    return Camera(K=np.asarray(K, dtype=np.float64).reshape(3, 3), width=w, height=h)


def _require_dir(path: Path, what: str) -> Path:
    if not path.exists():
        raise DataError(f"{what}: {path} does not exist")
    if not path.is_dir():
        raise DataError(f"{what}: {path} is not a folder")
    return path


# --------------------------------------------------------------------------------------------- YCB-Video


class _UnusableMeta(DataError):
    """A ``-meta.mat`` that cannot be read or lacks what a frame needs: that frame fails, not the batch."""


class YcbvFrameSource(FrameSource):
    """YCB-Video folder layout (``data/<video>/`` and ``data_syn/``); see the module docstring.

    Args:
        root: data set folder holding ``classes.txt`` and ``data/`` and/or ``data_syn/``.
    """

    def __init__(self, root: Path) -> None:
        self.root = _require_dir(Path(root), "ycbv root")
        classes = self.root / "classes.txt"
        if not classes.is_file():
            raise DataError(f"{classes}: missing (YCB-Video needs classes.txt, one object name per line)")
        self.classes = [ln.strip() for ln in read_text(classes).splitlines() if ln.strip()]
        if not self.classes:
            raise DataError(f"{classes}: empty (expected one object name per line)")
        #: (color path, scene_id, im_id, frame_id) per frame, in reading order.
        self._items: list[tuple[Path, int, int, str]] = []
        data = self.root / "data"
        if data.is_dir():
            for video in sorted(p for p in data.iterdir() if p.is_dir()):
                if not video.name.isdigit():
                    log.debug("%s: skipping non-numeric video folder", video)
                    continue
                for color in sorted(video.glob("*-color.png")):
                    im = color.name[: -len("-color.png")]
                    if im.isdigit():
                        self._items.append((color, int(video.name), int(im), f"{video.name}/{im}"))
        syn = self.root / "data_syn"
        if syn.is_dir():
            for color in sorted(syn.glob("*-color.png")):
                im = color.name[: -len("-color.png")]
                if im.isdigit():
                    self._items.append((color, YCBV_SYN_SCENE_ID, int(im), f"data_syn/{im}"))
        if not self._items:
            raise DataError(
                f"{self.root}: no YCB-Video frames (expected data/<video>/<frame>-color.png "
                "or data_syn/<frame>-color.png)"
            )
        for color, *_ in self._items:
            meta = self._meta_path(color)
            if not meta.is_file():
                raise DataError(f"{meta}: missing (every -color.png needs its -meta.mat)")
        self._warned: set[Path] = set()

    @staticmethod
    def _meta_path(color: Path) -> Path:
        return color.with_name(color.name.replace("-color.png", "-meta.mat"))

    def _read_meta(self, meta: Path) -> tuple[np.ndarray, tuple[ObjectPose, ...], float]:
        try:
            # meta.mat also holds a 480x640x3 vertmap; load only what we need.
            m = scipy.io.loadmat(str(meta), variable_names=["cls_indexes", "poses", "intrinsic_matrix", "factor_depth"])
        except (OSError, ValueError, TypeError, MatReadError) as e:
            raise _UnusableMeta(f"{meta}: cannot read MATLAB file ({one_line(e)})") from None
        for key in ("cls_indexes", "poses", "intrinsic_matrix"):
            if key not in m:
                raise _UnusableMeta(f"{meta}: missing variable {key!r}")
        try:
            K = np.asarray(m["intrinsic_matrix"], dtype=np.float64)
            cls = np.asarray(m["cls_indexes"]).reshape(-1).astype(int)
            poses = np.asarray(m["poses"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise _UnusableMeta(
                f"{meta}: cls_indexes, poses and intrinsic_matrix must be numbers ({one_line(e)})"
            ) from None
        if K.shape != (3, 3):
            raise _UnusableMeta(f"{meta}: intrinsic_matrix must be 3x3, got shape {K.shape}")
        if poses.ndim == 2:  # MATLAB drops the trailing singleton dimension of one object
            poses = poses[:, :, None]
        if poses.ndim != 3 or poses.shape[:2] != (3, 4) or poses.shape[2] != cls.size:
            raise _UnusableMeta(
                f"{meta}: poses must be 3x4x{cls.size} (one per cls_indexes entry), got shape {poses.shape}"
            )
        gt = []
        for i, c in enumerate(cls):
            if not 1 <= c <= len(self.classes):  # classes.txt is not this data set's: not one frame's fault
                raise DataError(f"{meta}: cls_indexes value {c} outside 1..{len(self.classes)} (classes.txt)")
            T = np.eye(4)
            T[:3, :] = poses[:, :, i]
            gt.append(ObjectPose(obj_name=self.classes[c - 1], cam_from_model=T))
        factor = np.asarray(m.get("factor_depth", 0), dtype=np.float64).reshape(-1)
        depth_scale_m = 1.0 / float(factor[0]) if factor.size and factor[0] > 0 else 0.0
        return K, tuple(gt), depth_scale_m

    def __iter__(self) -> Iterator[Frame]:
        for index, (color, scene_id, im_id, frame_id) in enumerate(self._items):
            meta = self._meta_path(color)
            error = None
            try:
                K, gt, depth_scale_m = self._read_meta(meta)
            except _UnusableMeta as e:  # the frame is listed and fails as bad_camera with this reason
                error = CameraError(str(e))
                K, gt, depth_scale_m = np.full((3, 3), np.nan), (), 0.0
                if meta not in self._warned:
                    log.warning("%s; frame %s is not estimated (bad_camera)", e, frame_id)
                    self._warned.add(meta)
            data = _read_bytes(color)
            depth = color.with_name(color.name.replace("-color.png", "-depth.png"))
            has_depth = depth_scale_m > 0 and depth.is_file()
            yield Frame(
                frame_id=frame_id,
                scene_id=scene_id,
                im_id=im_id,
                stamp_ns=index * FRAME_PERIOD_NS,
                camera=_camera_from_image(K, data, color),
                image_format="png",
                image_data=data,
                gt=gt,
                source=str(color),
                depth_format="png" if has_depth else "",
                depth_data=_read_bytes(depth) if has_depth else b"",
                depth_scale_m=depth_scale_m if has_depth else 0.0,
                error=error,
            )

    def count(self) -> int:
        return len(self._items)

    def obj_id(self, name: str) -> int:
        return self.classes.index(name) + 1 if name in self.classes else 0

    def describe(self) -> str:
        return f"ycbv {self.root} ({self.count()} frames)"


# --------------------------------------------------------------------------------------------------- BOP


def _load_json(path: Path) -> Any:
    text = read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None


class BopFrameSource(FrameSource):
    """BOP folder layout: ``ROOT/<scene>/{scene_camera.json, scene_gt.json, rgb/}`` (or ROOT is one scene).

    Args:
        root: split folder (e.g. ``ycbv/test``) or a single scene folder.
        obj_names: BOP obj_id -> object name; ids not listed are named ``obj_000001`` style.
    """

    def __init__(self, root: Path, obj_names: Mapping[Any, str] | None = None) -> None:
        self.root = _require_dir(Path(root), "bop root")
        self.obj_names: dict[int, str] = {}
        for k, v in (obj_names or {}).items():
            try:
                self.obj_names[int(k)] = str(v)
            except (TypeError, ValueError):
                raise ConfigError(f"frames.obj_names: key {k!r} is not an integer BOP obj_id") from None
        self._ids_by_name = {v: k for k, v in self.obj_names.items()}
        if (self.root / "scene_camera.json").is_file():
            scenes = [self.root]
        else:
            scenes = sorted(p for p in self.root.iterdir() if p.is_dir() and (p / "scene_camera.json").is_file())
        if not scenes:
            raise DataError(f"{self.root}: no BOP scenes (expected <scene>/scene_camera.json)")
        #: (scene folder, scene_id, im_id, image path, cam_K, depth path or None, depth metres per unit).
        self._items: list[tuple[Path, int, int, Path, np.ndarray, Path | None, float]] = []
        for scene in scenes:
            scene_id = int(scene.name) if scene.name.isdigit() else 0
            cams_path = scene / "scene_camera.json"
            cams = _load_json(cams_path)
            if not isinstance(cams, dict):
                raise DataError(f"{cams_path}: expected a mapping im_id -> camera")
            rgb = scene / "rgb"
            if not rgb.is_dir():
                raise DataError(f"{rgb}: missing (BOP images are rgb/<im_id:06d>.png|jpg)")
            files = {p.stem: p for p in rgb.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
            for key in sorted(cams, key=lambda k: int(k) if str(k).isdigit() else -1):
                if not str(key).isdigit():
                    raise DataError(f"{cams_path}: key {key!r} is not an integer im_id")
                im_id = int(key)
                cam_K = cams[key].get("cam_K") if isinstance(cams[key], dict) else None
                try:
                    K = np.asarray(cam_K, dtype=np.float64).reshape(3, 3)
                except (TypeError, ValueError):
                    raise DataError(
                        f"{cams_path}: im_id {im_id}: cam_K must be 9 numbers (row-major 3x3), got {cam_K!r:.80}"
                    ) from None
                image = files.get(f"{im_id:06d}")
                if image is None:
                    raise DataError(f"{rgb / f'{im_id:06d}.png'}: missing (listed in {cams_path.name})")
                depth = scene / "depth" / f"{im_id:06d}.png"
                scale = cams[key].get("depth_scale", 1.0)  # BOP: millimetres per unit
                if not isinstance(scale, (int, float)) or not scale > 0:
                    raise DataError(f"{cams_path}: im_id {im_id}: depth_scale must be a positive number, got {scale!r}")
                has_depth = depth.is_file()
                self._items.append(
                    (scene, scene_id, im_id, image, K, depth if has_depth else None, float(scale) / 1000.0)
                )
        if not self._items:
            raise DataError(f"{self.root}: scene_camera.json lists no images")

    def obj_name(self, obj_id: int) -> str:
        """Object name of a BOP obj_id (``obj_names`` or ``obj_000001`` style)."""
        return self.obj_names.get(obj_id, f"obj_{obj_id:06d}")

    def _scene_gt(self, scene: Path) -> dict[int, tuple[ObjectPose, ...]]:
        path = scene / "scene_gt.json"
        if not path.is_file():
            return {}
        raw = _load_json(path)
        if not isinstance(raw, dict):
            raise DataError(f"{path}: expected a mapping im_id -> list of object poses, got a {type(raw).__name__}")
        out: dict[int, tuple[ObjectPose, ...]] = {}
        for key, objs in raw.items():
            if not str(key).isdigit():
                raise DataError(f"{path}: key {key!r} is not an integer im_id")
            if not isinstance(objs, list):
                raise DataError(f"{path}: im_id {key}: expected a list of object poses, got a {type(objs).__name__}")
            poses = []
            for j, o in enumerate(objs):
                try:
                    R = np.asarray(o["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                    t_mm = np.asarray(o["cam_t_m2c"], dtype=np.float64).reshape(3)
                    obj_id = int(o["obj_id"])
                except (KeyError, TypeError, ValueError) as e:
                    raise DataError(
                        f"{path}: im_id {key} object {j}: expected obj_id, cam_R_m2c (9 numbers) and "
                        f"cam_t_m2c (3 numbers, mm) ({one_line(e)})"
                    ) from None
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = t_mm / 1000.0
                poses.append(ObjectPose(obj_name=self.obj_name(obj_id), cam_from_model=T))
            out[int(key)] = tuple(poses)
        return out

    def __iter__(self) -> Iterator[Frame]:
        gt_scene: Path | None = None
        gt: dict[int, tuple[ObjectPose, ...]] = {}
        for index, (scene, scene_id, im_id, image, K, depth, depth_scale_m) in enumerate(self._items):
            if scene != gt_scene:  # one scene's ground truth in memory at a time
                gt, gt_scene = self._scene_gt(scene), scene
            data = _read_bytes(image)
            yield Frame(
                frame_id=f"{scene_id:06d}/{im_id:06d}",
                scene_id=scene_id,
                im_id=im_id,
                stamp_ns=index * FRAME_PERIOD_NS,
                camera=_camera_from_image(K, data, image),
                image_format=image_format_of(image),
                image_data=data,
                gt=gt.get(im_id, ()),
                source=str(image),
                depth_format="png" if depth is not None else "",
                depth_data=_read_bytes(depth) if depth is not None else b"",
                depth_scale_m=depth_scale_m if depth is not None else 0.0,
            )

    def count(self) -> int:
        return len(self._items)

    def obj_id(self, name: str) -> int:
        if name in self._ids_by_name:
            return self._ids_by_name[name]
        if name.startswith("obj_") and name[4:].isdigit():
            return int(name[4:])
        return 0

    def describe(self) -> str:
        return f"bop {self.root} ({self.count()} frames)"


# ------------------------------------------------------------------------------------------ plain images


def load_intrinsics(path: Path) -> Camera:
    """Read a camera's intrinsics from YAML, in one of three forms:

    - batchpose's: ``fx, fy, cx, cy, width, height``, optional ``dist`` (OpenCV order), ``distortion_model``;
    - the camera-info YAML ROS's ``camera_calibration`` writes (``image_width``, ``image_height``,
      ``camera_matrix: {rows, cols, data}``, ``distortion_model``, ``distortion_coefficients``, ...);
    - OpenCV's FileStorage YAML (``!!opencv-matrix``, OpenCV 4's ``%YAML:1.0`` header) with the same key
      names, as OpenCV's calibration sample writes it.

    Raises:
        DataError: the file is missing, not UTF-8 text or not YAML.
        ConfigError: a key is missing, unknown or not a number.
        CameraError: the values do not make a valid camera.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: intrinsics file does not exist (expected YAML with {', '.join(INTRINSICS_KEYS)})")
    text = read_text(path)
    if text.startswith("%YAML:") or "!!opencv-matrix" in text:  # OpenCV's YAML: PyYAML reads neither
        return _camera_info_intrinsics(path, _opencv_yaml(path))
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise DataError(f"{path}: invalid YAML ({one_line(e)})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping with {', '.join(INTRINSICS_KEYS)}")
    if "camera_matrix" in raw:
        return _camera_info_intrinsics(path, raw)
    unknown = sorted(set(raw) - set(INTRINSICS_KEYS) - {"dist", "distortion_model"})
    if unknown:
        raise ConfigError(
            f"{path}: unknown key {unknown[0]!r} (allowed: {', '.join(INTRINSICS_KEYS)}, dist, distortion_model; "
            "or a ROS camera-info YAML with camera_matrix)"
        )
    missing = [k for k in INTRINSICS_KEYS if k not in raw]
    if missing:
        raise ConfigError(f"{path}: missing key {missing[0]!r} (need {', '.join(INTRINSICS_KEYS)})")
    flags = [k for k in INTRINSICS_KEYS if isinstance(raw[k], bool)]
    if flags:
        raise ConfigError(f"{path}: {flags[0]} must be a number, got {raw[flags[0]]!r}")
    try:
        fx, fy, cx, cy = (float(raw[k]) for k in ("fx", "fy", "cx", "cy"))
        width, height = int(raw["width"]), int(raw["height"])
        dist = np.asarray(raw.get("dist") or [], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{path}: intrinsics must be numbers (dist a list of numbers): {one_line(e)}") from None
    model = str(raw.get("distortion_model") or ("plumb_bob" if dist.size else ""))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, width=width, height=height, dist=dist, distortion_model=model)
    return cam.validate(where=str(path))


#: Keys of a ROS camera-info YAML (``camera_calibration``'s ``ost.yaml``); the first three are required.
CAMERA_INFO_KEYS = (
    "image_width",
    "image_height",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "camera_name",
    "rectification_matrix",
    "projection_matrix",
)


def _opencv_yaml(path: Path) -> dict[str, Any]:
    """The :data:`CAMERA_INFO_KEYS` an OpenCV FileStorage YAML holds, as a ROS camera-info YAML has them."""
    import cv2  # noqa: PLC0415 - only this rare format needs it here

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except (cv2.error, SystemError) as e:  # the binding wraps a parse error in a SystemError
        why = str(e.__cause__ or e).strip().splitlines()[-1].split("error: ")[-1]
        raise DataError(f"{path}: invalid OpenCV YAML ({why})") from None
    try:
        root = fs.root()
        raw: dict[str, Any] = {}
        for key in root.keys():
            node = fs.getNode(key)
            if node.isMap() and node.getNode("data").isSeq():  # !!opencv-matrix
                raw[key] = {"data": node.mat().reshape(-1).tolist()}
            elif node.isInt() or node.isReal():
                raw[key] = int(node.real()) if node.isInt() else node.real()
            elif node.isString():
                raw[key] = node.string()
            elif node.isSeq():
                raw[key] = {"data": [node.at(i).real() for i in range(node.size())]}
            else:
                raw[key] = None
    finally:
        fs.release()
    return raw


def _camera_info_intrinsics(path: Path, raw: dict[str, Any]) -> Camera:
    """A camera from a ROS camera-info YAML's keys (K and D: the raw image's camera)."""
    unknown = sorted(set(raw) - set(CAMERA_INFO_KEYS), key=str)
    if unknown:
        raise ConfigError(
            f"{path}: unknown key {unknown[0]!r} in a camera-info YAML (allowed: {', '.join(CAMERA_INFO_KEYS)})"
        )
    missing = [k for k in CAMERA_INFO_KEYS[:3] if k not in raw]
    if missing:
        raise ConfigError(
            f"{path}: missing key {missing[0]!r} (a camera-info YAML needs {', '.join(CAMERA_INFO_KEYS[:3])})"
        )

    def data(key: str) -> np.ndarray:
        m = raw.get(key)
        values = m.get("data") if isinstance(m, dict) else m
        try:
            if values is None or any(isinstance(v, bool) for v in values):
                raise TypeError(f"got {m!r}")
            return np.asarray(values, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{path}: {key}.data must be a list of numbers ({one_line(e)})") from None

    K = data("camera_matrix")
    if K.size != 9:
        raise ConfigError(f"{path}: camera_matrix.data must hold 9 numbers (3x3, row-major), got {K.size}")
    dist = data("distortion_coefficients") if raw.get("distortion_coefficients") is not None else np.zeros(0)
    sizes = [raw[k] for k in ("image_width", "image_height")]
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in sizes):
        raise ConfigError(f"{path}: image_width and image_height must be whole numbers, got {sizes}")
    model = str(raw.get("distortion_model") or ("plumb_bob" if dist.size else ""))
    cam = Camera(K=K.reshape(3, 3), width=sizes[0], height=sizes[1], dist=dist, distortion_model=model)
    return cam.validate(where=str(path))


def find_intrinsics(root: Path) -> Path | None:
    """The calibration file of an image folder: the first of :data:`INTRINSICS_NAMES` in ``root`` (None: none)."""
    for name in INTRINSICS_NAMES:
        if (Path(root) / name).is_file():
            return Path(root) / name
    return None


def list_images(root: Path) -> list[Path]:
    """The ``.png`` / ``.jpg`` files of a folder (not searched recursively), sorted by name: the frames of an
    ``images`` data set, in order."""
    return sorted(p for p in Path(root).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def folder_format(root: Path) -> str:
    """The layout of a data set folder: ``ycbv`` (``classes.txt`` and ``data/`` or ``data_syn/``), ``bop``
    (``scene_camera.json`` in it or in a scene folder) or ``images``."""
    root = Path(root)
    if (root / "classes.txt").is_file() and ((root / "data").is_dir() or (root / "data_syn").is_dir()):
        return "ycbv"
    if (root / "scene_camera.json").is_file() or any(
        (p / "scene_camera.json").is_file() for p in root.iterdir() if p.is_dir()
    ):
        return "bop"
    return "images"


class ImagesFrameSource(FrameSource):
    """A folder of ``.png`` / ``.jpg`` images (sorted by name) sharing one intrinsics YAML.

    Args:
        root: image folder (not searched recursively).
        intrinsics: intrinsics YAML; default: the first of :data:`INTRINSICS_NAMES` in ``root``
            (``intrinsics.yaml``, then ROS's ``ost.yaml``, ...).

    Raises:
        DataError: no folder, no image in it, or no calibration file (see :func:`load_intrinsics` for a bad one).
    """

    def __init__(self, root: Path, intrinsics: Path | None = None) -> None:
        self.root = _require_dir(Path(root), "images root")
        found = find_intrinsics(self.root) if intrinsics is None else Path(intrinsics)
        if found is None:
            raise DataError(
                f"{self.root}: no calibration file (expected one of {', '.join(INTRINSICS_NAMES)} in the folder, "
                "or frames.intrinsics in the manifest)"
            )
        self.intrinsics = found
        self.camera = load_intrinsics(self.intrinsics)
        self._paths = list_images(self.root)
        if not self._paths:
            raise DataError(f"{self.root}: no .png/.jpg images")
        self._warned_size = False

    def __iter__(self) -> Iterator[Frame]:
        for index, path in enumerate(self._paths):
            data = _read_bytes(path)
            size = image_size(data)
            if size is not None and size != (self.camera.width, self.camera.height) and not self._warned_size:
                log.warning(
                    "%s: image is %dx%d but %s says %dx%d (frames of another size fail as bad_image)",
                    path,
                    *size,
                    self.intrinsics,
                    self.camera.width,
                    self.camera.height,
                )
                self._warned_size = True
            yield Frame(
                frame_id=path.stem,
                scene_id=0,
                im_id=index,
                stamp_ns=index * FRAME_PERIOD_NS,
                camera=self.camera,
                image_format=image_format_of(path),
                image_data=data,
                source=str(path),
            )

    def count(self) -> int:
        return len(self._paths)

    def describe(self) -> str:
        return f"images {self.root} ({self.count()} frames, intrinsics {self.intrinsics})"


# --------------------------------------------------------------------------------------------- factory
