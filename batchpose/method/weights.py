"""Geometry-aware correspondence weights from voxel support (SPEC §3). Pure, vectorised."""

from __future__ import annotations

import numpy as np


def _check_points(X: np.ndarray) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {X.shape}")
    return X


def voxel_indices(X: np.ndarray, voxel_m: float) -> np.ndarray:
    """g_i = floor(X_i / v): (N, 3) metres -> (N, 3) int64 voxel indices."""
    return np.floor(_check_points(X) / voxel_m).astype(np.int64)


def support_to_weights(support: np.ndarray, w_min: float) -> np.ndarray:
    """w_i = w_min + (1 - w_min) * s_i / max_j s_j for support counts s (N,) -> (N,) float64."""
    s = np.asarray(support, dtype=np.float64)
    if s.size == 0:
        return s
    s_max = s.max()
    s_hat = s / s_max if s_max > 0 else np.zeros_like(s)
    return w_min + (1.0 - w_min) * s_hat


def correspondence_support(X: np.ndarray, voxel_m: float) -> np.ndarray:
    """s_i = number of this set's points in X_i's voxel. (N, 3) -> (N,) int64."""
    g = voxel_indices(X, voxel_m)
    if len(g) == 0:
        return np.zeros(0, np.int64)
    _, inverse, counts = np.unique(g, axis=0, return_inverse=True, return_counts=True)
    return counts[inverse.reshape(-1)]


def geom_weights(X: np.ndarray, voxel_m: float = 0.005, w_min: float = 0.2) -> np.ndarray:
    """Geometry-aware weights over the correspondences' own 3D points (``mode: correspondences``).

    Args:
        X: (N, 3) model-frame points, metres.

    Returns:
        (N,) float64 weights in [w_min, 1].
    """
    return support_to_weights(correspondence_support(X, voxel_m), w_min)


def model_voxel_grid(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel support of all template keypoints of a library (``mode: model``), computed once per object.

    Returns:
        keys (M, 3) int64 occupied voxel indices (lexicographically sorted) and counts (M,) int64.
    """
    g = voxel_indices(points, voxel_m)
    if len(g) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    keys, counts = np.unique(g, axis=0, return_counts=True)
    return keys, counts


def _pack(g: np.ndarray) -> np.ndarray:
    """Voxel indices (N, 3) -> (N,) int64 scalar keys that preserve equality (|index| < 2**20)."""
    off = g + (1 << 20)
    return (off[:, 0] << 42) | (off[:, 1] << 21) | off[:, 2]


def model_support(X: np.ndarray, keys: np.ndarray, counts: np.ndarray, voxel_m: float) -> np.ndarray:
    """Look up each point's voxel in a model grid: (N, 3) -> (N,) int64 support (0 if unseen)."""
    g = voxel_indices(X, voxel_m)
    if len(keys) == 0 or len(g) == 0:
        return np.zeros(len(g), np.int64)
    packed_keys = _pack(keys)
    order = np.argsort(packed_keys)
    sorted_keys = packed_keys[order]
    q = _pack(g)
    pos = np.clip(np.searchsorted(sorted_keys, q), 0, len(sorted_keys) - 1)
    hit = sorted_keys[pos] == q
    return np.where(hit, counts[order][pos], 0)
