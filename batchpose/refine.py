"""Render-and-match refinement: re-match the frame against the mesh rendered at the current pose.

A template seen from a generic viewpoint matches a real frame poorly; the mesh rendered at (nearly) the
right pose, with the frame's own camera, looks like the frame. Its SIFT keypoints, lifted to 3D through the
rendered depth, are matched to the frame keypoints that lie near their predicted positions (guided
matching), and the pose is solved again on the new pairs. The number of guided inliers also scores a
hypothesis: a wrong pose renders a view that does not line up with the frame.

Pure: the caller passes a ``render(cam_from_model) -> (rgb, depth_m)`` function.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from batchpose.config import FeatureConfig, GncConfig, RefineConfig
from batchpose.features import detect, to_gray
from batchpose.gnc_pnp import PnpResult, solve_pose
from batchpose.templates import lift_keypoints

RenderFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class Refined:
    """A refined hypothesis: the PnP result on guided pairs, with those pairs."""

    result: PnpResult
    x: np.ndarray
    X: np.ndarray

    @property
    def score(self) -> int:
        return self.result.n_inliers if self.result.status == "ok" else 0


def guided_matches(
    xy_r: np.ndarray,
    desc_r: np.ndarray,
    xy_q: np.ndarray,
    desc_q: np.ndarray,
    radius_px: float,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match rendered keypoints to frame keypoints within ``radius_px`` of the same pixel.

    Ratio test among the frame keypoints inside the radius, plus a mutual best-match check.

    Args:
        xy_r, desc_r: (R, 2) rendered keypoint pixels and (R, 128) descriptors.
        xy_q, desc_q: (Q, 2) frame keypoint pixels and (Q, 128) descriptors.

    Returns:
        r_idx, q_idx: (M,) int indices of matched pairs.
    """
    if len(xy_r) == 0 or len(xy_q) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    # Only frame keypoints inside the rendered keypoints' bounding box (+radius) can match.
    lo, hi = xy_r.min(axis=0) - radius_px, xy_r.max(axis=0) + radius_px
    cand = np.nonzero(np.all((xy_q >= lo) & (xy_q <= hi), axis=1))[0]
    if len(cand) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    q_xy, q_desc = xy_q[cand], desc_q[cand].astype(np.float64)
    r_desc = desc_r.astype(np.float64)
    d2 = (r_desc**2).sum(1)[:, None] + (q_desc**2).sum(1)[None, :] - 2.0 * r_desc @ q_desc.T
    d = np.sqrt(np.maximum(d2, 0.0))
    near = np.linalg.norm(xy_r[:, None, :] - q_xy[None, :, :], axis=2) <= radius_px
    d = np.where(near, d, np.inf)
    order = np.argsort(d, axis=1)[:, :2]
    rows = np.arange(len(d))
    best, second = d[rows, order[:, 0]], d[rows, order[:, 1]]
    ok = np.isfinite(best) & (best < ratio * second)
    # Mutual check: the frame keypoint's best rendered keypoint must be this one.
    best_r_for_q = np.argmin(d, axis=0)
    ok &= best_r_for_q[order[:, 0]] == rows
    r_idx = np.nonzero(ok)[0]
    return r_idx, cand[order[r_idx, 0]]


def refine_pose(
    cam_from_model: np.ndarray,
    xy_q: np.ndarray,
    desc_q: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    render: RenderFn,
    conf: RefineConfig,
    feature_conf: FeatureConfig,
    gnc_conf: GncConfig,
    w_geom_fn: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Refined | None:
    """Refine a pose by ``conf.iterations`` rounds of render -> SIFT -> guided match -> PnP.

    Returns:
        The last successful round (None when the first round finds too few pairs).
    """
    best: Refined | None = None
    T = cam_from_model
    gnc_conf = dataclasses.replace(gnc_conf, mu_final_px=conf.mu_final_px)
    for _ in range(conf.iterations):
        rgb, depth = render(T)
        ys, xs = np.nonzero(depth > 0)
        if len(xs) == 0:
            break
        pad = feature_conf.crop_padding_px
        h, w = depth.shape
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, w)
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, h)
        xy_r, desc_r = detect(to_gray(rgb[y0:y1, x0:x1]), feature_conf)
        xy_r = xy_r + np.array([x0, y0], np.float32)
        keep, X_r = lift_keypoints(xy_r, depth, K, np.linalg.inv(T))
        xy_r, desc_r = xy_r[keep], desc_r[keep]
        r_idx, q_idx = guided_matches(xy_r, desc_r, xy_q, desc_q, conf.radius_px, conf.ratio)
        if len(r_idx) < gnc_conf.min_inliers:
            break
        x, X = xy_q[q_idx].astype(np.float64), X_r[r_idx].astype(np.float64)
        w = w_geom_fn(X) if w_geom_fn is not None else None
        res = solve_pose(x, X, K, dist, w, gnc_conf)
        if res.status != "ok":
            break
        cand = Refined(res, x, X)
        if best is not None and cand.score < best.score:
            break
        best, T = cand, res.cam_from_model
    return best
