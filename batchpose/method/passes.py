"""The matching passes of one object in one image, each solved: 2D-3D pairs -> weights -> RANSAC, GNC, LM.

1. the whole-frame pass (:func:`coarse`): the frame keypoints' view vote, template -> frame matching of the
   voted views (the first ``match.first_views`` first), the solve;
2. when that pose is not strong (:func:`strong`), the fine pass (:func:`fine_pass`): SIFT again in the
   object's box (:func:`object_box`), upsampled, matched and solved;
3. when the best pose so far is weak (:func:`weak`), the locator (:func:`located_passes`): a fine pass
   wherever the keypoints' Hough votes put the object.

:func:`find_passes` runs them in that order; :func:`best` picks by support.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import cv2
import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera
from batchpose.method.correspondences import (
    Correspondences,
    locate,
    match_query_to_template,
    match_template_to_query,
    template_to_query_candidates,
    top_k_pairs,
    vote_views,
)
from batchpose.method.features import detect
from batchpose.method.gnc_pnp import PnpResult, solve_pose
from batchpose.method.objects import Objects
from batchpose.method.records import confidence
from batchpose.method.shot import Keypoints, Shot, nearest_templates

Box = tuple[int, int, int, int]


class Pass(NamedTuple):
    """One matching pass: its solved pose (None: too few pairs), its pairs, and the keypoints it matched
    (which the refinement's guided matching reuses)."""

    result: PnpResult | None
    pairs: Correspondences
    xy: np.ndarray
    desc: np.ndarray


def find_passes(
    objects: Objects,
    shot: Shot,
    name: str,
    keys: Keypoints,
    roi: np.ndarray | None,
    gt_pose: np.ndarray | None,
    timings: dict[str, float],
    quick: bool = False,
    sift=None,
) -> tuple[list[Pass], bool]:
    """The whole-frame pass, then (with ``fine.enabled``, unless it is strong or ``quick``) the fine pass
    and the locator's passes: (the passes, latest first; whether the whole-frame pass is strong)."""
    conf = objects.conf
    res, corr = coarse(objects, shot, name, keys, roi, timings, quick)
    passes = [Pass(res, corr, keys.xy, keys.desc)]
    is_strong = quick or strong(objects, name, res, shot.camera)
    if conf.fine.enabled and not is_strong:
        t0 = time.perf_counter()
        box = object_box(objects, name, res, corr, shot.camera, gt_pose)
        fine = None if box is None else fine_pass(objects, shot, name, box, sift=sift)
        if fine is not None:
            passes.insert(0, fine)
        if conf.fine.locate and conf.match.roi == "none" and weak(objects, name, best(passes, conf)[0], shot.camera):
            # The pose so far is weak: search again where the keypoints' votes put the object.
            for located in located_passes(objects, shot, name, keys, [] if box is None else [box], sift):
                passes.insert(0, located)
        timings["fine"] = time.perf_counter() - t0
    return passes, is_strong


def coarse(objects: Objects, shot: Shot, name: str, keys: Keypoints, roi, timings: dict[str, float], quick=False):
    """The whole-frame pass: (result, pairs). With ``match.first_views``, the most-voted views are
    matched first and the rest only when they give no strong pose (and the estimate is not ``quick``)."""
    conf, lib, camera = objects.conf, objects.libraries[name], shot.camera
    first, n_views = conf.match.first_views, conf.match.prefilter_views
    t0 = time.perf_counter()
    staged = conf.match.direction == "template_to_query" and 0 < first < n_views < lib.n_views
    if not staged:
        corr = match(objects, shot, name, keys, roi, n_views)
        timings["match"] = time.perf_counter() - t0
        return solve(objects, name, corr, camera, timings), corr
    views = voted_views(objects, shot, name, keys.desc, roi, n_views)
    assert views is not None  # staged: fewer views voted for than the library has
    cand = template_to_query_candidates(keys.index, lib, conf.match, roi, views[:first])
    corr = top_k_pairs(cand, lib, keys.xy, conf.match)
    timings["match"] = time.perf_counter() - t0
    res = solve(objects, name, corr, camera, timings)
    if quick or strong(objects, name, res, camera):
        return res, corr
    t0 = time.perf_counter()
    more = template_to_query_candidates(keys.index, lib, conf.match, roi, views[first:])
    corr = top_k_pairs(tuple(np.concatenate(p) for p in zip(cand, more, strict=True)), lib, keys.xy, conf.match)
    timings["match"] += time.perf_counter() - t0
    return solve(objects, name, corr, camera, timings), corr


def match(objects: Objects, shot: Shot, name: str, keys: Keypoints, roi, prefilter_views: int) -> Correspondences:
    """2D-3D pairs between the keypoints and the object's library (SPEC §2)."""
    conf, lib = objects.conf, objects.libraries[name]
    if conf.match.direction == "template_to_query":
        views = voted_views(objects, shot, name, keys.desc, roi, prefilter_views)
        return match_template_to_query(keys.xy, keys.index, lib, conf.match, candidate_mask=roi, views=views)
    sel = np.ones(len(keys.xy), bool) if roi is None else roi
    return match_query_to_template(keys.xy[sel], keys.desc[sel], objects.library_index(name), lib, conf.match)


def voted_views(objects: Objects, shot: Shot, name: str, desc_q, roi, n_views: int) -> np.ndarray | None:
    """The ``n_views`` views the keypoints vote for (None: test every view)."""
    lib = objects.libraries[name]
    if not n_views or n_views >= lib.n_views:
        return None
    # Shared with the locator, which runs without an ROI only; under one, query just the ROI's keypoints.
    nearest = nearest_templates(objects, shot, name, desc_q) if roi is None else None
    return vote_views(desc_q, objects.library_index(name), lib, n_views, objects.conf.match, roi, nearest)


def solve(objects: Objects, name: str, corr: Correspondences, camera: Camera, timings: dict[str, float]):
    """Weights + RANSAC + GNC + LM on the pairs; None when there are too few pairs."""
    if len(corr) < objects.conf.min_matches:
        return None
    t0 = time.perf_counter()
    w = objects.weights(name, corr.X)
    timings["weights"] = timings.get("weights", 0.0) + time.perf_counter() - t0
    res = solve_pose(corr.x, corr.X, camera.K, camera.dist, w, objects.conf.gnc)
    for k, v in res.timings.items():
        timings[k] = timings.get(k, 0.0) + v
    return res


def best(passes: list[Pass], conf: EstimatorConfig) -> Pass:
    """The pass with the most support (the earliest, i.e. the latest fine pass, on ties)."""
    return max(passes, key=lambda p: p[0].support(conf.support_px) if p[0] else -1)


def strong(objects: Objects, name: str, res, camera: Camera) -> bool:
    """True when ``res`` has at least ``strong_inliers`` inliers at a plausible pose."""
    n = objects.conf.strong_inliers
    if res is None or res.status != "ok" or not 0 < n <= res.n_inliers:
        return False
    return not objects.implausible(name, res.cam_from_model, camera)


def weak(objects: Objects, name: str, res, camera: Camera) -> bool:
    """True when ``res`` (the best pass so far) is no pose, an implausible one or one below
    ``fine.locate_below`` confidence."""
    if res is None or res.status != "ok" or objects.implausible(name, res.cam_from_model, camera):
        return True
    return confidence(res.n_inliers, res.median_residual_px, objects.conf) < objects.conf.fine.locate_below


def object_box(objects: Objects, name: str, res, corr: Correspondences, camera: Camera, gt_pose) -> Box | None:
    """The object's image box (x0, y0, x1, y1), grown by the fine margins and clipped; None if unknown.

    From the ground-truth pose with the ``gt_box`` oracle, else from the coarse pose (with its inliers),
    else around the densest cluster of matched keypoints.
    """
    conf = objects.conf
    fc, pts = conf.fine, None
    coarse_ok = res is not None and res.status == "ok" and not objects.implausible(name, res.cam_from_model, camera)
    pose = gt_pose if conf.match.roi == "gt_box" else (res.cam_from_model if coarse_ok else None)
    if pose is not None:
        X = objects.libraries[name].pts3d.astype(np.float64)
        z = X @ pose[2, :3] + pose[2, 3]
        if np.all(z > 1e-3):
            proj, _ = cv2.projectPoints(X, cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], camera.K, camera.dist)
            pts = proj.reshape(-1, 2)
            if coarse_ok and pose is not gt_pose:
                pts = np.vstack([pts, corr.x[res.inliers]])
    if pts is None:
        if conf.match.roi == "gt_box" or len(corr) < conf.min_matches:
            return None
        d = np.linalg.norm(corr.x[:, None] - corr.x[None], axis=2)
        centre = corr.x[np.argmax((d < fc.cluster_radius_px).sum(axis=1))]
        pts = corr.x[np.linalg.norm(corr.x - centre, axis=1) < 2 * fc.cluster_radius_px]
    return grown_box(pts.min(axis=0), pts.max(axis=0), fc, camera)


