"""The tracked estimate of a frame (:func:`estimate_tracked`): follow what the previous frame found, estimate
the rest afresh, seed tracks for the next frame.

1. **follow** (:func:`_follow_tracks`): each live track of the :class:`~batchpose.method.sequence.Sequence`
   is flowed into this frame (all in one call, minus points hidden behind the other tracked objects),
   pulled onto the render every ``track.render_every`` frames, and refreshed (:func:`refresh`) when old,
   thinned out or turned;
2. **lost and hidden** (:func:`_estimate_rest`): the objects not followed get a full estimate, or a quick one
   while they stay lost; one mostly behind tracked objects at its last confident pose is ``hidden``
   (:func:`hidden_lost`);
3. **seed** (:func:`_seed_tracks`): each confident fresh pose whose render looks like the frame
   (:func:`looks_alike`) starts a track (:func:`seed_track`).

The sequence is rebuilt as it goes: tracks, lost counts and last confident poses for the next frame, and
this frame as the previous one.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.appearance import texture_match
from batchpose.method.features import to_gray
from batchpose.method.objects import Objects
from batchpose.method.records import Replaced, confidence, pose_of
from batchpose.method.score import FrameEdges, compare
from batchpose.method.sequence import PreviousFrame, Sequence, Stamp, follows
from batchpose.method.shot import check_image
from batchpose.method.single import estimate_image
from batchpose.method.track import Track, anchor_to_render, covered, follow_all, occluders, seed, view_turn_deg
from batchpose.method.verify import VERIFY_MIN_PX

log = logging.getLogger("batchpose")


def estimate_tracked(
    objects: Objects, rgb: np.ndarray, frame: Frame, obj_names: list[str], sequence: Sequence, replaced: Replaced
) -> list[PoseRecord]:
    """:func:`batchpose.method.single.estimate_image` that follows the ``sequence``'s live tracks instead
    (see :mod:`batchpose.method.track`), and leaves in it what the next frame follows."""
    camera, tc = frame.camera, objects.conf.track
    camera.validate(frame.frame_id)
    check_image(rgb, frame.frame_id)
    t0 = time.perf_counter()
    gray = to_gray(rgb)
    t_gray = time.perf_counter() - t0
    before = _hand_over(sequence, frame, tc.max_gap_s)
    look: FrameEdges | None = None  # the frame as the checks see it (``track.min_match``), made on first use

    def frame_look() -> FrameEdges | None:
        nonlocal look
        if tc.min_match > 0 and look is None:
            look = FrameEdges(rgb)
        return look

    out = _follow_tracks(objects, gray, frame, obj_names, before, sequence, frame_look, t_gray)
    fresh = _estimate_rest(objects, rgb, frame, obj_names, before, out, replaced)
    _remember(objects, obj_names, out, before, sequence)
    _seed_tracks(objects, gray, camera, obj_names, out, fresh, sequence, frame_look)
    sequence.previous = PreviousFrame(Stamp.of(frame), gray, camera.dist)
    return [out[n] for n in obj_names]


def _hand_over(sequence: Sequence, frame: Frame, max_gap_s: float) -> Sequence:
    """What the previous frame left in ``sequence`` for this one: its tracks, lost counts, last confident
    poses and itself, when this frame follows it (:func:`batchpose.method.sequence.follows`), else nothing.
    Those fields of ``sequence`` are emptied, to be rebuilt by this frame (and stay empty if it fails)."""
    before = Sequence()
    if follows(sequence.previous, frame, max_gap_s):
        before.tracks, before.lost, before.last = sequence.tracks, sequence.lost, sequence.last
        before.previous = sequence.previous
    sequence.tracks, sequence.lost, sequence.last, sequence.previous = {}, {}, {}, None
    return before


def _remember(objects: Objects, obj_names: list[str], out: dict[str, PoseRecord], before: Sequence, sequence: Sequence):
    """Count each object not followed as lost one frame longer, and keep each one's last confident pose."""
    tc = objects.conf.track
    for n in obj_names:
        if n not in sequence.tracks:
            sequence.lost[n] = before.lost.get(n, 0) + 1
        if out[n].ok and out[n].confidence >= tc.min_confidence:
            sequence.last[n] = pose_of(out[n])
        elif n in before.last:
            sequence.last[n] = before.last[n]


