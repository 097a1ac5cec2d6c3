"""Find an object SIFT missed where the objects it did find stand (``plane.enabled``).

Objects in a recording mostly rest on something — a table, a shelf, the floor — and rest on it in one of a
few ways: a bottle upright or on its side, a box on one of its faces. When SIFT gives no pose for an object
(its plain side to the camera: the mustard bottle's back in ycbv_dev) but confident ones for others in the
frame, the surface those rest on fixes what a silhouette alone cannot — the distance: an object standing on
it at a given pixel is at one distance only. For such an object:

1. **support plane and resting poses** (:mod:`batchpose.method.support`): the surface the most found objects
   rest on (or the one found object's, by the image's up direction), and the object's stable poses on it,
   each turned about the plane's normal in ``angles`` steps;
2. **search**: for each resting pose and turn, its silhouette is correlated with the frame's colour
   log-odds map (the object's colours against the frame's outside the found objects; the pixels the found
   objects cover count 0: they are explained), at each place with the size the plane's distance there
   gives it. The best distinct placements by the colours they hold (4 x ``starts``) are candidates, and
   so are the best at a few other places by how much the silhouette *stands out* from a thin ring around
   it — a broad patch of the object's colours (a shadow under a grey-and-black marker, a found object's
   edge) holds more of them than a thin object does, but does not stand out. Rendered, the ``starts``
   whose texture and colour match the frame best go on (a silhouette cannot tell a box's front from its
   back), and the best at two places none of those is at. Near the frame's border a silhouette is scored
   on its part in the frame (the map padded with its median: the frame goes on as it mostly is), if at
   least ``min_visible`` of it is in the frame;
3. **refine**: each is turned about the normal and slid along the plane while the mesh rendered there
   matches the frame better, over the silhouette pixels no found object hides or covers (those behind it
   are the found object's texture): texture correlation in Lab plus ``colour_weight`` x mean colour
   log-odds plus ``edge_weight`` x the edge score (in 15 and 8 degree steps; the best then in 4 and 2).
   With ``reface``, the object on its other resting faces at each refined start's place (long axis kept)
   is judged, and the two best are refined too: a bottle on its left side and on its right barely differ
   in silhouette.
   The edge score is how closely the frame's edges (Canny) follow the silhouette's outline: the mean over
   its outline pixels of exp(-d² / 2 EDGE_PX²), d the distance to the nearest frame edge, leaving out the
   outline along found objects (their own outline is an edge). It peaks sharply at the right place, where
   colour and texture change little: on tabletop frames (the share of outline pixels within 1.5 px of an
   edge) 0.67-0.97 there, 0.3-0.8 one or two centimetres aside, 0.05 (90 % under 0.41) where the search
   places an object the frame does not show (reports/ACCURACY.md at 8fba8e3, "Session 27");
4. **verify**: a placement is kept if at least ``min_visible`` of its silhouette is not hidden by a found
   object (nor left out as an occluder's band), those pixels' mean colour log-odds is at least
   ``min_colour`` and exceeds the ring's around the silhouette by ``min_contrast`` (it stands out from where
   it stands), the texture correlation is at
   least ``min_match``, and — once finely refined — the edge score at least ``min_edge`` (not checked
   where the frame has no edges near the placement at all: a blurred frame). A finely refined placement
   whose edge score reaches ``edge_confirms`` may fail one of the two colour checks (``min_colour``,
   ``min_contrast``): a pale bottle on a white table has the table's colours, a thin marker a pixel aside
   has its own pixels in the ring. With a weak SIFT pose, it must also match the frame better than that
   pose. The best refined placement that passes all but the edge checks (with ``edge_confirms``, one colour
   check may fail too) is refined in the fine steps and kept if it then passes every check (else the next).
   With ``occluder_cuts``, where none passes, the refined placements are judged again with a lower band of
   the silhouette (by height along the plane's up direction in the image) left out where the band's colours
   are not the object's, each placement's best judgement counting, and steps 3-4 are repeated on them: an
   object not asked for, standing nearer on the same surface, hides the lower part, and nothing else
   explains its pixels.

With tracking on, the next frame of a sequence refines the previous frame's placement first (step 3 only)
and searches only when that no longer passes. reports/ACCURACY.md at 8fba8e3 ("Session 10", "Session 11") has the
figures.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.config import PlaneConfig
from batchpose.method.appearance import N_BINS, colour_bins, texture_match
from batchpose.method.support import Plane, resting, turn_to

#: The coarse search's resolution (every LEVEL-th pixel).
LEVEL = 4
#: A silhouette pixel is hidden where a found object's surface is this much nearer than the object's.
HIDDEN_M = 0.01
#: Consecutive sizes of the coarse search differ by this factor (the plane gives each place one of them).
SIZE_STEP = 1.1
#: The coarse search's best placements judged by rendering (texture and colour) for each one refined.
CANDIDATES_PER_START = 4
#: Besides its best, the coarse search keeps candidates at this many other places ...
SPOTS = 4
#: ... and the refinement starts from the best at this many places no better start is at.
EXTRA_STARTS = 2
#: The coarse search's standing-out score keeps this many places for each resting pose and turn (at least half
#: the object's span apart).
PEAKS = 3
#: The coarse search's ring around a silhouette: this fraction of the silhouette's half-extent wide (at least
#: a pixel at its resolution).
COARSE_RING = 0.1
#: The ring around a silhouette whose colours :attr:`Placed.contrast` compares with the silhouette's (4 px wide).
RING_KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))
#: A silhouette's outline: its pixels with a 4-neighbour outside it.
OUTLINE_KERNEL = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
#: The frame's edges (:attr:`Placed.edge`): Canny's hysteresis thresholds on the 8-bit grey image ...
CANNY = (50, 150)
#: ... and how far (px) an outline pixel may be from the nearest one: its credit is exp(-d² / 2 EDGE_PX²).
EDGE_PX = 2.0
#: Outline pixels this near (px) a found object are left out of the edge score: its own outline is an edge.
EDGE_CLEAR_PX = 2
#: An edge score needs at least this many outline pixels left (fewer: 0), and this many frame edge pixels in
#: the judged square (fewer: NaN, the frame says nothing there).
EDGE_MIN_PIXELS = 10
#: With ``plane.reface``, the best this many of a start's other resting faces are refined.
REFACED = 2
#: The refinement's turn (degrees) and slide (fraction of the diameter) steps, largest first: every start
#: is refined with the coarse ones, the best of them then with the fine ones.
COARSE_STEPS = ((15.0, 0.05), (8.0, 0.025))
FINE_STEPS = ((4.0, 0.0125), (2.0, 0.006))


@dataclass(frozen=True)
class Placed:
    """A pose the plane search kept."""

    cam_from_model: np.ndarray
    visible: float  # fraction of the silhouette no found object hides
    colour: float  # mean colour log-odds of those pixels
    match: float  # texture correlation (Lab) of the rendered mesh with the frame over those pixels
    contrast: float  # ``colour`` less that of the ring of pixels just outside the silhouette
    edge: float = 0.0  # how closely the frame's edges follow the silhouette's outline; NaN: no edges near
    followed: bool = False


@dataclass(frozen=True)
class Target:
    """What the search needs of the object looked for."""

    hull: np.ndarray  # (N, 3) convex-hull vertices, model frame
    centre: np.ndarray  # model frame
    diameter_m: float
    faces: tuple[np.ndarray, ...]  # resting faces' outward normals (model frame)
    hist: np.ndarray  # colour histogram (see batchpose.method.depth_search.colour_bins)


class _Judge:
    """Scores poses against one frame: renders the mesh in a ``size``-pixel square around the object's centre
    (far cheaper than the whole frame) and compares it with the frame where no found object hides it, and,
    with ``occluder_cuts``, also with a lower band of the silhouette left out (an object not asked for in front)."""

    def __init__(
        self, rgb, odds, found_mask, occluder_depth, render, K, target: Target, size: int, conf, up, edges=None
    ):
        self.lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)
        self.odds, self.found_mask, self.occluder_depth = odds, found_mask, occluder_depth
        self.render, self.K, self.target, self.size, self.conf = render, K, target, size, conf
        self.up = up  # the plane's normal, camera frame
        self.edges = edges  # :func:`_edge_credit`'s maps, or None: edges not scored
        self.cuts = False  # also judge with the lower bands of ``occluder_cuts`` left out

    def __call__(self, T: np.ndarray) -> tuple[float, Placed | None]:
        c = self.K @ (T[:3, :3] @ self.target.centre + T[:3, 3])
        if c[2] <= 0:
            return -np.inf, None
        x0, y0 = int(round(c[0] / c[2])) - self.size // 2, int(round(c[1] / c[2])) - self.size // 2
        K = self.K.copy()
        K[:2, 2] -= (x0, y0)
        ren_rgb, ren_depth = self.render(T, K, self.size, self.size)
        h, w = self.odds.shape
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + self.size, w), min(y0 + self.size, h)
        if xb <= xa or yb <= ya:
            return -np.inf, None
        crop, win = np.s_[ya - y0 : yb - y0, xa - x0 : xb - x0], np.s_[ya:yb, xa:xb]
        n = int((ren_depth > 0).sum())  # parts outside the frame count as not seen
        sil, depth = ren_depth[crop] > 0, ren_depth[crop]
        # A found object nearer than this one hides it; one behind it does not, but explains those pixels
        # (they are its texture): they are evidence neither way.
        seen = sil & ~(self.occluder_depth[win] < depth - HIDDEN_M) & ~self.found_mask[win]
        odds = self.odds[win]
        ring = cv2.dilate(sil.astype(np.uint8), RING_KERNEL).astype(bool) & ~sil & ~self.found_mask[win]
        ring_odds = float(odds[ring].mean()) if ring.any() else 0.0
        outline = sil & ~cv2.erode(sil.astype(np.uint8), OUTLINE_KERNEL).astype(bool)
        edge_credit = None
        if self.edges is not None:
            credit, near_found, count = self.edges
            if count[yb, xb] - count[ya, xb] - count[yb, xa] + count[ya, xa] >= EDGE_MIN_PIXELS:
                outline &= ~near_found[win]
                edge_credit = credit[win]
        best: tuple[float, Placed | None] = (-np.inf, None)
        for shown in [seen, *self._uncut(T, K, sil, seen, odds, (ya - y0, xa - x0))]:
            k = int(shown.sum())
            if k < 30 or k < self.conf.min_visible * n:
                continue
            colour = float(odds[shown].mean())
            if edge_credit is None:  # no edges here at all (a blurred frame): the cue says nothing
                edge = np.nan if self.edges is not None else 0.0
            else:
                rim = outline & shown
                edge = float(edge_credit[rim].mean()) if rim.sum() >= EDGE_MIN_PIXELS else 0.0
            match = texture_match(self.lab[win][shown], ren_rgb[crop][shown])
            placed = Placed(T, k / n, colour, match, colour - ring_odds, edge)  # ring_odds 0 without a ring
            score = placed.match + self.conf.colour_weight * placed.colour
            score += self.conf.edge_weight * edge if np.isfinite(edge) else 0.0
            if score > best[0]:
                best = (score, placed)
        return best

    def _uncut(self, T, K, sil, seen, odds, origin) -> list[np.ndarray]:
        """``occluder_cuts``: the silhouette's seen pixels less each lower band (by height along the plane's up
        direction in the image) whose colours are not the object's (mean log-odds under 0)."""
        if not self.cuts or not self.conf.occluder_cuts or not sil.any():
            return []
        centre = T[:3, :3] @ self.target.centre + T[:3, 3]
        a, b = K @ centre, K @ (centre + 0.05 * self.target.diameter_m * self.up)
        up = b[:2] / b[2] - a[:2] / a[2]
        if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-6:
            return []
        up /= np.linalg.norm(up)
        rows, cols = np.nonzero(sil)
        height = np.full(sil.shape, np.inf, np.float32)
        height[rows, cols] = (cols + origin[1]) * up[0] + (rows + origin[0]) * up[1]
        low, high = float(height[rows, cols].min()), float(height[rows, cols].max())
        out = []
        for cut in self.conf.occluder_cuts:
            band = seen & (height < low + cut * (high - low))
            if band.any() and float(odds[band].mean()) < 0.0:
                out.append(seen & ~band)
        return out


