"""Frame-to-frame tracking: follow a confident pose into the next frame without SIFT or matching.

A recording's consecutive frames differ by a few pixels, so after a confident full estimate batchpose
seeds corners on the object (:func:`seed`: Shi-Tomasi, inside the silhouette rendered at that pose and
where the frame correlates with the rendered mesh, so not on occluders; lifted to model-frame 3D points
through the rendered depth) and, in each following frame, moves them (:func:`follow`) with pyramidal
Lucas-Kanade optical flow (kept only when flowing back lands within ``fb_max_px`` of the start, then
re-aligned by flow straight from the keyframe so frame-to-frame errors do not add up) and solves the pose
by Levenberg-Marquardt from the previous pose, trimming points whose reprojection error exceeds
``reproj_px``. The 3D points never change while a track lives; only the flow can drift. Optionally
(:func:`anchor_to_render`) the points are found again by NCC against the mesh rendered at the tracked pose,
which removes drift altogether. A track ends (the next frame is estimated afresh) when fewer than
``min_fraction`` of its seeded points survive, at a scene change or a gap in time. Pure computation: the
caller (:func:`batchpose.method.tracked.estimate_tracked`) keeps one :class:`Track` per object in the
:class:`~batchpose.method.sequence.Sequence` and decides when tracks start, end and are refreshed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from batchpose.config import TrackConfig
from batchpose.method.templates import lift_keypoints


@dataclass
class Track:
    """One object's live track.

    Attributes:
        xy: (N, 2) float32 positions of the surviving points in the last frame.
        X: (N, 3) float64 their model-frame 3D points.
        cam_from_model: (4, 4) pose in the last frame.
        n_seeded: points at the keyframe (the survival fraction is measured against it).
        confidence: the keyframe estimate's confidence (a tracked pose never claims more).
        age: frames tracked since the keyframe.
        key_gray: the keyframe image; key_xy: (N, 2) the surviving points' positions in it.
        key_pose: (4, 4) the pose at the keyframe (None: unknown).
        thin: seeded near its outline (``track.thin_margin_px``: too few corners inside the flow window's
            margin): a thin object, whose points do not pin its depth.
    """

    xy: np.ndarray
    X: np.ndarray
    cam_from_model: np.ndarray
    n_seeded: int
    confidence: float
    age: int = 0
    key_gray: np.ndarray | None = None
    key_xy: np.ndarray | None = None
    key_pose: np.ndarray | None = None
    thin: bool = False


@dataclass
class TrackResult:
    """A tracked pose: the moved track plus the figures a pose record reports."""

    track: Track
    n_inliers: int
    median_residual_px: float


def patch_ncc(a: np.ndarray, b: np.ndarray, xy: np.ndarray, radius: int) -> np.ndarray:
    """Normalised cross-correlation of the (2r+1)^2 patches of images ``a`` and ``b`` around each point.

    Points whose patch leaves the image get -1; a flat patch (no contrast) gets 0.
    """
    h, w = a.shape
    u = np.rint(xy[:, 0]).astype(int)
    v = np.rint(xy[:, 1]).astype(int)
    inside = (u >= radius) & (v >= radius) & (u < w - radius) & (v < h - radius)
    out = np.full(len(xy), -1.0)
    if not inside.any():
        return out
    d = np.arange(-radius, radius + 1)
    rows = v[inside, None, None] + d[None, :, None]
    cols = u[inside, None, None] + d[None, None, :]
    pa = a[rows, cols].reshape(inside.sum(), -1).astype(np.float64)
    pb = b[rows, cols].reshape(inside.sum(), -1).astype(np.float64)
    pa -= pa.mean(axis=1, keepdims=True)
    pb -= pb.mean(axis=1, keepdims=True)
    den = np.sqrt((pa**2).sum(axis=1) * (pb**2).sum(axis=1))
    out[inside] = np.where(den > 1e-9, (pa * pb).sum(axis=1) / np.maximum(den, 1e-9), 0.0)
    return out


def seed(
    gray: np.ndarray,
    cam_from_model: np.ndarray,
    render_gray: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    conf: TrackConfig,
    hidden: Sequence[Occluder] = (),
    margin_px: int | None = None,
):
    """Corners on the object at a known pose, where the frame looks like the mesh rendered there.

    A corner is kept only when the frame's patch around it correlates (NCC >= ``conf.min_ncc``) with the
    rendered mesh's: a corner on something in front of the object (which the rendering does not know
    about) would otherwise be tracked as the object and drag its pose along with the occluder.

    Args:
        gray: (H, W) uint8 frame. render_gray: (H, W) uint8 the mesh rendered at ``cam_from_model``;
            depth_m: its z-depth (pinhole, no distortion), 0 off the object. dist: the frame's distortion
            coefficients (may be empty). hidden: what is in front of part of the object (:func:`occluders`):
            no corners where it is and the object is farther than its nearest point, so the corners are
            spread over the part that shows and ``conf.quality`` is relative to its strongest corner.
        margin_px: how far inside the silhouette a corner must be (default half the flow window,
            ``conf.window_px``: no window reaches over the outline, whose background does not move with the
            object).

    Returns:
        xy (N, 2) float32 and X (N, 3) float64 model-frame points; N may be 0.
    """
    mask = (depth_m > 0).astype(np.uint8)
    k = 2 * (conf.window_px // 2 if margin_px is None else margin_px) + 1
    mask = cv2.erode(mask, np.ones((k, k), np.uint8))
    for occ in hidden:
        mask[occ.mask & (depth_m > occ.near_m)] = 0
    if not mask.any():
        return np.zeros((0, 2), np.float32), np.zeros((0, 3))
    corners = cv2.goodFeaturesToTrack(
        gray, maxCorners=conf.points, qualityLevel=conf.quality, minDistance=conf.min_distance_px, mask=mask
    )
    if corners is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, 3))
    xy = corners.reshape(-1, 2).astype(np.float32)
    at = xy
    if dist is not None and np.any(dist):  # the rendered depth is where the undistorted ray lands
        at = cv2.undistortPoints(xy.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    looks_alike = patch_ncc(gray, render_gray, at, conf.ncc_radius_px) >= conf.min_ncc
    xy, at = xy[looks_alike], at[looks_alike]
    keep, X = lift_keypoints(at, depth_m, K, np.linalg.inv(cam_from_model), radius=2)
    return xy[keep], X.astype(np.float64)


def _residuals(X, xy, rvec, tvec, K, dist) -> np.ndarray:
    proj, _ = cv2.projectPoints(X, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - xy, axis=1)


def _median_residual(X, xy, T, K, dist) -> float:
    return float(np.median(_residuals(X, xy, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)))


def _solve_lm(X, xy, T, K, dist, conf: TrackConfig, n_needed: float):
    """LM from pose ``T``, trimming twice; (pose, kept mask, median residual) or None."""
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    tvec = T[:3, 3].reshape(3, 1).copy()
    keep = np.ones(len(xy), bool)
    for thresh in (None, conf.reproj_px):
        rvec, tvec = cv2.solvePnPRefineLM(X[keep], xy[keep], K, dist, rvec, tvec)
        r = _residuals(X, xy, rvec, tvec, K, dist)
        keep = r <= (max(conf.reproj_px, 3.0 * float(np.median(r[keep]))) if thresh is None else thresh)
        if keep.sum() < n_needed:
            return None
    rvec, tvec = cv2.solvePnPRefineLM(X[keep], xy[keep], K, dist, rvec, tvec)
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(rvec)[0]
    out[:3, 3] = tvec.ravel()
    if out[2, 3] <= 0:
        return None
    return out, keep, float(np.median(_residuals(X[keep], xy[keep], rvec, tvec, K, dist)))


def _hold_depth(X, xy, T, previous, K, dist, weight: float) -> np.ndarray:
    """``track.depth_prior``: the pose ``T`` solved again with the change of the points' depth since
    ``previous`` costing as much as ``weight`` points would if the points' rim moved as far in the image as
    that change makes it grow or shrink. Where the points pin the depth (many, spread out) it moves the pose
    by a fraction of a pixel; where they do not (a few points along a thin object, lifted at a pose a little
    off), it keeps the track from sliding along the line of sight."""
    c = X.mean(axis=0)
    rim_px = 0.5 * (K[0, 0] + K[1, 1]) * float(np.linalg.norm(X - c, axis=1).max())
    z0 = float((previous[:3, :3] @ c + previous[:3, 3])[2])
    if z0 <= 0 or rim_px <= 0:
        return T
    k = np.sqrt(weight) * rim_px / z0**2
    rvec, tvec = cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3].astype(np.float64).copy()
    for _ in range(5):  # Gauss-Newton from the LM's pose, which the prior moves only a little
        proj, jac = cv2.projectPoints(X, rvec, tvec, K, dist)
        R, dR = cv2.Rodrigues(rvec)
        J = np.vstack([jac[:, :6], k * np.r_[dR[:, 6:9] @ c, 0.0, 0.0, 1.0]])
        r = np.r_[(proj.reshape(-1, 2) - xy).ravel(), k * ((R @ c)[2] + tvec[2] - z0)]
        step = np.linalg.solve(J.T @ J + 1e-9 * np.eye(6), -J.T @ r)
        rvec, tvec = rvec + step[:3], tvec + step[3:]
        if np.abs(step).max() < 1e-9:
            break
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(rvec)[0]
    out[:3, 3] = tvec
    return out if out[2, 3] > 0 else T


def _lk_params(conf: TrackConfig) -> dict:
    return {
        "winSize": (conf.window_px, conf.window_px),
        "maxLevel": conf.levels,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    }


def _split(values: np.ndarray, sizes: list[int]) -> list[np.ndarray]:
    return np.split(values, np.cumsum(sizes)[:-1]) if sizes else []


def follow(
    prev_gray: np.ndarray, gray: np.ndarray, track: Track, K: np.ndarray, dist: np.ndarray, conf: TrackConfig
) -> TrackResult | None:
    """Move ``track`` from ``prev_gray`` into ``gray``; None when the track is lost."""
    return follow_all(prev_gray, gray, [track], K, dist, conf)[0]


@dataclass
class Occluder:
    """Something in front of part of a tracked object: its image region and its nearest depth."""

    mask: np.ndarray
    """(H, W) bool: where it is in the image (grown by a margin)."""
    near_m: float
    """Its nearest point's depth; it hides only the object's points farther than this."""


def occluders(hulls: list[np.ndarray], poses: list[np.ndarray], K, dist, width: int, height: int, margin_px: int):
    """Which of several objects may hide which: per object, the others whose image regions (the projected
    convex hull, grown by ``margin_px``) overlap its own, as :class:`Occluder` (an empty list: nothing).

    Args:
        hulls: each object's convex-hull vertices (M, 3), model frame. poses: each one's cam_from_model.
    """
    regions = []
    for X, T in zip(hulls, poses, strict=True):
        r = _region(X, T, K, dist)
        regions.append(None if r is None else (r[0].min(axis=0) - margin_px, r[0].max(axis=0) + margin_px, *r))
    out: list[list[Occluder]] = [[] for _ in hulls]
    k = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    for j, b in enumerate(regions):
        if b is None:
            continue
        mask = None
        for i, a in enumerate(regions):
            if i == j or a is None or not (np.all(a[0] <= b[1]) and np.all(b[0] <= a[1])):
                continue
            if mask is None:
                m = _fill(b[2], width, height)
                mask = (cv2.dilate(m, k) if margin_px > 0 else m).astype(bool)
            out[i].append(Occluder(mask, b[3]))
    return out


def _region(X: np.ndarray, T: np.ndarray, K, dist):
    """Model points ``X`` (the convex hull) at pose ``T``: their image points (N, 2) and the nearest depth,
    or None when they reach behind the camera (not projected)."""
    cam = X @ T[:3, :3].T + T[:3, 3]
    if np.any(cam[:, 2] <= 1e-3):
        return None
    uv, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)
    return uv.reshape(-1, 2), float(cam[:, 2].min())


def _fill(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) uint8: 1 inside the convex hull of the image points ``uv``."""
    m = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(m, np.rint(cv2.convexHull(uv.astype(np.float32))).astype(np.int32), 1)
    return m


