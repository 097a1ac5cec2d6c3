"""RANSAC-PnP initialisation, GNC-PnP with dual-filter inlier selection, final LM (SPEC §4). Pure."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from batchpose.config import GncConfig
from batchpose.core.geometry import rotation_error_deg


@dataclass
class PnpResult:
    """Outcome of :func:`solve_pose`.

    Attributes:
        status: "ok", "too_few_matches" or "pnp_failed"; reason says why when not ok.
        cam_from_model: (4, 4) model->camera, metres (None when failed).
        inliers: (N,) bool final inlier set.
        residuals_px: (N,) reprojection error of every correspondence at the final pose, pixels.
        timings: seconds per stage: ransac, gnc, lm.
        iterations: GNC iterations run.
    """

    status: str
    reason: str = ""
    cam_from_model: np.ndarray | None = None
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timings: dict[str, float] = field(default_factory=dict)
    iterations: int = 0

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def median_residual_px(self) -> float:
        return float(np.median(self.residuals_px[self.inliers])) if self.n_inliers else float("nan")

    def support(self, px: float = 0.0) -> int:
        """Pairs reprojected within ``px`` pixels (0: the inlier count); 0 when not ok."""
        if self.status != "ok":
            return 0
        return int((self.residuals_px < px).sum()) if px > 0 else self.n_inliers


def reprojection_errors(
    X: np.ndarray, x: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, dist: np.ndarray
) -> np.ndarray:
    """||project(K, R X + t) - x|| in pixels: X (N, 3) metres, x (N, 2) pixels -> (N,) float64."""
    if len(X) == 0:
        return np.zeros(0)
    proj, _ = cv2.projectPoints(X, rvec, tvec, K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - x, axis=1)


def planar_alternative(
    x: np.ndarray, X: np.ndarray, cam_from_model: np.ndarray, K: np.ndarray, dist: np.ndarray, spread: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The other pose a planar point set fits: (cam_from_model, residuals_px), or None.

    Points on one plane seen from afar (weak perspective) fit two poses, the plane tilted either way about
    the line of sight; IPPE returns both. None when the points are not planar (their smallest spread at
    least ``spread`` times the middle one), are fewer than 4, or the other pose is within 5 degrees of
    ``cam_from_model``.

    Args:
        x, X: (N, 2) pixels and (N, 3) model points (the pose's inliers).
    """
    if len(X) < 4 or spread <= 0:
        return None
    X, x = X.astype(np.float64), x.astype(np.float64)
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if not s[2] < spread * s[1]:
        return None
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, x, K, dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return None
    R0 = cam_from_model[:3, :3]
    best = None
    for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
        if not _valid_pose(tvec):
            continue
        turn = rotation_error_deg(R0, cv2.Rodrigues(rvec)[0])
        if turn > 5.0 and (best is None or turn > best[0]):
            best = (turn, rvec, tvec)
    if best is None:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(X, x, K, dist, best[1].copy(), best[2].copy())
    T = to_matrix(rvec, tvec)
    if not _valid_pose(tvec) or rotation_error_deg(R0, T[:3, :3]) <= 5.0:
        return None  # slid back to the pose itself
    return T, reprojection_errors(X, x, rvec, tvec, K, dist)


def to_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def _check(x: np.ndarray, X: np.ndarray, w_geom: np.ndarray) -> None:
    if x.ndim != 2 or x.shape[1] != 2:
        raise ValueError(f"image points must have shape (N, 2), got {x.shape}")
    if X.shape != (len(x), 3):
        raise ValueError(f"model points must have shape ({len(x)}, 3), got {X.shape}")
    if w_geom.shape != (len(x),):
        raise ValueError(f"geometry weights must have shape ({len(x)},), got {w_geom.shape}")


def _valid_pose(tvec: np.ndarray) -> bool:
    t = np.asarray(tvec).reshape(3)
    return bool(np.all(np.isfinite(t)) and t[2] > 0)