def search_plane(
    rgb: np.ndarray,
    K: np.ndarray,
    plane: Plane,
    target: Target,
    found_mask: np.ndarray,
    occluder_depth: np.ndarray,
    render,
    conf: PlaneConfig,
    previous: np.ndarray | None = None,
    incumbent: np.ndarray | None = None,
) -> Placed | None:
    """Look for the object on ``plane`` (see the module docstring); None when nothing passes the checks.

    Args:
        rgb: the frame. K: its intrinsics.
        found_mask: the pixels the found objects cover. occluder_depth: their rendered depth (inf elsewhere).
        render: callable(cam_from_model, K, width, height) -> (rgb, depth).
        previous: the placement kept in the previous frame of a sequence: refined first, and kept without a
            search when it passes.
        incumbent: a weak pose the estimate has: a placement must also match the frame better than it does.
    """
    bins = colour_bins(rgb)
    background = np.bincount(bins[~found_mask], minlength=N_BINS) / max(int((~found_mask).sum()), 1)
    odds = np.log((target.hist + 1e-3) / (background + 1e-3)).clip(-3, 3).astype(np.float32)[bins]
    odds[found_mask] = 0.0  # explained by the objects found there
    edges = _edge_credit(rgb, found_mask) if conf.edge_weight or conf.min_edge or conf.edge_confirms else None

    def judge_around(poses: list[np.ndarray]) -> _Judge:
        """A judge rendering a square that holds the object at any of ``poses`` (and the incumbent)."""
        span = max(_span_px(T, K, target) for T in [*poses, *([] if incumbent is None else [incumbent])])
        size = min(int(np.ceil((1.2 * span + 8) / 32)) * 32, 2 * max(rgb.shape[:2]))
        return _Judge(rgb, odds, found_mask, occluder_depth, render, K, target, size, conf, plane.normal, edges)

    def floor_of(judge: _Judge) -> float:
        """The incumbent's score: a placement must beat it."""
        return -np.inf if incumbent is None else judge(incumbent)[0]

    # Whole silhouettes first; where nothing passes, the same placements judged again with an occluder's band
    # left out (``occluder_cuts``: an object not asked for in front), which costs more a judgement.
    cuts = (False, True) if conf.occluder_cuts else (False,)
    if previous is not None:
        previous = _onto(previous, plane, target)
        judge = judge_around([previous])
        for with_cuts in cuts:
            judge.cuts = with_cuts
            score, placed = _refine(previous, plane, target, judge, FINE_STEPS)
            if _passes(conf, score, placed, floor_of(judge)):
                assert placed is not None  # passes() refuses None
                return dataclasses.replace(placed, followed=True)
    places = _places(odds, K, plane, target, conf.starts * CANDIDATES_PER_START, conf)
    if not places:
        return None
    judge = judge_around(places)
    # The coarse search cannot tell a box on its front from one on its back (or a bottle turned half round):
    # the texture decides which of its placements are refined — the best at each place first, so that one
    # place whose colours fit in several ways does not take every start.
    scored = [k for _, k in sorted(((judge(T)[0], k) for k, T in enumerate(places)), reverse=True)]
    starts = _spread(scored[: conf.starts], scored, places, target, EXTRA_STARTS)
    # Refined, a wrong placement can match the frame's texture better than the right one yet not stand out
    # from its surroundings: the best of those that pass the checks goes on.
    refined = [_refine(places[k], plane, target, judge, COARSE_STEPS) for k in starts]
    if conf.reface:
        refined += _refaced_starts(refined, plane, target, judge)
    if (placed := _settle(judge, refined, floor_of(judge), plane, target)) is not None or len(cuts) == 1:
        return placed
    judge.cuts = True
    return _settle(
        judge, [judge(p.cam_from_model) for _, p in refined if p is not None], floor_of(judge), plane, target
    )