def covered(
    hull: np.ndarray, pose: np.ndarray, others: list[tuple[np.ndarray, np.ndarray]], K, dist, width: int, height: int
) -> tuple[float, list[float]]:
    """How much of an object's image region (``hull`` projected at ``pose``) the ``others`` ((hull, pose)
    each) cover from in front (their centres nearer the camera): the fraction covered by all of them, and by
    each one (0 for one behind or beside it). (0, zeros) when the object is mostly (over half its region) off
    the image: it has left the view, and what moves over its last place does not hide it."""
    none = (0.0, [0.0] * len(others))
    r = _region(hull, pose, K, dist)
    if r is None:
        return none
    own = _fill(r[0], width, height).astype(bool)
    area = int(own.sum())
    if area == 0 or area < 0.5 * cv2.contourArea(cv2.convexHull(r[0].astype(np.float32))):
        return none
    union = np.zeros_like(own)
    each = []
    for X, T in others:
        o = _region(X, T, K, dist) if T[2, 3] < pose[2, 3] else None
        if o is None:
            each.append(0.0)
            continue
        m = own & _fill(o[0], width, height).astype(bool)
        union |= m
        each.append(float(m.sum()) / area)
    return float(union.sum()) / area, each


def _inside(mask: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Whether each point (N, 2) falls on a set pixel of ``mask`` (points off the image do not)."""
    h, w = mask.shape
    ij = np.rint(xy).astype(np.int64)
    on = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out = np.zeros(len(xy), bool)
    out[on] = mask[ij[on, 1], ij[on, 0]]
    return out


def follow_all(
    prev_gray: np.ndarray,
    gray: np.ndarray,
    tracks: list[Track],
    K: np.ndarray,
    dist: np.ndarray,
    conf: TrackConfig,
    hidden: list[list[Occluder]] | None = None,
) -> list[TrackResult | None]:
    """:func:`follow` for several tracks in one frame (None for each track that is lost).

    Lucas-Kanade tracks every point on its own, so all tracks' points share one forward and one backward
    flow call (and the anchor flow one call per keyframe image): each call builds both images' pyramids,
    which costs as much as flowing a few hundred points.

    Args:
        hidden: per track, what may be in front of the object (:func:`occluders`): the track's points
            inside an occluder's region, before or after the flow, and farther than its nearest point are
            dropped and count as never seeded.
    """
    lk = _lk_params(conf)
    out: list[TrackResult | None] = [None] * len(tracks)
    live = [i for i, t in enumerate(tracks) if len(t.xy) >= conf.min_points]
    if not live:
        return out
    sizes = [len(tracks[i].xy) for i in live]
    p0 = np.vstack([tracks[i].xy for i in live]).reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, None, **lk)
    p0r, st0, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, p1, None, **lk)
    fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1)
    ok_all = (st1.ravel() == 1) & (st0.ravel() == 1) & (fb <= conf.fb_max_px)
    moved = {}
    for i, p1_i, ok in zip(live, _split(p1.reshape(-1, 2), sizes), _split(ok_all, sizes), strict=True):
        track = tracks[i]
        n_seeded = track.n_seeded
        if hidden is not None and hidden[i]:
            z = track.X @ track.cam_from_model[2, :3] + track.cam_from_model[2, 3]
            covered = np.zeros(len(z), bool)
            for occ in hidden[i]:
                covered |= (_inside(occ.mask, track.xy) | _inside(occ.mask, p1_i)) & (z > occ.near_m)
            ok = ok & ~covered
            n_seeded = max(n_seeded - int(covered.sum()), 0)
        if ok.sum() >= max(conf.min_points, conf.min_fraction * n_seeded):
            key_xy = track.key_xy[ok] if track.key_xy is not None else None
            moved[i] = (p1_i[ok].astype(np.float64), track.X[ok], key_xy, n_seeded)
    if conf.anchor:
        # Flow straight from the keyframe, started where frame-to-frame flow ended: frame-to-frame errors
        # add up over a track, errors against the keyframe do not. One call per keyframe image.
        groups: dict[int, list[int]] = {}
        for i in moved:
            if tracks[i].key_gray is not None:
                groups.setdefault(id(tracks[i].key_gray), []).append(i)
        for members in groups.values():
            sizes_g = [len(moved[i][0]) for i in members]
            pk, stk, _ = cv2.calcOpticalFlowPyrLK(
                tracks[members[0]].key_gray,
                gray,
                np.vstack([_known(moved[i][2]) for i in members]).reshape(-1, 1, 2).astype(np.float32),
                np.vstack([moved[i][0] for i in members]).reshape(-1, 1, 2).astype(np.float32),
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                **{**lk, "maxLevel": 1},
            )
            for i, pk_i, st_i in zip(
                members, _split(pk.reshape(-1, 2), sizes_g), _split(stk.ravel(), sizes_g), strict=True
            ):
                xy = moved[i][0]
                agree = (st_i == 1) & (np.linalg.norm(pk_i - xy, axis=1) <= conf.anchor_px)
                xy[agree] = pk_i[agree]
    for i, (xy, X, key_xy, n_seeded) in moved.items():
        out[i] = _solve_track(tracks[i], xy, X, key_xy, K, dist, conf, n_seeded)
    return out


def _solve_track(track: Track, xy, X, key_xy, K, dist, conf: TrackConfig, n_seeded: int) -> TrackResult | None:
    """LM from the previous pose on the flowed points, trimming the points that do not fit (occluders, flow
    slips); the track moved on, or None when too few points fit. ``n_seeded``: the track's seeded points
    less those hidden since."""
    solved = _solve_lm(X, xy, track.cam_from_model, K, dist, conf, max(conf.min_points, conf.min_fraction * n_seeded))
    if solved is None:
        return None
    T, keep, med = solved
    if conf.depth_prior > 0:
        T = _hold_depth(X[keep], xy[keep], T, track.cam_from_model, K, dist, conf.depth_prior)
        med = _median_residual(X[keep], xy[keep], T, K, dist)  # the reported pose's, not the LM's
    # The points move on to where the pose puts them: single points cannot wander off the rigid object.
    snapped, _ = cv2.projectPoints(X[keep], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)
    moved = Track(
        snapped.reshape(-1, 2).astype(np.float32),
        X[keep],
        T,
        n_seeded,
        track.confidence,
        track.age + 1,
        track.key_gray,
        key_xy[keep] if key_xy is not None else None,
        track.key_pose,
        track.thin,
    )
    return TrackResult(moved, int(keep.sum()), med)


def anchor_to_render(
    gray: np.ndarray, render_gray: np.ndarray, track: Track, K: np.ndarray, dist: np.ndarray, conf: TrackConfig
) -> TrackResult | None:
    """Re-place the track's points on the mesh itself and solve again: each point's patch in the mesh
    rendered at the tracked pose is found in the frame by normalised cross-correlation within
    ``render_search_px``, so the pose is pulled back onto the model however far the flow has drifted
    (within the search radius). None when too few points are found. A thin track's pose (``track.thin``) is
    solved with ``conf.depth_prior`` as a followed pose is, against the tracked pose's depth: its points,
    found again in the render, let it slide along the line of sight as flowed points do (the held-out
    marker's carries jumped 4 % in depth there). Other tracks are not held: their points pin the depth, and
    the pull is what takes out the depth the flow has drifted (held too, a gelatin box moving through a
    generated log drifted to 0.37 d)."""
    h, r = conf.ncc_radius_px, conf.render_search_px
    H, W = gray.shape
    rvec = cv2.Rodrigues(track.cam_from_model[:3, :3])[0]
    tvec = track.cam_from_model[:3, 3]
    p_render = cv2.projectPoints(track.X, rvec, tvec, K, None)[0].reshape(-1, 2)  # the render is pinhole
    p_frame = cv2.projectPoints(track.X, rvec, tvec, K, dist)[0].reshape(-1, 2)
    found = np.full((len(p_frame), 2), np.nan)
    for i, (pr, pf) in enumerate(zip(p_render, p_frame, strict=True)):
        cr, cf = np.rint(pr).astype(int), np.rint(pf).astype(int)
        if not (
            h <= cr[0] < W - h and h <= cr[1] < H - h and h + r <= cf[0] < W - h - r and h + r <= cf[1] < H - h - r
        ):
            continue
        tmpl = render_gray[cr[1] - h : cr[1] + h + 1, cr[0] - h : cr[0] + h + 1]
        if float(tmpl.std()) < 2.0:
            continue
        win = gray[cf[1] - h - r : cf[1] + h + r + 1, cf[0] - h - r : cf[0] + h + r + 1]
        score = cv2.matchTemplate(win, tmpl, cv2.TM_CCOEFF_NORMED)
        dy, dx = np.unravel_index(int(np.argmax(score)), score.shape)
        if score[dy, dx] < conf.min_ncc or dy in (0, 2 * r) or dx in (0, 2 * r):
            continue  # a weak peak, or the best place is at the edge of the search (farther than r)

        def vertex(a, b, c):  # sub-pixel peak of a parabola through three samples
            den = a - 2 * b + c
            return 0.0 if abs(den) < 1e-9 else 0.5 * (a - c) / den

        sx = vertex(score[dy, dx - 1], score[dy, dx], score[dy, dx + 1])
        sy = vertex(score[dy - 1, dx], score[dy, dx], score[dy + 1, dx])
        found[i] = cf + np.array([dx - r + sx, dy - r + sy]) + (pr - cr)
    ok = np.isfinite(found[:, 0])
    if ok.sum() < max(conf.min_points, conf.min_fraction * len(track.X)):
        return None
    solved = _solve_lm(track.X[ok], found[ok], track.cam_from_model, K, dist, conf, conf.min_points)
    if solved is None:
        return None
    T, keep, med = solved
    if track.thin and conf.depth_prior > 0:
        X_kept, xy_kept = track.X[ok][keep], found[ok][keep]
        T = _hold_depth(X_kept, xy_kept, T, track.cam_from_model, K, dist, conf.depth_prior)
        med = _median_residual(X_kept, xy_kept, T, K, dist)
    moved = Track(
        cv2.projectPoints(track.X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, dist)[0].reshape(-1, 2).astype(np.float32),
        track.X,
        T,
        track.n_seeded,
        track.confidence,
        track.age,
        track.key_gray,
        track.key_xy,
        track.key_pose,
        track.thin,
    )
    return TrackResult(moved, int(keep.sum()), med)


def view_turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    """How far the camera has moved around the object between poses ``a`` and ``b`` (cam_from_model): the
    angle between the directions from the object's origin to the camera, in the model frame. A roll about
    the line of sight does not count: it shows the same sides."""
    va, vb = (-T[:3, :3].T @ T[:3, 3] for T in (a, b))
    cos = float(va @ vb) / (float(np.linalg.norm(va) * np.linalg.norm(vb)) + 1e-12)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _known(a: np.ndarray | None) -> np.ndarray:
    """``a``, which the caller has checked is there."""
    assert a is not None
    return a
