"""2D-3D correspondences between a frame's SIFT features and an object's template library (SPEC §2).

Pure computation over arrays; FLANN indices are built by the caller and reused (one per frame for
``template_to_query``, one per object library for ``query_to_template``).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from batchpose.config import MatchConfig
from batchpose.method.templates import TemplateLibrary

log = logging.getLogger("batchpose")

_LIBC: ctypes.CDLL | None
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


@dataclass(frozen=True)
class Location:
    """Where :func:`locate` puts the object: image centre and diameter (pixels), the number of agreeing
    votes and their 2D-3D pairs."""

    centre_xy: tuple[float, float]
    size_px: float
    votes: int
    pairs: Correspondences


def seed_c_rand(seed: int = 0) -> None:
    """Seed the generators FLANN's randomised KD-trees draw from (C ``rand()`` in older OpenCV builds,
    OpenCV's thread RNG in newer ones), so an index does not depend on what ran before it."""
    cv2.setRNGSeed(seed)
    if _LIBC is not None:
        _LIBC.srand(ctypes.c_uint(seed))


def flann_index(desc: np.ndarray, conf: MatchConfig, keep_in: Path | None = None):
    """A FLANN KD-tree index over (N, 128) float32 descriptors (None when N < 2).

    The trees are randomised; seeding first makes every index (and so every match) independent of what
    the process built before, so results do not depend on how frames are spread over workers.

    ``keep_in``: a folder (a template library's) to keep the built index in and load it from next time —
    the same trees, so the same matches, in ~0.1 s instead of ~0.5 s for a YCB library, in every worker of
    every run. The file is named by the FLANN settings and OpenCV's version and checked against a SHA-256
    beside it before OpenCV reads it; a folder that cannot be written only costs the build.
    """
    if len(desc) < 2:
        return None
    desc = np.ascontiguousarray(desc, np.float32)
    path = None if keep_in is None else Path(keep_in) / f"flann-kdtree{conf.flann_trees}-opencv{cv2.__version__}.idx"
    if path is not None and (index := _load_index(path, desc)) is not None:
        return index
    seed_c_rand(0)
    index = cv2.flann_Index(desc, {"algorithm": 1, "trees": conf.flann_trees})
    if path is not None:
        _save_index(index, path, desc)
    return index


def _index_check(index_bytes: bytes, desc: np.ndarray) -> str:
    """What the index file's SHA-256 side file holds: the file's digest and the descriptors' shape."""
    return f"{hashlib.sha256(index_bytes).hexdigest()} {desc.shape[0]}x{desc.shape[1]}\n"


def _load_index(path: Path, desc: np.ndarray):
    """The index kept in ``path`` when it and its check file agree; None otherwise."""
    check = path.with_name(path.name + ".sha256")
    try:
        data, expected = path.read_bytes(), check.read_text()
    except (OSError, UnicodeDecodeError):
        return None
    if _index_check(data, desc) != expected:
        log.warning("%s: kept descriptor index does not match its check file; building it again", path)
        return None
    index = cv2.flann_Index()
    if not index.load(desc, str(path)):
        return None
    return index