def _passes(conf: PlaneConfig, score: float, p: Placed | None, floor: float, final: bool = True) -> bool:
    """The checks; the edge score only on a ``final`` (finely refined) placement: a centimetre off, the coarse
    steps' placements can miss the outline they find."""
    if p is None or score <= floor or p.visible < conf.min_visible or p.match < conf.min_match:
        return False
    if final and p.edge < conf.min_edge:  # NaN: no edges to check with
        return False
    cues = (p.colour >= conf.min_colour) + (p.contrast >= conf.min_contrast)
    if cues == 2:
        return True
    # Edges that follow the outline closely stand in for one of the two colour cues; the coarse steps'
    # placements a centimetre off may miss the outline, so they go on to the fine steps.
    return cues == 1 and conf.edge_confirms > 0 and (not final or p.edge >= conf.edge_confirms)


def _settle(
    judge: _Judge, refined: list[tuple[float, Placed | None]], floor: float, plane: Plane, target: Target
) -> Placed | None:
    """The best coarsely refined placement that passes all but the edge checks, refined in the fine steps and
    kept if it then passes every check (else the next)."""
    conf = judge.conf
    for _, placed in sorted((r for r in refined if _passes(conf, *r, floor, final=False)), key=lambda r: -r[0]):
        assert placed is not None  # _passes() refused the None placements
        best = _refine(placed.cam_from_model, plane, target, judge, FINE_STEPS)
        if _passes(conf, *best, floor):
            return best[1]
    return None


