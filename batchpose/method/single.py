"""A full estimate of every object in one RGB image, without memory of other frames (:func:`estimate_image`).

For each object: the matching passes (:func:`batchpose.method.passes.find_passes`: whole frame, fine pass,
locator) -> refinement of the hypotheses -> plausibility -> the alternatives and planar checks -> polish ->
confidence (:func:`estimate_object`). Then the objects not found, or found weakly, are matched again against
their second library (:func:`retry_library`), and estimated again from keypoints detected at a lower contrast
threshold (:func:`retry`); the estimator gives the same retries to an object whose pose the verification
score rejects (:func:`retry_rejected`).
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

from batchpose.core.frames import Camera, ObjectPose
from batchpose.core.poses import PoseRecord
from batchpose.errors import BatchposeError
from batchpose.method import presence
from batchpose.method.features import detect_shapes, to_gray
from batchpose.method.gnc_pnp import PnpResult, pose_spread
from batchpose.method.hypotheses import alternative, planar_mirror, polish, refine
from batchpose.method.objects import Objects
from batchpose.method.passes import best, find_passes
from batchpose.method.records import NOT_FOUND, Replaced, confidence, pose_of
from batchpose.method.shot import Keypoints, LazyLab, Shot, check_image

#: ``max_pose_spread`` measures the pose's spread over every this-many-th of the mesh's surface samples.
SPREAD_POINT_STRIDE = 8


def estimate_image(
    objects: Objects,
    rgb: np.ndarray,
    camera: Camera,
    obj_names: list[str],
    gt: tuple[ObjectPose, ...] = (),
    frame_id: str = "image",
    quick: frozenset[str] = frozenset(),
    no_retry: frozenset[str] = frozenset(),
    replaced: Replaced | None = None,
) -> list[PoseRecord]:
    """Estimate every object in ``obj_names`` in one RGB image (see
    :meth:`batchpose.method.estimator.PoseEstimator.estimate_image` for the arguments).

    Args:
        replaced: filled with the retries' replacements of ok poses (the weak-pose check's fallback).

    Raises:
        ImageError / CameraError: the image or calibration is unusable.
    """
    camera.validate(frame_id)
    check_image(rgb, frame_id)
    for name in obj_names:
        if name not in objects.libraries:
            raise BatchposeError(f"{frame_id}: no template library for object {name!r}")
    shot, keys, t_sift = look(objects, rgb, camera, frame_id, gt)
    if replaced is not None:
        shot.replaced = replaced
    t0 = time.perf_counter()
    ask_joint(objects, shot, keys)
    t_presence = time.perf_counter() - t0
    records = []
    for name in obj_names:
        rec = absent(objects, shot, name, keys) or estimate_object(objects, shot, name, keys, name in quick)
        rec.timings["sift"] = t_sift
        rec.timings["presence"] = t_presence  # (like SIFT, the frame's lookup: every pair records it)
        records.append(rec)
    gone = frozenset(r.obj_name for r in records if r.status == "absent")
    retries(objects, shot, records, keys, quick | no_retry | gone)
    return records


def look(objects: Objects, rgb: np.ndarray, camera: Camera, frame_id: str, gt: tuple[ObjectPose, ...]):
    """The image's :class:`Shot` and its whole-frame keypoints, and the seconds SIFT took."""
    conf = objects.conf
    t0 = time.perf_counter()
    gray = to_gray(rgb)
    xy_q, desc_q, shapes_q = detect_shapes(gray, conf.features, sift=objects.sift)
    t_sift = time.perf_counter() - t0
    keys = Keypoints(xy_q, desc_q, shapes_q, objects=objects)
    checks = conf.planar_spread > 0 or conf.alternatives > 0
    gt_by_name = {p.obj_name: p.cam_from_model for p in gt}
    return Shot(gray, camera, frame_id, gt_by_name, LazyLab(rgb, gray) if checks else None), keys, t_sift


def has_retries(objects: Objects, name: str) -> bool:
    """Whether an object has a retry to be given: a second library, or ``features.retry_contrast_threshold``."""
    return name in objects.retry_libraries or objects.conf.features.retry_contrast_threshold > 0


