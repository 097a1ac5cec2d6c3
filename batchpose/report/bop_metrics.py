"""BOP 2019 pose errors and their average recalls: MSSD, MSPD, VSD, AR (pure functions, arrays in and out).

The definitions are those of the BOP challenge 2019/2020 (Hodaň et al., "BOP Challenge 2020 on 6D Object
Localization", ECCVW 2020; the bop_toolkit's ``pose_error.py`` and ``visibility.py``):

- MSSD: the smallest, over the object's symmetry transforms S, of the largest distance between a model
  point at the estimated pose and the same point at the true pose composed with S (metres);
- MSPD: the same distance measured in the image after projection with K (pixels);
- VSD: how much the visible surfaces of the object at the two poses differ, from distance maps of the model
  rendered at each pose and the frame's depth image (a fraction in [0, 1], one per tolerance tau).

A pose is correct under MSSD at threshold th when its error is strictly below th x the object diameter
(th = 0.05 .. 0.5), under MSPD when below th x (image width / 640) pixels (th = 5 .. 50), under VSD when
the error at tau (tau = 0.05 .. 0.5 x diameter) is below theta (BOP 2019: 0.05 .. 0.5). An instance's AR
under one error is the share of those thresholds it passes; an object's or a data set's AR is the mean of
its instances' (recall is linear in the instances, so this equals the BOP mean of per-threshold recalls).
AR is the mean of the available ARs. A missed pose has error +inf (a failure at every threshold).

Symmetries (:data:`SYMMETRIES`) are in the YCB-Video model frame of our meshes (metres), not in the frame
of BOP's millimetre models; ``tests/test_bop_metrics.py`` checks each one against the mesh.
"""

from __future__ import annotations

import cv2
import numpy as np

from batchpose.core.geometry import check_rotation

#: MSSD thresholds as fractions of the object diameter (BOP 2019: 0.05 .. 0.5, step 0.05).
MSSD_FRACTIONS = np.round(np.arange(1, 11) * 0.05, 2)
#: MSPD thresholds in pixels of a 640-pixel-wide image (BOP 2019: 5 .. 50, step 5), scaled by width / 640.
MSPD_PX_640 = np.arange(1, 11) * 5.0
#: VSD misalignment tolerances tau as fractions of the object diameter (BOP 2019: 0.05 .. 0.5).
VSD_TAU_FRACTIONS = MSSD_FRACTIONS
#: VSD correctness thresholds theta (BOP 2019: 0.05 .. 0.5, step 0.05; SIXD 2017 / BOP 2018 used 0.3 alone).
VSD_THETAS = MSSD_FRACTIONS
#: VSD visibility tolerance delta, metres (BOP: 15 mm).
VSD_DELTA_M = 0.015
#: Steps a continuous symmetry is discretised into (BOP uses 1 degree; 10 degrees moves a point of a
#: 0.25 m object by at most 2 cm, which the 0.05 d threshold of MSSD barely notices).
CONTINUOUS_STEPS = 36

#: Symmetries of YCB-Video objects, keyed by class name: ``continuous`` axes (unit axis, point on it,
#: metres) and ``discrete`` 4x4 model-frame transforms. From BOP's ycbv ``models_info.json``, which marks
#: 002_master_chef_can and 040_large_marker as continuously symmetric about their long axis and none of the
#: other objects with a textured mesh in YCB-Video (its discrete symmetries are for 036_wood_block,
#: 051/052 clamps and 061_foam_brick, which have none here). The axes are those of our YCB-Video meshes,
#: found on the meshes and checked against them by the tests: the can's axis is z, the marker's y.
SYMMETRIES: dict[str, dict[str, list]] = {
    "002_master_chef_can": {"continuous": [((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))], "discrete": []},
    "040_large_marker": {"continuous": [((0.0, 1.0, 0.0), (0.0, 0.0, 0.0))], "discrete": []},
}


