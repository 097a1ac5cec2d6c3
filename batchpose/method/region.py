"""One image region belongs to one object (``region.max_overlap``, :func:`claim_regions`).

Each object of a frame is estimated on its own, so two objects can claim the same pixels: a box found on
another box that carries the same brand print. After the frame's estimate and the weak-pose check, every
two ok poses (tracked ones too) are compared:

1. **overlap**: their meshes rendered at their poses share more than ``region.max_overlap`` of the smaller
   silhouette (pairs whose projected convex hulls overlap too little for that are not rendered);
2. **can both be right?** One of the two can stand in front of the other when (a) the other one's evidence
   (its inlier keypoints; a tracked pose's tracked points) is not where the front one hides it: per pixel,
   at most ``region.max_hidden_evidence`` as dense inside the front one's silhouette as over its own
   (:func:`hidden_evidence`), and (b) the rendered depths
   agree: over the shared pixels the front one's surface is not behind the other's (median, by more than
   :data:`DEPTH_TOLERANCE` of the distance). A real occlusion passes for one order: the nearer object covers
   the farther one where the farther one shows no evidence of itself. Two poses laid over the same features,
   or a pose whose evidence is visible only if it stood in front of an object it is rendered behind, pass
   for neither order: a **conflict**;
3. **the verification decides** a conflict: each mesh, rendered at its pose, is compared with the frame over
   the shared pixels (Lab correlation, as ``verify_below``'s check; not under 30 shared pixels); the better
   match keeps ``ok`` (the more confident pose when the matches are within :data:`MATCH_MARGIN`), the other
   becomes ``conflict``, its reason naming the winner, and leaves the sequence's tracks.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.core.frames import Camera, Frame
from batchpose.core.poses import PoseRecord
from batchpose.method.appearance import texture_match
from batchpose.method.objects import Objects
from batchpose.method.records import pose_of
from batchpose.method.sequence import Sequence
from batchpose.method.verify import VERIFY_MIN_PX

#: The front one of two poses may be rendered behind the other by this fraction of the distance (median over
#: the shared pixels): poses on real frames are 1-3 % off in distance, so two objects that touch (a marker
#: lying on a box) can come out in either order.
DEPTH_TOLERANCE = 0.05
#: A pose's evidence counts as hidden by a silhouette eroded by this many pixels: a keypoint beside an
#: occluding edge, under a pose a few pixels off, is not evidence against it.
EDGE_PX = 3
#: Two renders whose matches with the frame differ by less than this do not decide a conflict: the more
#: confident pose is kept. Lab correlations over the same pixels differ by 0.14-1.0 in the conflicts decided
#: right on the 12-object cycling log without the presence check; its one near tie (0.31 against 0.33, the
#: right pose's confidence 0.85 against 0.42) went the wrong way by the match alone.
MATCH_MARGIN = 0.1
#: Fewer of a pose's keypoints than this under another pose are no evidence against that one being in front.
MIN_HIDDEN = 3
#: The projected convex hulls are rendered when they share at least this part of ``region.max_overlap``: a
#: silhouette is smaller than its hull, so the fraction of it that is shared can exceed the hulls'.
HULL_SLACK = 0.5


@dataclass
class Claim:
    """What an ok pose claims of the frame: its record, its rendered rgb (H, W, 3) and depth (H, W, metres,
    0 off the mesh)."""

    rec: PoseRecord
    rgb: np.ndarray
    depth: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return self.depth > 0


@dataclass(frozen=True)
class Verdict:
    """Two overlapping poses judged: the shared fraction of the smaller silhouette, how much of each one's
    evidence lies under the other (:func:`hidden_evidence`), and each one's median depth over the shared
    pixels (metres)."""

    overlap: float
    hidden_a: float
    hidden_b: float
    depth_a: float
    depth_b: float

    def a_in_front(self, max_hidden: float) -> bool:
        """Whether a can stand in front of b: b's evidence is not under a, a is not rendered behind b."""
        return self.hidden_b <= max_hidden and self.depth_a <= self.depth_b * (1.0 + DEPTH_TOLERANCE)

    def b_in_front(self, max_hidden: float) -> bool:
        return self.hidden_a <= max_hidden and self.depth_b <= self.depth_a * (1.0 + DEPTH_TOLERANCE)

    def conflict(self, max_hidden: float) -> bool:
        """Neither can stand in front of the other: they claim the same pixels and cannot both be right."""
        return not (self.a_in_front(max_hidden) or self.b_in_front(max_hidden))