def solve_pose(
    x: np.ndarray,
    X: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray | None = None,
    w_geom: np.ndarray | None = None,
    conf: GncConfig = GncConfig(),
    seed: int = 0,
) -> PnpResult:
    """Estimate model->camera from 2D-3D pairs: RANSAC-PnP, then (if enabled) GNC-PnP, then LM.

    Args:
        x: (N, 2) image points, pixels. X: (N, 3) model points, metres. K: (3, 3).
        dist: OpenCV distortion coefficients (None or empty: none).
        w_geom: (N,) geometry-aware weights in [0, 1] (None: all 1).
        conf: thresholds and schedule; defaults are SPEC §4.
        seed: seeds OpenCV's RNG so RANSAC is reproducible.

    Returns:
        A :class:`PnpResult`; failures are results with a status, never exceptions.
    """
    x = np.ascontiguousarray(x, np.float64)
    X = np.ascontiguousarray(X, np.float64)
    n = len(x)
    w_geom = np.ones(n) if w_geom is None else np.asarray(w_geom, np.float64)
    _check(x, X, w_geom)
    K = np.asarray(K, np.float64)
    dist = np.zeros(0) if dist is None else np.asarray(dist, np.float64)
    timings = {"ransac": 0.0, "gnc": 0.0, "lm": 0.0}
    if n < max(conf.min_inliers, 4):
        return PnpResult("too_few_matches", f"{n} correspondences, need {max(conf.min_inliers, 4)}", timings=timings)

    start = _ransac(x, X, K, dist, conf, seed, timings)
    if isinstance(start, PnpResult):
        return start
    rvec, tvec, inliers, r = start
    iterations = 0
    if conf.enabled:
        t0 = time.perf_counter()
        rvec, tvec, inliers, iterations = gnc(x, X, K, dist, w_geom, rvec, tvec, inliers, r, conf)
        timings["gnc"] = time.perf_counter() - t0

    if conf.final_lm and inliers.sum() >= 4:
        t0 = time.perf_counter()
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], K, dist, rvec, tvec)
        timings["lm"] = time.perf_counter() - t0
    if not _valid_pose(tvec):
        return PnpResult("pnp_failed", "pose behind the camera after refinement", timings=timings)
    r = reprojection_errors(X, x, rvec, tvec, K, dist)
    return PnpResult("ok", "", to_matrix(rvec, tvec), inliers, r, timings, iterations)


def _ransac(x, X, K, dist, conf: GncConfig, seed: int, timings: dict[str, float]):
    """RANSAC-PnP (EPnP, seeded) polished by LM on its inliers: (rvec, tvec, inliers (N,) bool, residuals
    (N,) px), or a failed :class:`PnpResult`."""
    n = len(x)
    t0 = time.perf_counter()
    cv2.setRNGSeed(seed)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X,
            x,
            K,
            dist,
            iterationsCount=conf.ransac_iterations,
            reprojectionError=conf.ransac_reproj_px,
            confidence=conf.ransac_confidence,
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error as e:
        ok, msg = False, str(e).splitlines()[-1]
    else:
        msg = "no consensus"
    timings["ransac"] = time.perf_counter() - t0
    if not ok or inl is None or len(inl) < conf.min_inliers or not _valid_pose(tvec):
        n_inl = 0 if inl is None else len(inl)
        return PnpResult("pnp_failed", f"RANSAC-PnP failed ({msg}; {n_inl} inliers of {n})", timings=timings)
    inliers = np.zeros(n, bool)
    inliers[inl.reshape(-1)] = True
    # Polish the RANSAC pose on its inliers (EPnP in RANSAC is coarse).
    rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], K, dist, rvec, tvec)
    r = reprojection_errors(X, x, rvec, tvec, K, dist)
    return rvec, tvec, r < conf.ransac_reproj_px, r


