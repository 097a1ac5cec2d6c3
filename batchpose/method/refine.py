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
from scipy.spatial import cKDTree

from batchpose.config import FeatureConfig, GncConfig, RefineConfig
from batchpose.method.features import detect, to_gray
from batchpose.method.gnc_pnp import PnpResult, solve_pose
from batchpose.method.templates import lift_keypoints

RenderFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class Refined:
    """A refined hypothesis: the PnP result on guided pairs, with those pairs."""

    result: PnpResult
    x: np.ndarray
    X: np.ndarray
    support_px: float = 0.0

    @property
    def score(self) -> int:
        """The pairs reprojected within ``support_px`` (0: the inliers)."""
        return self.result.support(self.support_px)


def guided_matches(
    xy_r: np.ndarray,
    desc_r: np.ndarray,
    xy_q: np.ndarray,
    desc_q: np.ndarray,
    radius_px: float,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match rendered keypoints to frame keypoints within ``radius_px`` of the same pixel.

    Ratio test among the frame keypoints inside the radius, plus a mutual best-match check. Descriptor
    distances are computed only for the pairs that are close in the image (a KD-tree over positions).

    Args:
        xy_r, desc_r: (R, 2) rendered keypoint pixels and (R, 128) descriptors.
        xy_q, desc_q: (Q, 2) frame keypoint pixels and (Q, 128) descriptors.

    Returns:
        r_idx, q_idx: (M,) int indices of matched pairs.
    """
    empty = np.zeros(0, int), np.zeros(0, int)
    if len(xy_r) == 0 or len(xy_q) == 0:
        return empty
    pairs = cKDTree(xy_r).query_ball_tree(cKDTree(xy_q), r=radius_px)
    counts = np.fromiter((len(p) for p in pairs), int, len(pairs))
    if counts.sum() == 0:
        return empty
    ri = np.repeat(np.arange(len(xy_r)), counts)
    qi = np.fromiter((j for p in pairs for j in p), int, counts.sum())
    diff = desc_r[ri].astype(np.float32) - desc_q[qi].astype(np.float32)
    d = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    # Per rendered keypoint: best and second-best frame keypoint inside the radius.
    order = np.lexsort((d, ri))
    ri, qi, d = ri[order], qi[order], d[order]
    first = np.ones(len(ri), bool)
    first[1:] = ri[1:] != ri[:-1]
    start = np.nonzero(first)[0]
    n_per = np.diff(np.append(start, len(ri)))
    second = np.full(len(start), np.inf)
    has2 = n_per > 1
    second[has2] = d[start[has2] + 1]
    ok = d[start] < ratio * second
    # Mutual check: the frame keypoint's closest rendered keypoint (within the radius) must be this one.
    order_q = np.lexsort((d, qi))
    q_sorted = qi[order_q]
    q_first = np.ones(len(q_sorted), bool)
    q_first[1:] = q_sorted[1:] != q_sorted[:-1]
    best_r_for_q = dict(zip(q_sorted[q_first].tolist(), ri[order_q][q_first].tolist(), strict=True))
    r_best, q_best = ri[start], qi[start]
    mutual = np.fromiter(
        (best_r_for_q[q] == r for r, q in zip(r_best.tolist(), q_best.tolist(), strict=True)), bool, len(r_best)
    )
    ok &= mutual
    return r_best[ok], q_best[ok]


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
    iterations: int | None = None,
    support_px: float = 0.0,
) -> Refined | None:
    """Refine a pose by ``iterations`` (default ``conf.iterations``) rounds of render -> SIFT -> guided
    match -> PnP; a round that scores lower (:attr:`Refined.score`, with ``support_px``) ends it.

    Returns:
        The last successful round (None when the first round finds too few pairs).
    """
    best: Refined | None = None
    T = cam_from_model
    gnc_conf = dataclasses.replace(gnc_conf, mu_final_px=conf.mu_final_px, enabled=gnc_conf.enabled and conf.gnc)
    for _ in range(conf.iterations if iterations is None else iterations):
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
        cand = Refined(res, x, X, support_px)
        if best is not None and cand.score < best.score:
            break
        assert res.cam_from_model is not None  # an "ok" result carries its pose
        best, T = cand, res.cam_from_model
    return best
