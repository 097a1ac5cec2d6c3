"""A run directory and what belongs to it: claimed for one config, manifest and set of meshes, locked while
a run writes it, cleared by ``--overwrite`` (and never any file that is not a run's).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import importlib.metadata
import json
import logging
import os
import platform
from pathlib import Path

import yaml

from batchpose.config import EstimatorConfig, apply_overrides, load_estimator_config, load_yaml, to_dict
from batchpose.errors import ConfigError
from batchpose.io import library
from batchpose.io.files import write_text_atomic
from batchpose.io.manifest import Manifest, load_manifest
from batchpose.stages import estimate

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
def exclusive(run_dir: Path):
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
_RESULTS = (
    "ingest.json",
    "frames.parquet",
    "gt.parquet",
    "poses.parquet",
    "poses.csv",
    "trajectory.csv",
    "poses.mcap",
    "foxglove_layout.json",
    "objects.json",
)


def _clear_results(run_dir: Path) -> None:
    estimate.clear(run_dir)
    for name in _RESULTS:
        (run_dir / name).unlink(missing_ok=True)
    for tum in (run_dir / "tum").glob("*.txt"):
        tum.unlink()


def _estimated_nothing(run_dir: Path) -> bool:
    """True when the run in ``run_dir`` has no estimate yet: no shard, checkpoint or merged poses."""
    shards = run_dir / "shards"
    saved = (p for pattern in ("shard-*.parquet", "chunk-*.state") for p in shards.glob(pattern))
    return not (run_dir / "poses.parquet").exists() and next(saved, None) is None


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


@dataclasses.dataclass(frozen=True)
class Job:
    """A run's resolved inputs, checked before anything is written."""

    conf: EstimatorConfig
    conf_dict: dict
    manifest: Manifest
    run_dir: Path
    cache_dir: Path
    limit: int | None


def prepare(
    pipeline: Path, manifest: Path, run_dir: Path, cache_dir: Path | None, overrides: list[str], limit: int | None
) -> Job:
    """Load and check the pipeline (with ``--set`` overrides), the manifest and the paths; writes nothing."""
    conf_dict = apply_overrides(load_yaml(Path(pipeline)), list(overrides))
    where = str(pipeline) + (f" with --set {' '.join(overrides)}" if overrides else "")
    conf = load_estimator_config(conf_dict, where=where)
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
    return Job(conf, to_dict(conf), man, run_dir, cache_dir, limit)


def claim(job: Job, overwrite: bool) -> None:
    """Make ``job.run_dir`` this run's: refuse a folder of other files or of a run with another config,
    manifest or mesh (results are never mixed), clear it with ``overwrite``, and write the resolved config,
    the versions and the manifest into it."""
    run_dir, man = job.run_dir, job.manifest
    saved = run_dir / "config.yaml"
    # The meshes' contents belong to the run too: a changed mesh makes every pose of its object stale.
    meshes = {o.name: _mesh_hash(o.mesh) for o in man.objects}
    resolved = {"pipeline": job.conf_dict, "manifest": man.to_dict(), "meshes": meshes}
    previous = _previous_run(run_dir)
    if previous is not None and not overwrite:
        plain = json.loads(json.dumps(resolved))
        if _comparable(previous) != _comparable(plain) and _estimated_nothing(run_dir):
            # a run that failed before estimating (a wrong manifest, no ground truth) does not lock its folder
            log.info("%s: replacing an earlier run of another config or manifest that estimated nothing", run_dir)
            _clear_results(run_dir)
        elif _comparable(previous) != _comparable(plain):
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
        write_text_atomic(saved, yaml.safe_dump(resolved, sort_keys=False), encoding=None)
        write_text_atomic(run_dir / "versions.json", json.dumps(versions(), indent=2), encoding=None)
        write_text_atomic(run_dir / "manifest.yaml", yaml.safe_dump(man.to_dict(), sort_keys=False), encoding=None)
    except OSError as e:
        raise ConfigError(f"--out {run_dir}: cannot write there ({e.strerror or e})") from None
