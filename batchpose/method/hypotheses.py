"""From the passes' poses to one pose: render-and-match refinement of several hypotheses (:func:`refine`),
the frame's checks between poses (:func:`alternative`, :func:`planar_mirror`, by :func:`frame_prefers`), and
the optional dense finish (:func:`polish`)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from batchpose.core.frames import Camera
from batchpose.core.geometry import rotation_error_deg
from batchpose.method.depth_search import distinct_matches
from batchpose.method.features import to_gray
from batchpose.method.gnc_pnp import planar_alternative, solve_pose
from batchpose.method.objects import Objects
from batchpose.method.passes import Pass
from batchpose.method.refine import Refined, refine_pose
from batchpose.method.score import compare
from batchpose.method.shot import LazyLab
from batchpose.method.track import Track, anchor_to_render, seed


def refine(
    objects: Objects,
    name: str,
    passes: list[Pass],
    camera: Camera,
    xy_q: np.ndarray,
    desc_q: np.ndarray,
    strong: bool = False,
    tried: list | None = None,
) -> Refined | None:
    """Refine the passes' poses (and, with ``refine.hypotheses`` > 1, per-template poses); best guided score.
    Every refined hypothesis is appended to ``tried`` (when given).

    Args:
        passes: (result, pairs, ...) of the coarse and fine passes, best first.
        xy_q, desc_q: the keypoints guided matching uses.
        strong: the best pass has found the object (:func:`batchpose.method.passes.strong`): refine its pose
            only, once.
    """
    conf = objects.conf

    def render(T):
        return objects.render(name, T, camera)

    def once(T, iterations):
        r = refine_pose(
            T,
            xy_q,
            desc_q,
            camera.K,
            camera.dist,
            render,
            conf.refine,
            conf.features,
            conf.gnc,
            lambda X: objects.weights(name, X),
            iterations=iterations,
            support_px=conf.support_px,
        )
        if r is not None and tried is not None:
            tried.append(r)
        return r

    def finish(r):
        """The remaining rounds after a first one; keeps the first when they do not score higher."""
        if r is None or conf.refine.iterations <= 1:
            return r
        more = once(r.result.cam_from_model, conf.refine.iterations - 1)
        return more if more is not None and more.score >= r.score else r

    ok = [p[0] for p in passes if p[0] is not None and p[0].status == "ok"]
    # One round per hypothesis to rank them, the remaining rounds for the best one only.
    best = None
    for T in _starts(objects, name, passes, ok, camera, strong):
        r = once(T, 1)
        if r is not None and (best is None or r.score > best.score):
            best = r
    best = best if strong else finish(best)
    if best is not None and conf.refine.flips and not strong:
        # A turned hypothesis starts up to ~20 degrees off, so one that finds a third of the best score in
        # its first round gets the remaining rounds before it is compared.
        base = best.result.cam_from_model
        for F in objects.flips(name):
            r = once(base @ F, 1)
            if r is not None and 3 * r.score >= best.score:
                r = finish(r)
            if r is not None and r.score > best.score:
                best = r
    if best is not None and ok and best.result.n_inliers < max(r.n_inliers for r in ok):
        return None  # the guided pairs explain the frame worse than the template pairs
    return best


def _starts(
    objects: Objects, name: str, passes: list[Pass], ok: list, camera: Camera, strong: bool
) -> list[np.ndarray]:
    """The refinement's starting poses: the ok passes' poses (the best one only when ``strong``), then poses
    solved from each top template's pairs alone, up to ``refine.hypotheses`` in all, less those within
    ``refine.same_start_px`` of an earlier start."""
    conf = objects.conf
    box = _box_corners(objects.libraries[name].pts3d)
    starts: list[np.ndarray] = []
    seen: list[np.ndarray] = []  # each start's box corners in the image

    def add(T: np.ndarray) -> None:
        uv = _project(box, T, camera)
        if any(np.abs(uv - other).max() < conf.refine.same_start_px for other in seen):
            return  # the same guided pairs, so the same refined pose, as an earlier start
        starts.append(T)
        seen.append(uv)

    n_tried = 0
    for r in ok[: 1 if strong else conf.refine.hypotheses]:
        add(r.cam_from_model)
        n_tried += 1
    for _res, corr, *_ in [] if strong else passes:
        for v in corr.templates:
            if n_tried >= conf.refine.hypotheses:
                break
            sel = corr.view_ids == v
            if sel.sum() < conf.gnc.min_inliers:
                continue
            sub = solve_pose(corr.x[sel], corr.X[sel], camera.K, camera.dist, None, conf.gnc)
            if sub.status == "ok" and sub.cam_from_model is not None:
                add(sub.cam_from_model)
                n_tried += 1
    return starts


def _box_corners(X: np.ndarray) -> np.ndarray:
    """(8, 3) the corners of the axis-aligned box around the points ``X`` (N, 3)."""
    lo, hi = X.min(axis=0), X.max(axis=0)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _project(X: np.ndarray, T: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 2) pixels of the points ``X`` (N, 3) at pose ``T`` (pinhole; the distortion moves nearby poses'
    projections alike); inf for points behind the camera."""
    Y = X @ T[:3, :3].T + T[:3, 3]
    z = Y[:, 2:3]
    uv = (Y[:, :2] / np.where(z > 1e-6, z, np.nan)) * np.diag(camera.K)[:2] + camera.K[:2, 2]
    return np.where(np.isfinite(uv), uv, np.inf)


