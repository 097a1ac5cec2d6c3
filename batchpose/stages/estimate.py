"""Stage: estimate every (frame, object) pair in parallel, in resumable shards.

Results go to ``run_dir/shards/shard-*.parquet`` (each written atomically as soon as its frames are done),
then are merged into ``run_dir/poses.parquet``. A rerun reads the shards, skips every finished pair and
computes only the rest. Each worker process loads the template libraries once and keeps its estimator
for the whole run. Results do not depend on the number of workers or the backend: RANSAC and the FLANN
trees are seeded per frame.
"""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from pathlib import Path

import joblib
import pandas as pd
from tqdm import tqdm

from batchpose.config import EstimatorConfig, config_hash, load_estimator_config
from batchpose.core.frames import Frame
from batchpose.io import library
from batchpose.io.files import write_parquet_atomic
from batchpose.io.mesh import load_mesh
from batchpose.method.estimator import PoseEstimator
from batchpose.method.sequence import Sequence
from batchpose.stages.workers import loky_options

log = logging.getLogger("batchpose")

_WORKER: dict = {}


def _estimator(
    conf_dict: dict,
    lib_dirs: dict[str, str],
    obj_ids: dict[str, int],
    mesh_paths: dict[str, str],
    mesh_cache: str | None = None,
) -> PoseEstimator:
    """The worker's estimator, built on first use and kept for the rest of the run (``mesh_cache``: the
    cache folder :func:`batchpose.io.mesh.load_mesh` keeps loaded meshes in, or None)."""
    key = config_hash(conf_dict, lib_dirs, mesh_paths)
    if _WORKER.get("key") != key:
        conf = load_estimator_config(conf_dict)
        libs = {name: library.load(Path(d)) for name, d in lib_dirs.items()}
        models, renderer = {}, None
        if conf.refine.enabled or conf.track.enabled:
            from batchpose.method.render import get_renderer

            cache = Path(mesh_cache) if mesh_cache else None
            models = {name: load_mesh(Path(p), conf.mesh, name=name, cache_dir=cache) for name, p in mesh_paths.items()}
            renderer = get_renderer()
        _WORKER["key"] = key
        _WORKER["estimator"] = PoseEstimator(conf, libs, obj_ids, models=models, renderer=renderer)
        _WORKER["estimator"].warm_up()
    return _WORKER["estimator"]


def _relax_loky_leak_check() -> None:
    """Raise loky's per-worker memory-growth limit (300 MB) to 1.5 GB, our RSS budget per worker.

    Loading the meshes and GL textures after loky's first measurement looks like a leak to it and gets
    the worker restarted (and its libraries reloaded); the renderer bounds its own growth.
    """
    try:
        from joblib.externals.loky import process_executor  # noqa: PLC0415
    except ImportError:  # pragma: no cover
        return
    process_executor._MAX_MEMORY_LEAK_SIZE = max(process_executor._MAX_MEMORY_LEAK_SIZE, int(1.5e9))


def limit_threads(threads: int | None) -> None:
    """Let this worker's OpenCV and software renderer use ``threads`` threads (None: their defaults).

    Both start one thread per core in every process, so two workers on two cores would run four of each
    and fight over the cores; joblib caps only OpenMP/BLAS pools, and OpenCV's wheels use pthreads.
    ``LP_NUM_THREADS`` (llvmpipe) is read when a GL context is made, so it is set before the first render.
    """
    if threads is None or _WORKER.get("threads") == threads:
        return
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(threads)
    os.environ["LP_NUM_THREADS"] = str(threads)
    _WORKER["threads"] = threads


def threads_per_worker(jobs: int) -> int | None:
    """Threads each of ``jobs`` workers on this machine gets (None for one worker: use every core)."""
    if jobs <= 1:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // jobs)


