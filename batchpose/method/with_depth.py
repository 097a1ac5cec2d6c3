"""A registered depth image's use (``depth.enabled``, :func:`use_depth`): each pose moved along its viewing ray
onto the depth, checked against it and aligned to it (:func:`batchpose.method.depth.align_to_depth`); with
``depth.search``, each object then without a pose looked for by colour and depth (:func:`search_missing`,
:func:`batchpose.method.depth_search.search`)."""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from batchpose.core.frames import Frame, decode_depth
from batchpose.core.poses import PoseRecord
from batchpose.errors import ImageError
from batchpose.method.depth import align_to_depth
from batchpose.method.depth_search import search
from batchpose.method.objects import Objects
from batchpose.method.records import SEARCHED, pose_of
from batchpose.method.sequence import SearchPose, Sequence, Stamp, previous_pose, search_due

log = logging.getLogger("batchpose")


def use_depth(
    objects: Objects, frame: Frame, full: Frame, rgb: np.ndarray, records: list[PoseRecord], sequence: Sequence
) -> None:
    """``depth.enabled``: check each found pose against the depth image of ``full`` (the frame as read;
    ``frame`` is it at the working size) and align it to the depth. Tracks keep following the RGB poses. A
    pose the depth contradicts becomes pnp_failed; one the ICP cannot align keeps its ray alignment (or stays
    as it was), with the reason in ``reason``; a low-confidence pose (``min_confidence``) the ICP aligns is
    reported ok. With ``depth.search``, an object then without a pose is looked for by colour and depth."""
    dc = objects.conf.depth
    usable = [r for r in records if r.obj_name in objects.models and objects.renderer is not None]
    todo = [r for r in usable if r.ok or r.status == "low_confidence"]
    if not todo and not (dc.search and any(r.status in SEARCHED for r in usable)):
        return
    t0 = time.perf_counter()
    try:
        depth_m = _depth_image(frame, full)
    except ImageError as e:
        log.warning("%s: depth image not used: %s", frame.frame_id, e)
        for rec in todo:
            rec.reason = f"depth image not used ({e}): RGB pose"
        return
    if depth_m is None:  # the frame has no depth image (estimate_frame only calls this for one that has)
        return
    t_decode = (time.perf_counter() - t0) / max(len(todo), 1)
    contradicted = _align(objects, frame, depth_m, todo, t_decode)
    for rec in [r for r in usable if r.status in SEARCHED] if dc.search else []:
        if objects.tracking() and not search_due(sequence, sequence.found, rec.obj_name, frame, objects.conf.track):
            continue
        t0 = time.perf_counter()
        why = "the depth contradicted the RGB pose" if rec.obj_name in contradicted else "no SIFT pose"
        search_missing(objects, rec, frame, rgb, depth_m, why, sequence)
        rec.timings["depth"] = rec.timings.get("depth", 0.0) + time.perf_counter() - t0


def _depth_image(frame: Frame, full: Frame) -> np.ndarray | None:
    """The depth image (H, W) float metres of ``full`` at ``frame``'s (working) size; None without one."""
    depth_m = decode_depth(full)
    if depth_m is not None and depth_m.shape != (frame.camera.height, frame.camera.width):  # max_image_side_px
        depth_m = cv2.resize(depth_m, (frame.camera.width, frame.camera.height), interpolation=cv2.INTER_NEAREST)
    return depth_m


def _align(objects: Objects, frame: Frame, depth_m: np.ndarray, todo: list[PoseRecord], t_decode: float) -> set[str]:
    """Check and align each pose of ``todo`` to the depth; the names of those the depth contradicts."""
    dc, contradicted = objects.conf.depth, set()
    # Every level-th pixel and the camera that sees exactly those. Renders stay at the frame's size
    # (subsampled alike): a renderer changes GL context with the image size, which costs ~0.1 s.
    level = dc.level
    depth = np.ascontiguousarray(depth_m[::level, ::level])
    K = frame.camera.K.copy()
    K[:2] /= level
    for rec in todo:
        t0 = time.perf_counter()
        name = rec.obj_name
        fit = align_to_depth(
            pose_of(rec),
            depth,
            lambda T, name=name: objects.render(name, T, frame.camera)[1][::level, ::level],
            K,
            objects.surface(name),
            objects.models[name].diameter_m,
            dc,
        )
        if fit.contradicted:
            rec.status, rec.reason = "pnp_failed", fit.reason
            contradicted.add(name)
        elif fit.aligned:
            rec.cam_from_model = fit.cam_from_model
            if not rec.ok:
                rec.status, rec.reason = "ok", f"RGB confidence {rec.confidence:.2f}, aligned to the depth image"
        elif rec.ok and fit.ray_m:
            rec.cam_from_model = fit.cam_from_model
            rec.reason = (
                f"moved {100 * fit.ray_m:+.1f} cm along the viewing ray to the depth; not aligned: {fit.reason}"
            )
        elif rec.ok:
            rec.reason = f"depth not used: {fit.reason}: RGB pose"
        rec.timings["depth"] = t_decode + time.perf_counter() - t0
    return contradicted


def search_missing(
    objects: Objects, rec: PoseRecord, frame: Frame, rgb: np.ndarray, depth: np.ndarray, why: str, sequence: Sequence
) -> None:
    """``depth.search`` for one object without a pose (:func:`batchpose.method.depth_search.search`), starting
    from its pose in the previous frame of a tracked ``sequence``; ``why`` it has none goes into the reason of
    a pose found."""
    name, cam = rec.obj_name, frame.camera
    previous = previous_pose(sequence.found, name, frame, objects.conf.track.max_gap_s) if objects.tracking() else None
    found = search(
        rgb,
        depth,
        cam.K,
        objects.libraries[name],
        objects.silhouettes(name),
        objects.surface(name),
        objects.flips(name),
        objects.models[name].diameter_m,
        lambda T: objects.render(name, T, cam),
        objects.conf.depth,
        previous,
    )
    if found is None:
        sequence.found.pop(name, None)
        return
    sequence.found[name] = SearchPose(Stamp.of(frame), found.cam_from_model)
    rec.status, rec.cam_from_model = "ok", found.cam_from_model
    rec.confidence = 0.5 * found.visible * (1.0 - found.see_through)
    how = "followed from the previous frame's" if found.followed else "found by the"
    rec.reason = (
        f"{how} depth search ({why}): {100 * found.visible:.0f}% of it seen at its surface, "
        f"colour log-odds {found.colour:.1f}, texture match {found.match:.2f}"
    )
