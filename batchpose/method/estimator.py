"""One frame in, one pose record per target object out: SIFT -> matches -> weights -> GNC-PnP.

:class:`PoseEstimator` holds the template libraries (and their FLANN indices, built once per process).
``estimate_image`` is the library call and raises :class:`BatchposeError` on bad input;
``estimate_frame`` is the batch call and turns every failure into a record.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import cv2
import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera, Frame, ObjectPose, decode_depth, decode_image, working_camera
from batchpose.core.geometry import rotation_error_deg
from batchpose.core.poses import PoseRecord
from batchpose.errors import BatchposeError, ImageError
from batchpose.method.appearance import texture_match
from batchpose.method.correspondences import (
    Correspondences,
    flann_index,
    locate,
    match_query_to_template,
    match_template_to_query,
    nearest_with_rival,
    template_to_query_candidates,
    top_k_pairs,
    vote_views,
)
from batchpose.method.depth import Surface, align_to_depth
from batchpose.method.depth_search import Silhouettes, distinct_matches, search
from batchpose.method.features import detect, detect_shapes, make_sift, to_gray
from batchpose.method.gnc_pnp import planar_alternative, solve_pose
from batchpose.method.plane import Target, resting_faces, search_plane, stable_faces, support_plane
from batchpose.method.refine import refine_pose
from batchpose.method.templates import TemplateLibrary
from batchpose.method.track import Track, anchor_to_render, covered, follow_all, occluders, seed, view_turn_deg
from batchpose.method.weights import geom_weights, model_support, model_voxel_grid, support_to_weights

log = logging.getLogger("batchpose")
#: Statuses of an object the frame shows no pose of, which ``depth.search`` looks for.
NOT_FOUND = ("too_few_matches", "pnp_failed", "low_confidence")
#: ``verify_below`` judges a weak pose over at least this many of its rendered pixels.
VERIFY_MIN_PX = 30


def confidence(n_inliers: int, median_residual_px: float, conf: EstimatorConfig) -> float:
    """Confidence in [0, 1]: (1 - exp(-n_inliers / c_n)) * exp(-median_residual_px / c_r).

    Grows with the number of inliers (c_n = ``confidence_inliers``, 15 by default: 15 inliers give 0.63)
    and falls with their median reprojection error (c_r = ``confidence_residual_px``, 4 px).
    """
    if n_inliers <= 0 or not np.isfinite(median_residual_px):
        return 0.0
    c = (1.0 - np.exp(-n_inliers / conf.confidence_inliers)) * np.exp(-median_residual_px / conf.confidence_residual_px)
    return float(np.clip(c, 0.0, 1.0))


def check_image(rgb: np.ndarray, where: str = "image") -> None:
    """Raise ImageError for an empty image or one with no contrast at all (e.g. all black)."""
    if rgb is None or rgb.size == 0 or rgb.ndim != 3 or rgb.shape[2] != 3:
        shape = None if rgb is None else rgb.shape
        raise ImageError(f"{where}: expected an (H, W, 3) RGB image, got shape {shape}")
    if int(rgb.max()) == int(rgb.min()):
        raise ImageError(f"{where}: image is blank (every pixel is {int(rgb.max())})")


def fine_keypoints(gray: np.ndarray, box: tuple[int, int, int, int], conf: EstimatorConfig, sift=None):
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


def _grown_box(lo, hi, fc, camera: Camera) -> tuple[int, int, int, int] | None:
    """The box from ``lo`` to ``hi`` (x, y), grown by the fine margins and clipped to the image; None when
    under 16 px."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    grow = fc.margin * (hi - lo) + fc.margin_px
    x0, y0 = np.floor(np.maximum(lo - grow, 0)).astype(int)
    x1, y1 = np.ceil(np.minimum(hi + grow, [camera.width, camera.height])).astype(int)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> float:
    """Intersection over union."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - w * h
    return w * h / union


class _LazyLab:
    """An RGB image's Lab conversion, made on first use, and its gray image."""

    def __init__(self, rgb: np.ndarray, gray: np.ndarray) -> None:
        self._rgb, self._lab, self.gray = rgb, None, gray

    def get(self) -> np.ndarray:
        if self._lab is None:
            self._lab = cv2.cvtColor(self._rgb, cv2.COLOR_RGB2LAB)
        return self._lab


