"""Template library: rendered views of a mesh with SIFT keypoints lifted to model-frame 3D points.

Pure data and computation; :mod:`batchpose.stages.build_templates` caches libraries on disk.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.config import FeatureConfig, RenderConfig
from batchpose.core.model import ObjectModel
from batchpose.method.features import detect_shapes, make_sift, to_gray
from batchpose.method.views import sample_views

log = logging.getLogger("batchpose")


@dataclass
class TemplateLibrary:
    """All template keypoints of one object.

    Attributes:
        obj_name: object name.
        key: cache key (hash of mesh content, render and feature config, camera).
        K: (3, 3) template intrinsics; width, height: template image size.
        views: one row per view: view_id, azimuth_deg, elevation_deg, distance_m,
            cam_from_model (list of 16, row-major), n_keypoints.
        view_ids: (N,) int32 view of each keypoint.
        xy: (N, 2) float32 keypoint pixel position in its template.
        desc: (N, 128) float32 descriptors.
        pts3d: (N, 3) float32 model-frame 3D points, metres.
        shapes: (N, 2) float32 keypoint (size_px, angle_deg) in its template (see
            :func:`batchpose.method.features.detect_shapes`).
        folder: the cache folder it was loaded from (None when built in memory); its descriptor index is
            kept there too (:func:`batchpose.method.correspondences.flann_index`).
    """

    obj_name: str
    key: str
    K: np.ndarray
    width: int
    height: int
    views: pd.DataFrame
    view_ids: np.ndarray
    xy: np.ndarray
    desc: np.ndarray
    pts3d: np.ndarray
    shapes: np.ndarray
    folder: Path | None = None

    @property
    def n_views(self) -> int:
        return len(self.views)

    def cam_from_model(self, view_id: int) -> np.ndarray:
        return np.asarray(self.views["cam_from_model"].iloc[view_id], dtype=np.float64).reshape(4, 4)

    def cams_from_model(self) -> np.ndarray:
        """(n_views, 4, 4) every view's ``cam_from_model``, stacked once (the locator asks per frame)."""
        if getattr(self, "_cams", None) is None:
            self._cams = np.stack([self.cam_from_model(v) for v in range(self.n_views)])
        return self._cams


def auto_distances(model: ObjectModel, K: np.ndarray, width: int, height: int, conf: RenderConfig):
    """Camera distances (metres) at which the object's diameter spans ``conf.image_fractions``."""
    if conf.distances_m:
        return tuple(conf.distances_m)
    f = 0.5 * (K[0, 0] + K[1, 1])
    return tuple(float(f * model.diameter_m / (frac * min(width, height))) for frac in conf.image_fractions)


def lift_keypoints(
    xy: np.ndarray, depth_m: np.ndarray, K: np.ndarray, model_from_cam: np.ndarray, radius: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project keypoints through a rendered depth map into the model frame.

    A keypoint is kept only when every depth sample within ``radius`` pixels is on the surface, so
    silhouette keypoints (whose neighbourhood is background) are dropped.

    Args:
        xy: (N, 2) pixel positions. depth_m: (H, W) z-depth, 0 = background. K: (3, 3).
        model_from_cam: (4, 4).

    Returns:
        keep (N,) bool and pts3d (M, 3) float32 model-frame points for the kept keypoints.
    """
    h, w = depth_m.shape
    u = np.rint(xy[:, 0]).astype(int)
    v = np.rint(xy[:, 1]).astype(int)
    keep = (u >= radius) & (v >= radius) & (u < w - radius) & (v < h - radius)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            vv = np.clip(v + dv, 0, h - 1)
            uu = np.clip(u + du, 0, w - 1)
            keep &= depth_m[vv, uu] > 0
    d = depth_m[v[keep], u[keep]].astype(np.float64)
    pix = np.column_stack([xy[keep].astype(np.float64), np.ones(keep.sum())])
    cam = (np.linalg.inv(K) @ pix.T).T * d[:, None]
    model = cam @ model_from_cam[:3, :3].T + model_from_cam[:3, 3]
    return keep, model.astype(np.float32)


def _view_keypoints(rgb, depth, K, T, pad: int, feature_conf: FeatureConfig, sift):
    """SIFT on one rendered view's object box (grown by ``pad``), lifted to 3D through the rendered depth:
    (xy (N, 2), descriptors (N, 128), shapes (N, 2), model points (N, 3)) of the keypoints on the object;
    None when the view shows none of it."""
    height, width = depth.shape
    ys, xs = np.nonzero(depth > 0)
    if not len(xs):
        return None
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, width)
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, height)
    xy, desc, shapes = detect_shapes(to_gray(rgb[y0:y1, x0:x1]), feature_conf, sift=sift)
    xy = xy + np.array([x0, y0], np.float32)
    keep, pts = lift_keypoints(xy, depth, K, np.linalg.inv(T))
    return xy[keep], desc[keep], shapes[keep], pts


def _concatenated(parts: list[np.ndarray], shape: tuple[int, ...], dt) -> np.ndarray:
    return np.concatenate(parts).astype(dt) if parts else np.zeros(shape, dt)


def render_templates(
    model: ObjectModel,
    K: np.ndarray,
    width: int,
    height: int,
    render_conf: RenderConfig,
    feature_conf: FeatureConfig,
    renderer,
    key: str = "",
    progress=None,
) -> TemplateLibrary:
    """Render every view, run SIFT on the object's box and lift keypoints to 3D.

    Args:
        renderer: a :class:`batchpose.method.render.Renderer`.
        progress: optional callable(n) called after each view.
    """
    distances = auto_distances(model, K, width, height, render_conf)
    views = sample_views(
        render_conf.view_preset,
        model.center_m,
        distances,
        n_views=render_conf.n_views,
        min_elevation_deg=render_conf.min_elevation_deg,
        azimuth_step_deg=render_conf.paper_azimuth_step_deg,
        height_m=render_conf.paper_height_m,
    )
    sift = make_sift(feature_conf)
    pad = feature_conf.crop_padding_px
    all_ids, all_xy, all_desc, all_pts, all_shapes, rows = [], [], [], [], [], []
    for view in views:
        T = view["cam_from_model"]
        rgb, depth = renderer.render(
            model.content_hash,
            model.mesh,
            T,
            K,
            width,
            height,
            render_conf.shading,
            render_conf.znear_m,
            render_conf.zfar_m,
        )
        n_kept = 0
        found = _view_keypoints(rgb, depth, K, T, pad, feature_conf, sift)
        if found is not None:
            xy, desc, shapes, pts = found
            n_kept = len(xy)
            all_ids.append(np.full(n_kept, view["view_id"], np.int32))
            all_xy.append(xy)
            all_desc.append(desc)
            all_pts.append(pts)
            all_shapes.append(shapes)
        rows.append(
            {
                "view_id": view["view_id"],
                "azimuth_deg": view["azimuth_deg"],
                "elevation_deg": view["elevation_deg"],
                "distance_m": view["distance_m"],
                "cam_from_model": T.reshape(-1).tolist(),
                "n_keypoints": n_kept,
            }
        )
        if progress is not None:
            progress(1)

    cat = _concatenated
    return TemplateLibrary(
        obj_name=model.name,
        key=key,
        K=np.asarray(K, np.float64),
        width=width,
        height=height,
        views=pd.DataFrame(rows),
        view_ids=cat(all_ids, (0,), np.int32),
        xy=cat(all_xy, (0, 2), np.float32),
        desc=cat(all_desc, (0, 128), np.float32),
        pts3d=cat(all_pts, (0, 3), np.float32),
        shapes=cat(all_shapes, (0, 2), np.float32),
    )