def _follow_tracks(
    objects: Objects, gray, frame: Frame, obj_names: list[str], before: Sequence, sequence: Sequence, frame_look, t_gray
) -> dict[str, PoseRecord]:
    """Follow ``before``'s tracks of ``obj_names`` into this frame (``gray``): a tracked record of each one
    followed, its moved track in ``sequence``."""
    camera, tc, tracks = frame.camera, objects.conf.track, before.tracks
    out: dict[str, PoseRecord] = {}
    due = [n for n in obj_names if n in tracks and not (tc.redetect_every and tracks[n].age >= tc.redetect_every)]
    if not due:
        return out
    assert before.previous is not None  # tracks come with the frame they were left in
    t0 = time.perf_counter()
    hidden = hiders(objects, [tracks[n].cam_from_model for n in due], due, camera)
    moved_all = follow_all(before.previous.gray, gray, [tracks[n] for n in due], camera.K, camera.dist, tc, hidden)
    followed = dict(zip(due, moved_all, strict=True))
    t_flow = (time.perf_counter() - t0) / max(len(due), 1)  # one flow call for all: each pays its share
    for k, name in enumerate(due):
        tr = tracks[name]
        t0 = time.perf_counter() - t_flow
        res = followed[name]
        if res is None:
            log.debug("%s: track of %s lost, estimating afresh", frame.frame_id, name)
            continue
        res, t_refresh = _keep_up(objects, name, gray, res, camera, hidden[k] if hidden else (), frame_look)
        if res is None:
            log.debug("%s: track of %s no longer matches the mesh, estimating afresh", frame.frame_id, name)
            continue
        sequence.tracks[name] = moved = res.track
        if name in before.lost and moved.age < tc.lost_full_every:
            sequence.lost[name] = before.lost[name] + 1  # a young track: still counted as lost (see below)
        out[name] = PoseRecord(
            frame.frame_id,
            name,
            "ok",
            obj_id=objects.obj_id(name),
            cam_from_model=moved.cam_from_model,
            confidence=min(tr.confidence, confidence(res.n_inliers, res.median_residual_px, objects.conf)),
            n_matches=len(tr.xy),
            n_inliers=res.n_inliers,
            median_residual_px=res.median_residual_px,
            inliers_px=moved.xy,
            timings={"track": t_gray + time.perf_counter() - t0 - t_refresh, "seed": t_refresh},
            tracked=True,
        )
    return out


def _keep_up(objects: Objects, name: str, gray, res, camera: Camera, hidden, frame_look):
    """A followed track pulled onto the render (every ``track.render_every`` frames) and refreshed when due
    (``track.refresh_every`` frames old, thinned below ``reseed_fraction``, or turned ``refresh_turn_deg``):
    (the track result, None when the refresh finds the mesh no longer there; seconds the refresh took)."""
    tc = objects.conf.track
    if tc.render_every and res.track.age % tc.render_every == 0:
        rendered = objects.render_gray(name, res.track.cam_from_model, camera)
        anchored = anchor_to_render(gray, rendered, res.track, camera.K, camera.dist, tc)
        res = anchored if anchored is not None else res
    old_age, thinning = res.track.age, len(res.track.xy) < tc.reseed_fraction * res.track.n_seeded
    key = res.track.key_pose
    turned = tc.refresh_turn_deg > 0 and key is not None
    turned = turned and view_turn_deg(key, res.track.cam_from_model) > tc.refresh_turn_deg
    if not (tc.refresh_every and (old_age >= tc.refresh_every or thinning or turned)):
        return res, 0.0
    t1 = time.perf_counter()
    res = refresh(objects, name, gray, res, camera, hidden, frame_look())
    return res, time.perf_counter() - t1