def estimate_chunk(
    frames: list[Frame],
    targets: list[list[str]],
    conf_dict: dict,
    lib_dirs: dict[str, str],
    obj_ids: dict[str, int],
    mesh_paths: dict[str, str],
    threads: int | None = None,
    mesh_cache: str | None = None,
) -> list[dict]:
    """Worker task: estimate the given objects in each frame; returns ``poses.parquet`` rows."""
    _relax_loky_leak_check()
    limit_threads(threads)
    est = _estimator(conf_dict, lib_dirs, obj_ids, mesh_paths, mesh_cache)
    seq = Sequence()  # a track never crosses tasks: results do not depend on how tasks meet workers
    rows = []
    for frame, names in zip(frames, targets, strict=False):
        rows.extend(r.to_row() for r in est.estimate_frame(frame, names, seq))
    return rows


def done_pairs(shard_dir: Path) -> set[tuple[str, str]]:
    """(frame_id, obj_name) pairs already in complete shards."""
    done: set[tuple[str, str]] = set()
    for p in sorted(shard_dir.glob("shard-*.parquet")):
        try:
            df = pd.read_parquet(p, columns=["frame_id", "obj_name"])
        except (OSError, ValueError) as e:  # pyarrow's errors derive from these; never a killed run's (atomic)
            log.warning("%s: unreadable shard (%s); removed, its pairs are estimated again", p, e)
            p.unlink()
            continue
        done.update(zip(df["frame_id"], df["obj_name"], strict=False))
    return done


def _chunks(source, objects: list[str], targets_mode: str, done: set, chunk_size: int, limit: int | None):
    chunk_f, chunk_t = [], []
    for i, frame in enumerate(source):
        if limit is not None and i >= limit:
            break
        if targets_mode == "all":
            names = list(objects)
        else:
            listed = {p.obj_name for p in frame.gt}
            names = [o for o in objects if o in listed]
            if not names and frame.error is not None:
                names = list(objects)  # unreadable annotations: each object gets a failed row with the reason
        names = [n for n in names if (frame.frame_id, n) not in done]
        if not names:
            continue
        chunk_f.append(frame)
        chunk_t.append(names)
        if len(chunk_f) == chunk_size:
            yield chunk_f, chunk_t
            chunk_f, chunk_t = [], []
    if chunk_f:
        yield chunk_f, chunk_t


