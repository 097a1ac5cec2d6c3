"""Carrying a confident pose into the neighbouring frames where the object was missed (``carry.*``; the
``carry`` stage, :mod:`batchpose.stages.carry`, decides which poses go where).

A recorded log can be read in either order, and the tracker (:mod:`batchpose.method.track`) does not care
which: :func:`carry` seeds a track at a confident pose of one frame (:func:`~batchpose.method.tracked.seed_track`)
and follows it frame by frame through the frames it is given, the next ones or the previous ones in reverse
order. Every step is checked as tracking checks a refreshed track, then as a weak full estimate is checked:

1. **follow** (:func:`~batchpose.method.track.follow_all`): optical flow with the forward-backward check, the
   pose solved by LM with trimming; the track is lost under ``track.min_points`` / ``min_fraction`` points;
2. **refresh** (:func:`~batchpose.method.tracked.refresh`): the mesh rendered at the followed pose must look
   like the frame (``track.min_match``), the points are pulled onto the render, corners are seeded afresh
   there (at least ``track.min_points``): each carried frame is a new keyframe, so nothing drifts;
3. **confidence**: min(the source pose's, :func:`~batchpose.method.records.confidence` of the pulled
   points), at least ``min_confidence``;
4. **the weak-pose check** (``verify_below``, :func:`~batchpose.method.verify.looks_wrong`) when it is
   under ``verify_below``, over the pixels the frame's other poses do not hide.

In the frames the caller names (``scored``: where the estimate has a weak pose, ``carry.over_weak``) the
carried pose also gets its verification score (:mod:`batchpose.method.score`), for the caller to compare.

The first step that fails ends the carry: the frame keeps its record, and so do the frames beyond it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field

import numpy as np

from batchpose.core.frames import Frame, decode_image
from batchpose.core.poses import PoseRecord
from batchpose.method.estimator import working_size
from batchpose.method.features import to_gray
from batchpose.method.objects import Objects
from batchpose.method.records import confidence, pose_of, to_full_size
from batchpose.method.score import FrameEdges, comparisons
from batchpose.method.track import Track, follow_all
from batchpose.method.tracked import hiders, refresh, seed_track
from batchpose.method.verify import looks_wrong


@dataclass
class View:
    """One frame as a carry sees it.

    Attributes:
        frame: the frame at its working size (``max_image_side_px``; its camera scaled with it).
        rgb: (H, W, 3) uint8 RGB at that size; gray: (H, W) uint8.
        scale: (2,) x and y factors from the full frame to the working size.
        others: obj_name -> (4, 4) cam_from_model of the other objects' ok poses in the frame (what may hide
            the carried object, and what the weak-pose check leaves out).
    """

    frame: Frame
    rgb: np.ndarray
    gray: np.ndarray
    scale: np.ndarray
    others: dict[str, np.ndarray] = field(default_factory=dict)

    @functools.cached_property
    def look(self) -> FrameEdges:
        """The frame as the checks see it (its Lab image, its edges; made on first use)."""
        return FrameEdges(self.rgb)


def view_of(frame: Frame, others: dict[str, np.ndarray], max_side_px: int) -> View:
    """The frame decoded at its working size (raises the frame's :class:`~batchpose.errors.ImageError` or
    :class:`~batchpose.errors.CameraError` when it cannot be used)."""
    small, rgb, scale = working_size(frame, decode_image(frame), max_side_px)
    small.camera.validate(frame.frame_id)
    return View(small, rgb, to_gray(rgb), scale, others)


@dataclass
class Carried:
    """What :func:`carry` found: one ok record per frame it reached (``records[k]`` in ``views[k + 1]``), in
    the full frame's pixels, and why it stopped ("" when it reached the last view or ``max_steps``)."""

    records: list[PoseRecord]
    stopped: str


def carry(
    objects: Objects,
    name: str,
    views: list[View],
    start: PoseRecord,
    max_steps: int,
    scored: frozenset[str] = frozenset(),
) -> Carried:
    """Follow ``start``, an ok pose of ``name`` in ``views[0]``, through ``views[1:]`` in the order given
    (the frames after it, or the frames before it in reverse order) as far as the checks of the module
    docstring pass, at most ``max_steps`` frames, and on from a carried pose only while it is at least
    ``carry.min_confidence`` confident.

    Args:
        objects: the estimator's objects; needs the object's mesh and a renderer.
        name: the object carried.
        views: consecutive frames (:func:`view_of`), each the next of the one before in carrying order.
        start: its pose in ``views[0]`` (cam_from_model at any image size: poses are metric).
        max_steps: most frames carried into.
        scored: ids of the frames whose carried pose gets its verification score.
    """
    if not objects.can_render(name) or len(views) < 2:
        return Carried([], "no mesh to follow" if len(views) > 1 else "")
    t0 = time.perf_counter()
    first = views[0]
    hidden = _hidden(objects, name, pose_of(start), first)
    look = first.look if objects.conf.track.min_match > 0 else None
    track = seed_track(objects, name, first.gray, start, first.frame.camera, hidden, look)
    if track is None:
        why = "too few corners, or the mesh does not look like the frame there"
        return Carried([], f"no track could start at {first.frame.frame_id}'s pose ({why})")
    t_seed = time.perf_counter() - t0
    out: list[PoseRecord] = []
    for prev, view in zip(views[:max_steps], views[1 : max_steps + 1], strict=False):
        rec, track, why = _step(objects, name, prev, view, track, view.frame.frame_id in scored)
        if rec is None or track is None:
            return Carried(out, f"{view.frame.frame_id}: {why}")
        rec.timings["seed"] = rec.timings.get("seed", 0.0) + t_seed
        t_seed = 0.0
        out.append(rec)
        floor = objects.conf.carry.min_confidence
        if rec.confidence < floor:
            why = f"carried pose {rec.confidence:.2f} confident, under carry.min_confidence {floor:g}: no further"
            return Carried(out, f"{view.frame.frame_id}: {why}")
    return Carried(out, "")