def symmetry_transforms(obj_name: str, steps: int = CONTINUOUS_STEPS, table=None) -> np.ndarray:
    """The model-frame transforms that map an object onto itself, identity first.

    Each continuous symmetry is discretised into ``steps`` rotations about its axis; every discrete one
    is combined with every continuous step (as the bop_toolkit's ``get_symmetry_transformations`` does).

    Args:
        obj_name: YCB-Video class name; an object without an entry has the identity only.
        steps: rotations per continuous symmetry (>= 1).
        table: symmetry table (default :data:`SYMMETRIES`).

    Returns:
        (S, 4, 4) float64 transforms, model frame, metres; ``[0]`` is the identity.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    entry = (SYMMETRIES if table is None else table).get(obj_name, {})
    discrete = [np.eye(4)] + [np.asarray(T, dtype=np.float64).reshape(4, 4) for T in entry.get("discrete", [])]
    continuous = [np.eye(4)]
    for axis, offset in entry.get("continuous", []):
        a = np.asarray(axis, dtype=np.float64)
        a = a / np.linalg.norm(a)
        o = np.asarray(offset, dtype=np.float64)
        for i in range(1, steps):
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(a * (2.0 * np.pi * i / steps))[0]
            T[:3, 3] = o - T[:3, :3] @ o  # a rotation about the axis through the offset point
            continuous.append(T)
    return np.stack([c @ d for d in discrete for c in continuous])


def _check(R, t, name: str) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=np.float64)
    if t.shape not in ((3,), (3, 1)):
        raise ValueError(f"t_{name} must have shape (3,) or (3, 1), got {t.shape}")
    return check_rotation(R, f"R_{name}"), t.reshape(3)


def _gt_variants(R_gt, t_gt, syms: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(S, N, 3) model points at the true pose composed with each symmetry (camera frame, metres)."""
    syms = np.asarray(syms, dtype=np.float64)
    if syms.ndim != 3 or syms.shape[1:] != (4, 4) or len(syms) == 0:
        raise ValueError(f"syms must have shape (S, 4, 4) with S > 0, got {syms.shape}")
    R = R_gt @ syms[:, :3, :3]  # (S, 3, 3)
    t = syms[:, :3, 3] @ R_gt.T + t_gt  # (S, 3)
    return np.einsum("sij,nj->sni", R, pts) + t[:, None, :]


def _points(pts) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"pts must have shape (N, 3) with N > 0, got {pts.shape}")
    return pts


def mssd(R_est, t_est, R_gt, t_gt, pts, syms) -> float:
    """Maximum Symmetry-aware Surface Distance.

    Args:
        R_est, t_est: (3, 3) rotation and (3,) translation (metres) of the estimate, model -> camera.
        R_gt, t_gt: the same for the ground truth.
        pts: (N, 3) model points (vertices), metres, model frame.
        syms: (S, 4, 4) symmetry transforms (:func:`symmetry_transforms`).

    Returns:
        min over S of max over points of ``||T_est x - T_gt S x||``, metres.
    """
    pts = _points(pts)
    R_e, t_e = _check(R_est, t_est, "est")
    R_g, t_g = _check(R_gt, t_gt, "gt")
    est = pts @ R_e.T + t_e
    gt = _gt_variants(R_g, t_g, syms, pts)
    return float(np.linalg.norm(gt - est[None], axis=2).max(axis=1).min())


def _project(K: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    """(..., 2) pixels of (..., 3) camera-frame points (OpenCV K, pixel centres at integers)."""
    uvw = pts_cam @ K.T
    return uvw[..., :2] / uvw[..., 2:3]


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) -> float:
    """Maximum Symmetry-aware Projection Distance.

    Args:
        R_est, t_est, R_gt, t_gt, pts, syms: as for :func:`mssd`.
        K: (3, 3) camera intrinsics of the frame, pixels.

    Returns:
        min over S of max over points of the distance between the projections of ``T_est x`` and
        ``T_gt S x``, pixels.
    """
    pts = _points(pts)
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K.shape}")
    R_e, t_e = _check(R_est, t_est, "est")
    R_g, t_g = _check(R_gt, t_gt, "gt")
    est = _project(K, pts @ R_e.T + t_e)
    gt = _project(K, _gt_variants(R_g, t_g, syms, pts))
    return float(np.linalg.norm(gt - est[None], axis=2).max(axis=1).min())