class PoseEstimator:
    """Estimates poses of objects whose template libraries it holds.

    Args:
        conf: estimator config.
        libraries: obj_name -> TemplateLibrary.
        obj_ids: obj_name -> numeric id for records (BOP obj_id); optional.
        models: obj_name -> ObjectModel, needed (with ``renderer``) for ``refine.enabled``.
        renderer: a :class:`batchpose.method.render.Renderer` (or anything with its ``render`` method).
    """

    def __init__(
        self,
        conf: EstimatorConfig,
        libraries: dict[str, TemplateLibrary],
        obj_ids: dict[str, int] | None = None,
        models: dict | None = None,
        renderer=None,
    ) -> None:
        self.conf = conf
        self.libraries = libraries
        self.obj_ids = obj_ids or {}
        self.models = models or {}
        self.renderer = renderer
        self._sift = make_sift(conf.features)
        self._sift_retry: dict[float, object] = {}
        self._lib_index: dict[str, object] = {}
        # This image's nearest template descriptors of a keypoint set, per object: [(descriptors, result)].
        self._nearest: dict[str, list[tuple[np.ndarray, tuple]]] = {}
        self._voxels: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._flip_cache: dict[str, list[np.ndarray]] = {}
        self._extent: dict[str, tuple[np.ndarray, float]] = {}
        self._surfaces: dict[str, Surface] = {}
        self._silhouettes: dict[str, Silhouettes] = {}
        self._targets: dict[str, Target] = {}
        self._stable: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        # The depth search's and the plane search's last pose of each object: ((scene_id, im_id, stamp_ns, K), pose).
        self._found: dict[str, tuple[tuple, np.ndarray]] = {}
        self._placed: dict[str, tuple[tuple, np.ndarray]] = {}
        self._tracks: dict[str, Track] = {}
        self._lost: dict[str, int] = {}
        self._last: dict[str, np.ndarray] = {}  # each object's last confident pose in the current sequence
        self._hulls: dict[str, np.ndarray] = {}
        self._prev: dict | None = None
        self._lab: _LazyLab | None = None  # the frame estimate_image is estimating, in Lab
        # id(retry's record) -> (that record, the ok pose it replaced): the texture check falls back to the
        # replaced pose when it rejects the replacement (the current frame's; estimate_image resets it)
        self._replaced: dict[int, tuple[PoseRecord, PoseRecord]] = {}
        # The frame as read, while estimate_frame works on a resized copy (max_image_side_px): its depth.
        self._full_frame: Frame | None = None

    # -- per-object caches -------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Build every object's library index and render each mesh once now (a batch worker does this when
        it starts) rather than in the first frame that needs them: the first render makes the GL context,
        uploads the mesh and its textures and compiles the shaders (~0.1 s an object)."""
        if self.conf.method == "tp_ub":
            return  # needs no matching
        for name in self.libraries:
            self._library_index(name)
            if self._can_render(name):
                lib = self.libraries[name]
                self._render(name, lib.cam_from_model(0), Camera(lib.K, lib.width, lib.height))

    def _library_index(self, name: str):
        if name not in self._lib_index:
            lib = self.libraries[name]
            self._lib_index[name] = flann_index(lib.desc, self.conf.match, keep_in=lib.folder)
        return self._lib_index[name]

    def _nearest_templates(self, name: str, desc_q: np.ndarray) -> tuple:
        """:func:`nearest_with_rival` of ``desc_q`` into the object's library, computed once per keypoint set
        of the image (the view vote and the locator ask for the same; each query is independent, so the
        result is the same). None without keypoints or library."""
        if len(desc_q) == 0 or self._library_index(name) is None:
            return None
        seen = self._nearest.setdefault(name, [])
        for desc, found in seen:
            if desc is desc_q:
                return found
        found = nearest_with_rival(desc_q, self._library_index(name), self.libraries[name], self.conf.match)
        seen.append((desc_q, found))  # holding the array: its identity cannot pass to another one
        return found

    def _model_voxels(self, name: str):
        if name not in self._voxels:
            self._voxels[name] = model_voxel_grid(self.libraries[name].pts3d, self.conf.weights.voxel_m)
        return self._voxels[name]

    # -- library call ----------------------------------------------------------------------------
    def estimate_image(
        self,
        rgb: np.ndarray,
        camera: Camera,
        obj_names: list[str],
        gt: tuple[ObjectPose, ...] = (),
        frame_id: str = "image",
        quick: frozenset[str] = frozenset(),
        no_retry: frozenset[str] = frozenset(),
    ) -> list[PoseRecord]:
        """Estimate every object in ``obj_names`` in one RGB image.

        Args:
            rgb: (H, W, 3) uint8 RGB.
            camera: calibration of this image.
            obj_names: objects to look for (each must have a library).
            gt: ground-truth poses, used only by the ``match.roi: gt_box`` oracle and ``method: tp_ub``.
            quick: objects estimated as if the whole-frame pass were strong (its first stage only, no fine
                pass or locator, one refinement hypothesis): tracking's cheaper retry for an object that stays
                lost, or mostly hidden.
            no_retry: objects not given ``features.retry_contrast_threshold``'s retry (nor are the ``quick`` ones).

        Raises:
            ImageError / CameraError: the image or calibration is unusable.
        """
        camera.validate(frame_id)
        check_image(rgb, frame_id)
        self._nearest.clear()
        self._replaced.clear()
        for name in obj_names:
            if name not in self.libraries:
                raise BatchposeError(f"{frame_id}: no template library for object {name!r}")
        t0 = time.perf_counter()
        gray = to_gray(rgb)
        xy_q, desc_q, shapes_q = detect_shapes(gray, self.conf.features, sift=self._sift)
        t_sift = time.perf_counter() - t0
        query_index = None
        if self.conf.match.direction == "template_to_query":
            query_index = flann_index(desc_q, self.conf.match)
        gt_by_name = {p.obj_name: p.cam_from_model for p in gt}
        checks = self.conf.planar_spread > 0 or self.conf.alternatives > 0
        self._lab = _LazyLab(rgb, gray) if checks else None
        records = []
        for name in obj_names:
            rec = self._estimate_object(
                name, gray, (xy_q, desc_q, shapes_q), query_index, camera, gt_by_name.get(name), frame_id, name in quick
            )
            rec.timings["sift"] = t_sift
            records.append(rec)
        if self.conf.features.retry_contrast_threshold > 0:
            self._retry(records, gray, camera, gt_by_name, frame_id, quick | no_retry)
        return records

    def _retry(self, records: list[PoseRecord], gray, camera: Camera, gt_by_name: dict, frame_id: str, skip):
        """``features.retry_contrast_threshold``: estimate each object a full estimate did not find, or found
        only weakly (confidence below ``verify_below``), once more from keypoints detected at the lower
        contrast threshold; keep the new record when it is ok and more confident. With
        ``features.retry_sigma``, the objects still not found or weak get a second retry the same way, from
        keypoints detected at that SIFT σ. Not the objects in ``skip``."""
        fc = self.conf.features
        for sigma in dict.fromkeys((fc.sigma, fc.retry_sigma)):  # a retry_sigma equal to sigma: one retry
            if sigma > 0 and not self._retry_once(records, gray, camera, gt_by_name, frame_id, skip, sigma):
                return

    def _retry_once(self, records, gray, camera: Camera, gt_by_name: dict, frame_id: str, skip, sigma) -> bool:
        """One retry stage (see :meth:`_retry`); False when no object needed it."""
        weak = self.conf.verify_below
        todo = [
            i
            for i, r in enumerate(records)
            if (r.status in NOT_FOUND or (r.ok and r.confidence < weak)) and r.obj_name not in skip
        ]
        if not todo:
            return False
        t0 = time.perf_counter()
        fc = self.conf.features
        sift = self._sift_retry.get(sigma)
        if sift is None:
            sift = make_sift(dataclasses.replace(fc, contrast_threshold=fc.retry_contrast_threshold, sigma=sigma))
            self._sift_retry[sigma] = sift
        keypoints = detect_shapes(gray, fc, sift=sift)
        index = None
        if self.conf.match.direction == "template_to_query":
            index = flann_index(keypoints[1], self.conf.match)
        t_sift = (time.perf_counter() - t0) / len(todo)
        how = f"contrast {fc.retry_contrast_threshold:g}" + ("" if sigma == fc.sigma else f", sigma {sigma:g}")
        for i in todo:
            first = records[i]
            rec = self._estimate_object(
                first.obj_name, gray, keypoints, index, camera, gt_by_name.get(first.obj_name), frame_id, sift=sift
            )
            for k, v in first.timings.items():  # every attempt's time is the pair's
                rec.timings[k] = rec.timings.get(k, 0.0) + v
            rec.timings["sift"] = rec.timings.get("sift", 0.0) + t_sift
            if rec.ok and (not first.ok or rec.confidence > first.confidence):
                rec.reason = f"found with keypoints at {how}"
                records[i] = rec
                if first.ok:
                    self._replaced[id(rec)] = (rec, first)
            else:
                first.timings = rec.timings
        return True

    def _roi_mask(self, xy_q: np.ndarray, camera: Camera, cam_from_model: np.ndarray | None, name: str):
        if self.conf.match.roi == "none":
            return None
        if cam_from_model is None:
            return np.zeros(len(xy_q), bool)  # oracle ROI without ground truth: object not annotated
        pts = self.libraries[name].pts3d.astype(np.float64)
        rvec = cv2.Rodrigues(cam_from_model[:3, :3])[0]
        proj, _ = cv2.projectPoints(pts, rvec, cam_from_model[:3, 3], camera.K, camera.dist)
        proj = proj.reshape(-1, 2)
        m = self.conf.match.roi_margin_px
        lo, hi = proj.min(axis=0) - m, proj.max(axis=0) + m
        return np.all((xy_q >= lo) & (xy_q <= hi), axis=1)

    def _tp_ub(self, name: str, gt_pose: np.ndarray | None, frame_id: str) -> PoseRecord:
        """Template upper bound: the template rotation closest to ground truth, ground-truth translation."""
        lib = self.libraries[name]
        if gt_pose is None:
            return PoseRecord(frame_id, name, "error", "tp_ub needs ground truth for this object")
        Rs = np.stack([lib.cam_from_model(i)[:3, :3] for i in range(lib.n_views)])
        cos = (np.einsum("nij,ij->n", Rs, gt_pose[:3, :3]) - 1.0) / 2.0
        best = int(np.argmax(cos))
        T = np.eye(4)
        T[:3, :3] = Rs[best]
        T[:3, 3] = gt_pose[:3, 3]
        return PoseRecord(frame_id, name, "ok", cam_from_model=T, confidence=1.0, templates=(best,))

    def _estimate_object(
        self,
        name: str,
        gray: np.ndarray,
        keypoints: tuple[np.ndarray, np.ndarray, np.ndarray],
        query_index,
        camera: Camera,
        gt_pose: np.ndarray | None,
        frame_id: str,
        quick: bool = False,
        sift=None,
    ) -> PoseRecord:
        conf = self.conf
        if conf.method == "tp_ub":
            return self._tp_ub(name, gt_pose, frame_id)
        xy_q, desc_q, shapes_q = keypoints
        timings: dict[str, float] = {}
        rec = PoseRecord(frame_id, name, "ok", obj_id=self.obj_ids.get(name, 0), timings=timings)
        roi = self._roi_mask(xy_q, camera, gt_pose, name)
        res, corr = self._coarse(name, xy_q, desc_q, query_index, roi, camera, timings, quick)
        passes = [(res, corr, xy_q, desc_q)]
        strong = quick or self._strong(name, res, camera)
        if conf.fine.enabled and not strong:
            t0 = time.perf_counter()
            box = self._object_box(name, res, corr, camera, gt_pose)
            fine = None if box is None else self._fine_pass(name, gray, box, camera, sift=sift)
            if fine is not None:
                passes.insert(0, fine)
            if conf.fine.locate and conf.match.roi == "none" and self._weak(name, self._best(passes)[0], camera):
                # The pose so far is weak: search again where the keypoints' votes put the object.
                searched = [] if box is None else [box]
                for found in locate(
                    xy_q,
                    shapes_q,
                    desc_q,
                    self._library_index(name),
                    self.libraries[name],
                    conf.match,
                    camera.width,
                    camera.height,
                    ratio=conf.fine.locate_ratio,
                    angle_bin_deg=conf.fine.locate_angle_deg,
                    min_votes=conf.fine.locate_votes,
                    peaks=conf.fine.locate_peaks,
                    nearest=self._nearest_templates(name, desc_q),
                ):
                    c, half = np.asarray(found.centre_xy), 0.5 * found.size_px  # a square of the object's diameter
                    hough = _grown_box(c - half, c + half, conf.fine, camera)
                    if hough is None or any(_overlap(hough, b) >= 0.5 for b in searched):
                        continue
                    searched.append(hough)
                    located = self._fine_pass(
                        name, gray, hough, camera, found.pairs if conf.fine.locate_pairs else None, sift
                    )
                    if located is not None:
                        passes.insert(0, located)
            timings["fine"] = time.perf_counter() - t0
        res, corr, xy_k, desc_k = self._best(passes)
        rec.n_matches = len(corr)
        rec.templates = corr.templates
        x_used, X_used = corr.x, corr.X
        tried: list = []
        if self._can_refine(name):
            t0 = time.perf_counter()
            refined = self._refine(name, passes, camera, xy_k, desc_k, strong, tried)
            timings["refine"] = time.perf_counter() - t0
            if refined is not None:
                res, x_used, X_used = refined.result, refined.x, refined.X
        if res is None:
            rec.status = "too_few_matches"
            rec.reason = f"{len(corr)} matches after the ratio test, need {conf.min_matches}"
            return rec
        rec.status, rec.reason = res.status, res.reason
        if res.status == "ok" and (why := self._implausible(name, res.cam_from_model, camera)):
            rec.status, rec.reason = "pnp_failed", why
        if not rec.status == "ok":
            return rec
        if (other := self._alternative(name, res, tried, camera, timings)) is not None:
            (res, x_used, X_used), rec.reason = other
        if (mirrored := self._planar_mirror(name, res, x_used, X_used, camera, timings)) is not None:
            res, rec.reason = mirrored
        rec.cam_from_model = res.cam_from_model
        if conf.refine.polish and self._can_render(name):
            t0 = time.perf_counter()
            rec.cam_from_model = self._polish(name, gray, res.cam_from_model, camera)
            timings["refine"] = timings.get("refine", 0.0) + time.perf_counter() - t0
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
        return rec

    def _alternative(self, name: str, res, tried: list, camera: Camera, timings: dict):
        """``alternatives``: ((result, x, X), reason) of a refined hypothesis the frame prefers to the pose
        ``res`` by colour and by edges where their renders differ; None to keep the pose."""
        conf = self.conf
        if conf.alternatives <= 0 or self._lab is None or len(tried) < 2:
            return None
        t0 = time.perf_counter()
        diameter = self.models[name].diameter_m

        def same(A, B):
            return (
                rotation_error_deg(A[:3, :3], B[:3, :3]) <= 5.0
                and np.linalg.norm(A[:3, 3] - B[:3, 3]) <= 0.1 * diameter
            )

        top, least = max(r.score for r in tried), conf.alternatives_score
        ranked = sorted(tried, key=lambda r: -r.score)
        picked = []  # distinct poses, best score first
        for r in ranked:
            T = r.result.cam_from_model
            if r.result.status != "ok" or r.score <= 0 or r.score < least * top:
                continue
            if r.result.n_inliers < least * res.n_inliers:
                continue  # a pose that many more pairs support is not second-guessed by a few
            if same(T, res.cam_from_model) or any(same(T, p.result.cam_from_model) for p in picked):
                continue
            if self._implausible(name, T, camera):
                continue
            picked.append(r)
            if len(picked) == conf.alternatives:
                break
        if not picked:
            return None
        current, chosen, why = self._render(name, res.cam_from_model, camera), None, ""
        for r in picked:
            rendered = self._render(name, r.result.cam_from_model, camera)
            if (cues := self._frame_prefers(current, rendered)) is None:
                continue
            current, chosen = rendered, r
            why = f"a {r.result.n_inliers}-inlier alternative fits the frame better where the two differ ({cues})"
        timings["refine"] = timings.get("refine", 0.0) + time.perf_counter() - t0
        return None if chosen is None else ((chosen.result, chosen.x, chosen.X), why)

    def _planar_mirror(self, name: str, res, x: np.ndarray, X: np.ndarray, camera: Camera, timings: dict):
        """``planar_spread``: (the other pose of a planar inlier set as a result, a reason) when its mesh
        looks more like the frame than the pose's own; None to keep the pose. Its time counts as refinement."""
        conf = self.conf
        if self._lab is None or not self._can_render(name):  # None: neither check is on
            return None
        t0 = time.perf_counter()
        inl = res.inliers
        other = planar_alternative(x[inl], X[inl], res.cam_from_model, camera.K, camera.dist, conf.planar_spread)
        if other is None:
            return None
        T, r_inl = other
        own = max(res.median_residual_px, 0.5)
        if not np.median(r_inl) <= conf.planar_residual_ratio * own or self._implausible(name, T, camera):
            return None
        cues = self._frame_prefers(*(self._render(name, pose, camera) for pose in (res.cam_from_model, T)))
        timings["refine"] = timings.get("refine", 0.0) + time.perf_counter() - t0
        if cues is None:
            return None
        residuals = res.residuals_px.copy()
        residuals[inl] = r_inl
        why = f"the planar inliers' other pose (where the two differ: {cues})"
        return dataclasses.replace(res, cam_from_model=T, residuals_px=residuals), why

    def _frame_prefers(self, current, other) -> str | None:
        """Compare the renders ``current`` and ``other`` with the frame where they differ: the two cues'
        figures ("texture match ..., edges ...") when ``other`` fits better by colour *and* by edges, each
        leaving at most 1 / ``planar_mismatch_ratio`` of ``current``'s mismatch; None otherwise."""
        fits = distinct_matches(self._lab.get(), self._lab.gray, current, other)
        ratio = self.conf.planar_mismatch_ratio
        if fits is None or not all(1.0 - b <= (1.0 - a) / ratio for a, b in zip(*fits, strict=True)):
            return None
        (ca, ea), (cb, eb) = fits
        return f"texture match {cb:.2f} against {ca:.2f}, edges {eb:.2f} against {ea:.2f}"

    def _can_render(self, name: str) -> bool:
        return self.renderer is not None and name in self.models

    def _match(self, name, xy_q, desc_q, query_index, roi, prefilter_views: int) -> Correspondences:
        """2D-3D pairs between the frame keypoints and the object's library (SPEC §2)."""
        conf, lib = self.conf, self.libraries[name]
        if conf.match.direction == "template_to_query":
            views = self._voted_views(name, desc_q, roi, prefilter_views)
            return match_template_to_query(xy_q, query_index, lib, conf.match, candidate_mask=roi, views=views)
        sel = np.ones(len(xy_q), bool) if roi is None else roi
        return match_query_to_template(xy_q[sel], desc_q[sel], self._library_index(name), lib, conf.match)

    def _voted_views(self, name, desc_q, roi, n_views: int) -> np.ndarray | None:
        """The ``n_views`` views the frame keypoints vote for (None: test every view)."""
        lib = self.libraries[name]
        if not n_views or n_views >= lib.n_views:
            return None
        # Shared with the locator, which runs without an ROI only; under one, query just the ROI's keypoints.
        nearest = self._nearest_templates(name, desc_q) if roi is None else None
        return vote_views(desc_q, self._library_index(name), lib, n_views, self.conf.match, roi, nearest)

    def _coarse(self, name, xy_q, desc_q, query_index, roi, camera: Camera, timings: dict[str, float], quick=False):
        """The whole-frame pass: (result, pairs). With ``match.first_views``, the most-voted views are
        matched first and the rest only when they give no strong pose (and the estimate is not ``quick``)."""
        conf, lib = self.conf, self.libraries[name]
        first, n_views = conf.match.first_views, conf.match.prefilter_views
        t0 = time.perf_counter()
        staged = conf.match.direction == "template_to_query" and 0 < first < n_views < lib.n_views
        if not staged:
            corr = self._match(name, xy_q, desc_q, query_index, roi, n_views)
            timings["match"] = time.perf_counter() - t0
            return self._solve(name, corr, camera, timings), corr
        views = self._voted_views(name, desc_q, roi, n_views)
        cand = template_to_query_candidates(query_index, lib, conf.match, roi, views[:first])
        corr = top_k_pairs(cand, lib, xy_q, conf.match)
        timings["match"] = time.perf_counter() - t0
        res = self._solve(name, corr, camera, timings)
        if quick or self._strong(name, res, camera):
            return res, corr
        t0 = time.perf_counter()
        more = template_to_query_candidates(query_index, lib, conf.match, roi, views[first:])
        corr = top_k_pairs(tuple(np.concatenate(p) for p in zip(cand, more, strict=True)), lib, xy_q, conf.match)
        timings["match"] += time.perf_counter() - t0
        return self._solve(name, corr, camera, timings), corr

    def _solve(self, name: str, corr: Correspondences, camera: Camera, timings: dict[str, float]):
        """Weights + RANSAC + GNC + LM on the pairs; None when there are too few pairs."""
        if len(corr) < self.conf.min_matches:
            return None
        t0 = time.perf_counter()
        w = self._weights(name, corr)
        timings["weights"] = timings.get("weights", 0.0) + time.perf_counter() - t0
        res = solve_pose(corr.x, corr.X, camera.K, camera.dist, w, self.conf.gnc)
        for k, v in res.timings.items():
            timings[k] = timings.get(k, 0.0) + v
        return res

    def _implausible(self, name: str, pose: np.ndarray, camera: Camera) -> str:
        """Why ``pose`` cannot be what the frame shows ("" when it can): the object's apparent size."""
        if name not in self._extent:
            pts = self.libraries[name].pts3d
            self._extent[name] = (pts.mean(axis=0), float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))))
        centre, diam = self._extent[name]
        z = float(pose[2, :3] @ centre + pose[2, 3])
        if z <= 0:
            return f"implausible pose: the object is behind the camera (z = {z:.2f} m)"
        span = float(camera.K[0, 0]) * diam / z
        lo, hi = self.conf.min_object_px, self.conf.max_object_image_fraction * max(camera.width, camera.height)
        if not lo <= span <= hi:
            return f"implausible pose: the object would span {span:.0f} px at {z:.2f} m (allowed {lo:.0f}-{hi:.0f} px)"
        return ""

    def _object_box(self, name, res, corr: Correspondences, camera: Camera, gt_pose) -> tuple | None:
        """The object's image box (x0, y0, x1, y1), grown by the fine margins and clipped; None if unknown.

        From the ground-truth pose with the ``gt_box`` oracle, else from the coarse pose (with its inliers),
        else around the densest cluster of matched keypoints.
        """
        fc = self.conf.fine
        pts = None
        coarse_ok = res is not None and res.status == "ok" and not self._implausible(name, res.cam_from_model, camera)
        pose = gt_pose if self.conf.match.roi == "gt_box" else (res.cam_from_model if coarse_ok else None)
        if pose is not None:
            X = self.libraries[name].pts3d.astype(np.float64)
            z = X @ pose[2, :3] + pose[2, 3]
            if np.all(z > 1e-3):
                proj, _ = cv2.projectPoints(X, cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], camera.K, camera.dist)
                pts = proj.reshape(-1, 2)
                if coarse_ok and pose is not gt_pose:
                    pts = np.vstack([pts, corr.x[res.inliers]])
        if pts is None:
            if self.conf.match.roi == "gt_box" or len(corr) < self.conf.min_matches:
                return None
            d = np.linalg.norm(corr.x[:, None] - corr.x[None], axis=2)
            centre = corr.x[np.argmax((d < fc.cluster_radius_px).sum(axis=1))]
            pts = corr.x[np.linalg.norm(corr.x - centre, axis=1) < 2 * fc.cluster_radius_px]
        return _grown_box(pts.min(axis=0), pts.max(axis=0), fc, camera)

    def _best(self, passes: list) -> tuple:
        """The pass with the most support (the earliest, i.e. the latest fine pass, on ties)."""
        return max(passes, key=lambda p: p[0].support(self.conf.support_px) if p[0] else -1)

    def _strong(self, name: str, res, camera: Camera) -> bool:
        """True when ``res`` has at least ``strong_inliers`` inliers at a plausible pose."""
        n = self.conf.strong_inliers
        if res is None or res.status != "ok" or not 0 < n <= res.n_inliers:
            return False
        return not self._implausible(name, res.cam_from_model, camera)

    def _weak(self, name: str, res, camera: Camera) -> bool:
        """True when ``res`` (the best pass so far) is no pose, an implausible one or one below
        ``fine.locate_below`` confidence."""
        if res is None or res.status != "ok" or self._implausible(name, res.cam_from_model, camera):
            return True
        return confidence(res.n_inliers, res.median_residual_px, self.conf) < self.conf.fine.locate_below

    def _fine_pass(self, name, gray, box, camera, extra: Correspondences | None = None, sift=None):
        """Match again inside ``box``, upsampled, plus the ``extra`` pairs: (result, pairs, keypoints,
        descriptors) or None."""
        xy_f, desc_f = fine_keypoints(gray, box, self.conf, sift or self._sift)
        index = flann_index(desc_f, self.conf.match) if self.conf.match.direction == "template_to_query" else None
        corr_f = self._match(name, xy_f, desc_f, index, None, self.conf.fine.prefilter_views)
        if extra is not None and len(extra):
            corr_f = Correspondences(
                np.vstack([corr_f.x, extra.x]),
                np.vstack([corr_f.X, extra.X]),
                np.concatenate([corr_f.view_ids, extra.view_ids]),
                corr_f.templates,
                corr_f.n_candidates + extra.n_candidates,
            )
        res_f = self._solve(name, corr_f, camera, {})
        if res_f is None:
            return None
        return res_f, corr_f, xy_f, desc_f

    def _polish(self, name: str, gray: np.ndarray, T: np.ndarray, camera: Camera) -> np.ndarray:
        """``refine.polish``: align the pose ``T`` to the frame by the mesh rendered there, ``polish_rounds``
        times: corners of the frame on the render's silhouette where the two look alike
        (:func:`batchpose.method.track.seed`) are found again in the render by patch correlation and the pose is
        solved on them (:func:`batchpose.method.track.anchor_to_render`). Returns the last pose found (``T`` when
        the first round finds too few corners)."""
        rf = self.conf.refine
        tc = dataclasses.replace(self.conf.track, render_search_px=rf.polish_search_px, min_fraction=0.0)
        for _ in range(rf.polish_rounds):
            rgb, depth = self._render(name, T, camera)
            rendered = to_gray(rgb)
            xy, X = seed(gray, T, rendered, depth, camera.K, camera.dist, tc)
            if len(xy) < tc.min_points:
                break
            moved = anchor_to_render(gray, rendered, Track(xy, X, T, len(xy), 1.0), camera.K, camera.dist, tc)
            if moved is None:
                break
            T = moved.track.cam_from_model
        return T

    def _flips(self, name: str) -> list[np.ndarray]:
        if name not in self._flip_cache:
            self._flip_cache[name] = self.models[name].flips()
        return self._flip_cache[name]

    def _surface(self, name: str) -> Surface:
        if name not in self._surfaces:
            self._surfaces[name] = Surface.of(self.models[name].mesh)
        return self._surfaces[name]

    def _can_refine(self, name: str) -> bool:
        return self.conf.refine.enabled and self._can_render(name)

    def _refine(self, name, passes, camera: Camera, xy_q, desc_q, strong: bool = False, tried: list | None = None):
        """Refine the passes' poses (and, with ``refine.hypotheses`` > 1, per-template poses); best guided score.
        Every refined hypothesis is appended to ``tried`` (when given).

        Args:
            passes: (result, pairs, ...) of the coarse and fine passes, best first.
            xy_q, desc_q: the keypoints guided matching uses.
            strong: the best pass has found the object (:meth:`_strong`): refine its pose only, once.
        """
        conf = self.conf

        def render(T):
            return self._render(name, T, camera)

        ok = [p[0] for p in passes if p[0] is not None and p[0].status == "ok"]
        starts = [r.cam_from_model for r in ok][: 1 if strong else conf.refine.hypotheses]
        for _res, corr, *_ in [] if strong else passes:
            for v in corr.templates:
                if len(starts) >= conf.refine.hypotheses:
                    break
                sel = corr.view_ids == v
                if sel.sum() < conf.gnc.min_inliers:
                    continue
                sub = solve_pose(corr.x[sel], corr.X[sel], camera.K, camera.dist, None, conf.gnc)
                if sub.status == "ok":
                    starts.append(sub.cam_from_model)

        def refine(T, iterations):
            r = refine_pose(
                T,
                xy_q,
                desc_q,
                camera.K,
                camera.dist,
                render,
                conf.refine,
                conf.features,
                conf.gnc,
                lambda X: self._weights_for(name, X),
                iterations=iterations,
                support_px=conf.support_px,
            )
            if r is not None and tried is not None:
                tried.append(r)
            return r

        def finish(r):
            """The remaining rounds after a first one; keeps the first when they do not score higher."""
            if r is None or conf.refine.iterations <= 1:
                return r
            more = refine(r.result.cam_from_model, conf.refine.iterations - 1)
            return more if more is not None and more.score >= r.score else r

        # One round per hypothesis to rank them, the remaining rounds for the best one only.
        best = None
        for T in starts:
            r = refine(T, 1)
            if r is not None and (best is None or r.score > best.score):
                best = r
        best = best if strong else finish(best)
        if best is not None and conf.refine.flips and not strong:
            # A turned hypothesis starts up to ~20 degrees off, so one that finds a third of the best score in
            # its first round gets the remaining rounds before it is compared.
            base = best.result.cam_from_model
            for F in self._flips(name):
                r = refine(base @ F, 1)
                if r is not None and 3 * r.score >= best.score:
                    r = finish(r)
                if r is not None and r.score > best.score:
                    best = r
        if best is not None and ok and best.result.n_inliers < max(r.n_inliers for r in ok):
            return None  # the guided pairs explain the frame worse than the template pairs
        return best

    def _weights_for(self, name: str, X: np.ndarray) -> np.ndarray:
        wc = self.conf.weights
        if wc.mode == "none":
            return np.ones(len(X))
        if wc.mode == "correspondences":
            return geom_weights(X, wc.voxel_m, wc.w_min)
        keys, counts = self._model_voxels(name)
        return support_to_weights(model_support(X, keys, counts, wc.voxel_m), wc.w_min)

    def _weights(self, name: str, corr: Correspondences) -> np.ndarray:
        return self._weights_for(name, corr.X)

    # -- tracking ----------------------------------------------------------------------------------
    def reset_tracks(self) -> None:
        """Forget every track: the next frame is estimated afresh (a worker does this at each task)."""
        self._tracks = {}
        self._lost = {}
        self._last = {}
        self._prev = None
        self._found = {}
        self._placed = {}

    def tracking(self) -> bool:
        """True when :meth:`estimate_frame` follows confident poses into the next frames (``track.*``)."""
        c = self.conf
        return c.track.enabled and c.method == "gnc_pose" and c.match.roi == "none" and self.renderer is not None

    def _follows(self, frame: Frame) -> bool:
        """True when ``frame`` is the next image (``im_id`` + ``im_step``) of the previous frame's scene and
        camera, a short step later in time (folder data sets' stamps are synthetic, their ``im_id`` is not)."""
        p, cam = self._prev, frame.camera
        if p is None or p["scene_id"] != frame.scene_id or frame.im_id != p["im_id"] + frame.im_step:
            return False
        if p["gray"].shape != (cam.height, cam.width):
            return False
        gap_s = (frame.stamp_ns - p["stamp_ns"]) * 1e-9
        same_camera = np.array_equal(p["K"], cam.K) and np.array_equal(p["dist"], cam.dist)
        return same_camera and 0 < gap_s <= self.conf.track.max_gap_s

    def _render(self, name: str, T: np.ndarray, camera: Camera):
        """The object's mesh at pose ``T`` in ``camera``: (rgb, depth_m), albedo shading."""
        model = self.models[name]
        return self.renderer.render(
            model.content_hash,
            model.mesh,
            T,
            camera.K,
            camera.width,
            camera.height,
            "flat",
            self.conf.render.znear_m,
            self.conf.render.zfar_m,
        )

    def _render_gray(self, name: str, T: np.ndarray, camera: Camera) -> np.ndarray:
        return to_gray(self._render(name, T, camera)[0])

    def _seed(
        self, name: str, gray: np.ndarray, rec: PoseRecord, camera: Camera, hidden=(), lab: np.ndarray | None = None
    ) -> Track | None:
        """A new track from a confident full estimate (None when the object shows too few corners, or, given
        the frame's Lab image ``lab``, when the mesh at that pose does not look like the frame:
        :meth:`_looks_alike`); no corners where ``hidden`` (:meth:`_hidden`) puts something in front of it."""
        model = self.models.get(name)
        if model is None:
            return None
        T = rec.cam_from_model
        rgb, depth = self._render(name, T, camera)
        if lab is not None and not self._looks_alike(lab, rgb, depth, hidden):
            return None
        xy, X = seed(gray, T, to_gray(rgb), depth, camera.K, camera.dist, self.conf.track, hidden)
        if len(xy) < self.conf.track.min_points:
            return None
        return Track(xy, X, T, len(xy), rec.confidence, key_gray=gray, key_xy=xy.copy(), key_pose=T.copy())

    def _looks_alike(self, lab: np.ndarray, rgb: np.ndarray, depth: np.ndarray, hidden=()) -> bool:
        """``track.min_match``: the mesh rendered at a pose (``rgb``, ``depth``) looks like the frame (``lab``)
        over its silhouette, less what ``hidden`` puts in front of it; True when too little of it shows to
        judge."""
        if self.conf.track.min_match <= 0:
            return True
        seen = depth > 0
        for occ in hidden:
            seen &= ~(occ.mask & (depth > occ.near_m))
        return seen.sum() < VERIFY_MIN_PX or texture_match(lab[seen], rgb[seen]) >= self.conf.track.min_match

    def _refresh(self, name: str, gray: np.ndarray, res, camera: Camera, hidden=(), lab: np.ndarray | None = None):
        """A new keyframe at the tracked pose, checked against the mesh: the mesh rendered there must look like
        the frame (:meth:`_looks_alike`, given the frame's Lab image ``lab``), then the points are pulled onto
        it (:func:`batchpose.method.track.anchor_to_render`) and corners are seeded afresh at the pulled pose. None
        when the frame no longer matches the mesh at that pose (the track has drifted or is occluded)."""
        rgb, depth = self._render(name, res.track.cam_from_model, camera)
        if lab is not None and not self._looks_alike(lab, rgb, depth, hidden):
            return None
        anchored = anchor_to_render(gray, to_gray(rgb), res.track, camera.K, camera.dist, self.conf.track)
        if anchored is None:
            return None
        rec = PoseRecord("", name, "ok", cam_from_model=anchored.track.cam_from_model, confidence=res.track.confidence)
        fresh = self._seed(name, gray, rec, camera, hidden)
        if fresh is None:
            return None
        anchored.track = fresh
        return anchored

    def _estimate_tracked(self, rgb: np.ndarray, frame: Frame, obj_names: list[str]) -> list[PoseRecord]:
        """:meth:`estimate_image` that follows live tracks instead (see :mod:`batchpose.method.track`)."""
        camera, tc = frame.camera, self.conf.track
        camera.validate(frame.frame_id)
        check_image(rgb, frame.frame_id)
        t0 = time.perf_counter()
        gray = to_gray(rgb)
        t_gray = time.perf_counter() - t0
        prev = self._prev
        follows = self._follows(frame)
        tracks = self._tracks if follows else {}
        lost = self._lost if follows else {}
        last = self._last if follows else {}
        # rebuilt below; stay empty if this frame fails
        self._tracks, self._lost, self._last, self._prev = {}, {}, {}, None
        out: dict[str, PoseRecord] = {}
        due = [n for n in obj_names if n in tracks and not (tc.redetect_every and tracks[n].age >= tc.redetect_every)]
        t0 = time.perf_counter()
        hidden = self._hidden([tracks[n].cam_from_model for n in due], due, camera)
        moved_all = (
            follow_all(prev["gray"], gray, [tracks[n] for n in due], camera.K, camera.dist, tc, hidden) if due else []
        )
        followed = dict(zip(due, moved_all, strict=True))
        lab = _LazyLab(rgb, gray)  # the frame in Lab, made once, for the first check (``track.min_match``)

        def frame_lab() -> np.ndarray | None:
            return lab.get() if tc.min_match > 0 else None

        t_flow = (time.perf_counter() - t0) / max(len(due), 1)  # one flow call for all: each pays its share
        for k, name in enumerate(due):
            tr = tracks[name]
            t0 = time.perf_counter() - t_flow
            res = followed[name]
            if res is None:
                log.debug("%s: track of %s lost, estimating afresh", frame.frame_id, name)
                continue
            t_refresh = 0.0
            if tc.render_every and res.track.age % tc.render_every == 0:
                rendered = self._render_gray(name, res.track.cam_from_model, camera)
                anchored = anchor_to_render(gray, rendered, res.track, camera.K, camera.dist, tc)
                res = anchored if anchored is not None else res
            old_age, thinning = res.track.age, len(res.track.xy) < tc.reseed_fraction * res.track.n_seeded
            key = res.track.key_pose
            turned = tc.refresh_turn_deg > 0 and key is not None
            turned = turned and view_turn_deg(key, res.track.cam_from_model) > tc.refresh_turn_deg
            if tc.refresh_every and (old_age >= tc.refresh_every or thinning or turned):
                t1 = time.perf_counter()
                res = self._refresh(name, gray, res, camera, hidden[k] if hidden else (), frame_lab())
                t_refresh = time.perf_counter() - t1
                if res is None:
                    log.debug("%s: track of %s no longer matches the mesh, estimating afresh", frame.frame_id, name)
                    continue
            self._tracks[name] = moved = res.track
            if name in lost and moved.age < tc.lost_full_every:
                self._lost[name] = lost[name] + 1  # a young track: still counted as lost (see below)
            out[name] = PoseRecord(
                frame.frame_id,
                name,
                "ok",
                obj_id=self.obj_ids.get(name, 0),
                cam_from_model=moved.cam_from_model,
                confidence=min(tr.confidence, confidence(res.n_inliers, res.median_residual_px, self.conf)),
                n_matches=len(tr.xy),
                n_inliers=res.n_inliers,
                median_residual_px=res.median_residual_px,
                inliers_px=moved.xy,
                timings={"track": t_gray + time.perf_counter() - t0 - t_refresh, "seed": t_refresh},
                tracked=True,
            )
        rest = [n for n in obj_names if n not in out]
        # An object still lost since the previous frame gets the full estimate only every
        # ``lost_full_every``-th frame, a quick one in between. It counts as lost until a track of it lives
        # that many frames: a mostly hidden object's estimates start tracks that die a frame later, and each
        # would otherwise make the next estimate a full one.
        quick = frozenset(n for n in rest if lost.get(n, 0) % tc.lost_full_every)
        skipped, hidden = self._hidden_lost(rest, quick, out, last, frame)
        for rec in skipped:
            out[rec.obj_name] = rec
        rest = [n for n in rest if n not in out]
        if tc.hidden_quick:
            quick |= hidden
        no_retry = frozenset() if tc.hidden_retry else hidden
        fresh = []
        if rest:
            fresh = self.estimate_image(rgb, camera, rest, frame.gt, frame.frame_id, quick=quick, no_retry=no_retry)
        for rec in fresh:
            out[rec.obj_name] = rec
        for n in obj_names:
            if n not in self._tracks:
                self._lost[n] = lost.get(n, 0) + 1
            if out[n].ok and out[n].confidence >= tc.min_confidence:
                self._last[n] = out[n].cam_from_model
            elif n in last:
                self._last[n] = last[n]
        seeds = [r for r in fresh if r.ok and r.confidence >= tc.min_confidence]
        if seeds:
            # New tracks get no corners where an object found in this frame is in front of them.
            placed = [n for n in obj_names if out[n].ok]
            t0 = time.perf_counter()
            hidden_now = self._hidden([out[n].cam_from_model for n in placed], placed, camera)
            t_hidden = (time.perf_counter() - t0) / len(seeds)
            for rec in seeds:
                t0 = time.perf_counter() - t_hidden
                in_front = hidden_now[placed.index(rec.obj_name)] if hidden_now else ()
                tr = self._seed(rec.obj_name, gray, rec, camera, in_front, frame_lab())
                rec.timings["seed"] = time.perf_counter() - t0
                if tr is not None:
                    self._tracks[rec.obj_name] = tr
        self._prev = {
            "gray": gray,
            "scene_id": frame.scene_id,
            "im_id": frame.im_id,
            "stamp_ns": frame.stamp_ns,
            "K": camera.K,
            "dist": camera.dist,
        }
        return [out[n] for n in obj_names]

    def _hidden_lost(self, rest: list[str], quick, out: dict[str, PoseRecord], last: dict, frame: Frame):
        """``track.hidden_above``: which of the objects ``rest`` to estimate the objects tracked in this frame
        (``out``) cover enough from in front at their last confident poses (``last``): a ``hidden`` record
        for each due a ``quick`` estimate, and the set of the others (which ``track.hidden_quick`` makes quick)."""
        tc, camera, recs, hidden = self.conf.track, frame.camera, [], set()
        tracked = [n for n, r in out.items() if r.tracked and n in self.models]
        if tc.hidden_above >= 1 or not tracked:
            return recs, frozenset()
        others = [(self._hull(n), out[n].cam_from_model) for n in tracked]
        for name in rest:
            if name not in last or name not in self.models:
                continue
            t0 = time.perf_counter()
            frac, each = covered(
                self._hull(name), last[name], others, camera.K, camera.dist, camera.width, camera.height
            )
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
                    obj_id=self.obj_ids.get(name, 0),
                    timings={"track": time.perf_counter() - t0},
                )
            )
        return recs, frozenset(hidden)

    def _hull(self, name: str) -> np.ndarray:
        """The object's convex-hull vertices (model frame), computed once."""
        if name not in self._hulls:
            self._hulls[name] = np.asarray(self.models[name].mesh.convex_hull.vertices)
        return self._hulls[name]

    def _hidden(self, poses: list[np.ndarray], names: list[str], camera: Camera) -> list[list] | None:
        """``track.occlusion_margin_px``: what may hide each of the objects at ``poses``
        (:func:`batchpose.method.track.occluders`); None when off or with fewer than two objects."""
        margin = self.conf.track.occlusion_margin_px
        if margin < 0 or len(poses) < 2 or any(n not in self.models for n in names):
            return None
        hulls = [self._hull(n) for n in names]
        return occluders(hulls, poses, camera.K, camera.dist, camera.width, camera.height, margin)

    def _use_depth(self, frame: Frame, rgb: np.ndarray, records: list[PoseRecord]) -> None:
        """``depth.enabled``: check each found pose against the frame's depth image and align it to the depth
        (:func:`batchpose.method.depth.align_to_depth`). Tracks keep following the RGB poses. A pose the depth
        contradicts becomes pnp_failed; one it cannot align stays as it was, with the reason in ``reason``; a
        low-confidence pose (``min_confidence``) it aligns is reported ok. With ``depth.search``, an object then
        without a pose is looked for by colour and depth."""
        dc = self.conf.depth
        usable = [r for r in records if r.obj_name in self.models and self.renderer is not None]
        todo = [r for r in usable if r.ok or r.status == "low_confidence"]
        if not todo and not (dc.search and any(r.status in NOT_FOUND for r in usable)):
            return
        contradicted: set[str] = set()
        t0 = time.perf_counter()
        try:
            full = decode_depth(self._full_frame or frame)
            if full is not None and full.shape != (frame.camera.height, frame.camera.width):  # max_image_side_px
                full = cv2.resize(full, (frame.camera.width, frame.camera.height), interpolation=cv2.INTER_NEAREST)
        except ImageError as e:
            log.warning("%s: depth image not used: %s", frame.frame_id, e)
            for rec in todo:
                rec.reason = f"depth image not used ({e}): RGB pose"
            return
        # Every level-th pixel and the camera that sees exactly those. Renders stay at the frame's size
        # (subsampled alike): a renderer changes GL context with the image size, which costs ~0.1 s.
        level = dc.level
        depth = np.ascontiguousarray(full[::level, ::level])
        K = frame.camera.K.copy()
        K[:2] /= level
        t_decode = (time.perf_counter() - t0) / max(len(todo), 1)
        for rec in todo:
            t0 = time.perf_counter()
            name = rec.obj_name
            fit = align_to_depth(
                rec.cam_from_model,
                depth,
                lambda T, name=name: self._render(name, T, frame.camera)[1][::level, ::level],
                K,
                self._surface(name),
                self.models[name].diameter_m,
                dc,
            )
            if fit.contradicted:
                rec.status, rec.reason = "pnp_failed", fit.reason
                contradicted.add(name)
            elif fit.aligned:
                rec.cam_from_model = fit.cam_from_model
                if not rec.ok:
                    rec.status, rec.reason = "ok", f"RGB confidence {rec.confidence:.2f}, aligned to the depth image"
            elif rec.ok:
                rec.reason = f"depth not used: {fit.reason}: RGB pose"
            rec.timings["depth"] = t_decode + time.perf_counter() - t0
        for rec in [r for r in usable if r.status in NOT_FOUND] if dc.search else []:
            if not self._search_due(rec.obj_name, frame):
                continue
            t0 = time.perf_counter()
            self._search(
                rec,
                frame,
                rgb,
                full,
                "the depth contradicted the RGB pose" if rec.obj_name in contradicted else "no SIFT pose",
            )
            rec.timings["depth"] = rec.timings.get("depth", 0.0) + time.perf_counter() - t0

    def _search(self, rec: PoseRecord, frame: Frame, rgb: np.ndarray, depth: np.ndarray, why: str) -> None:
        """``depth.search`` for one object without a pose (:func:`batchpose.method.depth_search.search`);
        ``why`` it has none goes into the reason of a pose found."""
        name, cam = rec.obj_name, frame.camera
        found = search(
            rgb,
            depth,
            cam.K,
            self.libraries[name],
            self._silhouettes_of(name),
            self._surface(name),
            self._flips(name),
            self.models[name].diameter_m,
            lambda T: self._render(name, T, cam),
            self.conf.depth,
            self._previous_pose(self._found, name, frame),
        )
        if found is None:
            self._found.pop(name, None)
            return
        self._found[name] = ((frame.scene_id, frame.im_id, frame.stamp_ns, cam.K.copy()), found.cam_from_model)
        rec.status, rec.cam_from_model = "ok", found.cam_from_model
        rec.confidence = 0.5 * found.visible * (1.0 - found.see_through)
        how = "followed from the previous frame's" if found.followed else "found by the"
        rec.reason = (
            f"{how} depth search ({why}): {100 * found.visible:.0f}% of it seen at its surface, "
            f"colour log-odds {found.colour:.1f}, texture match {found.match:.2f}"
        )

    def _silhouettes_of(self, name: str) -> Silhouettes:
        """The object's colour histogram and view silhouettes
        (:class:`batchpose.method.depth_search.Silhouettes`), made once."""
        if name not in self._silhouettes:
            lib = self.libraries[name]
            self._silhouettes[name] = Silhouettes.of(
                lambda T: self._render(name, T, Camera(lib.K, lib.width, lib.height)),
                lib,
                self.models[name].diameter_m,
                self.conf.depth.search_view_step,
            )
        return self._silhouettes[name]

    def _search_due(self, name: str, frame: Frame, store: dict | None = None) -> bool:
        """Whether to search for ``name`` in this frame (the depth search; the plane search with ``store``
        its placements): always without tracking, and when it follows a pose the search found; for an object
        lost since earlier frames only when its RGB estimate was a full one (every
        ``track.lost_full_every``-th frame), as an absent object costs seconds a search."""
        store = self._found if store is None else store
        if not self.tracking() or name not in self._lost or self._previous_pose(store, name, frame) is not None:
            return True
        return (self._lost[name] - 1) % self.conf.track.lost_full_every == 0

    def _previous_pose(self, store: dict, name: str, frame: Frame) -> np.ndarray | None:
        """A search's pose of ``name`` in the previous frame (``store``: name -> (key, pose)), when tracking is
        on and ``frame`` is the next one of its sequence (same scene and camera, ``im_id`` + ``im_step``, within
        ``track.max_gap_s``)."""
        if name not in store or not self.tracking():
            return None
        (scene_id, im_id, stamp_ns, K), pose = store[name]
        gap_s = (frame.stamp_ns - stamp_ns) * 1e-9
        follows = (
            scene_id == frame.scene_id
            and frame.im_id == im_id + frame.im_step
            and np.array_equal(K, frame.camera.K)
            and 0 < gap_s <= self.conf.track.max_gap_s
        )
        return pose if follows else None

    def _verify_weak(self, frame: Frame, rgb: np.ndarray, records: list[PoseRecord]) -> None:
        """``verify_below``: a weak full estimate whose rendered mesh does not look like the frame where it puts
        the object (texture match below ``verify_min_match`` over the pixels no other reported pose hides)
        becomes low_confidence; so does one whose mesh shows under 30 px in the frame at all (beyond the
        renderer's far plane, off the image), which nothing can confirm."""
        conf = self.conf
        if self.renderer is None:
            return
        weak = [
            r for r in records
            if r.ok and not r.tracked and r.confidence < conf.verify_below and r.obj_name in self.models
        ]  # fmt: skip
        if not weak:
            return
        cam = frame.camera
        t0 = time.perf_counter()
        shown = {
            r.obj_name: self._render(r.obj_name, r.cam_from_model, cam)
            for r in records
            if r.ok and r.obj_name in self.models
        }
        lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)
        shared = (time.perf_counter() - t0) / len(weak)
        for rec in weak:
            t0 = time.perf_counter()
            why = self._looks_wrong(rec, shown[rec.obj_name], shown, lab)
            failed = rec
            # A retry's more confident pose that fails: the pose it replaced, checked in turn, when that one passes
            while why is not None and id(failed) in self._replaced:
                failed = self._replaced[id(failed)][1]
                view = self._render(failed.obj_name, failed.cam_from_model, cam)
                if self._looks_wrong(failed, view, shown, lab) is None:
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

    def _looks_wrong(self, rec: PoseRecord, view, shown: dict, lab: np.ndarray) -> str | None:
        """Why the weak pose ``rec``, whose mesh renders as ``view`` (rgb, depth), fails ``verify_below``'s texture
        check (over the pixels the other poses in ``shown`` do not hide); None when it passes."""
        conf = self.conf
        ren_rgb, depth = view
        seen = depth > 0
        weak_why = f"weak pose (confidence {rec.confidence:.2f} < verify_below {conf.verify_below:g})"
        if seen.sum() < VERIFY_MIN_PX:  # beyond the renderer's far plane, or off the image
            return (
                f"{weak_why} that shows {int(seen.sum())} px of the mesh in the frame (object centre "
                f"{rec.cam_from_model[2, 3]:.1f} m away): too little to check it against"
            )
        for name, (_, other) in shown.items():
            if name != rec.obj_name:
                seen &= ~((other > 0) & (other < depth - 0.01))
        if seen.sum() < VERIFY_MIN_PX:  # mostly hidden by reported poses: nothing to judge it by
            return None
        match = texture_match(lab[seen], ren_rgb[seen])
        if match < conf.verify_min_match:
            return (
                f"{weak_why} whose mesh does not look like the frame there (texture match "
                f"{match:.2f} < {conf.verify_min_match:g})"
            )
        return None

    def _use_plane(self, frame: Frame, rgb: np.ndarray, records: list[PoseRecord]) -> None:
        """``plane.enabled``: look for each object without a pose on the surface the confidently found ones rest
        on (:mod:`batchpose.method.plane`)."""
        pc = self.conf.plane
        if self.renderer is None:
            return
        lost = [
            r
            for r in records
            if (r.status in NOT_FOUND or (r.ok and not r.tracked and r.confidence < pc.min_confidence))
            and r.obj_name in self.models
            and self._search_due(r.obj_name, frame, self._placed)
        ]
        if not lost:
            return
        t0 = time.perf_counter()
        found = {
            r.obj_name: (r.cam_from_model, self.models[r.obj_name].mesh.convex_hull)
            for r in records
            if r.ok and r.confidence >= pc.min_confidence and r.obj_name in self.models
        }
        plane = support_plane(found, pc, {name: self._stable_faces(name)[0] for name in found})
        if plane is None:
            for rec in lost:
                self._placed.pop(rec.obj_name, None)
            return
        cam = frame.camera
        covered = np.zeros((cam.height, cam.width), bool)
        nearest = np.full((cam.height, cam.width), np.inf, np.float32)
        searched = {id(r) for r in lost}
        for r in records:  # every pose reported explains its pixels
            if not r.ok or id(r) in searched or r.obj_name not in self.models:
                continue
            depth = self._render(r.obj_name, r.cam_from_model, cam)[1]
            covered |= depth > 0
            nearest = np.where(depth > 0, np.minimum(nearest, depth), nearest)
        shared = (time.perf_counter() - t0) / len(lost)
        for rec in lost:
            t0 = time.perf_counter()
            name = rec.obj_name
            placed = search_plane(
                rgb,
                cam.K,
                plane,
                self._target(name),
                covered,
                nearest,
                lambda T, K, w, h, name=name: self._render(name, T, Camera(K, w, h)),
                pc,
                self._previous_pose(self._placed, name, frame),
                rec.cam_from_model if rec.ok else None,
            )
            rec.timings["plane"] = shared + time.perf_counter() - t0
            if placed is None:
                self._placed.pop(name, None)
                continue
            self._placed[name] = ((frame.scene_id, frame.im_id, frame.stamp_ns, cam.K.copy()), placed.cam_from_model)
            why = {"ok": "a weak SIFT pose", "low_confidence": "a low-confidence SIFT pose"}
            why = why.get(rec.status, "no SIFT pose")
            how = "followed from the previous frame's" if placed.followed else "found by the"
            rec.status, rec.cam_from_model = "ok", placed.cam_from_model
            rec.confidence = 0.25 * (1.0 + placed.match)
            rec.reason = (
                f"{how} plane search ({why}): resting on the surface under {', '.join(plane.objects)}, "
                f"{100 * placed.visible:.0f}% of it unhidden, colour log-odds {placed.colour:.1f}, "
                f"texture match {placed.match:.2f}, contrast {placed.contrast:.1f}"
                + ("" if placed.edge == 0 or not np.isfinite(placed.edge) else f", edges {placed.edge:.2f}")
            )

    def _stable_faces(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The faces the object can rest on (:func:`batchpose.method.plane.stable_faces`; made once)."""
        if name not in self._stable:
            self._stable[name] = stable_faces(self.models[name].mesh)
        return self._stable[name]

    def _target(self, name: str) -> Target:
        """What the plane search needs of the object (made once)."""
        if name not in self._targets:
            mesh = self.models[name].mesh
            self._targets[name] = Target(
                np.asarray(mesh.convex_hull.vertices),
                np.asarray(mesh.bounding_box.centroid),
                self.models[name].diameter_m,
                tuple(resting_faces(self._stable_faces(name), self.conf.plane.min_stable)),
                self._silhouettes_of(name).hist,
            )
        return self._targets[name]

    def _working_size(self, frame: Frame, rgb: np.ndarray) -> tuple[Frame, np.ndarray, np.ndarray]:
        """The frame and its pixels at the size it is estimated at (``max_image_side_px``), with the x and y
        scale factors; the frame itself when it is small enough."""
        cam, scale = working_camera(frame.camera, self.conf.max_image_side_px)
        if cam is frame.camera:
            return frame, rgb, scale
        self._full_frame = frame
        small = cv2.resize(rgb, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        return dataclasses.replace(frame, camera=cam), small, scale

    # -- batch call ------------------------------------------------------------------------------
    def estimate_frame(self, frame: Frame, obj_names: list[str]) -> list[PoseRecord]:
        """Estimate every object in a frame; never raises for bad input (failed records instead).

        With tracking on (``track.enabled`` and a renderer), a confident pose from the previous frame is
        followed into this one instead of being estimated afresh; call :meth:`reset_tracks` between
        unrelated sequences of frames.
        """
        t0 = time.perf_counter()
        full, scale = frame, np.ones(2)
        try:
            rgb = decode_image(frame)
            frame, rgb, scale = self._working_size(frame, rgb)
            t_decode = time.perf_counter() - t0
            if self.tracking():
                records = self._estimate_tracked(rgb, frame, obj_names)
            else:
                records = self.estimate_image(rgb, frame.camera, obj_names, frame.gt, frame.frame_id)
        except BatchposeError as e:
            kind = type(e).__name__
            status = {"ImageError": "bad_image", "CameraError": "bad_camera"}.get(kind, "error")
            records = [PoseRecord(frame.frame_id, n, status, str(e)) for n in obj_names]
            t_decode = time.perf_counter() - t0
        except Exception as e:  # an unexpected bug must not stop the batch; the record says what happened
            log.debug("frame %s failed", frame.frame_id, exc_info=True)
            records = [PoseRecord(frame.frame_id, n, "error", f"{type(e).__name__}: {e}") for n in obj_names]
            t_decode = time.perf_counter() - t0
        if any(r.status in ("bad_image", "bad_camera", "error") for r in records):
            self.reset_tracks()  # a frame that could not be read breaks every track
        else:
            searched = self.conf.depth.enabled and frame.has_depth
            stages = [self._verify_weak] if self.conf.verify_below > 0 else []
            if searched:
                stages.append(self._use_depth)
            if self.conf.plane.enabled and not (searched and self.conf.depth.search):
                stages.append(self._use_plane)
            for stage in stages:
                try:
                    stage(frame, rgb, records)
                except Exception as e:  # a bug in an optional stage must not cost the frame its RGB poses
                    log.warning("%s: %s failed (%s: %s); poses as estimated before it", frame.frame_id,
                                stage.__name__.lstrip("_"), type(e).__name__, e)  # fmt: skip
                    log.debug("%s failed", stage.__name__, exc_info=True)
        self._replaced.clear()
        self._full_frame = None
        if frame is not full:  # back to the full frame's pixels
            for rec in records:
                rec.inliers_px = (np.asarray(rec.inliers_px, float) + 0.5) / scale - 0.5
                rec.median_residual_px /= float(scale.mean())
        for rec in records:
            rec.scene_id, rec.im_id, rec.stamp_ns = frame.scene_id, frame.im_id, frame.stamp_ns
            rec.obj_id = self.obj_ids.get(rec.obj_name, rec.obj_id)
            rec.timings["decode"] = t_decode
        return records