def _estimate_rest(
    objects: Objects, rgb, frame: Frame, obj_names: list[str], before: Sequence, out: dict, replaced: Replaced
) -> list[PoseRecord]:
    """The objects not followed: ``hidden`` records for those due a quick estimate that tracked objects
    cover, a fresh estimate of the others (quick while they stay lost); all into ``out``. Returns the fresh
    records."""
    tc, lost = objects.conf.track, before.lost
    rest = [n for n in obj_names if n not in out]
    # An object still lost since the previous frame gets the full estimate only every
    # ``lost_full_every``-th frame, a quick one in between. It counts as lost until a track of it lives
    # that many frames: a mostly hidden object's estimates start tracks that die a frame later, and each
    # would otherwise make the next estimate a full one.
    quick = frozenset(n for n in rest if lost.get(n, 0) % tc.lost_full_every)
    skipped, hidden = hidden_lost(objects, rest, quick, out, before.last, frame)
    for rec in skipped:
        out[rec.obj_name] = rec
    rest = [n for n in rest if n not in out]
    if tc.hidden_quick:
        quick |= hidden
    no_retry = frozenset() if tc.hidden_retry else hidden
    fresh = []
    if rest:
        fresh = estimate_image(
            objects,
            rgb,
            frame.camera,
            rest,
            frame.gt,
            frame.frame_id,
            quick=quick,
            no_retry=no_retry,
            replaced=replaced,
        )
    for rec in fresh:
        out[rec.obj_name] = rec
    return fresh


def _seed_tracks(
    objects: Objects, gray, camera: Camera, obj_names, out: dict, fresh: list, sequence: Sequence, frame_look
):
    """Start a track in ``sequence`` from each fresh pose confident enough (``track.min_confidence``); no
    corners where an object found in this frame is in front of it."""
    seeds = [r for r in fresh if r.ok and r.confidence >= objects.conf.track.min_confidence]
    if not seeds:
        return
    placed = [n for n in obj_names if out[n].ok]
    t0 = time.perf_counter()
    hidden_now = hiders(objects, [pose_of(out[n]) for n in placed], placed, camera)
    t_hidden = (time.perf_counter() - t0) / len(seeds)
    for rec in seeds:
        t0 = time.perf_counter() - t_hidden
        in_front = hidden_now[placed.index(rec.obj_name)] if hidden_now else ()
        tr = seed_track(objects, rec.obj_name, gray, rec, camera, in_front, frame_look())
        rec.timings["seed"] = time.perf_counter() - t0
        if tr is not None:
            sequence.tracks[rec.obj_name] = tr


def seed_track(
    objects: Objects, name: str, gray: np.ndarray, rec: PoseRecord, camera: Camera, hidden=(), look=None
) -> Track | None:
    """A new track from a confident full estimate (None when the object shows too few corners, or, given
    the frame ``look`` (:class:`~batchpose.method.score.FrameEdges`), when the mesh at that pose does not look
    like the frame:
    :func:`looks_alike`); no corners where ``hidden`` (:func:`hiders`) puts something in front of it."""
    if objects.models.get(name) is None:
        return None
    T = pose_of(rec)
    rgb, depth = objects.render(name, T, camera)
    if look is not None and not looks_alike(objects, look, rgb, depth, hidden):
        return None
    tc, rendered = objects.conf.track, to_gray(rgb)
    xy, X = seed(gray, T, rendered, depth, camera.K, camera.dist, tc, hidden)
    thin = len(xy) < tc.min_points and 0 < tc.thin_margin_px < tc.window_px // 2  # seed nearer the outline
    if thin:
        xy, X = seed(gray, T, rendered, depth, camera.K, camera.dist, tc, hidden, margin_px=tc.thin_margin_px)
    if len(xy) < tc.min_points:
        return None
    return Track(xy, X, T, len(xy), rec.confidence, key_gray=gray, key_xy=xy.copy(), key_pose=T.copy(), thin=thin)