def retry_rejected(
    objects: Objects, rgb: np.ndarray, camera: Camera, frame_id: str, gt, records: list[PoseRecord], names
) -> None:
    """``retry_rejected``: the objects ``names``, whose ok poses the verification score rejected, given the
    retries of an object not found (:func:`retries`) from the image's keypoints,
    detected again. The caller scores what they find."""
    shot, keys, t_sift = look(objects, rgb, camera, frame_id, gt)
    skip = frozenset(r.obj_name for r in records) - frozenset(names)
    for r in records:
        if r.obj_name in names:
            r.timings["sift"] = r.timings.get("sift", 0.0) + t_sift / len(names)
    retries(objects, shot, records, keys, skip)


def retries(objects: Objects, shot: Shot, records: list[PoseRecord], keys: Keypoints, skip) -> None:
    """The retries, in order, of the objects not found or found weakly (not those in ``skip``): the second
    library (:func:`retry_library`), then keypoints at the lower contrast threshold (:func:`retry`)."""
    retry_library(objects, shot, records, keys, skip)
    if objects.conf.features.retry_contrast_threshold > 0:
        retry(objects, shot, records, skip)


def absent(objects: Objects, shot: Shot, name: str, keys: Keypoints) -> PoseRecord | None:
    """``match.presence_votes``: the object's ``absent`` record when the frame keypoints that count for it
    agree on no location with that many votes (:mod:`batchpose.method.presence`); None when it may be there
    (or the check is off)."""
    need = objects.conf.match.presence_votes
    if need <= 0:
        return None
    t0 = time.perf_counter()
    votes = presence_votes(objects, shot, name, keys)
    if votes >= need:
        return None
    rec = PoseRecord(shot.frame_id, name, "absent", obj_id=objects.obj_id(name))
    rec.reason = f"{votes} keypoints agree on where it would be, need {need} (match.presence_votes)"
    rec.timings["match"] = time.perf_counter() - t0
    return rec


def ask_joint(objects: Objects, shot: Shot, keys: Keypoints) -> None:
    """With the presence check on, the frame keypoints' query of the joint index into ``shot`` (once)."""
    if objects.conf.match.presence_votes <= 0 or shot.joint is not None:
        return
    joint = objects.joint_index
    if joint is None or keys.shapes is None or len(keys.desc) == 0:
        return
    shot.joint = presence.joint_nearest(joint, keys.desc, objects.conf.match)
    shot.joint_desc = keys.desc


def presence_votes(objects: Objects, shot: Shot, name: str, keys: Keypoints) -> int:
    """The most frame keypoints that count for the object and agree on one location of it (0: none)."""
    ask_joint(objects, shot, keys)
    joint = objects.joint_index
    if joint is None or shot.joint is None or keys.shapes is None or keys.desc is not shot.joint_desc:
        return 0
    cam = shot.camera
    return presence.votes(joint, shot.joint, name, objects.libraries[name], keys.xy, keys.shapes, keys.desc,
                          objects.conf.match, cam.width, cam.height)  # fmt: skip


def to_retry(objects: Objects, records: list[PoseRecord], skip) -> list[int]:
    """The records a retry estimates again: not found, or ok with a confidence below ``verify_below``; not
    the objects in ``skip``."""
    weak = objects.conf.verify_below
    return [
        i
        for i, r in enumerate(records)
        if (r.status in NOT_FOUND or (r.ok and r.confidence < weak)) and r.obj_name not in skip
    ]


def keep_better(shot: Shot, records: list[PoseRecord], i: int, rec: PoseRecord, how: str) -> None:
    """A retry's record ``rec`` in place of ``records[i]`` when it is ok and more confident (the reason says
    it was ``how`` found; a replaced ok pose goes into ``shot.replaced``); either way, the pair's time is both
    attempts'."""
    first = records[i]
    for k, v in first.timings.items():
        rec.timings[k] = rec.timings.get(k, 0.0) + v
    if rec.ok and (not first.ok or rec.confidence > first.confidence):
        rec.reason = f"found with {how}"
        records[i] = rec
        if first.ok:
            shot.replaced[id(rec)] = (rec, first)
    else:
        first.timings = rec.timings


