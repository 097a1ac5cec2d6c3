"""The main job: ingest -> template libraries -> estimate -> poses.csv / poses.mcap -> report.

Each stage is a module whose ``main`` returns the path it wrote; finished stages are skipped on a rerun.
"""

from __future__ import annotations

import contextlib
import fcntl
import importlib.metadata
import json
import logging
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from batchpose.config import apply_overrides, load_estimator_config, load_yaml, to_dict
from batchpose.core.frames import Camera, working_camera
from batchpose.errors import CameraError, ConfigError
from batchpose.io import library
from batchpose.io.files import write_text_atomic
from batchpose.io.manifest import load_manifest
from batchpose.io.mesh import load_mesh
from batchpose.stages import build_templates, export_mcap
from batchpose.stages import estimate as estimate_poses
from batchpose.stages import ingest as ingest_frames

log = logging.getLogger("batchpose")

_VERSIONED = (
    "batchpose",
    "numpy",
    "opencv-python-headless",
    "pyrender",
    "PyOpenGL",
    "trimesh",
    "mcap",
    "mcap-ros1-support",
    "mcap-ros2-support",
    "av",
    "pandas",
    "pyarrow",
    "joblib",
    "dask",
    "distributed",
    "scipy",
)


def versions() -> dict:
    out: dict[str, str | None] = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in _VERSIONED:
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = None
    return out


