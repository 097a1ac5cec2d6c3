"""Headless RGB + metric depth rendering with pyrender. The only module that imports the renderer.

Backend: ``PYOPENGL_PLATFORM`` if set, else OSMesa (samples exactly at pixel centres, and is faster than
EGL on llvmpipe). One GL context per process and image size, one scene in it holding every mesh.
"""

from __future__ import annotations

import atexit
import os
import threading
from typing import Any

import numpy as np

from batchpose.errors import RenderError

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
if not hasattr(np, "infty"):  # pyrender 0.1.45 uses np.infty, removed in numpy 2
    np.infty = np.inf  # type: ignore[attr-defined]

_GL_PACKAGES = {
    "osmesa": "libosmesa6",
    "egl": "libegl1 libegl-mesa0 libgl1-mesa-dri",
}

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _import_pyrender():
    platform = os.environ.get("PYOPENGL_PLATFORM", "osmesa")
    try:
        import pyrender

        return pyrender
    except Exception as e:  # ImportError, OSError, AttributeError from PyOpenGL's platform loader
        pkg = _GL_PACKAGES.get(platform, "libosmesa6 or libegl1 libegl-mesa0 libgl1-mesa-dri")
        raise RenderError(
            f"headless rendering through PYOPENGL_PLATFORM={platform} is unavailable ({type(e).__name__}: "
            f"{str(e).splitlines()[0] if str(e) else ''}); install the Debian package(s) {pkg} "
            "(make setup does) or set PYOPENGL_PLATFORM=egl/osmesa"
        ) from None


def _program_cache(pr):
    """A pyrender shader-program cache that finds its programs again under OSMesa.

    pyrender keys its cache by ``OpenGL.contextdata.getContext()``, which under OSMesa is a new ctypes
    object on every call: each render compiled its shader program again (~1.3 ms) and kept it (1-3 MB of
    llvmpipe code) until the context was deleted. A cache belongs to one renderer and so to one context;
    this one keys by the shaders and their defines alone.
    """

    class ProgramCache(pr.shader_program.ShaderProgramCache):
        def __init__(self) -> None:
            super().__init__()
            self._by_shaders: dict = {}

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            if key not in self._by_shaders:
                self._by_shaders[key] = super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)
            return self._by_shaders[key]

        def clear(self) -> None:
            super().clear()
            self._by_shaders.clear()

    return ProgramCache()


def _light_in_gl_camera(light_from: np.ndarray | None) -> np.ndarray:
    """The pose, in the OpenGL camera's axes, of a directional light shining from ``light_from`` (OpenCV
    camera axes; None: from the camera). pyrender's directional light shines along its node's -z."""
    if light_from is None:
        return np.eye(4)
    z = _CV_TO_GL[:3, :3] @ np.asarray(light_from, dtype=float)
    z /= np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return pose