def retry_library(objects: Objects, shot: Shot, records: list[PoseRecord], keys: Keypoints, skip) -> None:
    """``render.retry_shading``: each object a full estimate did not find, or found only weakly, estimated
    once more from the same keypoints against its second library (:attr:`Objects.retry_objects`); the new
    record is kept when it is ok and more confident. Not the objects in ``skip``."""
    other = objects.retry_objects
    if other is None:
        return
    todo = [i for i in to_retry(objects, records, skip) if records[i].obj_name in other.libraries]
    if not todo:
        return
    # The shot's library queries are the first library's: this one asks its own.
    again = dataclasses.replace(shot, nearest={}, joint=None, joint_desc=None)
    for i in todo:
        rec = estimate_object(other, again, records[i].obj_name, keys)
        keep_better(shot, records, i, rec, f"the {objects.conf.render.retry_shading} templates")


def retry(objects: Objects, shot: Shot, records: list[PoseRecord], skip: frozenset[str]) -> None:
    """``features.retry_contrast_threshold``: estimate each object a full estimate did not find, or found
    only weakly (confidence below ``verify_below``), once more from keypoints detected at the lower
    contrast threshold; keep the new record when it is ok and more confident. With
    ``features.retry_sigma``, the objects still not found or weak get a second retry the same way, from
    keypoints detected at that SIFT σ. Not the objects in ``skip``."""
    fc = objects.conf.features
    for sigma in dict.fromkeys((fc.sigma, fc.retry_sigma)):  # a retry_sigma equal to sigma: one retry
        if sigma > 0 and not _retry_once(objects, shot, records, skip, sigma):
            return


def _retry_once(objects: Objects, shot: Shot, records: list[PoseRecord], skip, sigma: float) -> bool:
    """One retry stage (see :func:`retry`); False when no object needed it."""
    todo = to_retry(objects, records, skip)
    if not todo:
        return False
    t0 = time.perf_counter()
    fc = objects.conf.features
    sift = objects.retry_sift(sigma)
    xy, desc, shapes = detect_shapes(shot.gray, fc, sift=sift)
    keys = Keypoints(xy, desc, shapes, objects=objects)
    t_sift = (time.perf_counter() - t0) / len(todo)
    how = f"contrast {fc.retry_contrast_threshold:g}" + ("" if sigma == fc.sigma else f", sigma {sigma:g}")
    for i in todo:
        rec = estimate_object(objects, shot, records[i].obj_name, keys, sift=sift)
        rec.timings["sift"] = rec.timings.get("sift", 0.0) + t_sift
        keep_better(shot, records, i, rec, f"keypoints at {how}")
    return True


def estimate_object(
    objects: Objects, shot: Shot, name: str, keys: Keypoints, quick: bool = False, sift=None
) -> PoseRecord:
    """One object's full estimate from the keypoint set ``keys``: the matching passes, the refinement of
    their hypotheses, plausibility, the frame's checks, polish and confidence. ``quick``: the whole-frame
    pass's first stage only, no fine pass or locator, one refinement hypothesis. ``sift``: the detector of
    the fine pass's crops (default: the base one)."""
    conf, camera = objects.conf, shot.camera
    gt_pose = shot.gt.get(name)
    if conf.method == "tp_ub":
        return tp_ub(objects, name, gt_pose, shot.frame_id)
    timings: dict[str, float] = {}
    rec = PoseRecord(shot.frame_id, name, "ok", obj_id=objects.obj_id(name), timings=timings)
    roi = roi_mask(objects, name, keys.xy, camera, gt_pose)
    passes, strong = find_passes(objects, shot, name, keys, roi, gt_pose, timings, quick, sift)
    res, corr, xy_k, desc_k = best(passes, conf)
    rec.n_matches = len(corr)
    rec.templates = corr.templates
    x_used, X_used = corr.x, corr.X
    tried: list = []
    if objects.can_refine(name):
        t0 = time.perf_counter()
        refined = refine(objects, name, passes, camera, xy_k, desc_k, strong, tried)
        timings["refine"] = time.perf_counter() - t0
        if refined is not None:
            res, x_used, X_used = refined.result, refined.x, refined.X
    if res is None:
        rec.status = "too_few_matches"
        rec.reason = f"{len(corr)} matches after the ratio test, need {conf.min_matches}"
        return rec
    rec.status, rec.reason = res.status, res.reason
    if res.status == "ok" and (why := objects.implausible(name, pose_of(res), camera)):
        rec.status, rec.reason = "pnp_failed", why
    if not rec.status == "ok":
        return rec
    if (other := alternative(objects, shot.lab, name, res, tried, camera, timings)) is not None:
        (res, x_used, X_used), rec.reason = other
    if (mirrored := planar_mirror(objects, shot.lab, name, res, x_used, X_used, camera, timings)) is not None:
        res, rec.reason = mirrored
    distinct = len(np.unique(np.round(x_used[res.inliers]).astype(np.int64), axis=0))
    if distinct < conf.min_distinct_inliers:
        rec.status = "pnp_failed"
        rec.reason = f"its {res.n_inliers} inliers lie on {distinct} distinct pixels, need {conf.min_distinct_inliers}"
        return rec
    _finish(objects, shot, rec, res, x_used, X_used)
    return rec