@contextlib.contextmanager
def _exclusive(run_dir: Path):
    """Hold an exclusive lock on the run directory itself (no file is added to it) for the block: a second
    ``batchpose run`` on the same ``--out`` stops at once instead of interleaving shards with this one."""
    fd = os.open(run_dir, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(
                f"--out {run_dir}: another batchpose run is writing there; wait for it to finish or use another --out"
            ) from None
        yield
    finally:
        os.close(fd)  # releases the lock


def _mesh_hash(path: Path) -> str:
    from batchpose.io.mesh import content_hash  # noqa: PLC0415

    try:
        return content_hash(path)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the mesh ({e.strerror or e})") from None


#: What ``--overwrite`` removes from an earlier run (the user's other files in the folder are left alone).
_RESULTS = ("ingest.json", "frames.parquet", "gt.parquet", "poses.parquet", "poses.csv", "poses.mcap", "objects.json")


def _clear_results(run_dir: Path) -> None:
    for p in sorted((run_dir / "shards").glob("shard-*.parquet")):
        p.unlink()
    for name in _RESULTS:
        (run_dir / name).unlink(missing_ok=True)


def _comparable(resolved: dict) -> dict:
    """A run's saved config without what may change between runs in one directory: the mesh hashes (checked
    on their own) and which of the data set's frames it uses (``frames:`` keys :data:`SELECT_KEYS`, like
    ``--limit``: ingest indexes the frames anew and the pairs already estimated are kept)."""
    from batchpose.io.sources import SELECT_KEYS  # noqa: PLC0415

    out = {**resolved, "meshes": None}
    manifest = out.get("manifest")
    if isinstance(manifest, dict) and isinstance(manifest.get("frames"), dict):
        frames = {k: v for k, v in manifest["frames"].items() if k not in SELECT_KEYS}
        out["manifest"] = {**manifest, "frames": frames}
    return out


def _previous_run(run_dir: Path) -> dict | None:
    """The config of the run in the directory ``run_dir`` (None when there is none yet); ConfigError when it
    has other files in it than a run's."""
    if not run_dir.exists():
        return None
    saved = run_dir / "config.yaml"
    if not saved.is_file():
        if any(run_dir.iterdir()):
            raise ConfigError(
                f"--out {run_dir}: is not empty and holds no batchpose run (no config.yaml); "
                "give a new or empty directory"
            )
        return None
    try:
        previous = yaml.safe_load(saved.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise ConfigError(
            f"{saved}: not a readable batchpose run config ({type(e).__name__}); use another --out"
        ) from None
    if not isinstance(previous, dict) or "pipeline" not in previous:
        raise ConfigError(f"{saved}: not a batchpose run config (no pipeline section); use another --out")
    return previous


def _check_annotated(gt: pd.DataFrame, objects: list[str], manifest: Path, limit: int | None) -> None:
    """``targets: annotations`` estimates the objects each frame's ground truth lists: none listed is an
    error (nothing would be estimated), some never listed a warning."""
    missing = [o for o in objects if o not in set(gt["obj_name"])]
    if not missing:
        return
    frames = f"the first {limit} frames" if limit is not None else "the data set"
    if len(missing) == len(objects):
        raise ConfigError(
            f"{manifest}: no ground truth in {frames} lists {', '.join(missing)}, so `targets: annotations` has "
            "nothing to estimate; use `targets: all` to look for the objects in every frame"
        )
    log.warning("no ground truth in %s lists %s: not estimated (targets: annotations)", frames, ", ".join(missing))


def _template_camera(frames_index: pd.DataFrame, manifest: Path, max_side_px: int) -> tuple[np.ndarray, int, int]:
    """K, width and height of the first frame with a usable calibration, at the size frames are estimated at
    (``max_image_side_px``): the templates are rendered with it; frames with a broken one fail on their own
    when estimated."""
    first_error = None
    for row in frames_index.itertuples():
        K = np.asarray(row.K, float).reshape(3, 3)
        try:
            cam = Camera(K, int(row.width), int(row.height)).validate(str(row.frame_id))
        except CameraError as e:
            first_error = first_error or e
            continue
        cam, _ = working_camera(cam, max_side_px)
        return cam.K, cam.width, cam.height
    raise CameraError(f"{manifest}: no frame has a usable camera calibration (first: {first_error})")


def _write_text_atomic(path: Path, text: str) -> None:
    write_text_atomic(path, text, encoding=None)


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
        except (OSError, ValueError) as e:  # ValueError: not an address
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
    overrides: Sequence[str] = (),
    jobs: int = 2,
    backend: str = "loky",
    scheduler: str | None = None,
    overwrite: bool = False,
    limit: int | None = None,
    max_pairs: int | None = None,
    report: bool = True,
) -> Path:
    """Run the whole pipeline; returns ``run_dir``."""
    from batchpose.io.sources import SelectedFrames, open_frames

    t_start = time.perf_counter()
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    if backend == "dask" and scheduler is None and jobs < 1:
        raise ConfigError("--backend dask needs --scheduler or --jobs >= 1 for a local cluster")
    conf_dict = apply_overrides(load_yaml(Path(pipeline)), list(overrides))
    conf = load_estimator_config(conf_dict, where=str(pipeline))
    conf_dict = to_dict(conf)
    if limit is not None and limit < 1:
        raise ConfigError(f"--limit must be >= 1, got {limit}")
    man = load_manifest(Path(manifest))
    run_dir = Path(run_dir)
    for flag, value in (("--out", run_dir), ("--cache", cache_dir)):
        try:
            str(value or "").encode("utf-8")
        except UnicodeEncodeError:
            raise ConfigError(f"{flag}: the path is not valid UTF-8 text; choose another") from None
    cache_dir = Path(cache_dir) if cache_dir else library.default_cache_dir()
    if cache_dir.exists() and not cache_dir.is_dir():
        raise ConfigError(f"--cache {cache_dir}: is a file, not a directory")

    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"--out {run_dir}: is a file, not a directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out {run_dir}: cannot write there ({e.strerror or e})") from None
    with _exclusive(run_dir):
        # A run directory belongs to one config and one manifest: refuse to mix results, and never write over
        # files that are not a run's.
        saved = run_dir / "config.yaml"
        # The meshes' contents belong to the run too: a changed mesh makes every pose of its object stale.
        meshes = {o.name: _mesh_hash(o.mesh) for o in man.objects}
        resolved = {"pipeline": conf_dict, "manifest": man.to_dict(), "meshes": meshes}
        previous = _previous_run(run_dir)
        if previous is not None and not overwrite:
            plain = json.loads(json.dumps(resolved))
            if _comparable(previous) != _comparable(plain):
                raise ConfigError(
                    f"{run_dir}: holds a run with a different config or manifest; use another --out or --overwrite"
                )
            changed = [n for n, h in meshes.items() if previous.get("meshes", meshes).get(n) != h]
            if changed:  # (a run directory of an earlier version has no mesh hashes: trusted)
                raise ConfigError(
                    f"{run_dir}: holds a run made with another version of the mesh of {', '.join(changed)}; "
                    "use another --out or --overwrite"
                )
        if overwrite and previous is not None:
            _clear_results(run_dir)  # before the new config is written: a killed rerun never mixes the two
        try:
            _write_text_atomic(saved, yaml.safe_dump(resolved, sort_keys=False))
            _write_text_atomic(run_dir / "versions.json", json.dumps(versions(), indent=2))
            _write_text_atomic(run_dir / "manifest.yaml", yaml.safe_dump(man.to_dict(), sort_keys=False))
        except OSError as e:
            raise ConfigError(f"--out {run_dir}: cannot write there ({e.strerror or e})") from None

        source = open_frames(man.frames, man.path.parent)
        log.info("data: %s", source.describe())
        objects = [o.name for o in man.objects]
        ingest_frames.main(source, objects, run_dir, overwrite=overwrite, limit=limit)

        frames_index = pd.read_parquet(run_dir / "frames.parquet")
        if frames_index.empty:
            if isinstance(source, SelectedFrames):
                sel = source.selection
                chosen = sel.describe()
                if source.span_s is not None and (sel.from_s is not None or sel.to_s is not None):
                    chosen += f"; its images span {source.span_s[0]:.3g}-{source.span_s[1]:.4g} s of the log"
                raise ConfigError(f"{man.path}: none of the data set's frames is chosen ({chosen})")
            raise ConfigError(f"{man.path}: the data set has no frames")
        if man.targets == "annotations":
            _check_annotated(pd.read_parquet(run_dir / "gt.parquet"), objects, man.path, limit)
        K0, width, height = _template_camera(frames_index, man.path, conf.max_image_side_px)
        models, lib_dirs, obj_ids = {}, {}, {}
        t0 = time.perf_counter()
        for spec in man.objects:
            models[spec.name] = load_mesh(spec.mesh, conf.mesh, name=spec.name, cache_dir=cache_dir)
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
                frame_ids=set(frames_index["frame_id"]),
                mesh_cache=cache_dir,
            )
        if max_pairs is not None and poses_path.name != "poses.parquet":
            return run_dir  # stopped early on purpose (resume tests)

        from batchpose.io import bop_csv as bop

        csv_path = bop.write_bop_csv(pd.read_parquet(poses_path), run_dir / "poses.csv")
        mcap_path = export_mcap.main(run_dir, poses_path, models, man.frames, source, overwrite=overwrite)
        if report:
            from batchpose.stages import report as report_stage

            report_stage.main(run_dir, overwrite=True)
        log.info("done in %.1f s: %s, %s", time.perf_counter() - t_start, csv_path, mcap_path)
        return run_dir
