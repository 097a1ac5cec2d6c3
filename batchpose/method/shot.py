"""One image under estimation (:class:`Shot`) and a keypoint set of it (:class:`Keypoints`).

A shot is made per image and dropped after it: what the estimates of its objects share — the gray image,
the Lab image the checks compare renders with (made on first use), the library queries of its keypoint
sets, and the retries' replaced records the weak-pose check may give back.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from batchpose.core.frames import Camera
from batchpose.errors import ImageError
from batchpose.method.correspondences import flann_index, nearest_with_rival
from batchpose.method.objects import Objects
from batchpose.method.presence import JointNearest, as_object
from batchpose.method.records import Replaced
from batchpose.method.score import FrameEdges


def check_image(rgb: np.ndarray, where: str = "image") -> None:
    """Raise ImageError for an empty image or one with no contrast at all (e.g. all black)."""
    if rgb is None or rgb.size == 0 or rgb.ndim != 3 or rgb.shape[2] != 3:
        shape = None if rgb is None else rgb.shape
        raise ImageError(f"{where}: expected an (H, W, 3) RGB image, got shape {shape}")
    if int(rgb.max()) == int(rgb.min()):
        raise ImageError(f"{where}: image is blank (every pixel is {int(rgb.max())})")


class LazyLab:
    """An RGB image's Lab conversion, made on first use, and its gray image."""

    def __init__(self, rgb: np.ndarray, gray: np.ndarray) -> None:
        self._rgb, self.gray = rgb, gray
        self._lab: np.ndarray | None = None

    @functools.cached_property
    def edges(self) -> FrameEdges:
        """The image as the verification score compares renders with it (made once, on first use)."""
        return FrameEdges(self._rgb)

    def get(self) -> np.ndarray:
        if self._lab is None:
            self._lab = cv2.cvtColor(self._rgb, cv2.COLOR_RGB2LAB)
        return self._lab


@dataclass
class Keypoints:
    """A keypoint set of the image (the whole frame's, a retry's or a fine pass's crop).

    Attributes:
        xy: (N, 2) float32 pixels; desc: (N, 128) float32 descriptors.
        shapes: (N, 2) each keypoint's size and angle (None: not kept, e.g. a fine pass's).
        objects: what :attr:`index` is built for (None: no index).
    """

    xy: np.ndarray
    desc: np.ndarray
    shapes: np.ndarray | None = None
    objects: Objects | None = field(default=None, repr=False)
    _index: object = field(default=None, init=False, repr=False)
    _built: bool = field(default=False, init=False, repr=False)

    @property
    def index(self):
        """The FLANN index over ``desc`` for ``match.direction: template_to_query`` (else None), built when
        first asked: a frame whose objects are all ``absent`` never needs it."""
        if not self._built:
            self._index = None if self.objects is None else query_index(self.desc, self.objects)
            self._built = True
        return self._index


def query_index(desc: np.ndarray, objects: Objects):
    """The FLANN index over a keypoint set's descriptors that ``template_to_query`` matching searches."""
    return flann_index(desc, objects.conf.match) if objects.conf.match.direction == "template_to_query" else None


@dataclass
class Shot:
    """One image being estimated, and what its objects' estimates share.

    Attributes:
        gray: (H, W) uint8; camera: its calibration; frame_id: for records and messages.
        gt: obj_name -> (4, 4) ground-truth pose (only the ``gt_box`` oracle and ``tp_ub`` use it).
        lab: the image in Lab for the alternatives and planar checks (None when both are off).
        nearest: obj_name -> [(descriptors, :func:`nearest_with_rival` of them)]: each keypoint set's library
            query, asked once by the view vote and the locator.
        replaced: the retries' replacements (:data:`batchpose.method.records.Replaced`).
        joint: the whole frame's keypoints' query of the joint index (:mod:`batchpose.method.presence`),
            asked once for every object's presence check; joint_desc: those keypoints' descriptors.
    """

    gray: np.ndarray
    camera: Camera
    frame_id: str
    gt: dict[str, np.ndarray]
    lab: LazyLab | None
    nearest: dict[str, list[tuple[np.ndarray, tuple]]] = field(default_factory=dict)
    replaced: Replaced = field(default_factory=dict)
    joint: JointNearest | None = None
    joint_desc: np.ndarray | None = None


def nearest_templates(objects: Objects, shot: Shot, name: str, desc_q: np.ndarray) -> tuple | None:
    """:func:`nearest_with_rival` of ``desc_q`` into the object's library, computed once per keypoint set
    of the image (the view vote and the locator ask for the same; each query is independent, so the
    result is the same); with ``match.joint_vote``, the presence check's joint query of those keypoints
    instead, as the object's (:func:`~batchpose.method.presence.as_object`). None without keypoints or
    library."""
    if len(desc_q) == 0 or objects.library_index(name) is None:
        return None
    joint = objects.joint_index if objects.conf.match.joint_vote and desc_q is shot.joint_desc else None
    if joint is not None and shot.joint is not None and name in joint.names:
        return as_object(joint, shot.joint, name)  # ``match.joint_vote``
    seen = shot.nearest.setdefault(name, [])
    for desc, found in seen:
        if desc is desc_q:
            return found
    found = nearest_with_rival(desc_q, objects.library_index(name), objects.libraries[name], objects.conf.match)
    seen.append((desc_q, found))  # holding the array: its identity cannot pass to another one
    return found