def _save_index(index, path: Path, desc: np.ndarray) -> None:
    """Keep ``index`` in ``path`` with its check file, each written whole (a killed run leaves none or an
    index without a matching check file, which is rebuilt)."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        index.save(str(tmp))
        check = _index_check(tmp.read_bytes(), desc)
        tmp_check = tmp.with_name(tmp.name + ".sha256")
        tmp_check.write_text(check)
        os.replace(tmp, path)
        os.replace(tmp_check, path.with_name(path.name + ".sha256"))
    except (OSError, cv2.error) as e:
        log.debug("%s: descriptor index not kept (%s)", path, e)
    finally:
        for p in (tmp, tmp.with_name(tmp.name + ".sha256")):
            try:
                p.unlink(missing_ok=True)
            except OSError:
                pass


def knn(
    index, queries: np.ndarray, k: int, conf: MatchConfig, checks: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """k nearest neighbours: indices (N, k) int and L2 distances (N, k) float64. ``checks``: the leaves to
    visit (default ``conf.flann_checks``)."""
    checks = conf.flann_checks if checks is None else checks
    idx, d2 = index.knnSearch(np.ascontiguousarray(queries, np.float32), k, params={"checks": checks})
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


def nearest_with_rival(desc_q: np.ndarray, lib_index, lib: TemplateLibrary, conf: MatchConfig, k: int = 4):
    """Each frame descriptor's ``k`` nearest template descriptors and its rival: the distance to the
    nearest of them whose 3D point lies farther than ``conf.distinct_3d_m`` from the best one's (inf when
    none does), so a second view of the same surface point is not a rival.

    Returns:
        idx, dist: (M, min(k, library size)) nearest template descriptor indices and distances;
        rival: (M,) the rival distance.
    """
    idx, dist = knn(lib_index, desc_q, min(k, len(lib.desc)), conf)
    return idx, dist, rival_distance(dist, far_points(lib.pts3d[idx], conf))


def far_points(pts: np.ndarray, conf: MatchConfig) -> np.ndarray:
    """(M, k) bool: which of each keypoint's k nearest template descriptors, (M, k, 3) 3D points ``pts``, lie
    farther than ``conf.distinct_3d_m`` from the nearest one's."""
    return np.linalg.norm(pts - pts[:, :1], axis=2) > conf.distinct_3d_m


def rival_distance(dist: np.ndarray, rival: np.ndarray) -> np.ndarray:
    """(M,) the distance to the nearest of each keypoint's k neighbours (``dist`` (M, k), nearest first) that
    ``rival`` (M, k) bool marks (the first is never one); inf where none is."""
    rival = rival.copy()
    rival[:, 0] = False
    return np.where(rival.any(axis=1), dist[np.arange(len(dist)), rival.argmax(axis=1)], np.inf)


def vote_views(
    desc_q: np.ndarray, lib_index, lib: TemplateLibrary, n_views: int, conf: MatchConfig, mask=None, nearest=None
) -> np.ndarray:
    """The ``n_views`` views with the most frame keypoints matched into them.

    Each frame keypoint votes for the view of its nearest template descriptor when it passes a loose
    ratio test (``conf.prefilter_ratio``) against the nearest descriptor of a different 3D point.

    ``nearest``: :func:`nearest_with_rival` of all of ``desc_q`` (default ``k``) when the caller has it.

    Returns:
        (n_views,) int view ids, most votes first.
    """
    q = desc_q if mask is None else desc_q[mask]
    if lib_index is None or len(q) == 0:
        return np.arange(min(n_views, lib.n_views))
    if nearest is None:
        idx, dist, rival = nearest_with_rival(q, lib_index, lib, conf)
    else:
        idx, dist, rival = (a if mask is None else a[mask] for a in nearest)
    ok = dist[:, 0] < conf.prefilter_ratio * rival
    votes = np.bincount(lib.view_ids[idx[ok, 0]], minlength=lib.n_views)
    return np.argsort(-votes, kind="stable")[:n_views]


