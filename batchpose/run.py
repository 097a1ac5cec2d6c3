"""The main job: ingest -> template libraries -> estimate -> poses.csv / poses.mcap -> report.

Each stage is a module whose ``main`` returns the path it wrote; finished stages are skipped on a rerun.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import json
import logging
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from batchpose import build_templates, estimate_poses, export_mcap, ingest_frames
from batchpose.config import apply_overrides, load_estimator_config, load_yaml, to_dict
from batchpose.errors import ConfigError
from batchpose.manifest import load_manifest
from batchpose.mesh import load_mesh

log = logging.getLogger("batchpose")

_VERSIONED = (
    "batchpose",
    "numpy",
    "opencv-python-headless",
    "pyrender",
    "PyOpenGL",
    "trimesh",
    "mcap",
    "pandas",
    "pyarrow",
    "joblib",
    "dask",
    "distributed",
    "scipy",
)


def versions() -> dict:
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in _VERSIONED:
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


@contextlib.contextmanager
def _backend(backend: str, scheduler: str | None, jobs: int):
    """Yields the joblib backend name; for dask, a distributed Client is open for the block."""
    if backend != "dask":
        yield "loky"
        return
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as e:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect to the Dask scheduler ({e})") from None
        cluster = None
    else:
        cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    try:
        yield "dask"
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def main(
    pipeline: Path,
    manifest: Path,
    run_dir: Path,
    cache_dir: Path | None = None,
    overrides: list[str] = (),
    jobs: int = 2,
    backend: str = "loky",
    scheduler: str | None = None,
    overwrite: bool = False,
    limit: int | None = None,
    max_pairs: int | None = None,
    report: bool = True,
) -> Path:
    """Run the whole pipeline; returns ``run_dir``."""
    from batchpose.datasets import open_frames

    t_start = time.perf_counter()
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    if backend == "dask" and scheduler is None and jobs < 1:
        raise ConfigError("--backend dask needs --scheduler or --jobs >= 1 for a local cluster")
    conf_dict = apply_overrides(load_yaml(Path(pipeline)), list(overrides))
    conf = load_estimator_config(conf_dict, where=str(pipeline))
    conf_dict = to_dict(conf)
    man = load_manifest(Path(manifest))
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    cache_dir = Path(cache_dir) if cache_dir else build_templates.default_cache_dir()

    # A run directory belongs to one config and one manifest: refuse to mix results.
    saved = run_dir / "config.yaml"
    resolved = {"pipeline": conf_dict, "manifest": man.to_dict()}
    if saved.is_file() and not overwrite:
        previous = yaml.safe_load(saved.read_text())
        if previous != json.loads(json.dumps(resolved)):
            raise ConfigError(
                f"{run_dir}: holds a run with a different config or manifest; use another --out or --overwrite"
            )
    _write_text_atomic(saved, yaml.safe_dump(resolved, sort_keys=False))
    _write_text_atomic(run_dir / "versions.json", json.dumps(versions(), indent=2))
    _write_text_atomic(run_dir / "manifest.yaml", yaml.safe_dump(man.to_dict(), sort_keys=False))

    source = open_frames(man.frames, man.path.parent)
    log.info("data: %s", source.describe())
    objects = [o.name for o in man.objects]
    ingest_frames.main(source, objects, run_dir, overwrite=overwrite, limit=limit)

    frames_index = pd.read_parquet(run_dir / "frames.parquet")
    if frames_index.empty:
        raise ConfigError(f"{man.path}: the data set has no frames")
    first = frames_index.iloc[0]
    K0 = np.asarray(first["K"], float).reshape(3, 3)
    models, lib_dirs, obj_ids = {}, {}, {}
    t0 = time.perf_counter()
    width, height = int(first["width"]), int(first["height"])
    for spec in man.objects:
        models[spec.name] = load_mesh(spec.mesh, conf.mesh, name=spec.name)
        obj_ids[spec.name] = source.obj_id(spec.name)
    lib_dirs = build_templates.build_all(models, conf, K0, width, height, cache_dir, jobs=jobs)
    log.info("template libraries ready for %d objects in %.1f s", len(models), time.perf_counter() - t0)
    _write_text_atomic(
        run_dir / "objects.json",
        json.dumps(
            {
                name: {
                    "obj_id": obj_ids[name],
                    "mesh": str(spec.mesh),
                    "points": str(spec.points) if spec.points else None,
                    "diameter_m": models[name].diameter_m,
                    "library": str(lib_dirs[name]),
                }
                for name, spec in zip(objects, man.objects, strict=False)
            },
            indent=2,
        ),
    )

    with _backend(backend, scheduler, jobs) as jl_backend:
        poses_path = estimate_poses.main(
            source,
            conf,
            conf_dict,
            lib_dirs,
            obj_ids,
            {o.name: o.mesh for o in man.objects},
            man.targets,
            run_dir,
            jobs=jobs,
            backend=jl_backend,
            overwrite=overwrite,
            limit=limit,
            max_pairs=max_pairs,
            # workers on this machine share its cores; a remote cluster's workers keep their defaults
            threads=None if scheduler else estimate_poses.threads_per_worker(jobs),
        )
    if max_pairs is not None and poses_path.name != "poses.parquet":
        return run_dir  # stopped early on purpose (resume tests)

    from batchpose import bop

    csv_path = bop.write_bop_csv(pd.read_parquet(poses_path), run_dir / "poses.csv")
    mcap_path = export_mcap.main(run_dir, poses_path, models, man.frames, source, overwrite=overwrite)
    if report:
        from batchpose import make_report

        make_report.main(run_dir, overwrite=True)
    log.info("done in %.1f s: %s, %s", time.perf_counter() - t_start, csv_path, mcap_path)
    return run_dir