def distance_map(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) distance from the camera centre to the surface seen at each pixel, metres, from a z-depth
    image (H, W, metres, 0 = no reading): ``d = z * ||K^-1 [u v 1]||``."""
    depth_m = np.asarray(depth_m, dtype=np.float64)
    if depth_m.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth_m.shape}")
    K = np.asarray(K, dtype=np.float64)
    h, w = depth_m.shape
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    y = (np.arange(h) - K[1, 2]) / K[1, 1]
    return depth_m * np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)


def vsd(
    depth_est: np.ndarray,
    depth_gt: np.ndarray,
    depth_test: np.ndarray,
    K: np.ndarray,
    diameter_m: float,
    delta_m: float = VSD_DELTA_M,
    tau_fractions: np.ndarray = VSD_TAU_FRACTIONS,
) -> np.ndarray:
    """Visible Surface Discrepancy (BOP 2019: step cost, visibility of missing depth as visible).

    Args:
        depth_est: (H, W) z-depth of the model rendered at the estimated pose, metres, 0 off the object.
        depth_gt: (H, W) the same at the true pose.
        depth_test: (H, W) the frame's depth image, metres, 0 where the sensor has no reading.
        K: (3, 3) intrinsics of the three images.
        diameter_m: object diameter, metres (the tolerances are fractions of it).
        delta_m: visibility tolerance, metres.
        tau_fractions: (T,) misalignment tolerances, fractions of the diameter.

    Returns:
        (T,) errors in [0, 1], one per tau (1 when neither pose shows any visible surface).
    """
    shapes = {np.shape(depth_est), np.shape(depth_gt), np.shape(depth_test)}
    if len(shapes) != 1:
        raise ValueError(f"depth_est, depth_gt and depth_test must have one shape, got {sorted(shapes)}")
    d_test = distance_map(depth_test, K)
    d_gt = distance_map(depth_gt, K)
    d_est = distance_map(depth_est, K)
    # BOP 2019 visibility: a model pixel is visible where it is not behind the scene by more than delta, or
    # where the sensor has no reading (shiny objects); the estimate's mask also takes the truth's visible part.
    unknown = d_test == 0
    visib_gt = (d_gt > 0) & ((d_gt - d_test <= delta_m) | unknown)
    visib_est = ((d_est > 0) & ((d_est - d_test <= delta_m) | unknown)) | (visib_gt & (d_est > 0))
    inter = visib_gt & visib_est
    n_union = int((visib_gt | visib_est).sum())
    taus = np.asarray(tau_fractions, dtype=np.float64) * float(diameter_m)
    if n_union == 0:
        return np.ones(taus.shape)
    dists = np.abs(d_gt[inter] - d_est[inter])
    n_outside = n_union - int(inter.sum())
    costs = (dists[None, :] >= taus[:, None]).sum(axis=1)
    return (costs + n_outside) / n_union


def ar_mssd(error_m: float, diameter_m: float) -> float:
    """An instance's MSSD recall: the share of :data:`MSSD_FRACTIONS` x diameter its error is below (inf or
    NaN error: 0)."""
    e = np.nan_to_num(float(error_m), nan=np.inf)
    return float(np.mean(e < MSSD_FRACTIONS * float(diameter_m)))


def ar_mspd(error_px: float, width_px: int) -> float:
    """An instance's MSPD recall: the share of :data:`MSPD_PX_640` x (width / 640) its error is below."""
    e = np.nan_to_num(float(error_px), nan=np.inf)
    return float(np.mean(e < MSPD_PX_640 * (float(width_px) / 640.0)))


def ar_vsd(errors: np.ndarray | None, thetas: np.ndarray = VSD_THETAS) -> float:
    """An instance's VSD recall: the share of (tau, theta) pairs with error(tau) < theta; ``None`` (a missed
    pose): 0."""
    if errors is None:
        return 0.0
    e = np.asarray(errors, dtype=np.float64)
    return float(np.mean(e[:, None] < np.asarray(thetas, dtype=np.float64)[None, :]))
