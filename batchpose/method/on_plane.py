"""The plane search's step (``plane.enabled``, :func:`use_plane`): each object without a pose, or with a weak
untracked one, looked for on the surface the confidently found objects rest on
(:mod:`batchpose.method.plane`)."""

from __future__ import annotations

import time

import numpy as np

from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.objects import Objects
from batchpose.method.plane import Placed, search_plane
from batchpose.method.records import NOT_FOUND, SEARCHED, pose_of
from batchpose.method.sequence import SearchPose, Sequence, Stamp, previous_pose, search_due
from batchpose.method.support import Plane, one_object_plane, resting_faces, support_plane

#: What the plane search replaced, by the record's status before it.
_REPLACED = {
    "ok": "a weak SIFT pose",
    "low_confidence": "a low-confidence SIFT pose",
    "conflict": "a SIFT pose on another object's pixels",
    "absent": "no SIFT evidence of it",
}


def use_plane(objects: Objects, frame: Frame, rgb: np.ndarray, records: list[PoseRecord], sequence: Sequence) -> None:
    """``plane.enabled``: look for each object without a pose on the surface the confidently found ones rest
    on, starting from its placement in the previous frame of a tracked ``sequence``."""
    pc = objects.conf.plane
    if objects.renderer is None:
        return
    tracking = objects.tracking()
    lost = [
        r
        for r in records
        if (
            r.status in (SEARCHED if pc.search_absent else NOT_FOUND)
            or (r.ok and not r.tracked and r.confidence < pc.min_confidence)
        )
        and r.obj_name in objects.models
        and (not tracking or search_due(sequence, sequence.placed, r.obj_name, frame, objects.conf.track))
    ]
    if not lost:
        return
    t0 = time.perf_counter()
    found = {
        r.obj_name: (pose_of(r), objects.models[r.obj_name].mesh.convex_hull)
        for r in records
        if r.ok and r.confidence >= pc.min_confidence and r.obj_name in objects.models
    }
    if len(found) == 1:
        ((name, (T, hull)),) = found.items()
        plane = one_object_plane(name, T, hull, resting_faces(objects.stable_faces(name), pc.min_stable), pc)
    else:
        plane = support_plane(found, pc, {name: objects.stable_faces(name)[0] for name in found})
    if plane is None:
        for rec in lost:
            sequence.placed.pop(rec.obj_name, None)
        return
    covered, nearest = _explained(objects, frame.camera, records, {id(r) for r in lost})
    shared = (time.perf_counter() - t0) / len(lost)
    for rec in lost:
        t0 = time.perf_counter()
        name = rec.obj_name
        previous = previous_pose(sequence.placed, name, frame, objects.conf.track.max_gap_s) if tracking else None
        placed = search_plane(
            rgb,
            frame.camera.K,
            plane,
            objects.target(name),
            covered,
            nearest,
            lambda T, K, w, h, name=name: objects.render(name, T, Camera(K, w, h)),
            pc,
            previous,
            rec.cam_from_model if rec.ok else None,
        )
        rec.timings["plane"] = shared + time.perf_counter() - t0
        if placed is None:
            sequence.placed.pop(name, None)
            continue
        sequence.placed[name] = SearchPose(Stamp.of(frame), placed.cam_from_model)
        _place(rec, placed, plane)


def _explained(objects: Objects, cam: Camera, records: list[PoseRecord], searched: set[int]):
    """The pixels every pose reported (but the ``searched`` records') explains: ((H, W) bool covered, (H, W)
    float32 nearest rendered depth, inf where none)."""
    covered = np.zeros((cam.height, cam.width), bool)
    nearest = np.full((cam.height, cam.width), np.inf, np.float32)
    for r in records:
        if not r.ok or id(r) in searched or r.obj_name not in objects.models:
            continue
        depth = objects.render(r.obj_name, pose_of(r), cam)[1]
        covered |= depth > 0
        nearest = np.where(depth > 0, np.minimum(nearest, depth), nearest)
    return covered, nearest


def _place(rec: PoseRecord, placed: Placed, plane: Plane) -> None:
    """The placement into ``rec``: pose, confidence 0.25 (1 + texture match) and the reason."""
    why = _REPLACED.get(rec.status, "no SIFT pose")
    how = "followed from the previous frame's" if placed.followed else "found by the"
    rec.status, rec.cam_from_model = "ok", placed.cam_from_model
    rec.confidence = 0.25 * (1.0 + placed.match)
    rec.reason = (
        f"{how} plane search ({why}): resting on the surface under {', '.join(plane.objects)}, "
        f"{100 * placed.visible:.0f}% of it unhidden, colour log-odds {placed.colour:.1f}, "
        f"texture match {placed.match:.2f}, contrast {placed.contrast:.1f}"
        + ("" if placed.edge == 0 or not np.isfinite(placed.edge) else f", edges {placed.edge:.2f}")
    )
