"""What the estimator knows of each object, and makes once: :class:`Objects`.

The template libraries, meshes, renderer and ids it was given; and, built on first use and kept for the
process, each library's descriptor index and the joint index over all of them, its model voxel grid, the
mesh's half-turn flips, extent, surface samples, silhouettes, stable faces, convex hull and plane-search
target; the SIFT detectors. Nothing here depends on a frame or a sequence of frames.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import numpy as np

from batchpose.config import EstimatorConfig
from batchpose.core.frames import Camera
from batchpose.method.correspondences import flann_index
from batchpose.method.depth import Surface
from batchpose.method.depth_search import Silhouettes
from batchpose.method.features import make_sift, to_gray
from batchpose.method.plane import Target
from batchpose.method.presence import JointIndex, joint_index
from batchpose.method.support import resting_faces, stable_faces
from batchpose.method.templates import TemplateLibrary
from batchpose.method.weights import geom_weights, model_support, model_voxel_grid, support_to_weights


class Objects:
    """The objects an estimator looks for, and everything it derives from them once.

    Args:
        conf: estimator config.
        libraries: obj_name -> TemplateLibrary.
        obj_ids: obj_name -> numeric id for records (BOP obj_id); optional.
        models: obj_name -> ObjectModel, needed (with ``renderer``) for refinement, tracking and the checks.
        renderer: a :class:`batchpose.method.render.Renderer` (or anything with its ``render`` method).
        retry_libraries: obj_name -> its second library (``render.retry_shading``), which
            :attr:`retry_objects` matches against; a mapping that loads each library when first asked for
            keeps the ones never needed out of memory.
    """

    def __init__(
        self,
        conf: EstimatorConfig,
        libraries: Mapping[str, TemplateLibrary],
        obj_ids: dict[str, int] | None = None,
        models: dict | None = None,
        renderer=None,
        retry_libraries: Mapping[str, TemplateLibrary] | None = None,
    ) -> None:
        self.conf = conf
        self.libraries = libraries
        self.retry_libraries = retry_libraries or {}
        self.obj_ids = obj_ids or {}
        self.models = models or {}
        self.renderer = renderer
        self.sift = make_sift(conf.features)
        self._retry_sift: dict[float, object] = {}
        self._lib_index: dict[str, object] = {}
        self._voxels: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._flips: dict[str, list[np.ndarray]] = {}
        self._extent: dict[str, tuple[np.ndarray, float]] = {}
        self._surfaces: dict[str, Surface] = {}
        self._silhouettes: dict[str, Silhouettes] = {}
        self._stable: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._targets: dict[str, Target] = {}
        self._hulls: dict[str, np.ndarray] = {}

    def warm_up(self) -> None:
        """Build every object's library index and render each mesh once now (a batch worker does this when
        it starts) rather than in the first frame that needs them: the first render makes the GL context,
        uploads the mesh and its textures and compiles the shaders (~0.1 s an object)."""
        if self.conf.method == "tp_ub":
            return  # needs no matching
        for name in self.libraries:
            self.library_index(name)
            if self.can_render(name):
                lib = self.libraries[name]
                self.render(name, lib.cam_from_model(0), Camera(lib.K, lib.width, lib.height))

    # -- what the configuration and the inputs allow ------------------------------------------------
    def tracking(self) -> bool:
        """True when confident poses are followed into the next frames (``track.*``; needs a renderer)."""
        c = self.conf
        return c.track.enabled and c.method == "gnc_pose" and c.match.roi == "none" and self.renderer is not None

    def can_render(self, name: str) -> bool:
        return self.renderer is not None and name in self.models

    def can_refine(self, name: str) -> bool:
        return self.conf.refine.enabled and self.can_render(name)

    def obj_id(self, name: str, default: int = 0) -> int:
        return self.obj_ids.get(name, default)

    # -- matching --------------------------------------------------------------------------------
    def retry_sift(self, sigma: float):
        """The SIFT detector of ``features.retry_contrast_threshold`` at base blur ``sigma`` (made once)."""
        sift = self._retry_sift.get(sigma)
        if sift is None:
            fc = self.conf.features
            sift = make_sift(dataclasses.replace(fc, contrast_threshold=fc.retry_contrast_threshold, sigma=sigma))
            self._retry_sift[sigma] = sift
        return sift

    def library_index(self, name: str):
        """The FLANN index over the object's template descriptors (None for a library under 2 keypoints)."""
        if name not in self._lib_index:
            lib = self.libraries[name]
            self._lib_index[name] = flann_index(lib.desc, self.conf.match, keep_in=lib.folder)
        return self._lib_index[name]

    @functools.cached_property
    def retry_objects(self) -> Objects | None:
        """These objects with their second libraries (``render.retry_shading``) for the objects that have
        one; the detectors and the mesh's derived data are shared. None: no second library."""
        if not self.retry_libraries:
            return None
        other = Objects(self.conf, self.retry_libraries, self.obj_ids, self.models, self.renderer)
        other.sift, other._retry_sift = self.sift, self._retry_sift
        other._flips, other._surfaces, other._hulls = self._flips, self._surfaces, self._hulls
        other._stable = self._stable
        return other

    @functools.cached_property
    def joint_index(self) -> JointIndex | None:
        """The index over every object's template descriptors that the presence check asks
        (:mod:`batchpose.method.presence`; built on first use)."""
        return joint_index(self.libraries, self.conf.match)

    def weights(self, name: str, X: np.ndarray) -> np.ndarray:
        """(N,) geometry-aware weights of the object's model points ``X`` (N, 3) (``weights.mode``)."""
        wc = self.conf.weights
        if wc.mode == "none":
            return np.ones(len(X))
        if wc.mode == "correspondences":
            return geom_weights(X, wc.voxel_m, wc.w_min)
        if name not in self._voxels:
            self._voxels[name] = model_voxel_grid(self.libraries[name].pts3d, wc.voxel_m)
        keys, counts = self._voxels[name]
        return support_to_weights(model_support(X, keys, counts, wc.voxel_m), wc.w_min)

    def implausible(self, name: str, pose: np.ndarray, camera: Camera) -> str:
        """Why ``pose`` cannot be what the frame shows ("" when it can): the object's apparent size."""
        if name not in self._extent:
            pts = self.libraries[name].pts3d
            self._extent[name] = (pts.mean(axis=0), float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))))
        centre, diam = self._extent[name]
        z = float(pose[2, :3] @ centre + pose[2, 3])
        if z <= 0:
            return f"implausible pose: the object is behind the camera (z = {z:.2f} m)"
        span = float(camera.K[0, 0]) * diam / z
        lo, hi = self.conf.min_object_px, self.conf.max_object_image_fraction * max(camera.width, camera.height)
        if not lo <= span <= hi:
            return f"implausible pose: the object would span {span:.0f} px at {z:.2f} m (allowed {lo:.0f}-{hi:.0f} px)"
        return ""

    # -- the mesh --------------------------------------------------------------------------------
    def render(self, name: str, T: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """The object's mesh at pose ``T`` in ``camera``: (rgb (H, W, 3) uint8, depth_m (H, W) float32),
        albedo shading."""
        model = self.models[name]
        return self.renderer.render(
            model.content_hash,
            model.mesh,
            T,
            camera.K,
            camera.width,
            camera.height,
            "flat",
            self.conf.render.znear_m,
            self.conf.render.zfar_m,
        )

    def render_gray(self, name: str, T: np.ndarray, camera: Camera) -> np.ndarray:
        return to_gray(self.render(name, T, camera)[0])

    def flips(self, name: str) -> list[np.ndarray]:
        """The mesh's half turns about its principal axes (:meth:`ObjectModel.flips`)."""
        if name not in self._flips:
            self._flips[name] = self.models[name].flips()
        return self._flips[name]

    def surface(self, name: str) -> Surface:
        """Samples of the mesh's surface with normals, for aligning to depth."""
        if name not in self._surfaces:
            self._surfaces[name] = Surface.of(self.models[name].mesh)
        return self._surfaces[name]

    def hull(self, name: str) -> np.ndarray:
        """The object's convex-hull vertices (model frame)."""
        if name not in self._hulls:
            self._hulls[name] = np.asarray(self.models[name].mesh.convex_hull.vertices)
        return self._hulls[name]

    def silhouettes(self, name: str) -> Silhouettes:
        """The object's colour histogram and view silhouettes (:class:`batchpose.method.depth_search.Silhouettes`)."""
        if name not in self._silhouettes:
            lib = self.libraries[name]
            self._silhouettes[name] = Silhouettes.of(
                lambda T: self.render(name, T, Camera(lib.K, lib.width, lib.height)),
                lib,
                self.models[name].diameter_m,
                self.conf.depth.search_view_step,
            )
        return self._silhouettes[name]

    def stable_faces(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The faces the object can rest on (:func:`batchpose.method.support.stable_faces`)."""
        if name not in self._stable:
            self._stable[name] = stable_faces(self.models[name].mesh)
        return self._stable[name]

    def target(self, name: str) -> Target:
        """What the plane search needs of the object."""
        if name not in self._targets:
            mesh = self.models[name].mesh
            self._targets[name] = Target(
                np.asarray(mesh.convex_hull.vertices),
                np.asarray(mesh.bounding_box.centroid),
                self.models[name].diameter_m,
                tuple(resting_faces(self.stable_faces(name), self.conf.plane.min_stable)),
                self.silhouettes(name).hist,
            )
        return self._targets[name]