def _refaced_starts(refined: list, plane: Plane, target: Target, judge) -> list:
    """``plane.reface``: a silhouette barely tells a bottle lying on its left side from one on its right;
    the texture does. At each refined start's place, the :data:`REFACED` best of its other resting faces
    (long axis kept; turned more than 30 degrees from the start and from one another) are refined too."""
    out = []
    for _, p in refined:
        if p is None:
            continue
        ranked: list[np.ndarray] = []  # best first
        for T in sorted(_refaced(p.cam_from_model, plane, target), key=lambda T: -judge(T)[0]):
            if all(_turn_deg(T, U) > 30.0 for U in [p.cam_from_model, *ranked]):
                ranked.append(T)
        out += [_refine(T, plane, target, judge, COARSE_STEPS) for T in ranked[:REFACED]]
    return out


def _edge_credit(rgb: np.ndarray, found_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the edge credit an outline pixel there earns (1 on a frame edge, falling off with the
    distance to the nearest one over EDGE_PX); the pixels too near a found object to count; and the edge
    pixels' integral image (how many edges a window holds)."""
    edges = cv2.Canny(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), *CANNY)
    dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    credit = np.exp(-(np.minimum(dist, 10 * EDGE_PX) ** 2) / (2 * EDGE_PX**2)).astype(np.float32)
    size = 2 * EDGE_CLEAR_PX + 1
    near = cv2.dilate(found_mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    return credit, near, cv2.integral((edges > 0).astype(np.uint8))


def _span_px(T: np.ndarray, K: np.ndarray, target: Target) -> float:
    """How many pixels the object's diameter spans at pose T."""
    z = float((T[:3, :3] @ target.centre + T[:3, 3])[2])
    return 0.5 * (K[0, 0] + K[1, 1]) * target.diameter_m / max(z, 1e-3)


def _places(
    odds: np.ndarray, K: np.ndarray, plane: Plane, target: Target, count: int, conf: PlaneConfig
) -> list[np.ndarray]:
    """The coarse search: the ``count`` best distinct resting placements by the colours a silhouette holds,
    best first; then, at each of SPOTS other places, the CANDIDATES_PER_START best by how much the silhouette
    stands out from the ring around it (:func:`_kernels`)."""
    h, w = odds.shape[0] // LEVEL, odds.shape[1] // LEVEL
    small = cv2.resize(odds, (w, h), interpolation=cv2.INTER_AREA)
    # A silhouette partly out of the frame is scored as if the frame went on as it mostly is (its median
    # odds): near the border the kernels reach past it, and neutral odds there would favour placements that
    # hang out of the frame over the frame's background.
    outside, inside = float(np.median(small)), np.ones_like(small)
    Ks = K.copy()
    Ks[:2] /= LEVEL
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - Ks[0, 2]) / Ks[0, 0], (v - Ks[1, 2]) / Ks[1, 1], np.ones_like(u)], axis=-1)
    along = rays @ plane.normal
    n = plane.normal
    f_px = 0.5 * (Ks[0, 0] + Ks[1, 1])
    held: list[tuple[float, np.ndarray]] = []  # by the colours held
    standing: list[tuple[float, np.ndarray]] = []  # by standing out
    for face in target.faces:
        for angle in np.deg2rad(np.arange(0.0, 360.0, 360.0 / conf.angles)):
            R, height = resting(face, n, angle, target.hull, target.centre)
            with np.errstate(divide="ignore", invalid="ignore"):
                z = (plane.offset + height) / along  # the centre's distance (rays have z = 1)
            span = f_px * target.diameter_m / np.where(z > 0, z, np.nan)
            ok = (z > 0) & (span >= conf.min_span_px / LEVEL) & (span <= 0.9 * h)
            if not ok.any():
                continue
            best = np.full((2, h, w), -np.inf, np.float32)
            z_k = float(np.nanmin(np.where(ok, z, np.nan)))
            while z_k <= np.nanmax(np.where(ok, z, np.nan)) * SIZE_STEP:
                mask, ring, c = _kernels(R, target, Ks, z_k)
                band = ok & (np.abs(np.log(z / z_k)) <= 0.5 * np.log(SIZE_STEP))
                if band.any() and mask.shape[0] < h and mask.shape[1] < w:
                    padded = cv2.copyMakeBorder(small, c[1], c[1], c[0], c[0], cv2.BORDER_CONSTANT, value=outside)
                    S = cv2.matchTemplate(padded, mask, cv2.TM_CCORR)
                    S = np.stack([S, S - cv2.matchTemplate(padded, ring, cv2.TM_CCORR)])
                    # As the judge: too little of the silhouette in the frame to tell.
                    frame = cv2.copyMakeBorder(inside, c[1], c[1], c[0], c[0], cv2.BORDER_CONSTANT, value=0.0)
                    S[:, cv2.matchTemplate(frame, mask, cv2.TM_CCORR) < conf.min_visible * mask.sum()] = -np.inf
                    best = np.where(band, np.maximum(best, S), best)
                z_k *= SIZE_STEP

            def pose_at(y: int | np.integer, x: int | np.integer, R=R, z=z) -> np.ndarray:
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = z[y, x] * rays[y, x] - R @ target.centre
                return T

            y, x = np.unravel_index(int(np.argmax(best[0])), (h, w))
            if np.isfinite(best[0, y, x]):
                held.append((float(best[0, y, x]), pose_at(y, x)))
            for _ in range(PEAKS):  # a few places a turn: the first may be a found object's edge
                y, x = np.unravel_index(int(np.argmax(best[1])), (h, w))
                if not np.isfinite(best[1, y, x]):
                    break
                standing.append((float(best[1, y, x]), pose_at(y, x)))
                r = max(int(0.5 * span[y, x]), 1)
                best[1, max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = -np.inf
    distinct: list[np.ndarray] = []
    for _, T in sorted(held, key=lambda f: -f[0]):
        if not any(_near(T, k, target) for k in distinct):
            distinct.append(T)
        if len(distinct) == count:
            break
    taken = [_centre(T, target) for T in distinct]
    spots: list[tuple[np.ndarray, list[np.ndarray]]] = []
    for _, T in sorted(standing, key=lambda f: -f[0]):
        centre = _centre(T, target)
        if any(_same_place(centre, t, target) for t in taken):
            continue
        at = [s for s in spots if _same_place(centre, s[0], target)]
        if not at and len(spots) < SPOTS:
            spots.append((centre, [T]))
        elif at and len(at[0][1]) < CANDIDATES_PER_START and not any(_near(T, k, target) for k in at[0][1]):
            at[0][1].append(T)
    return distinct + [T for _, turns in spots for T in turns]


def _refaced(T: np.ndarray, plane: Plane, target: Target) -> list[np.ndarray]:
    """The object at T's place (its centre's viewing ray, resting on the plane) on each of its resting faces,
    its long axis along T's either way (a face it stands up on: T's turn and three quarter turns more)."""
    n = plane.normal
    axis = _long_axis(target)
    across = np.eye(3)[int(np.argmin(np.abs(axis)))]  # a model axis well off the long one
    c = _centre(T, target)
    ray = c / c[2]

    def flat(v: np.ndarray) -> np.ndarray:
        return v - (v @ n) * n

    def turn(have: np.ndarray, want: np.ndarray) -> float:
        """The turn about n taking ``have`` to ``want`` (both in the plane)."""
        return float(np.arctan2(np.cross(have, want) @ n, have @ want))

    want = flat(T[:3, :3] @ axis)
    out = []
    for face in target.faces:
        R0 = turn_to(face, -n)  # the face down, not yet turned (as :func:`resting` with angle 0)
        have = flat(R0 @ axis)
        if np.linalg.norm(have) > 0.3 and np.linalg.norm(want) > 0.3:
            base = turn(have, want)
            angles = [base, base + np.pi]
        else:
            have = flat(R0 @ across)
            base = turn(have, flat(T[:3, :3] @ across)) if np.linalg.norm(have) > 1e-6 else 0.0
            angles = [base + k * np.pi / 2 for k in range(4)]
        for angle in angles:
            R, height = resting(face, n, angle, target.hull, target.centre)
            U = np.eye(4)
            U[:3, :3] = R
            U[:3, 3] = ray * (plane.offset + height) / float(ray @ n) - R @ target.centre
            out.append(U)
    return out


def _long_axis(target: Target) -> np.ndarray:
    """The direction (model frame) along which the object is longest: its hull's first principal axis."""
    v = target.hull - target.hull.mean(axis=0)
    return np.linalg.svd(v, full_matrices=False)[2][0]


def _centre(T: np.ndarray, target: Target) -> np.ndarray:
    return T[:3, :3] @ target.centre + T[:3, 3]


def _same_place(a: np.ndarray, b: np.ndarray, target: Target) -> bool:
    """Object centres ``a`` and ``b`` within half its diameter: one place for the coarse search's spread."""
    return bool(np.linalg.norm(a - b) < 0.5 * target.diameter_m)


def _spread(chosen: list[int], ranked, poses: list[np.ndarray], target: Target, extra: int) -> list[int]:
    """``chosen`` and the best of ``ranked`` at each of up to ``extra`` other places (:func:`_same_place`) —
    so that one place whose colours fit the object in several ways (a shadow of its colours, a found
    object's edge) cannot take every candidate."""
    out = list(chosen)
    places = [_centre(poses[k], target) for k in out]
    added = 0
    for k in ranked:
        if added == extra:
            break
        c = _centre(poses[k], target)
        if k not in out and not any(_same_place(c, p, target) for p in places):
            out.append(k)
            places.append(c)
            added += 1
    return out


def _turn_deg(A: np.ndarray, B: np.ndarray) -> float:
    """The angle (degrees) between poses A's and B's rotations."""
    return float(np.rad2deg(np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2, -1, 1))))


