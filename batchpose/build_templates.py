"""Stage: build or load the cached template library (and model voxel grid) of each object.

Cache layout: ``CACHE/templates/<obj_name>-<key>/{views.parquet, templates.npz, voxels.npz}``, where key
hashes the mesh content, the mesh/render/feature config and the template camera. A second build with the
same key loads and renders nothing. Entries are written to a temporary folder and renamed when complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from batchpose.config import EstimatorConfig, config_hash, to_dict
from batchpose.errors import DataError
from batchpose.mesh import ObjectModel
from batchpose.templates import TemplateLibrary, render_templates
from batchpose.weights import model_voxel_grid
from batchpose.workers import loky_options

log = logging.getLogger("batchpose")

FILES = ("views.parquet", "templates.npz", "voxels.npz")
LIBRARY_FORMAT = 2  # part of the cache key: bumped when the files gain a field (2: keypoint shapes)


def default_cache_dir() -> Path:
    return Path(os.environ.get("BATCHPOSE_CACHE", Path.home() / ".cache" / "batchpose"))


def template_camera(conf: EstimatorConfig, K: np.ndarray, width: int, height: int):
    """Template intrinsics and size: the data set camera's, or ``render.width/height`` with K rescaled."""
    w = conf.render.width or width or 640
    h = conf.render.height or height or 480
    K = np.asarray(K, np.float64).copy()
    if width and (w, h) != (width, height):
        K[0] *= w / width
        K[1] *= h / height
    return K, w, h


#: FeatureConfig fields that only change how frames are searched, not the templates: left out of the key.
QUERY_ONLY_FEATURES = ("retry_contrast_threshold", "retry_sigma")


def library_key(model: ObjectModel, conf: EstimatorConfig, K: np.ndarray, width: int, height: int) -> str:
    features = {k: v for k, v in to_dict(conf.features).items() if k not in QUERY_ONLY_FEATURES}
    return config_hash(
        LIBRARY_FORMAT,
        model.content_hash,
        model.scale,
        conf.mesh,
        conf.render,
        features,
        np.round(np.asarray(K, float), 4).tolist(),
        width,
        height,
    )


def library_dir(cache_dir: Path, model: ObjectModel, key: str) -> Path:
    return Path(cache_dir) / "templates" / f"{model.name}-{key}"


def _remove_abandoned(out_dir: Path) -> None:
    """Remove the half-saved copies of ``out_dir`` that killed processes left (``NAME.tmp-PID`` of a PID no
    longer running); a live process's copy is left to it."""
    for tmp in out_dir.parent.glob(f"{out_dir.name}.tmp-*"):
        pid = tmp.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            shutil.rmtree(tmp, ignore_errors=True)


def save(lib: TemplateLibrary, out_dir: Path, voxel_m: float) -> Path:
    """Write a library atomically (temporary folder, then rename). Returns ``out_dir``."""
    out_dir = Path(out_dir)
    _remove_abandoned(out_dir)
    tmp = out_dir.with_name(out_dir.name + f".tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    lib.views.to_parquet(tmp / "views.parquet", index=False)
    np.savez(
        tmp / "templates.npz",
        view_ids=lib.view_ids,
        xy=lib.xy,
        desc=lib.desc,
        pts3d=lib.pts3d,
        shapes=lib.shapes,
        K=lib.K,
        size=np.array([lib.width, lib.height]),
        obj_name=np.array(lib.obj_name),
        key=np.array(lib.key),
    )
    keys, counts = model_voxel_grid(lib.pts3d, voxel_m)
    np.savez(tmp / "voxels.npz", keys=keys, counts=counts, voxel_m=np.array(voxel_m))
    try:
        os.replace(tmp, out_dir)
    except OSError:  # another worker finished the same library first: keep theirs
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def load(lib_dir: Path) -> TemplateLibrary:
    lib_dir = Path(lib_dir)
    try:
        views = pd.read_parquet(lib_dir / "views.parquet")
        with np.load(lib_dir / "templates.npz") as z:
            return TemplateLibrary(
                obj_name=str(z["obj_name"]),
                key=str(z["key"]),
                K=z["K"],
                width=int(z["size"][0]),
                height=int(z["size"][1]),
                views=views,
                view_ids=z["view_ids"],
                xy=z["xy"],
                desc=z["desc"],
                pts3d=z["pts3d"],
                shapes=z["shapes"],
                folder=lib_dir,
            )
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise DataError(f"{lib_dir}: template library is unreadable ({e}); delete it to build it again") from None


def _cached(lib_dir: Path) -> bool:
    """A cached library with all its files, each of which opens (a copy or a disk error can break one;
    saving is atomic)."""
    if not all((lib_dir / f).is_file() for f in FILES):
        return False
    try:
        pd.read_parquet(lib_dir / "views.parquet", columns=["view_id"])
        for name in ("templates.npz", "voxels.npz"):
            with np.load(lib_dir / name) as z:
                z.files  # noqa: B018 - reads the zip directory
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
        log.warning("%s: cached template library unreadable (%s); building it again", lib_dir, e)
        return False
    return True


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
    if not overwrite and _cached(out):
        log.info("Skipping %s: template library cached (%s)", model.name, out)
        return out
    if renderer is None:
        from batchpose.render import get_renderer

        renderer = get_renderer()
    t0 = time.perf_counter()
    n_views = conf.render.n_views * max(len(conf.render.distances_m or conf.render.image_fractions), 1)
    if conf.render.view_preset == "paper":
        n_views = int(round(360 / conf.render.paper_azimuth_step_deg))
    with tqdm(total=n_views, desc=f"templates {model.name}", unit="view", leave=False, disable=None) as bar:
        lib = render_templates(model, K_t, w, h, conf.render, conf.features, renderer, key, bar.update)
    if out.exists():  # --overwrite, or an unreadable library
        shutil.rmtree(out)
    save(lib, out, conf.weights.voxel_m)
    log.info(
        "built %s: %d views, %d keypoints in %.1f s",
        model.name,
        lib.n_views,
        len(lib.desc),
        time.perf_counter() - t0,
    )
    return out


def _build_in_worker(mesh_path: str, name: str, conf: EstimatorConfig, K, width, height, cache_dir) -> Path:
    from batchpose.mesh import load_mesh  # noqa: PLC0415

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
        if _cached(d):
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