def grown_box(lo, hi, fc, camera: Camera) -> Box | None:
    """The box from ``lo`` to ``hi`` (x, y), grown by the fine margins and clipped to the image; None when
    under 16 px."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    grow = fc.margin * (hi - lo) + fc.margin_px
    x0, y0 = np.floor(np.maximum(lo - grow, 0)).astype(int)
    x1, y1 = np.ceil(np.minimum(hi + grow, [camera.width, camera.height])).astype(int)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def overlap(a: Box, b: Box) -> float:
    """Intersection over union."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - w * h
    return w * h / union


def fine_keypoints(gray: np.ndarray, box: Box, conf: EstimatorConfig, sift=None):
    """SIFT inside ``box`` (x0, y0, x1, y1), upsampled by ``conf.fine.upsample`` (capped by max_side_px).

    Returns:
        xy (N, 2) float32 in full-image pixels and descriptors (N, 128) float32.
    """
    x0, y0, x1, y1 = box
    crop = gray[y0:y1, x0:x1]
    s = max(1.0, min(conf.fine.upsample, conf.fine.max_side_px / max(crop.shape)))
    if s > 1.0:
        crop = cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)
    xy, desc = detect(crop, conf.features, sift=sift)
    xy = (xy + 0.5) / s - 0.5 + np.array([x0, y0], np.float32)
    return xy.astype(np.float32), desc