def claim_regions(objects: Objects, frame: Frame, rgb: np.ndarray, records: list[PoseRecord], sequence: Sequence):
    """``region.max_overlap``: of every two ok poses of the frame that claim the same pixels and cannot both
    be right (see the module docstring), the one whose render matches the frame worse over the shared pixels
    becomes ``conflict`` and leaves ``sequence`` (its track and last confident pose)."""
    rc = objects.conf.region
    if rc.max_overlap <= 0 or objects.renderer is None:
        return
    placed = [r for r in records if r.ok and r.obj_name in objects.models]
    pairs = candidate_pairs(objects, placed, frame.camera, rc.max_overlap * HULL_SLACK)
    if not pairs:
        return
    t0 = time.perf_counter()
    cam = frame.camera
    claims: dict[int, Claim] = {}

    def claim(rec: PoseRecord) -> Claim:
        if id(rec) not in claims:
            claims[id(rec)] = Claim(rec, *objects.render(rec.obj_name, pose_of(rec), cam))
        return claims[id(rec)]

    lab = None
    for a, b in pairs:
        if not (a.ok and b.ok):
            continue  # one lost an earlier conflict
        ca, cb = claim(a), claim(b)
        verdict = judge(ca, cb)
        if verdict is None or verdict.overlap <= rc.max_overlap or not verdict.conflict(rc.max_hidden_evidence):
            continue
        shared = ca.mask & cb.mask
        if shared.sum() < VERIFY_MIN_PX:
            continue  # too few pixels to tell which pose they show
        lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB) if lab is None else lab
        match_a, match_b = (texture_match(lab[shared], c.rgb[shared]) for c in (ca, cb))
        by_match = abs(match_a - match_b) >= MATCH_MARGIN
        key = (lambda x: -x[1]) if by_match else (lambda x: -x[0].confidence)
        (win, m_win), (lose, m_lose) = sorted(((a, match_a), (b, match_b)), key=key)
        lose.status = "conflict"
        lose.reason = (
            f"claims the pixels of {win.obj_name} ({100 * verdict.overlap:.0f}% of the smaller silhouette "
            f"shared; keypoints under the other, per pixel, against over its own: {a.obj_name} "
            f"{verdict.hidden_a:.2f}, {b.obj_name} {verdict.hidden_b:.2f}; median depth there "
            f"{verdict.depth_a:.2f} / {verdict.depth_b:.2f} m): its mesh matches the frame there {m_lose:.2f}, "
            f"{win.obj_name}'s {m_win:.2f} (confidence {lose.confidence:.2f} against {win.confidence:.2f}"
            + ("" if by_match else f"; matches within {MATCH_MARGIN:g}: the more confident pose kept")
            + ")"
        )
        sequence.drop(lose)
    share = (time.perf_counter() - t0) / max(len(claims), 1)
    for c in claims.values():
        c.rec.timings["refine"] = c.rec.timings.get("refine", 0.0) + share


def candidate_pairs(objects: Objects, placed: list[PoseRecord], cam: Camera, min_hull_overlap: float):
    """The pairs of ``placed`` whose projected convex hulls (polygons cut to the image, no rasterising) share
    more than ``min_hull_overlap`` of the smaller one's area, most overlapping first (a pose reaching behind
    the camera pairs with every other)."""
    hulls = [_hull_polygon(objects.hull(r.obj_name), pose_of(r), cam) for r in placed]
    scored = []
    for (i, a), (j, b) in itertools.combinations(enumerate(placed), 2):
        ha, hb = hulls[i], hulls[j]
        if ha is None or hb is None:
            scored.append((1.0, a, b))
            continue
        if len(ha) < 3 or len(hb) < 3:
            continue  # off the image
        small = min(cv2.contourArea(ha), cv2.contourArea(hb))
        shared = cv2.intersectConvexConvex(ha, hb)[0] if small > 0 else 0.0
        if shared > min_hull_overlap * small:
            scored.append((shared / small, a, b))
    scored.sort(key=lambda s: -s[0])
    return [(a, b) for _, a, b in scored]


def judge(ca: Claim, cb: Claim) -> Verdict | None:
    """The overlap of two rendered poses, each one's evidence under the other, their depths over the shared
    pixels; None when either shows no pixel."""
    ma, mb = ca.mask, cb.mask
    na, nb = int(ma.sum()), int(mb.sum())
    if na == 0 or nb == 0:
        return None
    shared = ma & mb
    n = int(shared.sum())
    if n == 0:
        return Verdict(0.0, 0.0, 0.0, 0.0, 0.0)
    return Verdict(
        n / min(na, nb),
        hidden_evidence(ca.rec.inliers_px, ma, mb),
        hidden_evidence(cb.rec.inliers_px, mb, ma),
        float(np.median(ca.depth[shared])),
        float(np.median(cb.depth[shared])),
    )


def hidden_evidence(xy: np.ndarray, own: np.ndarray, other: np.ndarray) -> float:
    """How much of a pose's evidence lies where another pose would hide it: the share of its evidence pixels
    ``xy`` (N, 2) inside ``other`` (H, W bool, eroded by :data:`EDGE_PX`) over the share of its own silhouette
    ``own`` (H, W bool) there. About 1 when its keypoints are as dense under the other as anywhere on it
    (both claim the same features), about 0 for an object hidden there; 0 without evidence or with fewer
    than :data:`MIN_HIDDEN` keypoints there (one keypoint on an edge is no claim)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    k = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
    core = cv2.erode(other.astype(np.uint8), k).astype(bool)
    area = float((own & core).sum()) / max(float(own.sum()), 1.0)
    if len(xy) == 0 or area == 0:
        return 0.0
    h, w = core.shape
    ij = np.rint(xy).astype(np.int64)
    on = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    inside = np.zeros(len(xy), bool)
    inside[on] = core[ij[on, 1], ij[on, 0]]
    n = int(inside.sum())
    return 0.0 if n < MIN_HIDDEN else n / len(xy) / area


def _hull_polygon(hull: np.ndarray, T: np.ndarray, cam: Camera) -> np.ndarray | None:
    """The convex hull ``hull`` (M, 3, model frame) projected at pose ``T`` and cut to the image: a convex
    polygon (K, 2) float32 (empty when off the image); None when it reaches behind the camera."""
    if np.any(hull @ T[2, :3] + T[2, 3] <= 1e-3):
        return None
    uv, _ = cv2.projectPoints(hull, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], cam.K, cam.dist)
    poly = cv2.convexHull(uv.reshape(-1, 2).astype(np.float32)).reshape(-1, 2)
    w, h = cam.width - 0.5, cam.height - 0.5
    image = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], np.float32)
    area, cut = cv2.intersectConvexConvex(poly, image)
    return cut.reshape(-1, 2).astype(np.float32) if area > 0 and cut is not None else np.zeros((0, 2), np.float32)
