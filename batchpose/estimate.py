"""One frame in, one pose record per target object out: SIFT -> matches -> weights -> GNC-PnP.

:class:`PoseEstimator` holds the template libraries (and their FLANN indices, built once per process).
``estimate_image`` is the library call and raises :class:`BatchposeError` on bad input;
``estimate_frame`` is the batch call and turns every failure into a record.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.correspondences import (
    Correspondences,
    flann_index,
    match_query_to_template,
    match_template_to_query,
    vote_views,
)
from batchpose.errors import BatchposeError, ImageError
from batchpose.features import detect, make_sift, to_gray
from batchpose.frames import Camera, Frame, ObjectPose, decode_image
from batchpose.gnc_pnp import solve_pose
from batchpose.poses import PoseRecord
from batchpose.refine import refine_pose
from batchpose.templates import TemplateLibrary
from batchpose.weights import geom_weights, model_support, model_voxel_grid, support_to_weights

log = logging.getLogger("batchpose")


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


class PoseEstimator:
    """Estimates poses of objects whose template libraries it holds.

    Args:
        conf: estimator config.
        libraries: obj_name -> TemplateLibrary.
        obj_ids: obj_name -> numeric id for records (BOP obj_id); optional.
        models: obj_name -> ObjectModel, needed (with ``renderer``) for ``refine.enabled``.
        renderer: a :class:`batchpose.render.Renderer` (or anything with its ``render`` method).
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
        self._lib_index: dict[str, object] = {}
        self._voxels: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    # -- per-object caches -------------------------------------------------------------------------
    def _library_index(self, name: str):
        if name not in self._lib_index:
            self._lib_index[name] = flann_index(self.libraries[name].desc, self.conf.match)
        return self._lib_index[name]

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
    ) -> list[PoseRecord]:
        """Estimate every object in ``obj_names`` in one RGB image.

        Args:
            rgb: (H, W, 3) uint8 RGB.
            camera: calibration of this image.
            obj_names: objects to look for (each must have a library).
            gt: ground-truth poses, used only by the ``match.roi: gt_box`` oracle and ``method: tp_ub``.

        Raises:
            ImageError / CameraError: the image or calibration is unusable.
        """
        camera.validate(frame_id)
        check_image(rgb, frame_id)
        for name in obj_names:
            if name not in self.libraries:
                raise BatchposeError(f"{frame_id}: no template library for object {name!r}")
        t0 = time.perf_counter()
        xy_q, desc_q = detect(to_gray(rgb), self.conf.features, sift=self._sift)
        t_sift = time.perf_counter() - t0
        query_index = None
        if self.conf.match.direction == "template_to_query":
            query_index = flann_index(desc_q, self.conf.match)
        gt_by_name = {p.obj_name: p.cam_from_model for p in gt}
        records = []
        for name in obj_names:
            rec = self._estimate_object(name, xy_q, desc_q, query_index, camera, gt_by_name.get(name), frame_id)
            rec.timings["sift"] = t_sift
            records.append(rec)
        return records

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
        xy_q: np.ndarray,
        desc_q: np.ndarray,
        query_index,
        camera: Camera,
        gt_pose: np.ndarray | None,
        frame_id: str,
    ) -> PoseRecord:
        conf = self.conf
        if conf.method == "tp_ub":
            return self._tp_ub(name, gt_pose, frame_id)
        lib = self.libraries[name]
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        roi = self._roi_mask(xy_q, camera, gt_pose, name)
        if conf.match.direction == "template_to_query":
            views = None
            if conf.match.prefilter_views and conf.match.prefilter_views < lib.n_views:
                views = vote_views(desc_q, self._library_index(name), lib, conf.match.prefilter_views, conf.match, roi)
            corr = match_template_to_query(xy_q, query_index, lib, conf.match, candidate_mask=roi, views=views)
        else:
            sel = np.ones(len(xy_q), bool) if roi is None else roi
            corr = match_query_to_template(xy_q[sel], desc_q[sel], self._library_index(name), lib, conf.match)
        timings["match"] = time.perf_counter() - t0
        rec = PoseRecord(frame_id, name, "ok", obj_id=self.obj_ids.get(name, 0), timings=timings)
        rec.n_matches = len(corr)
        rec.templates = corr.templates
        if len(corr) < conf.min_matches:
            rec.status = "too_few_matches"
            rec.reason = f"{len(corr)} matches after the ratio test, need {conf.min_matches}"
            return rec
        t0 = time.perf_counter()
        w = self._weights(name, corr)
        timings["weights"] = time.perf_counter() - t0
        res = solve_pose(corr.x, corr.X, camera.K, camera.dist, w, conf.gnc)
        timings.update(res.timings)
        x_used = corr.x
        if self._can_refine(name):
            t0 = time.perf_counter()
            refined = self._refine(name, res, corr, camera, xy_q, desc_q)
            timings["refine"] = time.perf_counter() - t0
            if refined is not None:
                res, x_used = refined.result, refined.x
        rec.status, rec.reason = res.status, res.reason
        if not res.status == "ok":
            return rec
        rec.cam_from_model = res.cam_from_model
        rec.n_inliers = res.n_inliers
        rec.median_residual_px = res.median_residual_px
        rec.inliers_px = x_used[res.inliers]
        rec.confidence = confidence(rec.n_inliers, rec.median_residual_px, conf)
        return rec

    def _can_refine(self, name: str) -> bool:
        return self.conf.refine.enabled and self.renderer is not None and name in self.models

    def _refine(self, name, res, corr: Correspondences, camera: Camera, xy_q, desc_q):
        """Refine the pose (and, with ``refine.hypotheses`` > 1, per-template poses); best guided score."""
        conf = self.conf
        model = self.models[name]

        def render(T):
            return self.renderer.render(
                model.content_hash,
                model.mesh,
                T,
                camera.K,
                camera.width,
                camera.height,
                "flat",
                conf.render.znear_m,
                conf.render.zfar_m,
            )

        starts = [res.cam_from_model] if res.status == "ok" else []
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
            return refine_pose(
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
            )

        # One round per hypothesis to rank them, the remaining rounds for the best one only.
        best = None
        for T in starts:
            r = refine(T, 1)
            if r is not None and (best is None or r.score > best.score):
                best = r
        if best is not None and conf.refine.iterations > 1:
            more = refine(best.result.cam_from_model, conf.refine.iterations - 1)
            if more is not None and more.score >= best.score:
                best = more
        if best is not None and res.status == "ok" and best.score < res.n_inliers:
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

    # -- batch call ------------------------------------------------------------------------------
    def estimate_frame(self, frame: Frame, obj_names: list[str]) -> list[PoseRecord]:
        """Estimate every object in a frame; never raises for bad input (failed records instead)."""
        t0 = time.perf_counter()
        try:
            rgb = decode_image(frame)
            t_decode = time.perf_counter() - t0
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
        for rec in records:
            rec.scene_id, rec.im_id, rec.stamp_ns = frame.scene_id, frame.im_id, frame.stamp_ns
            rec.obj_id = self.obj_ids.get(rec.obj_name, rec.obj_id)
            rec.timings["decode"] = t_decode
        return records