def alternative(objects: Objects, lab: LazyLab | None, name: str, res, tried: list, camera: Camera, timings: dict):
    """``alternatives``: ((result, x, X), reason) of a refined hypothesis the frame (``lab``) prefers to the
    pose ``res`` by colour and by edges where their renders differ, or by the verification score
    (``checks_score_margin``); None to keep the pose."""
    conf = objects.conf
    if conf.alternatives <= 0 or lab is None or len(tried) < 2:
        return None
    t0 = time.perf_counter()
    picked = _distinct_hypotheses(objects, name, res, tried, camera)
    if not picked:
        return None
    current, chosen, why = objects.render(name, res.cam_from_model, camera), None, ""
    for r in picked:
        rendered = objects.render(name, r.result.cam_from_model, camera)
        cues = frame_prefers(lab, current, rendered, conf.planar_mismatch_ratio)
        if cues is None and (cues := score_prefers(lab, current, rendered, conf.checks_score_margin)) is None:
            continue
        current, chosen = rendered, r
        why = f"a {r.result.n_inliers}-inlier alternative fits the frame better where the two differ ({cues})"
    timings["refine"] = timings.get("refine", 0.0) + time.perf_counter() - t0
    return None if chosen is None else ((chosen.result, chosen.x, chosen.X), why)


def _distinct_hypotheses(objects: Objects, name: str, res, tried: list, camera: Camera) -> list:
    """Up to ``alternatives`` refined hypotheses worth comparing with the pose ``res``: scored at least
    ``alternatives_score`` of the best, with at least that fraction of its inliers, plausible, and more than
    5 degrees or 0.1 diameters from it and from each other; best score first."""
    conf = objects.conf
    diameter = objects.models[name].diameter_m

    def same(A, B):
        return rotation_error_deg(A[:3, :3], B[:3, :3]) <= 5.0 and np.linalg.norm(A[:3, 3] - B[:3, 3]) <= 0.1 * diameter

    top, least = max(r.score for r in tried), conf.alternatives_score
    picked: list[Refined] = []  # distinct poses, best score first
    for r in sorted(tried, key=lambda r: -r.score):
        T = r.result.cam_from_model
        if r.result.status != "ok" or r.score <= 0 or r.score < least * top:
            continue
        if r.result.n_inliers < least * res.n_inliers:
            continue  # a pose that many more pairs support is not second-guessed by a few
        if same(T, res.cam_from_model) or any(same(T, p.result.cam_from_model) for p in picked):
            continue
        if objects.implausible(name, T, camera):
            continue
        picked.append(r)
        if len(picked) == conf.alternatives:
            break
    return picked