def main(
    source,
    conf: EstimatorConfig,
    conf_dict: dict,
    lib_dirs: dict[str, Path],
    obj_ids: dict[str, int],
    mesh_paths: dict[str, Path],
    targets_mode: str,
    run_dir: Path,
    jobs: int = 2,
    backend: str = "loky",
    overwrite: bool = False,
    limit: int | None = None,
    chunk_size: int = 2,
    max_pairs: int | None = None,
    threads: int | None = None,
    frame_ids: set[str] | None = None,
    mesh_cache: Path | None = None,
) -> Path:
    """Estimate poses for all frames of ``source``; returns ``run_dir/poses.parquet``.

    Args:
        conf_dict: the pipeline config as a plain dict (sent to workers).
        lib_dirs: object name -> template library folder.
        mesh_paths: object name -> mesh file (workers load it to render for refinement).
        targets_mode: "annotations" or "all" (see :mod:`batchpose.io.manifest`).
        backend: joblib backend ("loky", or "dask" inside a ``dask.distributed`` client context).
        max_pairs: stop after about this many newly estimated pairs (used to test resuming).
        threads: OpenCV / renderer threads per worker (see :func:`limit_threads`; None: their defaults).
        frame_ids: the frames this run covers (``frames.parquet``); shards of other frames (an earlier
            run with a larger ``--limit``) stay on disk but are left out of ``poses.parquet``.
        mesh_cache: the cache folder workers load meshes through (:func:`batchpose.io.mesh.load_mesh`).
    """
    run_dir = Path(run_dir)
    out = run_dir / "poses.parquet"
    shard_dir = run_dir / "shards"
    if overwrite:
        for p in shard_dir.glob("shard-*.parquet"):
            p.unlink()
        out.unlink(missing_ok=True)
    shard_dir.mkdir(parents=True, exist_ok=True)
    for p in shard_dir.glob("*.tmp"):  # half-written shard of a killed run: never trusted
        p.unlink()
    done = done_pairs(shard_dir)
    # (ingest removes poses.parquet whenever the frames it covers change)
    if out.is_file() and not overwrite and not _pending(source, targets_mode, done, limit, lib_dirs):
        log.info("Skipping estimation: %s is complete", out)
        return out
    if done:
        log.info("Resuming: %d (frame, object) pairs already estimated", len(done))
    objects = list(lib_dirs)
    lib_strs = {k: str(v) for k, v in lib_dirs.items()}
    mesh_strs = {k: str(v) for k, v in mesh_paths.items()}
    cache = str(mesh_cache) if mesh_cache else None
    if conf.track.enabled:
        chunk_size = max(chunk_size, conf.track.chunk_frames)
    n_shards = len(list(shard_dir.glob("shard-*.parquet")))
    total = source.count() if limit is None else min(source.count(), limit)
    t0 = time.perf_counter()
    new_pairs = 0
    tasks = (
        joblib.delayed(estimate_chunk)(f, t, conf_dict, lib_strs, obj_ids, mesh_strs, threads, cache)
        for f, t in _chunks(source, objects, targets_mode, done, chunk_size, limit)
    )
    bar = tqdm(desc="estimate", unit="frame", total=total, initial=0, leave=False, disable=None)
    try:
        loky = loky_options() if backend == "loky" else {}
        with joblib.parallel_config(backend=backend, n_jobs=jobs if backend == "loky" else -1, **loky):
            # Unordered: each task's shard is written as soon as it is done, not held behind a slower task
            # dispatched earlier (a killed run keeps it; merge_shards orders the rows).
            parallel = joblib.Parallel(return_as="generator_unordered", pre_dispatch="2*n_jobs")
            for rows in parallel(tasks):
                if rows:
                    shard = shard_dir / f"shard-{n_shards:06d}.parquet"
                    write_parquet_atomic(pd.DataFrame(rows), shard)
                    n_shards += 1
                    new_pairs += len(rows)
                    bar.update(len({r["frame_id"] for r in rows}))
                if max_pairs is not None and new_pairs >= max_pairs:
                    log.info("Stopping after %d pairs (max_pairs)", new_pairs)
                    return shard_dir
    finally:
        bar.close()
    df = merge_shards(shard_dir)
    if frame_ids is not None:
        df = df[df["frame_id"].isin(frame_ids)].reset_index(drop=True)
    write_parquet_atomic(df, out)
    counts = Counter(df["status"])
    ok = counts.pop("ok", 0)
    others = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    log.info(
        "estimated %d / %d (frame, object) pairs ok%s; %d new in %.1f s",
        ok,
        len(df),
        f", {others}" if others else "",
        new_pairs,
        time.perf_counter() - t0,
    )
    return out


def _pending(source, targets_mode, done, limit, lib_dirs) -> bool:
    """True when some (frame, object) pair of the source is not in ``done``."""
    for _ in _chunks(source, list(lib_dirs), targets_mode, done, 1, limit):
        return True
    return False


def merge_shards(shard_dir: Path) -> pd.DataFrame:
    """All shard rows, one per (frame, object), in a deterministic order."""
    parts = [pd.read_parquet(p) for p in sorted(Path(shard_dir).glob("shard-*.parquet"))]
    if not parts:
        from batchpose.core.poses import PoseRecord

        return pd.DataFrame(columns=list(PoseRecord("", "", "ok").to_row()))
    df = pd.concat(parts, ignore_index=True)
    df = df.drop_duplicates(subset=["frame_id", "obj_name"], keep="last")
    return df.sort_values(["scene_id", "im_id", "frame_id", "obj_name"], kind="stable").reset_index(drop=True)
