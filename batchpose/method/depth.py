"""Align an RGB pose to a registered depth image (``depth.enabled``; batchpose's addition to GNC-Pose).

A monocular pose is weakest along the viewing ray: the object's image size fixes only the ratio of its size
to its distance, and on real YCB-Video frames our RGB poses sit 1-4 % too far (reports/ACCURACY.md). Where
the log has a depth image registered to the colour image, each pose the RGB estimator finds is

0. moved along its viewing ray (``ray_align``, :func:`along_ray`): the translation scaled, which keeps the
   object's projection, so that the rendered surface meets the sensor's readings on the silhouette. A pose
   2-5 cm too far at ~1 m (typical of real frames) is beyond the ICP's first gate, and judged where it was
   the sensor would see nothing of it: steps 1 and 2 take the moved pose;
1. checked: the mesh is rendered at the pose; where the sensor sees *past* the rendered surface on most of
   the silhouette, the pose puts the object where there is none (readings nearer than the surface are
   occluders and do not count); where almost no reading is near the rendered surface, the object is seen
   nowhere there (e.g. a pose far behind the things in front of it);
2. aligned: sensor points on and around the silhouette are registered to points sampled on the mesh by
   robust point-to-plane ICP (Huber weights, a 3D distance gate narrowing from ``gate_m`` to
   ``gate_final_m``, Levenberg damping so that what the depth cannot see, such as a can's turn about its
   axis, stays as the RGB estimate had it), and checked again at the aligned pose. Two renders per pose,
   three where the ray alignment moved it.

Sensor points are back-projected with K alone (no distortion model), as the renderer draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from batchpose.config import DepthConfig

#: Surface points sampled per mesh for the alignment.
SURFACE_POINTS = 4000
#: Readings needed on a silhouette to judge the pose (fewer than ``DepthConfig.min_pixels`` to align it).
MIN_CHECK_PIXELS = 10
#: Step of the ray alignment's search over depth offsets (metres).
RAY_STEP_M = 0.002
#: The ray alignment moves a pose only where that puts at least this many times as many readings on its
#: surface: a pose whose readings spread along the ray (off sideways, or turned) is left to the ICP, which
#: fits all six degrees of freedom, rather than moved on a slight majority.
RAY_GAIN = 2.0
#: A pose the ray alignment moved is kept only where at least this fraction of the readings just outside
#: its silhouette lie ``gate_m`` beyond the surface next to them (the object stands out against what is
#: behind it: true poses on ycbv_dev's real frames 0.19-0.8, the gelatin box lying on the table the least;
#: a box moved onto a plain wall 0.0-0.07); else it is judged where it was.
RAY_MIN_EDGE = 0.1


@dataclass(frozen=True)
class Surface:
    """Points sampled evenly on a mesh (model frame, metres), their face normals and a k-d tree over them."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree

    @classmethod
    def of(cls, mesh: trimesh.Trimesh, n: int = SURFACE_POINTS, seed: int = 0) -> Surface:
        points, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        points = np.asarray(points, dtype=np.float64)
        return cls(points, np.asarray(mesh.face_normals[face], dtype=np.float64), cKDTree(points))


@dataclass
class DepthFit:
    """The outcome for one pose.

    Attributes:
        cam_from_model: the aligned pose: the ICP's, else the input pose moved along its viewing ray (the
            input pose when neither moved it).
        aligned: the ICP alignment was made and kept.
        ray_m: how far the object's centre was moved along its viewing ray, metres (positive: farther).
        contradicted: the depth shows the pose is wrong (see :func:`align_to_depth`).
        see_through: fraction of the silhouette's pixels with a reading where the sensor sees past the surface.
        agree: fraction of them whose reading is within a quarter of the diameter of the rendered surface.
        reason: why the pose was not aligned or is contradicted ("" otherwise).
    """

    cam_from_model: np.ndarray
    aligned: bool = False
    ray_m: float = 0.0
    contradicted: bool = False
    see_through: float = 0.0
    agree: float = 0.0
    reason: str = ""


