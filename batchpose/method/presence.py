"""Which objects a frame shows, decided once per frame before the expensive steps (``match.presence_votes``).

One descriptor index over every object's template library (:class:`JointIndex`) is asked once for the
frame's keypoints: each keypoint's nearest template descriptors among all objects, and its rival, the
nearest that is another object's or another 3D point of the same object. A keypoint counts for the object
of its nearest descriptor when it passes the ratio test against that rival, so a keypoint that looks as
much like another object as like this one counts for neither. The keypoints that count for an object vote
for its image centre, size and in-plane rotation (the locator's Hough vote,
:func:`batchpose.method.correspondences.locate`); an object whose votes agree on no location with at least
``presence_votes`` of them is ``absent``. Chance matches scatter; an object's own matches agree.

One query for all objects costs about what one object's library query costs (a k-d tree search visits
``flann_checks`` leaves whatever the index's size), so an absent object costs a share of that query and a
Hough vote instead of the matching passes, the retries and the refinement.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from batchpose.config import MatchConfig
from batchpose.method.correspondences import far_points, flann_index, knn, locate, rival_distance
from batchpose.method.templates import TemplateLibrary

#: Nearest template descriptors asked per keypoint (the rival is the nearest of them of another object or
#: another 3D point).
K_NEAREST = 4


@dataclass
class JointIndex:
    """A FLANN index over the template descriptors of several objects.

    Attributes:
        names: the objects, in the order of ``owner``'s values.
        index: the FLANN index over ``desc`` (N, 128) float32 (kept: the index reads it).
        owner: (N,) which object (index into ``names``) each descriptor is of.
        local: (N,) the descriptor's index in its own library.
        pts: (N, 3) float32 the descriptor's 3D model point, metres.
    """

    names: tuple[str, ...]
    index: object
    desc: np.ndarray
    owner: np.ndarray
    local: np.ndarray
    pts: np.ndarray


def joint_index(libraries: Mapping[str, TemplateLibrary], conf: MatchConfig) -> JointIndex | None:
    """The joint index over ``libraries`` (None when they hold under 2 descriptors). Kept beside the
    libraries' cache folders (in a folder named by them) when they all have one, like each library's own
    index (:func:`batchpose.method.correspondences.flann_index`)."""
    names = tuple(libraries)
    desc = np.ascontiguousarray(np.vstack([libraries[n].desc for n in names]), np.float32)
    owner = np.concatenate([np.full(len(libraries[n].desc), i, np.int32) for i, n in enumerate(names)])
    local = np.concatenate([np.arange(len(libraries[n].desc)) for n in names])
    pts = np.vstack([libraries[n].pts3d for n in names]).astype(np.float32)
    index = flann_index(desc, conf, keep_in=index_folder(libraries))
    return None if index is None else JointIndex(names, index, desc, owner, local, pts)


def index_folder(libraries: Mapping[str, TemplateLibrary]) -> Path | None:
    """The folder the joint index is kept in: beside the libraries' folders, named by them (None when a
    library has no folder, or they are in different places)."""
    folders = [lib.folder for lib in libraries.values()]
    if not folders or any(f is None for f in folders):
        return None
    parents = {Path(f).parent for f in folders if f is not None}
    if len(parents) != 1:
        return None
    digest = hashlib.sha256("\n".join(sorted(Path(f).name for f in folders if f is not None)).encode()).hexdigest()
    keep = parents.pop() / f"presence-{digest[:16]}"
    try:
        keep.mkdir(exist_ok=True)
    except OSError:
        return None
    return keep


@dataclass(frozen=True)
class JointNearest:
    """The joint index's answer for one keypoint set: (M, k) nearest descriptors (joint indices) and
    distances, and (M,) the rival distance (inf when none of the k is a rival)."""

    idx: np.ndarray
    dist: np.ndarray
    rival: np.ndarray


def joint_nearest(joint: JointIndex, desc_q: np.ndarray, conf: MatchConfig) -> JointNearest:
    """Each of ``desc_q``'s (M, 128) nearest template descriptors over all objects, and its rival: the nearest
    of another object, or of a 3D point farther than ``conf.distinct_3d_m`` from the best one's."""
    idx, dist = knn(joint.index, desc_q, min(K_NEAREST, len(joint.desc)), conf, conf.presence_checks)
    own = joint.owner[idx]
    return JointNearest(idx, dist, rival_distance(dist, (own != own[:, :1]) | far_points(joint.pts[idx], conf)))


def votes(
    joint: JointIndex,
    found: JointNearest,
    name: str,
    lib: TemplateLibrary,
    xy: np.ndarray,
    shapes: np.ndarray,
    desc: np.ndarray,
    conf: MatchConfig,
    width: int,
    height: int,
) -> int:
    """The most keypoints that count for object ``name`` (nearest descriptor its, ratio test against the
    rival) and agree on one location of it (0: none)."""
    nearest = as_object(joint, found, name)
    if not np.isfinite(nearest[1]).any():
        return 0
    peak = locate(xy, shapes, desc, joint.index, lib, conf, width, height, min_votes=1, peaks=1, nearest=nearest)
    return peak[0].votes if peak else 0


def as_object(joint: JointIndex, found: JointNearest, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``found`` as object ``name``'s library query (:func:`~batchpose.method.correspondences.nearest_with_rival`)
    of its nearest column: (M, 1) indices into the object's library, (M, 1) distances (inf where the nearest
    descriptor is another object's, so that keypoint fails every ratio test) and the (M,) rival distances."""
    mine = joint.owner[found.idx[:, 0]] == joint.names.index(name)
    idx = np.where(mine, joint.local[found.idx[:, 0]], 0)[:, None]
    dist = np.where(mine, found.dist[:, 0], np.inf)[:, None]
    return idx, dist, found.rival
