"""2D-3D correspondences between a frame's SIFT features and an object's template library (SPEC §2).

Pure computation over arrays; FLANN indices are built by the caller and reused (one per frame for
``template_to_query``, one per object library for ``query_to_template``).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.config import MatchConfig
from batchpose.templates import TemplateLibrary

try:
    _LIBC = ctypes.CDLL(None)
except OSError:  # pragma: no cover - platforms without a C library handle
    _LIBC = None


@dataclass
class Correspondences:
    """Matched pairs.

    Attributes:
        x: (N, 2) float64 image points, pixels.
        X: (N, 3) float64 model points, metres.
        view_ids: (N,) int32 template each pair came from.
        templates: the selected template view ids, best first.
        n_candidates: matches that passed the ratio test before top-k selection.
    """

    x: np.ndarray
    X: np.ndarray
    view_ids: np.ndarray
    templates: tuple[int, ...]
    n_candidates: int

    def __len__(self) -> int:
        return len(self.x)

    def subset(self, mask: np.ndarray) -> Correspondences:
        return Correspondences(self.x[mask], self.X[mask], self.view_ids[mask], self.templates, self.n_candidates)


def seed_c_rand(seed: int = 0) -> None:
    """Seed the generators FLANN's randomised KD-trees draw from (C ``rand()`` in older OpenCV builds,
    OpenCV's thread RNG in newer ones), so an index does not depend on what ran before it."""
    cv2.setRNGSeed(seed)
    if _LIBC is not None:
        _LIBC.srand(ctypes.c_uint(seed))


def flann_index(desc: np.ndarray, conf: MatchConfig):
    """A FLANN KD-tree index over (N, 128) float32 descriptors (None when N < 2).

    The trees are randomised; seeding first makes every index (and so every match) independent of what
    the process built before, so results do not depend on how frames are spread over workers.
    """
    if len(desc) < 2:
        return None
    seed_c_rand(0)
    return cv2.flann_Index(np.ascontiguousarray(desc, np.float32), {"algorithm": 1, "trees": conf.flann_trees})


def knn(index, queries: np.ndarray, k: int, conf: MatchConfig) -> tuple[np.ndarray, np.ndarray]:
    """k nearest neighbours: indices (N, k) int and L2 distances (N, k) float64."""
    idx, d2 = index.knnSearch(np.ascontiguousarray(queries, np.float32), k, params={"checks": conf.flann_checks})
    return idx.astype(np.int64), np.sqrt(np.maximum(d2.astype(np.float64), 0.0))


def _select_top_k(
    q_idx: np.ndarray, t_idx: np.ndarray, dist: np.ndarray, lib: TemplateLibrary, xy_q: np.ndarray, k: int
) -> Correspondences:
    """Keep the k views with most matches; one pair per (view, query keypoint), the closest."""
    n_cand = len(q_idx)
    if n_cand == 0:
        return Correspondences(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int32), (), 0)
    views = lib.view_ids[t_idx]
    counts = np.bincount(views, minlength=lib.n_views)
    top = np.argsort(-counts, kind="stable")[:k]
    top = top[counts[top] > 0]
    sel = np.isin(views, top)
    q_idx, t_idx, dist, views = q_idx[sel], t_idx[sel], dist[sel], views[sel]
    # One pair per (view, query keypoint): several template keypoints of one view may claim the same
    # frame keypoint; the closest descriptor wins.
    order = np.lexsort((dist, q_idx, views))
    q_idx, t_idx, views = q_idx[order], t_idx[order], views[order]
    first = np.ones(len(q_idx), bool)
    first[1:] = (q_idx[1:] != q_idx[:-1]) | (views[1:] != views[:-1])
    q_idx, t_idx, views = q_idx[first], t_idx[first], views[first]
    return Correspondences(
        x=xy_q[q_idx].astype(np.float64),
        X=lib.pts3d[t_idx].astype(np.float64),
        view_ids=views.astype(np.int32),
        templates=tuple(int(v) for v in top),
        n_candidates=n_cand,
    )