class Renderer:
    """Renders one mesh at a time; keeps one GL context per process and per image size."""

    def __init__(self) -> None:
        self._pr = _import_pyrender()
        self._renderer: Any = None  # pyrender.OffscreenRenderer (pyrender ships no types)
        self._size: tuple[int, int] | None = None
        self._meshes: dict[str, object] = {}  # key -> pyrender.Mesh (kept across contexts)
        self._scene: Any = None  # this context's pyrender.Scene
        self._lock = threading.Lock()

    def _context(self, width: int, height: int):
        if self._renderer is None or self._size != (width, height):
            self._delete_context()
            try:
                self._renderer = self._pr.OffscreenRenderer(width, height)
            except Exception as e:
                platform = os.environ.get("PYOPENGL_PLATFORM", "osmesa")
                if "OSMesaCreateContextAttribs" in str(e):
                    raise RenderError(
                        "PyOpenGL is too old for OSMesa (pyrender pins 3.1.0); run "
                        "`pip install PyOpenGL==3.1.10` (make setup does) or set PYOPENGL_PLATFORM=egl"
                    ) from None
                pkg = _GL_PACKAGES.get(platform, "libosmesa6 (osmesa) or libegl1 libegl-mesa0 libgl1-mesa-dri (egl)")
                raise RenderError(
                    f"cannot create an offscreen GL context with PYOPENGL_PLATFORM={platform} ({e}); install "
                    f"the Debian package(s) {pkg} (make setup does) or set PYOPENGL_PLATFORM=osmesa or egl"
                ) from None
            self._renderer._renderer._program_cache = _program_cache(self._pr)
            self._size = (width, height)
        return self._renderer

    def _delete_context(self) -> None:
        """Free the GL context and everything in it: ``OffscreenRenderer.delete`` without its
        ``gc.collect()`` (~85 ms with a worker's heap; the context's buffers are freed without it)."""
        r, self._renderer = self._renderer, None
        self._scene = None
        if r is None:
            return
        r._platform.make_current()
        r._renderer.delete()  # deletes the meshes' and textures' GL objects, so the Mesh objects can be reused
        r._platform.delete_context()
        r._renderer = r._platform = None

    def render(
        self,
        key: str,
        mesh,
        cam_from_model: np.ndarray,
        K: np.ndarray,
        width: int,
        height: int,
        shading: str = "flat",
        znear_m: float = 0.01,
        zfar_m: float = 20.0,
        light_from: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render a trimesh mesh.

        Args:
            key: cache key for the uploaded mesh (e.g. the mesh content hash).
            mesh: trimesh.Trimesh in metres.
            cam_from_model: (4, 4) model->camera (OpenCV camera axes), metres.
            K: (3, 3) OpenCV intrinsics (pixel centres at integers).
            width, height: image size in pixels.
            shading: "flat" (albedo) or "lit" (one directional light + ambient).
            light_from: with "lit", the direction towards the light in camera axes (OpenCV: x right, y down,
                z forward); None: from the camera (a headlight).

        Returns:
            rgb (H, W, 3) uint8 and depth_m (H, W) float32 z-depth in metres, 0 where there is no surface.
        """
        pr = self._pr
        with self._lock:
            r = self._context(width, height)
            scene = self._scene_with(key, mesh)
            scene.ambient_light = [1.0, 1.0, 1.0] if shading == "flat" else [0.35, 0.35, 0.35]
            # pyrender's principal point counts from pixel edges, OpenCV's from pixel centres.
            cam = pr.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=znear_m, zfar=zfar_m)
            model_from_cam_gl = np.linalg.inv(cam_from_model) @ _CV_TO_GL
            added = [scene.add(cam, pose=model_from_cam_gl)]
            flags = pr.RenderFlags.FLAT if shading == "flat" else pr.RenderFlags.NONE
            if shading == "lit":
                light_pose = model_from_cam_gl @ _light_in_gl_camera(light_from)
                added.append(scene.add(pr.DirectionalLight(color=np.ones(3), intensity=2.5), pose=light_pose))
            try:
                color, depth = r.render(scene, flags=flags)
            finally:
                for node in added:
                    scene.remove_node(node)
        return np.ascontiguousarray(color[:, :, :3]), depth.astype(np.float32)

    def _scene_with(self, key: str, mesh):
        """The context's one scene, holding every mesh rendered in it, with only ``key``'s visible.

        pyrender uploads the meshes and textures of the scene it renders and deletes those of the previous
        scene that this one lacks, so a scene per render would upload an object's textures again every time
        the rendered object changes (~25 ms for a 2048² texture); hidden meshes stay in GL memory instead.
        """
        pr = self._pr
        if self._scene is None:
            self._scene = pr.Scene(bg_color=[0.0, 0.0, 0.0, 0.0])
        if key not in self._meshes:
            self._meshes[key] = pr.Mesh.from_trimesh(mesh, smooth=False)
        wanted = self._meshes[key]
        if wanted not in self._scene.meshes:
            self._scene.add(wanted)
        for m in self._scene.meshes:
            m.is_visible = m is wanted
        return self._scene

    def close(self) -> None:
        """Free the GL context (pyrender's own finaliser fails noisily during interpreter shutdown)."""
        try:
            self._delete_context()
        except Exception:  # noqa: BLE001 - best effort at exit
            self._renderer = None
        self._meshes.clear()


_RENDERER: Renderer | None = None


def get_renderer() -> Renderer:
    """The process's renderer (one GL context per worker process, created on first use)."""
    global _RENDERER
    if _RENDERER is None:
        _RENDERER = Renderer()
        atexit.register(_RENDERER.close)
    return _RENDERER