def looks_alike(objects: Objects, frame: FrameEdges, rgb: np.ndarray, depth: np.ndarray, hidden=()) -> bool:
    """``track.min_match``: the mesh rendered at a pose (``rgb``, ``depth``) looks like the ``frame`` over its
    silhouette, less what ``hidden`` puts in front of it: its colours match (texture match), or, with
    ``verified_tracks``, its verification score passes (:func:`~batchpose.method.score.compare`). True when
    too little of it shows to judge."""
    conf = objects.conf
    if conf.track.min_match <= 0:
        return True
    seen = depth > 0
    for occ in hidden:
        seen &= ~(occ.mask & (depth > occ.near_m))
    if seen.sum() < VERIFY_MIN_PX or texture_match(frame.lab[seen], rgb[seen]) >= conf.track.min_match:
        return True
    if not (conf.verified_tracks and conf.min_verification > 0):
        return False
    c = compare(frame, rgb, depth, seen)
    return c is not None and c.score() >= conf.min_verification


def refresh(objects: Objects, name: str, gray: np.ndarray, res, camera: Camera, hidden=(), look=None):
    """A new keyframe at the tracked pose, checked against the mesh: the mesh rendered there must look like
    the frame (:func:`looks_alike`, given the frame ``look``), then the points are pulled onto
    it (:func:`batchpose.method.track.anchor_to_render`; a thin track's depth held as a followed pose's is,
    ``track.depth_prior``) and corners are seeded afresh at the pulled pose. None
    when the frame no longer matches the mesh at that pose (the track has drifted or is occluded)."""
    rgb, depth = objects.render(name, res.track.cam_from_model, camera)
    if look is not None and not looks_alike(objects, look, rgb, depth, hidden):
        return None
    anchored = anchor_to_render(gray, to_gray(rgb), res.track, camera.K, camera.dist, objects.conf.track)
    if anchored is None:
        return None
    rec = PoseRecord("", name, "ok", cam_from_model=anchored.track.cam_from_model, confidence=res.track.confidence)
    fresh = seed_track(objects, name, gray, rec, camera, hidden)
    if fresh is None:
        return None
    anchored.track = fresh
    return anchored


def hidden_lost(objects: Objects, rest: list[str], quick, out: dict[str, PoseRecord], last: dict, frame: Frame):
    """``track.hidden_above``: which of the objects ``rest`` to estimate the objects tracked in this frame
    (``out``) cover enough from in front at their last confident poses (``last``): a ``hidden`` record
    for each due a ``quick`` estimate, and the set of the others (which ``track.hidden_quick`` makes quick)."""
    tc, camera = objects.conf.track, frame.camera
    recs: list[PoseRecord] = []
    hidden: set[str] = set()
    tracked = [n for n, r in out.items() if r.tracked and n in objects.models]
    if tc.hidden_above >= 1 or not tracked:
        return recs, frozenset()
    others = [(objects.hull(n), pose_of(out[n])) for n in tracked]
    for name in rest:
        if name not in last or name not in objects.models:
            continue
        t0 = time.perf_counter()
        frac, each = covered(objects.hull(name), last[name], others, camera.K, camera.dist, camera.width, camera.height)
        if frac < tc.hidden_above:
            continue
        if name not in quick:
            hidden.add(name)
            continue
        by = ", ".join(n for n, f in sorted(zip(tracked, each, strict=True), key=lambda x: -x[1]) if f > 0)
        recs.append(
            PoseRecord(
                frame.frame_id,
                name,
                "hidden",
                f"{100 * frac:.0f}% of it is behind {by} at its last pose; not estimated",
                obj_id=objects.obj_id(name),
                timings={"track": time.perf_counter() - t0},
            )
        )
    return recs, frozenset(hidden)


def hiders(objects: Objects, poses: list[np.ndarray], names: list[str], camera: Camera) -> list[list] | None:
    """``track.occlusion_margin_px``: what may hide each of the objects at ``poses``
    (:func:`batchpose.method.track.occluders`); None when off or with fewer than two objects."""
    margin = objects.conf.track.occlusion_margin_px
    if margin < 0 or len(poses) < 2 or any(n not in objects.models for n in names):
        return None
    hulls = [objects.hull(n) for n in names]
    return occluders(hulls, poses, camera.K, camera.dist, camera.width, camera.height, margin)