def _finish(
    objects: Objects, shot: Shot, rec: PoseRecord, res: PnpResult, x_used: np.ndarray, X_used: np.ndarray
) -> None:
    """The chosen pose into ``rec``: polished (``refine.polish``), with its inliers, residual and confidence;
    low_confidence under ``min_confidence`` or over ``max_pose_spread``."""
    conf, name = objects.conf, rec.obj_name
    rec.cam_from_model = res.cam_from_model
    if conf.refine.polish and objects.can_render(name):
        t0 = time.perf_counter()
        rec.cam_from_model = polish(objects, name, shot.gray, pose_of(res), shot.camera)
        rec.timings["refine"] = rec.timings.get("refine", 0.0) + time.perf_counter() - t0
    rec.n_inliers = res.n_inliers
    rec.median_residual_px = res.median_residual_px
    rec.inliers_px = x_used[res.inliers]
    rec.confidence = confidence(rec.n_inliers, rec.median_residual_px, conf)
    if rec.confidence < conf.min_confidence:
        rec.status = "low_confidence"
        rec.reason = (
            f"confidence {rec.confidence:.2f} below estimator.min_confidence {conf.min_confidence:g} "
            f"({rec.n_inliers} inliers, median residual {rec.median_residual_px:.1f} px)"
        )
    elif conf.max_pose_spread > 0 and name in objects.models:
        points = objects.surface(name).points[::SPREAD_POINT_STRIDE]
        spread = pose_spread(pose_of(res), X_used[res.inliers], shot.camera.K, points) / objects.models[name].diameter_m
        if spread > conf.max_pose_spread:
            rec.status = "low_confidence"
            rec.reason = (
                f"its {rec.n_inliers} inliers pin the pose only to {spread:.2f} of the object's diameter "
                f"per pixel of noise, over estimator.max_pose_spread {conf.max_pose_spread:g}"
            )


def roi_mask(objects: Objects, name: str, xy_q: np.ndarray, camera: Camera, cam_from_model: np.ndarray | None):
    """``match.roi: gt_box`` (an evaluation oracle): the keypoints inside the ground-truth box grown by
    ``match.roi_margin_px``; None without the oracle."""
    if objects.conf.match.roi == "none":
        return None
    if cam_from_model is None:
        return np.zeros(len(xy_q), bool)  # oracle ROI without ground truth: object not annotated
    pts = objects.libraries[name].pts3d.astype(np.float64)
    rvec = cv2.Rodrigues(cam_from_model[:3, :3])[0]
    proj, _ = cv2.projectPoints(pts, rvec, cam_from_model[:3, 3], camera.K, camera.dist)
    proj = proj.reshape(-1, 2)
    m = objects.conf.match.roi_margin_px
    lo, hi = proj.min(axis=0) - m, proj.max(axis=0) + m
    return np.all((xy_q >= lo) & (xy_q <= hi), axis=1)


def tp_ub(objects: Objects, name: str, gt_pose: np.ndarray | None, frame_id: str) -> PoseRecord:
    """Template upper bound: the template rotation closest to ground truth, ground-truth translation."""
    lib = objects.libraries[name]
    if gt_pose is None:
        return PoseRecord(frame_id, name, "error", "tp_ub needs ground truth for this object")
    Rs = np.stack([lib.cam_from_model(i)[:3, :3] for i in range(lib.n_views)])
    cos = (np.einsum("nij,ij->n", Rs, gt_pose[:3, :3]) - 1.0) / 2.0
    best_view = int(np.argmax(cos))
    T = np.eye(4)
    T[:3, :3] = Rs[best_view]
    T[:3, 3] = gt_pose[:3, 3]
    return PoseRecord(frame_id, name, "ok", cam_from_model=T, confidence=1.0, templates=(best_view,))