def template_to_query_candidates(
    query_index, lib: TemplateLibrary, conf: MatchConfig, candidate_mask=None, views: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The template keypoints (of ``views``, default all) that pass the ratio test into the frame's.

    Each template keypoint is tested on its own, so the candidates of several view sets concatenate to
    those of their union.

    Returns:
        q_idx, t_idx, dist: (N,) frame keypoint, template keypoint and descriptor distance of each pair.
    """
    if query_index is None or len(lib.desc) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    rows = np.arange(len(lib.desc)) if views is None else np.nonzero(np.isin(lib.view_ids, views))[0]
    idx, dist = knn(query_index, lib.desc[rows], 2, conf)
    ok = dist[:, 0] < conf.ratio * dist[:, 1]
    if candidate_mask is not None:
        ok &= candidate_mask[idx[:, 0]]
    keep = np.nonzero(ok)[0]
    return idx[keep, 0], rows[keep], dist[keep, 0]


def top_k_pairs(candidates, lib: TemplateLibrary, xy_q: np.ndarray, conf: MatchConfig) -> Correspondences:
    """The pairs of the ``conf.top_k_templates`` views with most candidates (see :func:`_select_top_k`)."""
    q_idx, t_idx, dist = candidates
    return _select_top_k(q_idx, t_idx, dist, lib, xy_q, conf.top_k_templates)


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
    return top_k_pairs(template_to_query_candidates(query_index, lib, conf, candidate_mask, views), lib, xy_q, conf)


def match_query_to_template(
    xy_q: np.ndarray, desc_q: np.ndarray, lib_index, lib: TemplateLibrary, conf: MatchConfig, k: int = 8
) -> Correspondences:
    """Ratio test from every frame keypoint into the object's template descriptors.

    The rival of the nearest neighbour is the nearest one whose 3D point lies more than
    ``conf.distinct_3d_m`` away: another view of the same surface point is not a rival.
    """
    if lib_index is None or len(desc_q) == 0:
        return _select_top_k(np.zeros(0, int), np.zeros(0, int), np.zeros(0), lib, xy_q, conf.top_k_templates)
    idx, dist, rival = nearest_with_rival(desc_q, lib_index, lib, conf, k)
    ok = dist[:, 0] < conf.ratio * rival
    q_idx = np.nonzero(ok)[0]
    return _select_top_k(q_idx, idx[q_idx, 0], dist[q_idx, 0], lib, xy_q, conf.top_k_templates)


def locate(
    xy_q: np.ndarray,
    shapes_q: np.ndarray,
    desc_q: np.ndarray,
    lib_index,
    lib: TemplateLibrary,
    conf: MatchConfig,
    width: int,
    height: int,
    ratio: float = 0.8,
    angle_bin_deg: float = 30.0,
    min_votes: int = 4,
    peaks: int = 1,
    nearest=None,
) -> list[Location]:
    """Where the object is, by Hough voting (Lowe 2004, §7): each frame keypoint matched into the library
    predicts the object's image centre, size and in-plane rotation from the template keypoint's position,
    size and angle.

    A frame keypoint is matched to its nearest template descriptor when it passes the ratio test
    ``ratio`` against the nearest descriptor of another 3D point. The pair's size ratio ``s`` and angle
    difference ``a`` map the template's vector from the keypoint to the object's centre (the mean of the
    library's 3D points, projected) into the frame; the object's size (its diameter in the template,
    times ``s``) and ``a`` are voted for too. Votes fall into cells of 1/20 of the image's longer side,
    one octave of size and ``angle_bin_deg`` of rotation (0: rotation not voted on), each into the two
    nearest cells per dimension. Chance matches scatter; the object's own pairs agree.

    ``nearest``: :func:`nearest_with_rival` of ``desc_q`` (default ``k``) when the caller has it.

    Returns:
        Up to ``peaks`` locations, fullest first, each with at least ``min_votes`` agreeing votes: the
        fullest cell's (the medians of its agreeing votes, and those votes' pairs), then the fullest
        cell of the votes left over, and so on.
    """
    if lib_index is None or len(desc_q) == 0 or len(lib.shapes) != len(lib.desc):
        return []
    votes = _votes(xy_q, shapes_q, desc_q, lib_index, lib, conf, width, height, ratio, min_votes, nearest)
    if votes is None:
        return []
    return _peaks(votes, xy_q, lib, width, height, angle_bin_deg, min_votes, peaks)


def _votes(
    xy_q, shapes_q, desc_q, lib_index, lib: TemplateLibrary, conf: MatchConfig, width, height, ratio, min_votes, nearest
):
    """:func:`locate`'s votes: (centre (M, 2) px, size (M,) px, angle (M,) degrees, frame keypoint (M,),
    template keypoint (M,)) of each match that passes the ratio test and lands in the image; None when
    fewer than ``min_votes``."""
    idx, dist, rival = nearest_with_rival(desc_q, lib_index, lib, conf) if nearest is None else nearest
    q = np.nonzero(dist[:, 0] < ratio * rival)[0]
    if len(q) < min_votes:
        return None
    t = idx[q, 0]
    # The object's centre and diameter in each template view.
    centre = lib.pts3d.mean(axis=0).astype(np.float64)
    diam = float(np.linalg.norm(lib.pts3d.max(axis=0) - lib.pts3d.min(axis=0)))
    T = lib.cams_from_model()
    c_cam = T[:, :3, :3] @ centre + T[:, :3, 3]
    c_img = (c_cam @ lib.K.T)[:, :2] / c_cam[:, 2:3]
    d_img = lib.K[0, 0] * diam / c_cam[:, 2]
    v = lib.view_ids[t]
    s = shapes_q[q, 0] / np.maximum(lib.shapes[t, 0], 1e-6)
    a_deg = (shapes_q[q, 1] - lib.shapes[t, 1]) % 360.0
    a = np.deg2rad(a_deg)
    r = c_img[v] - lib.xy[t]
    cos, sin = np.cos(a), np.sin(a)
    c = xy_q[q] + s[:, None] * np.stack([cos * r[:, 0] - sin * r[:, 1], sin * r[:, 0] + cos * r[:, 1]], axis=1)
    size = s * d_img[v]
    inside = (c[:, 0] >= 0) & (c[:, 0] < width) & (c[:, 1] >= 0) & (c[:, 1] < height) & (size > 1.0)
    c, size, a_deg, q, t = c[inside], size[inside], a_deg[inside], q[inside], t[inside]
    if len(c) < min_votes:
        return None
    return c, size, a_deg, q, t


def _peaks(votes, xy_q, lib: TemplateLibrary, width, height, angle_bin_deg, min_votes, peaks) -> list[Location]:
    """:func:`locate`'s locations: the fullest cells of the votes, each taking the votes that agree with it."""
    c, size, a_deg, q, t = votes
    cell = max(width, height) / 20.0
    cols = [c / cell, np.log2(size)[:, None]]
    n_rot = int(round(360.0 / angle_bin_deg)) if angle_bin_deg > 0 else 0
    if n_rot:
        cols.append((a_deg / (360.0 / n_rot))[:, None])
    f = np.hstack(cols)  # continuous bin coordinates
    lo = np.floor(f - 0.5).astype(np.int64)  # the two nearest cells per dimension: lo and lo + 1
    base = lo.min(axis=0)
    dims = lo.max(axis=0) - base + 2
    if n_rot:
        base[3], dims[3] = 0, n_rot  # rotation wraps around
    found: list[Location] = []
    left = np.ones(len(f), bool)  # votes not yet explained by a location
    while len(found) < peaks and left.sum() >= min_votes:
        acc = np.zeros(int(np.prod(dims)), np.int32)
        for corner in np.ndindex(*(2,) * f.shape[1]):
            cells = lo[left] - base + np.array(corner)
            if n_rot:
                cells[:, 3] %= n_rot
            np.add.at(acc, np.ravel_multi_index(cells.T, dims), 1)
        best = np.unravel_index(int(np.argmax(acc)), dims)
        d = np.abs(f - (np.array(best) + base + 0.5))  # distance from the fullest cell's centre, in cells
        if n_rot:
            d[:, 3] = np.minimum(d[:, 3] % n_rot, n_rot - d[:, 3] % n_rot)
        agree = left & np.all(d <= 1.0, axis=1)
        if agree.sum() < min_votes:
            break
        left &= ~agree
        pairs = Correspondences(
            xy_q[q[agree]].astype(np.float64),
            lib.pts3d[t[agree]].astype(np.float64),
            lib.view_ids[t[agree]].astype(np.int32),
            tuple(np.unique(lib.view_ids[t[agree]]).tolist()),
            int(agree.sum()),
        )
        centre = (float(np.median(c[agree, 0])), float(np.median(c[agree, 1])))
        found.append(Location(centre, float(np.median(size[agree])), int(agree.sum()), pairs))
    return found