def _near(A: np.ndarray, B: np.ndarray, target: Target) -> bool:
    """Same place (centres within 0.2 diameter) and nearly the same turn (within 20 degrees)."""
    near = np.linalg.norm(_centre(A, target) - _centre(B, target)) < 0.2 * target.diameter_m
    return bool(near and _turn_deg(A, B) < 20.0)


def _kernels(R: np.ndarray, target: Target, Ks: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """The coarse search's kernels for the object turned by R with its centre ``z`` away on the optical axis:
    its filled hull polygon (1 inside), and the thin ring around it weighted so that it sums to the polygon's
    area (the polygon's correlation minus the ring's: its area times how much more of the object's colours it
    holds than its surroundings — a broad patch of them, a shadow, scores nothing); and the centre's pixel."""
    p = target.hull @ R.T + (np.array([0.0, 0.0, z]) - R @ target.centre)
    xy = p[:, :2] / p[:, 2:] * [Ks[0, 0], Ks[1, 1]]
    extent = float(np.abs(xy).max())
    r = int(np.ceil(extent * (1.0 + COARSE_RING))) + 2
    mask = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    poly = cv2.convexHull(np.round(xy + r).astype(np.int32))
    cv2.fillConvexPoly(mask, poly, 1.0)
    width = max(1, int(round(COARSE_RING * extent)))
    ring = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1, 2 * width + 1))) - mask
    return mask, ring * (mask.sum() / max(float(ring.sum()), 1.0)), (r, r)