def _back_project(xs: np.ndarray, ys: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.stack([(xs - K[0, 2]) * z / K[0, 0], (ys - K[1, 2]) * z / K[1, 1], z], axis=1)


def _agreement(depth_m: np.ndarray, rendered_m: np.ndarray, diameter_m: float, conf: DepthConfig):
    """(see_through, agree, reason): how the sensor's readings on the silhouette sit against the rendered
    surface, and why that contradicts the pose ("" when it does not)."""
    seen = (rendered_m > 0) & (depth_m > 0)
    gap = depth_m[seen] - rendered_m[seen]
    band = max(conf.gate_m, 0.25 * diameter_m)
    see_through = float(np.mean(gap > conf.gate_m)) if gap.size else 0.0
    agree = float(np.mean(np.abs(gap) < band)) if gap.size else 0.0
    if see_through > conf.max_see_through:
        return (
            see_through,
            agree,
            (
                f"the depth image contradicts the pose: on {100 * see_through:.0f}% of the object's pixels the "
                f"sensor sees more than {100 * conf.gate_m:.0f} cm past it"
            ),
        )
    if agree < conf.min_agree:
        return (
            see_through,
            agree,
            (
                f"the depth image contradicts the pose: only {100 * agree:.0f}% of the object's pixels have a "
                f"reading within {100 * band:.0f} cm of its surface"
            ),
        )
    return see_through, agree, ""


def along_ray(gap_m: np.ndarray, lo_m: float, hi_m: float, conf: DepthConfig) -> tuple[float, int]:
    """The depth offset that best puts a rendered surface onto the sensor's readings: a robust 1-D fit.

    Every offset ``d`` from ``lo_m`` to ``hi_m`` (steps of ``RAY_STEP_M``) is scored by the silhouette's
    readings: +1 for each within ``conf.gate_final_m`` of the surface moved by ``d``, -1 for each more than
    ``conf.gate_m`` past it (the sensor would see through the object there) but within reach (up to
    ``hi_m``: a far background counts against no offset); nearer readings are occluders and count neither
    way. So a half-hidden object is placed by its visible half unless the occluder covers over twice as
    much of it. The best offset (ties to the smallest move) is refined to the median gap of the readings
    within the band, and used only where it has ``RAY_GAIN`` times as many of them as offset 0 (a pose off
    sideways, whose readings spread along the ray, is left to the ICP).

    Args:
        gap_m: (N,) sensor minus rendered depth on the silhouette's pixels with a reading, metres.
        lo_m, hi_m: the offsets allowed, metres (lo_m <= 0 <= hi_m).

    Returns:
        (offset in metres, readings within the band at it); (0.0, readings at 0) where no offset scores
        better than 0 with ``MIN_CHECK_PIXELS`` readings and ``RAY_GAIN`` times as many as offset 0, or where
        the best lies within the band of either end of the range (a pose whose readings go on past the
        range, like a mustard bottle placed 17 % too far on a real ycbv_dev frame, is judged where it is).
    """
    band, past = conf.gate_final_m, conf.gate_m
    g = np.sort(gap_m)
    d = np.concatenate([[0.0], np.arange(lo_m, hi_m + 0.5 * RAY_STEP_M, RAY_STEP_M)])
    inside = np.searchsorted(g, d + band) - np.searchsorted(g, d - band)
    seen_through = np.maximum(np.searchsorted(g, hi_m + band) - np.searchsorted(g, d + past, side="right"), 0)
    score = inside - seen_through
    best = int(np.argmax(score - 1e-3 * np.abs(d)))  # ties: the smallest move
    if inside[best] < MIN_CHECK_PIXELS or inside[best] < RAY_GAIN * inside[0] or score[best] <= score[0]:
        return 0.0, int(inside[0])
    offset = float(d[best])
    for _ in range(2):  # centre the offset on its readings (a flat face counts the same over 2 * band)
        near = g[np.abs(g - offset) < band]
        if near.size:
            offset = float(np.clip(np.median(near), lo_m, hi_m))
    if offset - lo_m < band or hi_m - offset < band:
        return 0.0, int(inside[0])  # the readings go on past the range: where they end is not known
    return offset, int(np.sum(np.abs(g - offset) < band))


def _ray_align(T: np.ndarray, depth_m: np.ndarray, rendered: np.ndarray, render_depth, surface: Surface, conf):
    """(pose, metres moved, its render): ``T`` moved along the ray through the object's centre by
    :func:`along_ray`, within ``conf.ray_range`` of its distance; ``T`` itself where that does not move it or
    the moved object would not stand out (:func:`_stands_out`). One render more for a moved pose."""
    centre = T[:3, :3] @ surface.points.mean(axis=0) + T[:3, 3]
    z = float(centre[2])
    seen = (rendered > 0) & (depth_m > 0)
    if z <= 0 or seen.sum() < MIN_CHECK_PIXELS:
        return T, 0.0, rendered
    gap = (depth_m[seen] - rendered[seen]).astype(np.float64)
    offset, _ = along_ray(gap, -conf.ray_range * z, conf.ray_range * z, conf)
    if offset == 0.0:
        return T, 0.0, rendered
    out = T.copy()
    out[:3, 3] += offset / z * centre  # every surface point's depth moves by the offset; the centre's pixel stays
    moved = render_depth(out)
    if _stands_out(depth_m, moved, conf.gate_m) < RAY_MIN_EDGE:
        return T, 0.0, rendered  # flush with what is around it: a pose on a wall or a table top, not an object
    return out, offset / z * float(np.linalg.norm(centre)), moved


def _stands_out(depth_m: np.ndarray, rendered: np.ndarray, margin_m: float) -> float:
    """Fraction of the readings just outside the silhouette more than ``margin_m`` beyond the farthest
    rendered surface next to them: an object seen against its surroundings has something behind part of
    its outline; a pose laid onto a wall or a table top has not."""
    sil = rendered > 0
    grow = int(np.ceil(0.03 * np.sqrt(sil.sum()))) + 2
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1,) * 2)
    ring = (cv2.dilate(sil.astype(np.uint8), kernel) > 0) & ~sil & (depth_m > 0)
    if not ring.any():
        return 1.0  # nothing around it to be flush with
    far = cv2.dilate(rendered.astype(np.float32), kernel)[ring]  # the farthest surface nearby
    return float(np.mean(depth_m[ring] > far + margin_m))


