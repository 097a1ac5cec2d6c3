"""The weak-pose check (``verify_below``, :func:`verify_weak`): a full estimate under 0.5 confidence must look
like the frame where it puts the object, or it is not reported."""

from __future__ import annotations

import time

import cv2
import numpy as np

from batchpose.core.frames import Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.appearance import texture_match
from batchpose.method.objects import Objects
from batchpose.method.records import Replaced, pose_of

#: ``verify_below`` judges a weak pose over at least this many of its rendered pixels.
VERIFY_MIN_PX = 30


def verify_weak(objects: Objects, frame: Frame, rgb: np.ndarray, records: list[PoseRecord], replaced: Replaced) -> None:
    """``verify_below``: a weak full estimate whose rendered mesh does not look like the frame where it puts
    the object (texture match below ``verify_min_match`` over the pixels no other reported pose hides)
    becomes low_confidence; so does one whose mesh shows under 30 px in the frame at all (beyond the
    renderer's far plane, off the image), which nothing can confirm. A retry's pose that fails gives way to
    the pose it replaced (``replaced``) when that one passes."""
    conf = objects.conf
    if objects.renderer is None:
        return
    weak = [
        r for r in records
        if r.ok and not r.tracked and r.confidence < conf.verify_below and r.obj_name in objects.models
    ]  # fmt: skip
    if not weak:
        return
    cam = frame.camera
    t0 = time.perf_counter()
    shown = {
        r.obj_name: objects.render(r.obj_name, pose_of(r), cam)
        for r in records
        if r.ok and r.obj_name in objects.models
    }
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)
    shared = (time.perf_counter() - t0) / len(weak)
    for rec in weak:
        t0 = time.perf_counter()
        why = looks_wrong(objects, rec, shown[rec.obj_name], shown, lab)
        failed = rec
        # A retry's more confident pose that fails: the pose it replaced, checked in turn, when that one passes
        while why is not None and id(failed) in replaced:
            failed = replaced[id(failed)][1]
            view = objects.render(failed.obj_name, pose_of(failed), cam)
            if looks_wrong(objects, failed, view, shown, lab) is None:
                failed.timings = rec.timings
                failed.reason = (
                    f"{failed.reason + '; ' if failed.reason else ''}kept over a retry's more confident pose: {why}"
                )
                records[next(i for i, r in enumerate(records) if r is rec)] = failed
                shown[rec.obj_name] = view
                rec, why = failed, None
        if why is not None:
            rec.status, rec.reason = "low_confidence", why
        rec.timings["refine"] = rec.timings.get("refine", 0.0) + shared + time.perf_counter() - t0


def hidden_by(front_depth: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of a render (``depth``, metres, 0 off the mesh) that another render
    (``front_depth``) covers over 1 cm nearer."""
    return (front_depth > 0) & (front_depth < depth - 0.01)


def looks_wrong(objects: Objects, rec: PoseRecord, view, shown: dict, lab: np.ndarray) -> str | None:
    """Why the weak pose ``rec``, whose mesh renders as ``view`` (rgb, depth), fails ``verify_below``'s texture
    check (over the pixels the other poses in ``shown`` do not hide); None when it passes."""
    conf = objects.conf
    ren_rgb, depth = view
    seen = depth > 0
    weak_why = f"weak pose (confidence {rec.confidence:.2f} < verify_below {conf.verify_below:g})"
    if seen.sum() < VERIFY_MIN_PX:  # beyond the renderer's far plane, or off the image
        return (
            f"{weak_why} that shows {int(seen.sum())} px of the mesh in the frame (object centre "
            f"{pose_of(rec)[2, 3]:.1f} m away): too little to check it against"
        )
    for name, (_, other) in shown.items():
        if name != rec.obj_name:
            seen &= ~hidden_by(other, depth)
    if seen.sum() < VERIFY_MIN_PX:  # mostly hidden by reported poses: nothing to judge it by
        return None
    match = texture_match(lab[seen], ren_rgb[seen])
    if match < conf.verify_min_match:
        return (
            f"{weak_why} whose mesh does not look like the frame there (texture match "
            f"{match:.2f} < {conf.verify_min_match:g})"
        )
    return None