def _onto(T: np.ndarray, plane: Plane, target: Target) -> np.ndarray:
    """The pose moved along the plane's normal until the object's lowest point is on the plane (a previous
    frame's placement on this frame's plane: the refinement only turns and slides along it)."""
    out = T.copy()
    out[:3, 3] += (plane.offset - ((target.hull @ T[:3, :3].T + T[:3, 3]) @ plane.normal).min()) * plane.normal
    return out


def _refine(start: np.ndarray, plane: Plane, target: Target, judge: _Judge, steps) -> tuple[float, Placed | None]:
    """Steepest ascent from ``start`` over turns about the plane's normal (through the object's centre) and
    slides along the plane, with each of ``steps`` ((degrees, fraction of the diameter), largest first) until
    no move improves."""
    n = plane.normal
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    best, (score, placed) = start, judge(start)
    for step_deg, step in steps:
        while True:
            moves = []
            for sign in (1.0, -1.0):
                T = best.copy()
                T[:3, :3] = cv2.Rodrigues(n * np.deg2rad(sign * step_deg))[0] @ best[:3, :3]
                T[:3, 3] += best[:3, :3] @ target.centre - T[:3, :3] @ target.centre
                moves.append(T)
                for e in (e1, e2):
                    T = best.copy()
                    T[:3, 3] += sign * step * target.diameter_m * e
                    moves.append(T)
            s, p, T = max(((*judge(T), T) for T in moves), key=lambda m: m[0])
            if not s > score + 1e-4:
                break
            best, score, placed = T, s, p
    return score, placed