def align_to_depth(
    T: np.ndarray,
    depth_m: np.ndarray,
    render_depth,
    K: np.ndarray,
    surface: Surface,
    diameter_m: float,
    conf: DepthConfig,
) -> DepthFit:
    """Align pose ``T`` to the sensor depth and check the result (see the module docstring).

    With ``conf.ray_align`` the pose is first moved along its viewing ray (:func:`along_ray`); the ICP starts
    there. The check is made at the ICP's pose when the alignment succeeds (a pose a few pixels off, which the
    sensor partly sees past, is aligned first), else at the ray-aligned pose (``T`` without ``ray_align``).

    Args:
        T: (4, 4) model->camera pose from the RGB estimate.
        depth_m: (H, W) sensor depth in metres, 0 where there is no reading.
        render_depth: callable(pose) -> (H, W) the mesh's depth rendered in the same camera, 0 off it.
        K: (3, 3) intrinsics of both images.
        surface: the mesh's :class:`Surface`.
        diameter_m: the object's diameter (limits how far an alignment may move it).
    """
    fit = DepthFit(np.asarray(T, dtype=np.float64).copy())
    rendered = render_depth(fit.cam_from_model)
    if conf.ray_align:
        fit.cam_from_model, fit.ray_m, rendered = _ray_align(
            fit.cam_from_model, depth_m, rendered, render_depth, surface, conf
        )
    n_seen = int(((rendered > 0) & (depth_m > 0)).sum())
    if n_seen < conf.min_pixels:
        # Too few to align to; enough to see that a tiny, far-away pose is behind everything in the frame.
        if n_seen >= MIN_CHECK_PIXELS:
            fit.see_through, fit.agree, contradiction = _agreement(depth_m, rendered, diameter_m, conf)
            if contradiction:
                fit.contradicted, fit.reason = True, contradiction
                return fit
        fit.reason = f"{n_seen} of the object's pixels have a depth reading, need {conf.min_pixels}"
        return fit
    T_new, why = _icp(fit.cam_from_model, depth_m, rendered > 0, K, surface, diameter_m, conf)
    if T_new is not None:
        rendered = render_depth(T_new)
    fit.see_through, fit.agree, contradiction = _agreement(depth_m, rendered, diameter_m, conf)
    if contradiction:
        fit.contradicted, fit.reason = True, contradiction
    elif T_new is None:
        fit.reason = why
    else:
        fit.cam_from_model, fit.aligned = T_new, True
    return fit


