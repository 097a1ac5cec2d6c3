"""The surface the found objects rest on (``plane.*``), and how an object rests on it: what
:mod:`batchpose.method.plane`'s search stands an object SIFT missed on.

1. **support plane** (:func:`support_plane`): every found object's convex-hull faces propose a plane normal;
   along each, the most objects that rest on it with one of the faces they can stand on, their lowest points
   within ``max_spread_m`` of one another, with the camera above it (two objects reach down equally to many
   planes, most of them touching a corner or an edge); the normal with the largest group, the least spread
   among equals, is the surface. With one found object (:func:`one_object_plane`), its resting face nearest
   the image's up direction, if that is clear;
2. **resting poses** (:func:`resting_faces`, :func:`resting`): the object's stable poses on a plane
   (:meth:`trimesh.Trimesh.compute_stable_poses`, those with probability at least ``min_stable``), each turned
   about the plane's normal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from batchpose.config import PlaneConfig

if TYPE_CHECKING:
    import trimesh

#: A support plane must be one each found object rests on with a stable face turned at most this far from it.
STABLE_DEG = 10.0
#: One object's surface (:func:`one_object_plane`) is the resting face nearest the image's up direction only
#: when every other is at least this much farther (degrees; resting faces are merged within 15).
MARGIN_DEG = 15.0


@dataclass(frozen=True)
class Plane:
    """A support plane in camera coordinates: ``normal . x == offset`` on it, ``normal`` pointing to the side
    the objects (and the camera) are on."""

    normal: np.ndarray
    offset: float
    spread_m: float  # how far apart the found objects' lowest points are along the normal
    objects: tuple[str, ...]


def support_plane(
    found: dict[str, tuple[np.ndarray, trimesh.Trimesh]],
    conf: PlaneConfig,
    stable: dict[str, np.ndarray] | None = None,
) -> Plane | None:
    """The plane the most found objects rest on (at least ``min_objects``; with ``plane.all_objects``, all of
    them), or None when no such group rests on one.

    Args:
        found: name -> (cam_from_model, hull) for each confidently found object, ``hull`` a
            trimesh convex hull of its mesh (model frame).
        stable: name -> (K, 3) the model-frame outward normals of the faces the object can rest on
            (:func:`stable_faces`' first): a plane is one each object rests on with one of them (within
            STABLE_DEG) — two objects reach down equally to many planes, most of them touching a corner
            or an edge.

    Each found object's largest hull faces, turned downwards, propose a normal; along each, the group is the
    most objects that rest on it whose lowest points are within ``max_spread_m`` of one another, with the
    camera above them. The normal with the largest group wins, the least spread among equals. One object
    standing on another, or a pose off in distance, leaves the others' surface to them.
    """
    if len(found) < conf.min_objects:
        return None
    names = list(found)
    down_faces = []
    for T, hull in found.values():
        biggest = np.argsort(-hull.area_faces)[: conf.plane_candidates]
        down_faces.append(-(hull.face_normals[biggest] @ T[:3, :3].T))  # a resting face points down
    normals = np.concatenate(down_faces)
    lows = np.stack([((h.vertices @ T[:3, :3].T + T[:3, 3]) @ normals.T).min(axis=0) for T, h in found.values()])
    rests = np.ones(lows.shape, bool)  # (objects, candidates)
    for i, name in enumerate(names):
        if stable is not None and name in stable:
            down = stable[name] @ found[name][0][:3, :3].T  # the faces' normals in the camera; one points down
            rests[i] = (down @ -normals.T).max(axis=0) >= np.cos(np.deg2rad(STABLE_DEG))
    least = len(found) if conf.all_objects else conf.min_objects
    best: tuple[int, float, int, np.ndarray] | None = None
    for c in range(len(normals)):
        group, spread = _lowest_group(lows[:, c], rests[:, c], conf.max_spread_m)
        if len(group) < least or lows[group, c].mean() >= 0:  # the camera (the origin) must be above it
            continue
        if best is None or (len(group), -spread) > (best[0], -best[1]):
            best = (len(group), spread, c, group)
    if best is None:
        return None
    _, spread, c, group = best
    return Plane(normals[c], float(lows[group, c].mean()), float(spread), tuple(names[i] for i in group))


def _lowest_group(lows: np.ndarray, rests: np.ndarray, max_spread: float) -> tuple[np.ndarray, float]:
    """Of the objects that ``rests``, the most whose ``lows`` are within ``max_spread`` of one another, the
    least spread among equals: (their indices, ascending, and their spread)."""
    idx = np.flatnonzero(rests)
    if not len(idx):
        return idx, 0.0
    order = idx[np.argsort(lows[idx])]
    values = lows[order]
    best = (1, 0.0, 0, 1)
    for i in range(len(order)):
        j = int(np.searchsorted(values, values[i] + max_spread, side="right"))
        size, spread = j - i, float(values[j - 1] - values[i])
        if (size, -spread) > (best[0], -best[1]):
            best = (size, spread, i, j)
    return np.sort(order[best[2] : best[3]]), best[1]


def one_object_plane(name: str, T: np.ndarray, hull: trimesh.Trimesh, faces: list[np.ndarray], conf: PlaneConfig):
    """The plane one found object rests on (``plane.one_object_tilt_deg``), or None.

    With two objects, the height they share picks the surface; one object could rest on any of its resting
    faces. The camera's roll and pitch pick it instead: of ``faces`` (:func:`resting_faces`: the model-frame
    outward normals of the faces it rests on, rotated into the camera by ``T``), the surface is the one whose
    upward normal is nearest the image's up direction (camera -y): within ``one_object_tilt_deg`` of it, every
    other face at least :data:`MARGIN_DEG` farther, and the camera above it, looking down at the object by at
    least that angle. Otherwise (a box seen along its diagonal or from straight above, a rolled camera) None:
    the search does not guess.
    """
    if not conf.one_object_tilt_deg or not faces:
        return None
    ups = -(np.asarray(faces, float) @ T[:3, :3].T)  # camera frame, pointing away from the surface
    tilt = np.degrees(np.arccos(np.clip(-ups[:, 1] / np.linalg.norm(ups, axis=1), -1.0, 1.0)))
    order = np.argsort(tilt)
    if tilt[order[0]] > conf.one_object_tilt_deg or (len(order) > 1 and tilt[order[1]] < tilt[order[0]] + MARGIN_DEG):
        return None
    normal = ups[order[0]] / np.linalg.norm(ups[order[0]])
    offset = float(((hull.vertices @ T[:3, :3].T + T[:3, 3]) @ normal).min())
    centre = T[:3, :3] @ hull.centroid + T[:3, 3]
    # The camera (height -offset) must look down at the object's centre (height normal . centre - offset): from
    # straight above, a box lying flat would otherwise stand on the side face nearest the image's up.
    looks_down = -(normal @ centre) >= np.sin(np.deg2rad(MARGIN_DEG)) * np.linalg.norm(centre)
    return Plane(normal, offset, 0.0, (name,)) if offset < 0 and looks_down else None


def stable_faces(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Every face the mesh can rest on (trimesh's stable poses): (K, 3) model-frame outward normals and (K,)
    probabilities."""
    transforms, probs = mesh.compute_stable_poses(n_samples=1)
    down = np.array([np.linalg.inv(T)[:3, :3] @ [0.0, 0.0, -1.0] for T in transforms]).reshape(-1, 3)
    return down, np.asarray(probs, dtype=float)


