"""The object a run looks for: a textured mesh in metres (loaded by :mod:`batchpose.io.mesh`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist


@dataclass(frozen=True)
class ObjectModel:
    """A textured object mesh in metres.

    Attributes:
        name: object name ("003_cracker_box").
        path: the mesh file.
        mesh: trimesh mesh, vertices in metres, texture or vertex colours attached.
        diameter_m: largest distance between two vertices, metres.
        content_hash: sha256 over the mesh file and the material/texture files it references.
        scale: factor applied to the file's coordinates (1.0, or 0.001 for a converted mm mesh).
    """

    name: str
    path: Path
    mesh: trimesh.Trimesh
    diameter_m: float
    content_hash: str
    scale: float = 1.0

    @property
    def center_m(self) -> np.ndarray:
        """(3,) centre of the axis-aligned bounding box, model frame, metres."""
        return self.mesh.bounds.mean(axis=0)

    def flips(self) -> list[np.ndarray]:
        """(4, 4) model-frame turns of 180 degrees about each principal axis through the surface centroid.

        Boxes, cans and bottles look alike turned this way (shape and often texture); the turned poses are
        the hypotheses a texture-symmetric match most often confuses with the true one.
        """
        tri = self.mesh.triangles_center
        w = self.mesh.area_faces
        c = (tri * w[:, None]).sum(axis=0) / w.sum()
        d = tri - c
        _, vecs = np.linalg.eigh((d * w[:, None]).T @ d)
        out = []
        for a in vecs.T:
            R = 2.0 * np.outer(a, a) - np.eye(3)  # 180 degrees about unit axis a
            F = np.eye(4)
            F[:3, :3] = R
            F[:3, 3] = c - R @ c
            out.append(F)
        return out


def diameter(vertices: np.ndarray) -> float:
    """Largest pairwise distance between points (N, 3) -> float, via the convex hull."""
    pts = np.asarray(vertices, dtype=np.float64)
    if len(pts) > 4:
        try:
            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # degenerate (flat) point set: fall back to all points
            pass
    return float(pdist(pts).max()) if len(pts) > 1 else 0.0
