"""Find an object SIFT missed, by colour and depth (``depth.search``; needs ``depth.enabled`` and a depth image).

SIFT finds nothing on an object whose visible side has no texture (the mustard bottle's plain back in
ycbv_dev, a black drill). Colour alone cannot place it — the object's size in the image and its distance
trade off, and a smaller silhouette inside the object's colour blob always fits best — but with a depth
image the distance at each pixel is known, so each silhouette size is tried only where the sensor sees
something at the distance that size implies. For such an object:

1. **colour**: each pixel's log-odds of the object's colours (a hue-saturation histogram of its mesh
   rendered in the library's views; grey levels for unsaturated pixels) against the frame's own, at 1/4
   resolution;
2. **search**: silhouettes of the library's views (every ``search_view_step``-th, at
   ``search_angles`` in-plane turns and sizes from 24 px to 0.9 of the image height) are correlated with
   that map; a placement counts only where the sensor depth there agrees with the size's distance;
3. **align**: the ``search_hypotheses`` best places, and each turned 180° about the mesh's principal axes,
   are aligned to the depth (:func:`batchpose.method.depth.align_to_depth`, allowed to move further than a
   check of an RGB pose is); alignments whose seen pixels do not look like the object are dropped;
4. **polish**: the ``search_polish`` best-fitting distinct alignments whose texture lines up at all (the
   mesh rendered there correlates positively with the frame) are turned about their principal axes (20°,
   10°, 5°) and aligned again while that fits better. "Fits" counts only the silhouette's pixels not
   hidden by something nearer — a bottle behind a box is judged by its visible half (an alignment alone
   stops in the nearest minimum, e.g. the bottle turned so that its base sits where the box is) — plus a
   little of the texture's correlation, which tells a can's front from its back where the depth cannot;
5. **verify**: the best polished pose is kept if the sensor sees at least ``search_min_visible`` of its
   silhouette at its surface (within 1 cm), at most ``search_max_see_through`` past it, its seen
   pixels' mean colour log-odds against the frame outside the silhouette is at least ``search_min_colour``
   and the mesh rendered there correlates with the frame at least ``search_min_match`` (the texture's
   layout, not only its colours); otherwise the object stays not found.

With tracking on, the estimator hands the search the pose it found in the previous frame of the sequence
(``previous``): aligned and polished, it is kept when it passes the checks, and the frame is not searched.

reports/ACCURACY.md ("ycbv_dev with depth") has the figures: on ycbv_dev it finds the mustard bottle's
plain back; on objects absent from a frame it must find nothing.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.config import DepthConfig
from batchpose.method.appearance import (
    N_BINS,
    colour_bins,
    gradient_match,
    texture_match,
)
from batchpose.method.depth import Surface, align_to_depth

#: The search's resolution (every LEVEL-th pixel).
LEVEL = 4
#: Sensor readings within this of an aligned hypothesis's surface see it.
SEEN_M = 0.01
#: The alignments' Levenberg damping (relative; see ``depth.damping``, which is heavier for RGB poses).
SEARCH_DAMPING = 0.001
#: Weight of the texture match in a hypothesis's score (its depth fit is within 0.01 of 1 when right).
MATCH_WEIGHT = 0.1


@dataclass(frozen=True)
class _View:
    view_id: int
    mask: np.ndarray  # uint8, the view's silhouette cropped to its box
    centre: np.ndarray  # the model centre's pixel in the crop
    span_px: float  # the object's diameter in the render


@dataclass(frozen=True)
class Silhouettes:
    """What the search needs of one object: its colour histogram and its views' silhouettes."""

    hist: np.ndarray
    views: tuple[_View, ...]

    @classmethod
    def of(cls, render, lib, diameter_m: float, view_step: int) -> Silhouettes:
        """Render every ``view_step``-th library view at the nearest library distance.

        Args:
            render: callable(cam_from_model) -> (rgb, depth) in the library's camera.
            lib: the object's TemplateLibrary.
        """
        dist = lib.views["distance_m"].to_numpy()
        f_lib = 0.5 * (lib.K[0, 0] + lib.K[1, 1])
        hist = np.zeros(N_BINS)
        views = []
        for v in np.flatnonzero(np.isclose(dist, dist.min()))[::view_step]:
            rgb, depth = render(lib.cam_from_model(int(v)))
            sil = depth > 0
            if sil.sum() < 50:
                continue
            hist += np.bincount(colour_bins(rgb)[sil], minlength=N_BINS)
            ys, xs = np.nonzero(sil)
            x0, y0 = xs.min(), ys.min()
            crop = sil[y0 : ys.max() + 1, x0 : xs.max() + 1].astype(np.uint8)
            views.append(_View(int(v), crop, lib.K[:2, 2] - [x0, y0], f_lib * diameter_m / dist[v]))
        return cls(hist / max(hist.sum(), 1.0), tuple(views))