def gnc(x, X, K, dist, w_geom, rvec, tvec, inliers, r, conf: GncConfig):
    """Graduated non-convexity from a RANSAC start (SPEC §4): Geman–McClure weights at a scale ``mu`` that
    shrinks by ``gamma`` each round; the pose is solved again on the pairs both filters keep (GNC weight
    above ``tau_gnc`` and geometry weight ``w_geom`` above ``tau_geom``) until the selection stops changing,
    fewer than ``min_inliers`` remain or ``mu`` reaches ``mu_final_px``.

    Returns:
        (rvec, tvec, inliers (N,) bool, iterations): the last pose solved and the pairs it was solved on.
    """
    iterations = 0
    rr = r**2 if conf.residual == "squared" else r
    base = rr if conf.mu0_from == "all" else rr[inliers]
    # No inliers left after the polish: NaN selects nothing and ends GNC at once (without numpy's warning).
    mu = conf.kappa * float(np.median(base)) + conf.epsilon if base.size else float("nan")
    prev: np.ndarray | None = None
    gnc_inliers = inliers
    while iterations < conf.max_iterations:
        w_gnc = mu**2 / (rr**2 + mu**2)
        sel = (w_gnc > conf.tau_gnc) & (w_geom > conf.tau_geom)
        if sel.sum() < conf.min_inliers:
            break
        if prev is not None and np.array_equal(sel, prev):
            break
        ok, rv, tv = cv2.solvePnP(
            X[sel],
            x[sel],
            K,
            dist,
            rvec.copy(),
            tvec.copy(),
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        iterations += 1
        if not ok or not _valid_pose(tv):
            break
        rvec, tvec, gnc_inliers, prev = rv, tv, sel, sel
        r = reprojection_errors(X, x, rvec, tvec, K, dist)
        rr = r**2 if conf.residual == "squared" else r
        if mu <= conf.mu_final_px:
            break
        mu = max(conf.gamma * mu, conf.mu_final_px)
    return rvec, tvec, gnc_inliers, iterations


def pose_spread(cam_from_model: np.ndarray, X: np.ndarray, K: np.ndarray, points: np.ndarray) -> float:
    """How loosely the pairs ``X`` (inliers' model points, (N, 3) metres) pin the pose ``cam_from_model``:
    the RMS displacement of the model ``points`` (metres) that 1-px noise on the pairs' image positions
    would cause, in metres (inf when the pairs leave some motion of the pose unconstrained).

    A least-squares pose's covariance under 1-px image noise is ``(J^T J)^-1``, J the Jacobian of the
    pairs' projections with respect to a small turn w (about the camera's axes) and shift s of the pose;
    a model point p moves by ``-[R p]x w + s``. Lens distortion is ignored (the Jacobian barely moves with
    it). Pairs that all lie along a line (a pen seen side-on) leave its distance and tilt trading off
    against each other: the spread is then a large share of the object's diameter."""
    R, t = cam_from_model[:3, :3], cam_from_model[:3, 3]
    Y = X @ R.T + t
    if len(Y) < 3 or np.any(Y[:, 2] <= 0):
        return float("inf")
    fx, fy, z = K[0, 0], K[1, 1], Y[:, 2]
    dpi = np.zeros((len(Y), 2, 3))  # d(u, v) / dY
    dpi[:, 0, 0], dpi[:, 0, 2] = fx / z, -fx * Y[:, 0] / z**2
    dpi[:, 1, 1], dpi[:, 1, 2] = fy / z, -fy * Y[:, 1] / z**2
    J = np.concatenate([dpi @ -_skew(X @ R.T), dpi], axis=2).reshape(-1, 6)
    w, V = np.linalg.eigh(J.T @ J)
    if w[0] <= 1e-9 * w[-1]:
        return float("inf")
    cov = (V / w) @ V.T
    A = np.concatenate([-_skew(points @ R.T), np.broadcast_to(np.eye(3), (len(points), 3, 3))], axis=2)
    return float(np.sqrt(np.einsum("nij,jk,nik->", A, cov, A) / len(points)))


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) vectors -> (N, 3, 3) cross-product matrices [v]x."""
    m = np.zeros((len(v), 3, 3))
    m[:, 0, 1], m[:, 0, 2], m[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    return m - m.transpose(0, 2, 1)
