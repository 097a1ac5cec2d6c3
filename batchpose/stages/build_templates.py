"""Stage: build or load the cached template library (and model voxel grid) of each object.

Cache layout: ``CACHE/templates/<obj_name>-<key>/{views.parquet, templates.npz, voxels.npz}``, where key
hashes the mesh content, the mesh/render/feature config and the template camera. A second build with the
same key loads and renders nothing. Entries are written to a temporary folder and renamed when complete.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from batchpose.config import EstimatorConfig
from batchpose.core.model import ObjectModel
from batchpose.io import library
from batchpose.io.files import write_text_atomic
from batchpose.io.library import (
    is_cached,
    library_dir,
    library_key,
    retry_library_conf,
    save,
)
from batchpose.method import presence
from batchpose.method.templates import render_templates
from batchpose.method.weights import model_voxel_grid
from batchpose.stages.workers import loky_options

log = logging.getLogger("batchpose")


def template_camera(conf: EstimatorConfig, K: np.ndarray, width: int, height: int):
    """Template intrinsics and size: the data set camera's, or ``render.width/height`` with K rescaled."""
    w = conf.render.width or width or 640
    h = conf.render.height or height or 480
    K = np.asarray(K, np.float64).copy()
    if width and (w, h) != (width, height):
        K[0] *= w / width
        K[1] *= h / height
    return K, w, h


def build_library(
    model: ObjectModel,
    conf: EstimatorConfig,
    K: np.ndarray,
    width: int,
    height: int,
    cache_dir: Path,
    overwrite: bool = False,
    renderer=None,
) -> Path:
    """Build (or find) the template library of one object; returns its cache folder."""
    K_t, w, h = template_camera(conf, K, width, height)
    key = library_key(model, conf, K_t, w, h)
    out = library_dir(cache_dir, model, key)
    if not overwrite and is_cached(out):
        log.info("Skipping %s: template library cached (%s)", model.name, out)
        return out
    if renderer is None:
        from batchpose.method.render import get_renderer

        renderer = get_renderer()
    t0 = time.perf_counter()
    n_views = conf.render.n_views * max(len(conf.render.distances_m or conf.render.image_fractions), 1)
    if conf.render.view_preset == "paper":
        n_views = int(round(360 / conf.render.paper_azimuth_step_deg))
    with tqdm(total=n_views, desc=f"templates {model.name}", unit="view", leave=False, disable=None) as bar:
        lib = render_templates(model, K_t, w, h, conf.render, conf.features, renderer, key, bar.update)
    if out.exists():  # --overwrite, or an unreadable library
        shutil.rmtree(out)
    save(lib, out, model_voxel_grid(lib.pts3d, conf.weights.voxel_m), conf.weights.voxel_m)
    log.info(
        "built %s: %d views, %d keypoints in %.1f s",
        model.name,
        lib.n_views,
        len(lib.desc),
        time.perf_counter() - t0,
    )
    return out


def _build_in_worker(mesh_path: str, name: str, conf: EstimatorConfig, K, width, height, cache_dir) -> Path:
    from batchpose.io.mesh import load_mesh, quiet_mesh_warnings  # noqa: PLC0415

    quiet_mesh_warnings([mesh_path])  # the run warned about the mesh's units
    model = load_mesh(Path(mesh_path), conf.mesh, name=name, cache_dir=cache_dir)
    return build_library(model, conf, K, width, height, cache_dir)