def _icp(T0: np.ndarray, depth_m: np.ndarray, sil: np.ndarray, K, surface: Surface, diameter_m: float, conf):
    """(aligned pose, "") or (None, why not): robust point-to-plane ICP of the readings around ``sil``."""
    # Candidate pixels: the silhouette grown by a few pixels (the RGB pose may be off by that much).
    grow = int(np.ceil(0.03 * np.sqrt(sil.sum()))) + 2
    near = cv2.dilate(sil.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1,) * 2)) > 0
    ys, xs = np.nonzero(near & (depth_m > 0))
    if len(xs) > conf.max_points:
        keep = np.linspace(0, len(xs) - 1, conf.max_points).astype(int)
        ys, xs = ys[keep], xs[keep]
    P = _back_project(xs.astype(np.float64), ys.astype(np.float64), depth_m[ys, xs].astype(np.float64), K)
    T_new = T0.copy()
    for it in range(conf.iterations):
        gate = conf.gate_m + (conf.gate_final_m - conf.gate_m) * it / max(conf.iterations - 1, 1)
        R, t = T_new[:3, :3], T_new[:3, 3]
        q = (P - t) @ R  # sensor points in the model frame
        dist, idx = surface.tree.query(q, distance_upper_bound=gate)
        use = np.isfinite(dist)
        if use.sum() < conf.min_pixels:
            return None, f"{int(use.sum())} depth pixels within {100 * gate:.1f} cm of the mesh, need {conf.min_pixels}"
        q, idx = q[use], idx[use]
        n = surface.normals[idx]
        r = np.einsum("ij,ij->i", q - surface.points[idx], n)
        J = np.hstack([np.cross(q, n), n])  # d r / d (rotation, translation) of the model-frame points
        scale = 1.4826 * np.median(np.abs(r)) + 1e-4
        w = 1.0 / np.maximum(1.0, np.abs(r) / (1.5 * scale))  # Huber
        A = (J * w[:, None]).T @ J
        A += conf.damping * np.trace(A) / 6.0 * np.eye(6)
        step = -np.linalg.solve(A, (J * w[:, None]).T @ r)
        D = np.eye(4)
        D[:3, :3] = cv2.Rodrigues(step[:3])[0]
        D[:3, 3] = step[3:]
        T_new = T_new @ np.linalg.inv(D)  # the points move by D in the model frame: the model by D^-1
        if np.linalg.norm(step[3:]) < 1e-5 and np.linalg.norm(step[:3]) < 1e-5:
            break
    c = surface.points.mean(axis=0)  # the object's centre moves by this much
    moved = np.linalg.norm((T_new[:3, :3] - T0[:3, :3]) @ c + T_new[:3, 3] - T0[:3, 3])
    turned = np.degrees(np.linalg.norm(cv2.Rodrigues(T_new[:3, :3] @ T0[:3, :3].T)[0]))
    if moved > conf.max_shift * diameter_m or turned > conf.max_turn_deg:
        return None, (
            f"the alignment to the depth moved the object {100 * moved:.1f} cm and turned it {turned:.0f} deg "
            f"(limits {100 * conf.max_shift * diameter_m:.1f} cm, {conf.max_turn_deg:.0f} deg): not used"
        )
    return T_new, ""