def _step(
    objects: Objects, name: str, prev: View, view: View, track: Track, score: bool = False
) -> tuple[PoseRecord | None, Track | None, str]:
    """One frame of a carry: the track followed from ``prev`` into ``view`` and checked (module docstring):
    (the frame's record, with its verification score if ``score``; the track to follow on; "") or (None,
    None, why it failed)."""
    conf, cam = objects.conf, view.frame.camera
    t0 = time.perf_counter()
    behind = _hidden(objects, name, track.cam_from_model, prev)
    res = follow_all(prev.gray, view.gray, [track], cam.K, cam.dist, conf.track, [behind])
    t_follow = time.perf_counter() - t0
    if res[0] is None:
        return None, None, "track lost (too few points followed)"
    t0 = time.perf_counter()
    hidden = _hidden(objects, name, res[0].track.cam_from_model, view)
    moved = refresh(objects, name, view.gray, res[0], cam, hidden, view.look if conf.track.min_match > 0 else None)
    if moved is None:
        return None, None, "the mesh at the followed pose does not look like the frame, or too few corners there"
    c = min(track.confidence, confidence(moved.n_inliers, moved.median_residual_px, conf))
    rec = PoseRecord(
        view.frame.frame_id,
        name,
        "ok",
        scene_id=view.frame.scene_id,
        im_id=view.frame.im_id,
        stamp_ns=view.frame.stamp_ns,
        obj_id=objects.obj_id(name),
        cam_from_model=moved.track.cam_from_model,
        confidence=c,
        n_matches=len(track.xy),
        n_inliers=moved.n_inliers,
        median_residual_px=moved.median_residual_px,
        inliers_px=moved.track.xy.astype(float),
        tracked=True,
        carried=True,
    )
    why = _weak(objects, rec, view)
    rec.timings = {"track": t_follow, "seed": time.perf_counter() - t0}
    if why is not None:
        return None, None, why
    if score:
        t0 = time.perf_counter()
        others = [PoseRecord(view.frame.frame_id, n, "ok", cam_from_model=T) for n, T in view.others.items()]
        found = comparisons(objects, view.frame, view.rgb, [rec, *others], [rec])[id(rec)]
        rec.verification = found.score() if found is not None else 0.0
        rec.timings["verify"] = time.perf_counter() - t0
    if not np.allclose(view.scale, 1.0):
        to_full_size([rec], view.scale)
    return rec, moved.track, ""


def _weak(objects: Objects, rec: PoseRecord, view: View) -> str | None:
    """Why a carried pose fails the checks a full estimate's pose passes (``min_confidence``, then
    ``verify_below``'s texture check over the pixels the frame's other poses do not hide); None when it
    passes."""
    conf = objects.conf
    if rec.confidence < conf.min_confidence:
        return f"carried pose {rec.confidence:.2f} confident, under min_confidence {conf.min_confidence:g}"
    if conf.verify_below <= 0 or rec.confidence >= conf.verify_below:
        return None
    cam = view.frame.camera
    shown = {n: objects.render(n, T, cam) for n, T in view.others.items() if objects.can_render(n)}
    return looks_wrong(objects, rec, objects.render(rec.obj_name, pose_of(rec), cam), shown, view.look.lab)


def _hidden(objects: Objects, name: str, pose: np.ndarray, view: View) -> list:
    """What of the view's other poses may be in front of ``name`` at ``pose`` (:func:`hiders`'s occluders;
    empty: nothing)."""
    others = [n for n in view.others if n != name]
    found = hiders(objects, [pose, *(view.others[n] for n in others)], [name, *others], view.frame.camera)
    return [] if found is None else found[0]


def with_timings(rec: PoseRecord, before: dict[str, float]) -> PoseRecord:
    """The carried ``rec`` with the time the estimate spent on the pair before (``before``, stage -> seconds)
    added to its own."""
    timings = dict(before)
    for k, v in rec.timings.items():
        timings[k] = timings.get(k, 0.0) + v
    return dataclasses.replace(rec, timings=timings)
