"""What outlives a frame: :class:`Sequence`, the memory of the frames before this one.

Tracking (``track.*``) follows poses from one frame into the next, and the depth and plane searches start
from the pose they found in the previous frame. All of that memory is one :class:`Sequence` that the
caller owns and hands to :meth:`batchpose.method.estimator.PoseEstimator.estimate_frame` with each frame of
a sequence; a new ``Sequence()`` starts without memory. It is plain data (numpy arrays in dataclasses), so
it pickles: a batch worker can save it mid-sequence and a resumed run continues exactly where it stopped.

Whether a frame continues the sequence is one rule (:func:`is_next`): same scene and intrinsics, the next
image id (``im_id`` + ``im_step``) and at most ``track.max_gap_s`` later. Following tracks also needs the
same image size and distortion (:func:`follows`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from batchpose.config import TrackConfig
from batchpose.core.frames import Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.track import Track


@dataclass(frozen=True)
class Stamp:
    """Where a frame sits in its sequence: its scene, image id, capture time and intrinsics (3, 3)."""

    scene_id: int
    im_id: int
    stamp_ns: int
    K: np.ndarray

    @classmethod
    def of(cls, frame: Frame) -> Stamp:
        return cls(frame.scene_id, frame.im_id, frame.stamp_ns, frame.camera.K.copy())


@dataclass(frozen=True)
class PreviousFrame:
    """The frame before this one: where it sat, its (H, W) uint8 gray image and distortion coefficients."""

    stamp: Stamp
    gray: np.ndarray
    dist: np.ndarray


@dataclass(frozen=True)
class SearchPose:
    """A search's (depth or plane) pose of an object, (4, 4) cam_from_model, and the frame it was found in."""

    stamp: Stamp
    cam_from_model: np.ndarray


@dataclass
class Sequence:
    """The memory of a sequence of frames, carried from one frame to the next (see the module docstring).

    Attributes:
        tracks: obj_name -> its live track.
        lost: obj_name -> frames since it was last followed by a track that lived ``track.lost_full_every``
            frames (a lost object gets the full estimate every ``lost_full_every``-th frame, quick ones between).
        last: obj_name -> (4, 4) its last confident pose (where ``track.hidden_above`` looks for it).
        previous: the previous frame, None before the first.
        found: obj_name -> the depth search's pose in the previous frame it searched.
        placed: obj_name -> the plane search's pose in the previous frame it searched.
    """

    tracks: dict[str, Track] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)
    last: dict[str, np.ndarray] = field(default_factory=dict)
    previous: PreviousFrame | None = None
    found: dict[str, SearchPose] = field(default_factory=dict)
    placed: dict[str, SearchPose] = field(default_factory=dict)

    def drop(self, rec: PoseRecord) -> None:
        """Stop following a pose found wrong after the estimate (``rec``): its track, and its last
        confident pose and search poses when this frame set them."""
        self.tracks.pop(rec.obj_name, None)
        if self.last.get(rec.obj_name) is rec.cam_from_model:
            self.last.pop(rec.obj_name)
        for store in (self.found, self.placed):
            if rec.obj_name in store and store[rec.obj_name].cam_from_model is rec.cam_from_model:
                store.pop(rec.obj_name)

    def forget(self) -> None:
        """Forget everything: the next frame starts a new sequence (a frame that could not be read breaks
        every track)."""
        fresh = Sequence()
        for f in fields(self):
            setattr(self, f.name, getattr(fresh, f.name))


def is_next(stamp: Stamp, frame: Frame, max_gap_s: float) -> bool:
    """True when ``frame`` is the next image (``im_id`` + ``im_step``) after the frame at ``stamp`` in the
    same scene, with the same intrinsics, a short step later in time (folder data sets' stamps are
    synthetic, their ``im_id`` is not)."""
    gap_s = (frame.stamp_ns - stamp.stamp_ns) * 1e-9
    return (
        stamp.scene_id == frame.scene_id
        and frame.im_id == stamp.im_id + frame.im_step
        and np.array_equal(stamp.K, frame.camera.K)
        and 0 < gap_s <= max_gap_s
    )


def follows(previous: PreviousFrame | None, frame: Frame, max_gap_s: float) -> bool:
    """True when tracks can be followed from ``previous`` into ``frame``: :func:`is_next`, and the same
    image size and distortion coefficients."""
    if previous is None or not is_next(previous.stamp, frame, max_gap_s):
        return False
    cam = frame.camera
    return previous.gray.shape == (cam.height, cam.width) and np.array_equal(previous.dist, cam.dist)


def previous_pose(store: dict[str, SearchPose], name: str, frame: Frame, max_gap_s: float) -> np.ndarray | None:
    """A search's pose of ``name`` in the previous frame (``store``: :attr:`Sequence.found` or
    :attr:`Sequence.placed`) when ``frame`` is the next one of its sequence (:func:`is_next`); else None."""
    seen = store.get(name)
    if seen is None or not is_next(seen.stamp, frame, max_gap_s):
        return None
    return seen.cam_from_model


def search_due(sequence: Sequence, store: dict[str, SearchPose], name: str, frame: Frame, tc: TrackConfig) -> bool:
    """Whether a search (the depth search, ``store`` its :attr:`Sequence.found`; the plane search, its
    :attr:`Sequence.placed`) looks for ``name`` in this frame of a tracked sequence: when it follows a pose
    the search found, or the object is not lost; for an object lost since earlier frames only when its RGB
    estimate was a full one (every ``track.lost_full_every``-th frame), as an absent object costs seconds a
    search. Without tracking, call it not at all: every frame is searched."""
    if name not in sequence.lost or previous_pose(store, name, frame, tc.max_gap_s) is not None:
        return True
    return (sequence.lost[name] - 1) % tc.lost_full_every == 0