@dataclass
class Found:
    """A pose the search found and kept."""

    cam_from_model: np.ndarray
    visible: float  # fraction of the silhouette the sensor sees at its surface
    see_through: float  # fraction the sensor sees past
    colour: float  # mean colour log-odds of the visible pixels
    match: float  # correlation of the rendered mesh's colours with the frame's over the visible pixels
    followed: bool = False  # from the previous frame's found pose, without searching this frame


def _colour_map(rgb: np.ndarray, hist: np.ndarray, level: int) -> np.ndarray:
    small = cv2.resize(rgb, (rgb.shape[1] // level, rgb.shape[0] // level), interpolation=cv2.INTER_AREA)
    bins = colour_bins(small)
    frame = np.bincount(bins.ravel(), minlength=N_BINS) / bins.size
    return np.log((hist + 1e-3) / (frame + 1e-3)).clip(-3, 3)[bins].astype(np.float32)


def _block_depth(depth: np.ndarray, level: int, shape: tuple[int, int]) -> np.ndarray:
    """Median sensor depth of each level x level block (0 where none has a reading)."""
    h, w = shape
    d = depth[: h * level, : w * level].astype(np.float32).copy()
    d[d <= 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # blocks without a reading
        med = np.nanmedian(d.reshape(h, level, w, level), axis=(1, 3))
    return np.nan_to_num(med, nan=0.0)


def _placed(view: _View, span_px: float, angle: float, level: int) -> np.ndarray:
    """The view's silhouette with the object ``span_px`` across, turned by ``angle``, centred in a square."""
    scale = span_px / view.span_px / level
    size = int(np.ceil(0.6 * span_px / level)) * 2 + 1
    A = cv2.getRotationMatrix2D((float(view.centre[0]), float(view.centre[1])), -np.degrees(angle), scale)
    A[:, 2] += (size - 1) / 2 - view.centre
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.warpAffine(view.mask.astype(np.float32), A, (size, size), flags=interp)


def pose_from_view(lib, view_id: int, angle: float, depth_m: float, centre_xy, K: np.ndarray) -> np.ndarray:
    """The pose showing library view ``view_id`` turned by ``angle`` in the image, its centre at
    ``centre_xy`` and ``depth_m`` away (the view turned so that the centre's viewing ray is its axis)."""
    T = lib.cam_from_model(view_id)
    dist = float(lib.views["distance_m"].iloc[view_id])
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
    centre_model = T[:3, :3].T @ (np.array([0.0, 0.0, dist]) - T[:3, 3])
    ray = np.linalg.solve(K, np.array([centre_xy[0], centre_xy[1], 1.0]))
    ray /= np.linalg.norm(ray)
    axis = np.cross([0.0, 0.0, 1.0], ray)
    sin_a = float(np.linalg.norm(axis))
    R_ray = np.eye(3) if sin_a < 1e-12 else cv2.Rodrigues(axis / sin_a * np.arcsin(min(sin_a, 1.0)))[0]
    out = np.eye(4)
    out[:3, :3] = R_ray @ R
    out[:3, 3] = depth_m / ray[2] * ray - out[:3, :3] @ centre_model
    return out


def _places(lmap, zs, sil: Silhouettes, f_px: float, diameter_m: float, image_h: int, conf: DepthConfig):
    """The best-scoring depth-consistent placements, distinct, best first: (score, view, angle, span, x, y)."""
    found = []
    span = 24.0
    while span <= 0.9 * image_h:
        z = f_px * diameter_m / span  # the object's centre distance at this size
        for angle in np.deg2rad(np.arange(0.0, 360.0, 360.0 / conf.search_angles)):
            for view in sil.views:
                M = _placed(view, span, angle, LEVEL)
                if M.shape[0] >= lmap.shape[0] or M.shape[1] >= lmap.shape[1]:
                    continue
                r = cv2.matchTemplate(lmap, M, cv2.TM_CCORR)
                half = (M.shape[0] - 1) // 2
                zc = zs[half : half + r.shape[0], half : half + r.shape[1]]  # the reading at the centre
                # The centre lies behind the visible surface by up to the object's size.
                ok = (zc > 0) & (z > zc - 0.1 * diameter_m) & (z < zc + 0.7 * diameter_m)
                if not ok.any():
                    continue
                _, best, _, (x, y) = cv2.minMaxLoc(np.where(ok, r, -np.inf).astype(np.float32))
                found.append(
                    (best, view.view_id, angle, span, (x + half + 0.5) * LEVEL - 0.5, (y + half + 0.5) * LEVEL - 0.5)
                )
        span *= 2**0.25
    found.sort(key=lambda f: -f[0])
    kept: list[tuple] = []
    for f in found:
        if all(f[1] != k[1] or np.hypot(f[4] - k[4], f[5] - k[5]) > 0.3 * min(f[3], k[3]) for k in kept):
            kept.append(f)
        if len(kept) == conf.search_hypotheses:
            break
    return kept


@dataclass
class _Candidate:
    """An aligned hypothesis and how the sensor and the colours see it."""

    fit_pose: np.ndarray
    visible: float  # fraction of the silhouette the sensor sees at its surface
    unhidden: float  # the same, of the silhouette's pixels not hidden by something nearer (nor without a reading)
    see_through: float
    colour: float
    match: float  # correlation of the rendered mesh's colours with the frame's where the sensor sees it

    @property
    def score(self) -> float:
        """How well the depth fits (occluders in front of the object do not count against it), and a little how
        well the texture does: the depth cannot tell a can's or a bottle's front from its back."""
        return self.unhidden - 2.0 * self.see_through + MATCH_WEIGHT * self.match

    def found(self, followed: bool = False) -> Found:
        return Found(self.fit_pose, self.visible, self.see_through, self.colour, self.match, followed)

    def passes(self, conf: DepthConfig) -> bool:
        return (
            self.visible >= conf.search_min_visible
            and self.see_through <= conf.search_max_see_through
            and self.colour >= conf.search_min_colour
            and self.match >= conf.search_min_match
        )


def _colour_odds(
    bins: np.ndarray, frame_counts: np.ndarray, hist: np.ndarray, sil: np.ndarray, seen: np.ndarray
) -> float:
    """Mean log-odds of the seen pixels' colours under the object's histogram against the frame's outside the
    silhouette (the frame's own histogram would count a large object's colours as background)."""
    bg = frame_counts - np.bincount(bins[sil], minlength=N_BINS)
    bg = bg / max(bg.sum(), 1)
    odds = np.log((hist + 1e-3) / (bg + 1e-3)).clip(-3, 3)
    return float(odds[bins[seen]].mean())


def distinct_matches(
    frame_lab: np.ndarray,
    frame_gray: np.ndarray,
    a: tuple[np.ndarray, np.ndarray],
    b: tuple[np.ndarray, np.ndarray],
    min_px: int = 30,
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """How well each of two renders (rgb, depth) of one object fits the frame where the two differ: in one
    silhouette only, or in both with colours apart by more than 20 per channel on average. Where they agree
    the frame cannot tell them apart, and counting it would only dilute the difference.

    Returns:
        For a and for b: (:func:`texture_match` over its differing pixels, :func:`gradient_match` over them
        grown by 2 px, so its outline counts); None when either has fewer than ``min_px`` such pixels.
    """
    (rgb_a, depth_a), (rgb_b, depth_b) = a, b
    sil_a, sil_b = depth_a > 0, depth_b > 0
    apart = np.abs(rgb_a.astype(np.int16) - rgb_b.astype(np.int16)).sum(axis=2) > 60
    differ = (sil_a ^ sil_b) | (sil_a & sil_b & apart)
    out = []
    for sil, rgb in ((sil_a, rgb_a), (sil_b, rgb_b)):
        px = differ & sil
        if px.sum() < min_px:
            return None
        grown = cv2.dilate(px.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        out.append((texture_match(frame_lab[px], rgb[px]), gradient_match(frame_gray, gray, grown)))
    return out[0], out[1]


#: The polish's turn sizes (degrees), largest first.
POLISH_STEPS_DEG = (20.0, 10.0, 5.0)


def _turns(surface: Surface) -> list[list[np.ndarray]]:
    """For each of :data:`POLISH_STEPS_DEG`: model-frame turns by +- that about the surface's principal axes
    through its centroid."""
    c = surface.points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((surface.points - c).T))
    out = []
    for step in POLISH_STEPS_DEG:
        turns = []
        for a in axes.T:
            for sign in (1.0, -1.0):
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(sign * np.deg2rad(step) * a)[0]
                T[:3, 3] = c - T[:3, :3] @ c
                turns.append(T)
        out.append(turns)
    return out


def search(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    lib,
    sil: Silhouettes,
    surface: Surface,
    flips: list[np.ndarray],
    diameter_m: float,
    render,
    conf: DepthConfig,
    previous: np.ndarray | None = None,
) -> Found | None:
    """Look for the object (see the module docstring); None when nothing passes the checks.

    Args:
        rgb, depth_m: the frame and its registered depth (metres, 0: no reading), same size.
        K: their intrinsics. lib: the object's TemplateLibrary. flips: the mesh's half-turns.
        render: callable(cam_from_model) -> (rgb, depth) in the frame's camera.
        previous: the pose the search found in the previous frame of a sequence: aligned and polished
            first, and kept without searching the frame when it passes the checks.
    """
    # Hypotheses start further off than an RGB pose; light damping lets the depth turn them.
    # Hypotheses are placed at the depth their size implies and aligned by the ICP alone (no ray alignment).
    wide = dataclasses.replace(conf, max_shift=0.5, max_turn_deg=45.0, damping=SEARCH_DAMPING, ray_align=False)
    bins = colour_bins(rgb)
    frame_counts = np.bincount(bins.ravel(), minlength=N_BINS)

    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)
    turns = _turns(surface)
    last: dict = {}

    def rendered(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # the alignment's last render is the one judged
        key = np.asarray(T, dtype=np.float64).tobytes()
        if key not in last:
            last.clear()
            last[key] = render(T)
        return last[key]

    def aligned(start: np.ndarray) -> _Candidate | None:
        fit = align_to_depth(start, depth_m, lambda T: rendered(T)[1], K, surface, diameter_m, wide)
        if not fit.aligned:
            return None
        ren_rgb, ren_depth = rendered(fit.cam_from_model)
        sil_px = ren_depth > 0
        seen = sil_px & (np.abs(depth_m - ren_depth) < SEEN_M)
        if not seen.any():
            return None
        hidden = sil_px & ((depth_m <= 0) | (depth_m < ren_depth - SEEN_M))
        n = int(sil_px.sum())
        return _Candidate(
            fit.cam_from_model,
            float(seen.sum()) / n,
            float(seen.sum()) / max(n - int(hidden.sum()), 1),
            fit.see_through,
            _colour_odds(bins, frame_counts, sil.hist, sil_px, seen),
            texture_match(lab[seen], ren_rgb[seen]),
        )

    if previous is not None:
        cand = aligned(previous)
        if cand is not None and cand.match > 0.0:
            cand = _polish(cand, aligned, turns) if conf.search_polish else cand
            if cand.passes(conf):
                return cand.found(followed=True)
    lmap = _colour_map(rgb, sil.hist, LEVEL)
    zs = _block_depth(depth_m, LEVEL, lmap.shape)
    f_px = 0.5 * (K[0, 0] + K[1, 1])
    places = _places(lmap, zs, sil, f_px, diameter_m, rgb.shape[0], conf)
    found = []
    for _score, view_id, angle, span, x, y in places:
        start = pose_from_view(lib, view_id, angle, f_px * diameter_m / span, (x, y), K)
        found += [
            c
            for c in (aligned(start @ F) for F in [np.eye(4), *flips])
            if c is not None and c.match > 0.0  # turned or misplaced: the texture does not line up at all
        ]
    best = _best(found, surface.points.mean(axis=0), diameter_m, conf, aligned, turns)
    return None if best is None else best.found()


def _best(found: list[_Candidate], centre, diameter_m: float, conf: DepthConfig, aligned, turns) -> _Candidate | None:
    """The best-scoring of the distinct candidates (``search_polish`` of them polished first) that passes
    the checks; ``centre``: the model's centre, which decides when two candidates are the same pose."""
    found = sorted(found, key=lambda c: -c.score)
    distinct: list[_Candidate] = []  # alignments from several places often end at the same pose
    for cand in found:
        if all(not _same_pose(cand.fit_pose, d.fit_pose, centre, diameter_m) for d in distinct):
            distinct.append(cand)
    best = None
    for cand in distinct[: max(conf.search_polish, 1)]:
        if conf.search_polish:
            cand = _polish(cand, aligned, turns)
        if cand.passes(conf) and (best is None or cand.score > best.score):
            best = cand
    return best


def _same_pose(A: np.ndarray, B: np.ndarray, c: np.ndarray, diameter_m: float) -> bool:
    """Centres (``c`` in the model frame) within a tenth of the diameter and orientations within 30 degrees."""
    moved = np.linalg.norm(A[:3, :3] @ c + A[:3, 3] - B[:3, :3] @ c - B[:3, 3])
    turned = np.degrees(np.linalg.norm(cv2.Rodrigues(A[:3, :3] @ B[:3, :3].T)[0]))
    return bool(moved < 0.1 * diameter_m and turned < 30.0)


def _polish(cand: _Candidate, aligned, turns: list[list[np.ndarray]]) -> _Candidate:
    """Turn the candidate by each of ``turns`` (:func:`_turns`, largest first), each turn aligned to the depth
    again, while that scores better: an alignment stops in the nearest minimum, often a bottle turned about
    its axis with its base where the occluder in front of it is."""
    level = 0
    while level < len(turns):
        better = None
        for turn in turns[level]:
            c = aligned(cand.fit_pose @ turn)
            if c is not None and c.score > (better or cand).score + 1e-3:
                better = c
        if better is None:
            level += 1
        else:
            cand = better
    return cand