def fine_pass(objects: Objects, shot: Shot, name: str, box: Box, extra: Correspondences | None = None, sift=None):
    """Match again inside ``box``, upsampled, plus the ``extra`` pairs: a :class:`Pass` or None (also when
    the box covers more than ``fine.max_box_fraction`` of the image)."""
    x0, y0, x1, y1 = box
    if (x1 - x0) * (y1 - y0) > objects.conf.fine.max_box_fraction * shot.camera.width * shot.camera.height:
        return None
    xy_f, desc_f = fine_keypoints(shot.gray, box, objects.conf, sift or objects.sift)
    keys = Keypoints(xy_f, desc_f, None, objects=objects)
    corr_f = match(objects, shot, name, keys, None, objects.conf.fine.prefilter_views)
    if extra is not None and len(extra):
        corr_f = Correspondences(
            np.vstack([corr_f.x, extra.x]),
            np.vstack([corr_f.X, extra.X]),
            np.concatenate([corr_f.view_ids, extra.view_ids]),
            corr_f.templates,
            corr_f.n_candidates + extra.n_candidates,
        )
    res_f = solve(objects, name, corr_f, shot.camera, {})
    if res_f is None:
        return None
    return Pass(res_f, corr_f, xy_f, desc_f)


def located_passes(objects: Objects, shot: Shot, name: str, keys: Keypoints, searched: list[Box], sift=None):
    """The locator: a fine pass (with the votes' pairs, ``fine.locate_pairs``) in each place the keypoints'
    Hough votes put the object, unless it mostly overlaps a box ``searched`` already; the passes found."""
    conf, camera = objects.conf, shot.camera
    assert keys.shapes is not None  # the whole image's keypoints keep their sizes and angles
    out = []
    for found in locate(
        keys.xy,
        keys.shapes,
        keys.desc,
        objects.library_index(name),
        objects.libraries[name],
        conf.match,
        camera.width,
        camera.height,
        ratio=conf.fine.locate_ratio,
        angle_bin_deg=conf.fine.locate_angle_deg,
        min_votes=conf.fine.locate_votes,
        peaks=conf.fine.locate_peaks,
        nearest=nearest_templates(objects, shot, name, keys.desc),
    ):
        c, half = np.asarray(found.centre_xy), 0.5 * found.size_px  # a square of the object's diameter
        hough = grown_box(c - half, c + half, conf.fine, camera)
        if hough is None or any(overlap(hough, b) >= 0.5 for b in searched):
            continue
        searched.append(hough)
        located = fine_pass(objects, shot, name, hough, found.pairs if conf.fine.locate_pairs else None, sift)
        if located is not None:
            out.append(located)
    return out