def planar_mirror(
    objects: Objects, lab: LazyLab | None, name: str, res, x: np.ndarray, X: np.ndarray, camera: Camera, timings: dict
):
    """``planar_spread``: (the other pose of a planar inlier set as a result, a reason) when its mesh
    looks more like the frame (``lab``) than the pose's own; None to keep the pose. Its time counts as
    refinement."""
    conf = objects.conf
    if lab is None or not objects.can_render(name):  # None: neither check is on
        return None
    t0 = time.perf_counter()
    inl = res.inliers
    other = planar_alternative(x[inl], X[inl], res.cam_from_model, camera.K, camera.dist, conf.planar_spread)
    if other is None:
        return None
    T, r_inl = other
    own = max(res.median_residual_px, 0.5)
    if not np.median(r_inl) <= conf.planar_residual_ratio * own or objects.implausible(name, T, camera):
        return None
    current, mirrored = (objects.render(name, pose, camera) for pose in (res.cam_from_model, T))
    cues = frame_prefers(lab, current, mirrored, conf.planar_mismatch_ratio)
    if cues is None:
        cues = score_prefers(lab, current, mirrored, conf.checks_score_margin)
    timings["refine"] = timings.get("refine", 0.0) + time.perf_counter() - t0
    if cues is None:
        return None
    residuals = res.residuals_px.copy()
    residuals[inl] = r_inl
    why = f"the planar inliers' other pose (where the two differ: {cues})"
    return dataclasses.replace(res, cam_from_model=T, residuals_px=residuals), why


def frame_prefers(lab: LazyLab, current, other, ratio: float) -> str | None:
    """Compare the renders ``current`` and ``other`` (rgb, depth) with the frame where they differ: the two
    cues' figures ("texture match ..., edges ...") when ``other`` fits better by colour *and* by edges, each
    leaving at most 1 / ``ratio`` (``planar_mismatch_ratio``) of ``current``'s mismatch; None otherwise."""
    fits = distinct_matches(lab.get(), lab.gray, current, other)
    if fits is None or not all(1.0 - b <= (1.0 - a) / ratio for a, b in zip(*fits, strict=True)):
        return None
    (ca, ea), (cb, eb) = fits
    return f"texture match {cb:.2f} against {ca:.2f}, edges {eb:.2f} against {ea:.2f}"


def score_prefers(lab: LazyLab, current, other, margin: float) -> str | None:
    """The two renders' verification scores ("verification score ...") when ``other``'s, each over its whole
    silhouette, is higher than ``current``'s by at least ``margin`` (``checks_score_margin``); None otherwise
    (always with a margin of 1)."""
    if margin >= 1.0:
        return None
    a, b = (compare(lab.edges, rgb, depth, depth > 0) for rgb, depth in (current, other))
    if a is None or b is None or not b.score() >= a.score() + margin:
        return None
    return f"verification score {b.score():.2f} against {a.score():.2f}"


def polish(objects: Objects, name: str, gray: np.ndarray, T: np.ndarray, camera: Camera) -> np.ndarray:
    """``refine.polish``: align the pose ``T`` to the frame (``gray``) by the mesh rendered there,
    ``polish_rounds`` times: corners of the frame on the render's silhouette where the two look alike
    (:func:`batchpose.method.track.seed`) are found again in the render by patch correlation and the pose is
    solved on them (:func:`batchpose.method.track.anchor_to_render`). Returns the last pose found (``T`` when
    the first round finds too few corners)."""
    rf = objects.conf.refine
    tc = dataclasses.replace(objects.conf.track, render_search_px=rf.polish_search_px, min_fraction=0.0)
    for _ in range(rf.polish_rounds):
        rgb, depth = objects.render(name, T, camera)
        rendered = to_gray(rgb)
        xy, X = seed(gray, T, rendered, depth, camera.K, camera.dist, tc)
        if len(xy) < tc.min_points:
            break
        moved = anchor_to_render(gray, rendered, Track(xy, X, T, len(xy), 1.0), camera.K, camera.dist, tc)
        if moved is None:
            break
        T = moved.track.cam_from_model
    return T
