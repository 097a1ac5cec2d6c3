"""Template viewpoints (SPEC §1): where the template cameras sit around the object. Pure functions."""

from __future__ import annotations

import numpy as np


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV camera at ``eye`` looking at ``target``.

    Args:
        eye, target, up: (3,) points / direction in the model frame, metres.

    Returns:
        (4, 4) cam_from_model (x right, y down, z forward).
    """
    z = target - eye
    z = z / np.linalg.norm(z)
    if abs(float(np.dot(z, up))) > 0.999 * np.linalg.norm(up):
        up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, -up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in model coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def fibonacci_directions(n: int, min_elevation_deg: float = -90.0) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (z up) above ``min_elevation_deg``."""
    z_min = np.sin(np.deg2rad(min_elevation_deg))
    i = np.arange(n) + 0.5
    z = 1.0 - i / n * (1.0 - z_min)
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sample_views(
    preset: str,
    center_m: np.ndarray,
    distances_m: tuple[float, ...],
    n_views: int = 160,
    min_elevation_deg: float = -90.0,
    azimuth_step_deg: float = 10.0,
    height_m: float = 1.0,
) -> list[dict]:
    """Template camera poses.

    Args:
        preset: "sphere" (Fibonacci over the view sphere, every distance) or "paper" (an azimuth ring over
            [-180, 180) at ``height_m`` above the centre, horizontal distance ``distances_m[0]``).
        center_m: (3,) point the cameras look at (the mesh's bounding-box centre), model frame.

    Returns:
        One dict per view: view_id, azimuth_deg, elevation_deg, distance_m, cam_from_model (4, 4).
    """
    center = np.asarray(center_m, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0])
    eyes: list[np.ndarray] = []
    if preset == "paper":
        d = distances_m[0]
        for az in np.arange(-180.0, 180.0, azimuth_step_deg):
            a = np.deg2rad(az)
            eyes.append(center + np.array([d * np.cos(a), d * np.sin(a), height_m]))
    elif preset == "sphere":
        dirs = fibonacci_directions(n_views, min_elevation_deg)
        for d in distances_m:
            eyes.extend(center + d * dirs)
    else:
        raise ValueError(f"unknown view preset {preset!r}")
    views = []
    for i, eye in enumerate(eyes):
        v = eye - center
        dist = float(np.linalg.norm(v))
        views.append(
            {
                "view_id": i,
                "azimuth_deg": float(np.degrees(np.arctan2(v[1], v[0]))),
                "elevation_deg": float(np.degrees(np.arcsin(np.clip(v[2] / dist, -1, 1)))),
                "distance_m": dist,
                "cam_from_model": look_at(eye, center, up),
            }
        )
    return views