def vote_views(
    desc_q: np.ndarray, lib_index, lib: TemplateLibrary, n_views: int, conf: MatchConfig, mask=None
) -> np.ndarray:
    """The ``n_views`` views with the most frame keypoints matched into them.

    Each frame keypoint votes for the view of its nearest template descriptor when it passes a loose
    ratio test (``conf.prefilter_ratio``) against the nearest descriptor of a different 3D point.

    Returns:
        (n_views,) int view ids, most votes first.
    """
    q = desc_q if mask is None else desc_q[mask]
    if lib_index is None or len(q) == 0:
        return np.arange(min(n_views, lib.n_views))
    k = min(4, len(lib.desc))
    idx, dist = knn(lib_index, q, k, conf)
    p = lib.pts3d[idx]
    far = np.linalg.norm(p - p[:, :1], axis=2) > conf.distinct_3d_m
    far[:, 0] = False
    rival = np.where(far.any(axis=1), dist[np.arange(len(dist)), far.argmax(axis=1)], np.inf)
    ok = dist[:, 0] < conf.prefilter_ratio * rival
    votes = np.bincount(lib.view_ids[idx[ok, 0]], minlength=lib.n_views)
    return np.argsort(-votes, kind="stable")[:n_views]


def match_template_to_query(
    xy_q: np.ndarray,
    query_index,
    lib: TemplateLibrary,
    conf: MatchConfig,
    candidate_mask=None,
    views: np.ndarray | None = None,
) -> Correspondences:
    """Ratio test from every template keypoint (of ``views``, default all) into the frame's keypoints.

    Args:
        xy_q: (M, 2) frame keypoints. query_index: FLANN index over the frame's descriptors.
        candidate_mask: optional (M,) bool; matches to frame keypoints outside it are dropped (ROI).
        views: optional view ids whose keypoints are tested (see :func:`vote_views`).
    """
    if query_index is None or len(lib.desc) == 0:
        return _select_top_k(np.zeros(0, int), np.zeros(0, int), np.zeros(0), lib, xy_q, conf.top_k_templates)
    rows = np.arange(len(lib.desc)) if views is None else np.nonzero(np.isin(lib.view_ids, views))[0]
    idx, dist = knn(query_index, lib.desc[rows], 2, conf)
    ok = dist[:, 0] < conf.ratio * dist[:, 1]
    if candidate_mask is not None:
        ok &= candidate_mask[idx[:, 0]]
    keep = np.nonzero(ok)[0]
    idx, dist, t_idx = idx[keep], dist[keep], rows[keep]
    return _select_top_k(idx[:, 0], t_idx, dist[:, 0], lib, xy_q, conf.top_k_templates)


def match_query_to_template(
    xy_q: np.ndarray, desc_q: np.ndarray, lib_index, lib: TemplateLibrary, conf: MatchConfig, k: int = 8
) -> Correspondences:
    """Ratio test from every frame keypoint into the object's template descriptors.

    The rival of the nearest neighbour is the nearest one whose 3D point lies more than
    ``conf.distinct_3d_m`` away: another view of the same surface point is not a rival.
    """
    if lib_index is None or len(desc_q) == 0:
        return _select_top_k(np.zeros(0, int), np.zeros(0, int), np.zeros(0), lib, xy_q, conf.top_k_templates)
    k = min(k, len(lib.desc))
    idx, dist = knn(lib_index, desc_q, k, conf)
    p = lib.pts3d[idx]  # (M, k, 3)
    far = np.linalg.norm(p - p[:, :1], axis=2) > conf.distinct_3d_m
    far[:, 0] = False
    has_rival = far.any(axis=1)
    rival = np.where(has_rival, dist[np.arange(len(dist)), far.argmax(axis=1)], np.inf)
    ok = dist[:, 0] < conf.ratio * rival
    q_idx = np.nonzero(ok)[0]
    return _select_top_k(q_idx, idx[q_idx, 0], dist[q_idx, 0], lib, xy_q, conf.top_k_templates)
