"""Stage: build or load the cached template library (and model voxel grid) of each object.

Cache layout: ``CACHE/templates/<obj_name>-<key>/{views.parquet, templates.npz, voxels.npz}``, where key
hashes the mesh content, the mesh/render/feature config and the template camera. A second build with the
same key loads and renders nothing. Entries are written to a temporary folder and renamed when complete.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from batchpose.config import EstimatorConfig
from batchpose.core.model import ObjectModel
from batchpose.io.library import (
    is_cached,
    library_dir,
    library_key,
    save,
)
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


def main(
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
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415

    model = load_mesh(Path(mesh_path), conf.mesh, name=name, cache_dir=cache_dir)
    return main(model, conf, K, width, height, cache_dir)


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
            out[n] = main(models[n], conf, K, width, height, cache_dir)
    return {n: out[n] for n in models}
