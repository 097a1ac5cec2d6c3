"""Template libraries on disk: their cache key and folder, and atomic save / checked load.

Cache layout: ``CACHE/templates/<obj_name>-<key>/{views.parquet, templates.npz, voxels.npz}``, where key
hashes the mesh content, the mesh/render/feature config and the template camera. Entries are written to a
temporary folder and renamed when complete, so a killed build never leaves a library a rerun would trust.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.config import EstimatorConfig, config_hash, to_dict
from batchpose.core.model import ObjectModel
from batchpose.errors import DataError
from batchpose.method.templates import TemplateLibrary

log = logging.getLogger("batchpose")


FILES = ("views.parquet", "templates.npz", "voxels.npz")


LIBRARY_FORMAT = 2  # part of the cache key: bumped when the files gain a field (2: keypoint shapes)


def default_cache_dir() -> Path:
    return Path(os.environ.get("BATCHPOSE_CACHE", Path.home() / ".cache" / "batchpose"))


#: FeatureConfig fields that only change how frames are searched, not the templates: left out of the key.
QUERY_ONLY_FEATURES = ("retry_contrast_threshold", "retry_sigma")


#: RenderConfig fields that choose which libraries a run uses, not how one is rendered: left out of the key.
QUERY_ONLY_RENDER = ("retry_shading",)


def library_key(model: ObjectModel, conf: EstimatorConfig, K: np.ndarray, width: int, height: int) -> str:
    features = {k: v for k, v in to_dict(conf.features).items() if k not in QUERY_ONLY_FEATURES}
    render = {k: v for k, v in to_dict(conf.render).items() if k not in QUERY_ONLY_RENDER}
    return config_hash(
        LIBRARY_FORMAT,
        model.content_hash,
        model.scale,
        conf.mesh,
        render,
        features,
        np.round(np.asarray(K, float), 4).tolist(),
        width,
        height,
    )


def retry_library_conf(conf: EstimatorConfig) -> EstimatorConfig | None:
    """The config the second library (``render.retry_shading``) is built with: ``conf`` but for the
    shading. None: no second library ("none", or the shading of the first)."""
    shading = conf.render.retry_shading
    if shading in ("none", conf.render.shading):
        return None
    return dataclasses.replace(conf, render=dataclasses.replace(conf.render, shading=shading, retry_shading="none"))


def library_dir(cache_dir: Path, model: ObjectModel, key: str) -> Path:
    return Path(cache_dir) / "templates" / f"{model.name}-{key}"


def _remove_abandoned(out_dir: Path) -> None:
    """Remove the half-saved copies of ``out_dir`` that killed processes left (``NAME.tmp-PID`` of a PID no
    longer running); a live process's copy is left to it."""
    for tmp in out_dir.parent.glob(f"{out_dir.name}.tmp-*"):
        pid = tmp.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            shutil.rmtree(tmp, ignore_errors=True)


def save(lib: TemplateLibrary, out_dir: Path, voxels: tuple[np.ndarray, np.ndarray], voxel_m: float) -> Path:
    """Write a library and its model voxel grid (``(keys, counts)`` of
    :func:`batchpose.method.weights.model_voxel_grid` at ``voxel_m``) atomically: a temporary folder, then a
    rename. Returns ``out_dir``."""
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
    keys, counts = voxels
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


def is_cached(lib_dir: Path) -> bool:
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