def build_all(
    models: dict[str, ObjectModel],
    conf: EstimatorConfig,
    K: np.ndarray,
    width: int,
    height: int,
    cache_dir: Path,
    jobs: int = 1,
) -> dict[str, Path]:
    """Build (or find) every object's library; objects missing from the cache are built in parallel.

    Returns:
        obj_name -> library folder.
    """
    import joblib  # noqa: PLC0415

    K_t, w, h = template_camera(conf, K, width, height)
    out: dict[str, Path] = {}
    todo = []
    for name, model in models.items():
        d = library_dir(cache_dir, model, library_key(model, conf, K_t, w, h))
        if is_cached(d):
            log.info("Skipping %s: template library cached (%s)", name, d)
            out[name] = d
        else:
            todo.append(name)
    if len(todo) > 1 and jobs > 1:
        with joblib.parallel_config(backend="loky", **loky_options()):
            dirs = joblib.Parallel(n_jobs=min(jobs, len(todo)))(
                joblib.delayed(_build_in_worker)(str(models[n].path), n, conf, K, width, height, cache_dir)
                for n in todo
            )
        out.update(zip(todo, dirs, strict=True))
    else:
        for n in todo:
            out[n] = build_library(models[n], conf, K, width, height, cache_dir)
    return {n: out[n] for n in models}


@dataclass(frozen=True)
class TemplateInputs:
    """What the template stage reads besides the config.

    Attributes:
        models: object name -> loaded mesh, in manifest order.
        obj_ids: object name -> data set id.
        K, width, height: the camera the frames are estimated with (the templates' camera is made from it).
        cache_dir: the template library cache.
        jobs: libraries built in parallel.
        mesh_paths: object name -> the mesh file the manifest names (reported in ``objects.json``).
        points: object name -> the model points file the manifest names (reported in ``objects.json``).
        presence: build the presence check's joint index too (:mod:`batchpose.method.presence`), once here
            rather than in every worker at once.
    """

    models: dict[str, ObjectModel]
    obj_ids: dict[str, int]
    K: np.ndarray
    width: int
    height: int
    cache_dir: Path
    jobs: int = 1
    mesh_paths: dict[str, Path] = field(default_factory=dict)
    points: dict[str, Path | None] = field(default_factory=dict)
    presence: bool = False


def main(conf: EstimatorConfig, inputs: TemplateInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Build (or find in the cache) every object's template library and write ``run_dir/objects.json``
    (each object's id, mesh, points, diameter, library folder and ``render.retry_shading``'s second library
    folder); returns its path. ``overwrite`` does not rebuild cached libraries: their key is the hash of
    everything that makes them."""
    t0 = time.perf_counter()
    m = inputs.models
    lib_dirs = build_all(m, conf, inputs.K, inputs.width, inputs.height, inputs.cache_dir, jobs=inputs.jobs)
    retry_dirs: dict[str, Path] = {}
    if (retry_conf := retry_library_conf(conf)) is not None:  # render.retry_shading
        retry_dirs = build_all(m, retry_conf, inputs.K, inputs.width, inputs.height, inputs.cache_dir, inputs.jobs)
    log.info("template libraries ready for %d objects in %.1f s", len(m), time.perf_counter() - t0)
    if inputs.presence:
        t0 = time.perf_counter()
        presence.joint_index({name: library.load(d) for name, d in lib_dirs.items()}, conf.match)
        log.info("presence index over %d objects ready in %.1f s", len(m), time.perf_counter() - t0)
    objects = {
        name: {
            "obj_id": inputs.obj_ids[name],
            "mesh": str(inputs.mesh_paths.get(name, model.path)),
            "points": str(inputs.points[name]) if inputs.points.get(name) else None,
            "diameter_m": model.diameter_m,
            "library": str(lib_dirs[name]),
            "retry_library": str(retry_dirs[name]) if name in retry_dirs else None,
        }
        for name, model in m.items()
    }
    return write_text_atomic(Path(run_dir) / "objects.json", json.dumps(objects, indent=2), encoding=None)


def library_dirs(objects_json: Path, which: str = "library") -> dict[str, Path]:
    """object name -> library folder, from the ``objects.json`` :func:`main` wrote; ``which="retry_library"``:
    the second libraries (``render.retry_shading``; empty without them)."""
    return {name: Path(o[which]) for name, o in json.loads(Path(objects_json).read_text()).items() if o.get(which)}