def resting_faces(stable: tuple[np.ndarray, np.ndarray], min_stable: float) -> list[np.ndarray]:
    """Of ``stable`` (:func:`stable_faces`), the normals of the faces the mesh rests on with probability at
    least ``min_stable`` (stable poses within 15 degrees of one another counted as one), likeliest first."""
    faces: list[list] = []
    for down, p in zip(*stable, strict=True):
        for f in faces:
            if f[1] @ down > np.cos(np.deg2rad(15.0)):
                f[0] += p
                break
        else:
            faces.append([float(p), down])
    return [f[1] for f in sorted(faces, key=lambda f: -f[0]) if f[0] >= min_stable]


def resting(face: np.ndarray, normal: np.ndarray, angle: float, target_hull: np.ndarray, centre: np.ndarray):
    """The rotation that lays the model's resting ``face`` (outward normal, model frame) on a plane with
    ``normal``, turned by ``angle`` about it; and the height of the model point ``centre`` above the plane."""
    R = cv2.Rodrigues(normal * angle)[0] @ turn_to(face, -normal)
    return R, float(normal @ (R @ centre) - (target_hull @ R.T @ normal).min())


def turn_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The shortest rotation taking unit vector ``a`` to unit vector ``b``."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        other = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(a, other)
        return cv2.Rodrigues(axis / np.linalg.norm(axis) * np.pi)[0]
    return cv2.Rodrigues(axis / s * np.arctan2(s, c))[0]
