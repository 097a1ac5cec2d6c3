"""Stage: estimate every (frame, object) pair in parallel, resumably.

Frames go to the workers in chunks of consecutive frames (``track.chunk_frames`` while tracking, fewer in a
short run so that it makes ``track.min_chunks`` chunks; a track runs within a chunk and never across two:
results do not depend on ``--jobs`` or the backend; RANSAC and the FLANN trees are seeded per frame). Each
worker loads the template libraries once and keeps its estimator for the whole run; each chunk starts a
fresh :class:`~batchpose.method.sequence.Sequence`. Progress is saved as
:mod:`batchpose.stages.checkpoints` describes, so a killed run resumes where it was, and the shards are
merged into ``run_dir/poses.parquet``.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
from collections import Counter
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import joblib
import pandas as pd
from tqdm import tqdm

from batchpose.config import EstimatorConfig, config_hash, load_estimator_config, to_dict
from batchpose.core.frames import Frame, FrameSource
from batchpose.core.poses import PoseRecord
from batchpose.io import library
from batchpose.io.files import write_parquet_atomic
from batchpose.io.mesh import load_mesh, quiet_mesh_warnings
from batchpose.method.estimator import PoseEstimator
from batchpose.method.sequence import Sequence, Stamp, is_next
from batchpose.method.templates import TemplateLibrary
from batchpose.stages import up_to_date
from batchpose.stages.checkpoints import ChunkFiles, Saver, chunk_key
from batchpose.stages.workers import limit_threads, loky_options, relax_loky_leak_check

log = logging.getLogger("batchpose")


@dataclass(frozen=True)
class EstimateInputs:
    """What the estimate stage reads besides the config.

    Attributes:
        source: the frames (:func:`batchpose.io.sources.open_frames`).
        lib_dirs: object name -> template library folder.
        obj_ids: object name -> data set id for the records.
        mesh_paths: object name -> mesh file (workers load it to render).
        targets_mode: "annotations" (the objects each frame's ground truth lists) or "all".
        limit: only the first ``limit`` frames.
        frame_ids: the frames this run covers (``frames.parquet``); shards of other frames (an earlier run
            with a larger ``--limit``) stay on disk but are left out of ``poses.parquet``.
        mesh_cache: the cache folder workers load meshes through (:func:`batchpose.io.mesh.load_mesh`).
        jobs: parallel workers.
        backend: joblib backend ("loky", or "dask" inside a ``dask.distributed`` client context).
        threads: OpenCV / renderer threads per worker (None: their defaults).
        chunk_size: frames per worker task when not tracking.
        retry_lib_dirs: object name -> its second library folder (``render.retry_shading``; empty: none).
    """

    source: FrameSource
    lib_dirs: dict[str, Path]
    obj_ids: dict[str, int]
    mesh_paths: dict[str, Path]
    targets_mode: str = "annotations"
    limit: int | None = None
    frame_ids: set[str] | None = None
    mesh_cache: Path | None = None
    jobs: int = 2
    backend: str = "loky"
    threads: int | None = None
    chunk_size: int = 2
    retry_lib_dirs: dict[str, Path] = field(default_factory=dict)


@dataclass(frozen=True)
class WorkerSetup:
    """What a worker needs to build its estimator (plain data: it is sent to each worker)."""

    conf_dict: dict
    lib_dirs: dict[str, str]
    obj_ids: dict[str, int]
    mesh_paths: dict[str, str]
    mesh_cache: str | None = None
    threads: int | None = None
    retry_lib_dirs: dict[str, str] = field(default_factory=dict)


@dataclass
class Chunk:
    """Consecutive frames one worker task estimates in order, and the pairs of them already saved."""

    chunk_id: str
    frames: list[Frame] = field(default_factory=list)
    targets: list[list[str]] = field(default_factory=list)
    done: set[tuple[str, str]] = field(default_factory=set)

    @property
    def key(self) -> str:
        return chunk_key([f.frame_id for f in self.frames], self.targets)


_WORKER: dict = {}


class LazyLibraries(Mapping[str, TemplateLibrary]):
    """Object name -> template library, loaded from its folder when first asked for: the second libraries
    (``render.retry_shading``), which most objects of most runs never need."""

    def __init__(self, dirs: dict[str, str]) -> None:
        self._dirs = dirs
        self._loaded: dict[str, TemplateLibrary] = {}

    def __getitem__(self, name: str) -> TemplateLibrary:
        if name not in self._loaded:
            self._loaded[name] = library.load(Path(self._dirs[name]))
        return self._loaded[name]

    def __contains__(self, name: object) -> bool:
        return name in self._dirs

    def __iter__(self) -> Iterator[str]:
        return iter(self._dirs)

    def __len__(self) -> int:
        return len(self._dirs)


def _estimator(setup: WorkerSetup) -> PoseEstimator:
    """The worker's estimator, built on first use and kept for the rest of the run."""
    key = config_hash(setup.conf_dict, setup.lib_dirs, setup.retry_lib_dirs, setup.mesh_paths, setup.obj_ids)
    if _WORKER.get("key") != key:
        conf = load_estimator_config(setup.conf_dict)
        libs = {name: library.load(Path(d)) for name, d in setup.lib_dirs.items()}
        retry_libs = LazyLibraries(setup.retry_lib_dirs)
        models, renderer = {}, None
        if conf.refine.enabled or conf.track.enabled:
            from batchpose.method.render import get_renderer  # noqa: PLC0415 - GL only where it renders

            cache = Path(setup.mesh_cache) if setup.mesh_cache else None
            quiet_mesh_warnings(setup.mesh_paths.values())  # the run warned about the meshes' units
            models = {
                name: load_mesh(Path(p), conf.mesh, name=name, cache_dir=cache) for name, p in setup.mesh_paths.items()
            }
            renderer = get_renderer()
        _WORKER["key"] = key
        _WORKER["estimator"] = PoseEstimator(conf, libs, setup.obj_ids, models, renderer, retry_libs)
        _WORKER["estimator"].warm_up()
    return _WORKER["estimator"]


def estimate_chunk(chunk: Chunk, setup: WorkerSetup, shard_dir: str | None) -> list[dict]:
    """Worker task: estimate the chunk's frames in order, from its saved state when a killed run left one;
    returns the ``poses.parquet`` rows of the pairs not saved before. ``shard_dir``: where to save progress
    (None: nowhere, e.g. a cluster's workers, which may not see the run directory)."""
    relax_loky_leak_check()
    limit_threads(setup.threads)
    est = _estimator(setup)
    files = ChunkFiles(Path(shard_dir), chunk.chunk_id) if shard_dir else None
    start, sequence = (files.load_state(chunk.key) if files else None) or (0, Sequence())
    saver, rows = Saver(files, chunk.key), []
    for i in range(start, len(chunk.frames)):
        frame = chunk.frames[i]
        new = [r.to_row() for r in est.estimate_frame(frame, chunk.targets[i], sequence)]
        new = [r for r in new if (frame.frame_id, r["obj_name"]) not in chunk.done]
        rows.extend(new)
        if i + 1 < len(chunk.frames):  # (a finished chunk's rows go back to the run, which saves them)
            saver.after_frame(new, i + 1, sequence)
    return rows


def done_pairs(shard_dir: Path) -> set[tuple[str, str]]:
    """(frame_id, obj_name) pairs already in saved shards (a chunk's, or a part of one)."""
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


def _targets(frame: Frame, objects: list[str], targets_mode: str) -> list[str]:
    if targets_mode == "all":
        return list(objects)
    listed = {p.obj_name for p in frame.gt}
    names = [o for o in objects if o in listed]
    if not names and frame.error is not None:
        return list(objects)  # unreadable annotations: each object gets a failed row with the reason
    return names


def _chunks(inputs: EstimateInputs, done: set, chunk_size: int, max_gap_s: float | None = None) -> Iterator[Chunk]:
    """The chunks with a pair not in ``done``. A chunk is the same frames whatever was done before (its id
    is its first frame's index), so a resumed run estimates what an uninterrupted one would. With
    ``max_gap_s`` (tracking), a chunk also ends where the sequence breaks (a frame that is not the next of
    the one before: :func:`~batchpose.method.sequence.is_next`), where the estimator starts afresh anyway:
    unrelated sequences go to different workers."""
    objects, chunk = list(inputs.lib_dirs), None
    for i, frame in enumerate(inputs.source):
        if inputs.limit is not None and i >= inputs.limit:
            break
        names = _targets(frame, objects, inputs.targets_mode)
        if not names:
            continue
        if chunk is not None and max_gap_s is not None and not is_next(Stamp.of(chunk.frames[-1]), frame, max_gap_s):
            if len(chunk.done) < sum(map(len, chunk.targets)):
                yield chunk
            chunk = None
        chunk = chunk or Chunk(f"c{i:06d}")
        chunk.frames.append(frame)
        chunk.targets.append(names)
        chunk.done.update((frame.frame_id, n) for n in names if (frame.frame_id, n) in done)
        if len(chunk.frames) == chunk_size:
            if len(chunk.done) < sum(map(len, chunk.targets)):
                yield chunk
            chunk = None
    if chunk is not None and len(chunk.done) < sum(map(len, chunk.targets)):
        yield chunk


def main(conf: EstimatorConfig, inputs: EstimateInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Estimate poses for all frames of ``inputs.source``; returns ``run_dir/poses.parquet``."""
    run_dir = Path(run_dir)
    out, shard_dir = run_dir / "poses.parquet", run_dir / "shards"
    if overwrite:
        clear(run_dir)
    shard_dir.mkdir(parents=True, exist_ok=True)
    for p in shard_dir.glob("*.tmp"):  # half-written file of a killed run: never trusted
        p.unlink()
    done = done_pairs(shard_dir)
    chunk_size = task_frames(conf, inputs)
    pending = _chunks(inputs, done, chunk_size, conf.track.max_gap_s if conf.track.enabled else None)
    first = next(pending, None)
    # (ingest removes poses.parquet whenever the frames it covers change)
    if up_to_date("estimation", out, overwrite, fresh=first is None, detail="every pair estimated"):
        return out
    if done:
        log.info("Resuming: %d (frame, object) pairs already estimated", len(done))
    t0 = time.perf_counter()
    new_pairs = _run_chunks(conf, inputs, shard_dir, itertools.chain([] if first is None else [first], pending))
    df = estimated_rows(run_dir, inputs.frame_ids)
    write_parquet_atomic(df, out)
    _log_counts(df, new_pairs, time.perf_counter() - t0)
    return out


def task_frames(conf: EstimatorConfig, inputs: EstimateInputs) -> int:
    """Frames per worker task: ``track.chunk_frames`` while tracking (``inputs.chunk_size`` otherwise), cut
    so that the run makes at least ``track.min_chunks`` tasks."""
    size = max(inputs.chunk_size, conf.track.chunk_frames) if conf.track.enabled else inputs.chunk_size
    return max(1, min(size, math.ceil(_n_frames(inputs) / conf.track.min_chunks)))


def _n_frames(inputs: EstimateInputs) -> int:
    return inputs.source.count() if inputs.limit is None else min(inputs.source.count(), inputs.limit)


def clear(run_dir: Path) -> None:
    """Remove every saved estimate of a run (``--overwrite``)."""
    shard_dir = Path(run_dir) / "shards"
    for pattern in ("shard-*.parquet", "chunk-*.state"):
        for p in shard_dir.glob(pattern):
            p.unlink()
    for p in (Path(run_dir) / "carry").glob("*.parquet"):  # the carry stage's, carried from these
        p.unlink()
    (Path(run_dir) / "poses.parquet").unlink(missing_ok=True)
    (Path(run_dir) / "carry.json").unlink(missing_ok=True)


def _run_chunks(conf: EstimatorConfig, inputs: EstimateInputs, shard_dir: Path, chunks: Iterator[Chunk]) -> int:
    """Estimate the chunks on the workers; each chunk's shard is written as soon as it is done. Returns the
    number of pairs estimated."""
    if inputs.targets_mode == "annotations" and conf.match.presence_votes:
        # The ground truth says each target is in its frame: no object is looked for that is not there.
        conf = dataclasses.replace(conf, match=dataclasses.replace(conf.match, presence_votes=0))
    setup = WorkerSetup(
        to_dict(conf),
        {k: str(v) for k, v in inputs.lib_dirs.items()},
        dict(inputs.obj_ids),
        {k: str(v) for k, v in inputs.mesh_paths.items()},
        str(inputs.mesh_cache) if inputs.mesh_cache else None,
        inputs.threads,
        {k: str(v) for k, v in inputs.retry_lib_dirs.items()},
    )
    # Workers on this machine save their progress; a cluster's may not see the run directory.
    saves = str(shard_dir) if inputs.backend == "loky" else None
    tasks = (joblib.delayed(_task)(chunk, setup, saves) for chunk in chunks)

    total = _n_frames(inputs)
    new_pairs = 0
    loky = loky_options() if inputs.backend == "loky" else {}
    n_jobs = inputs.jobs if inputs.backend == "loky" else -1
    with (
        tqdm(desc="estimate", unit="frame", total=total, leave=False, disable=None) as bar,
        joblib.parallel_config(backend=inputs.backend, n_jobs=n_jobs, **loky),
    ):
        # Unordered: each chunk's shard is written as soon as it is done, not held behind a slower one.
        parallel = joblib.Parallel(return_as="generator_unordered", pre_dispatch="2*n_jobs")
        for chunk_id, rows in parallel(tasks):
            ChunkFiles(shard_dir, chunk_id).finish(rows)
            new_pairs += len(rows)
            bar.update(len({r["frame_id"] for r in rows}))
    return new_pairs


def _task(chunk: Chunk, setup: WorkerSetup, shard_dir: str | None) -> tuple[str, list[dict]]:
    return chunk.chunk_id, estimate_chunk(chunk, setup, shard_dir)


def _log_counts(df: pd.DataFrame, new_pairs: int, seconds: float) -> None:
    counts = Counter(df["status"])
    ok = counts.pop("ok", 0)
    others = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    log.info(
        "estimated %d / %d (frame, object) pairs ok%s; %d new in %.1f s",
        ok,
        len(df),
        f", {others}" if others else "",
        new_pairs,
        seconds,
    )


def estimated_rows(run_dir: Path, frame_ids: set[str] | None = None) -> pd.DataFrame:
    """The estimate's rows of the frames ``frame_ids`` (None: all saved), as this stage writes them to
    ``poses.parquet`` (the carry stage rewrites that file and reads the estimate's rows from here)."""
    df = merge_shards(Path(run_dir) / "shards")
    if frame_ids is not None:
        df = df[df["frame_id"].isin(frame_ids)].reset_index(drop=True)
    return df


def merge_shards(shard_dir: Path) -> pd.DataFrame:
    """All shard rows, one per (frame, object), in a deterministic order."""
    parts = [pd.read_parquet(p) for p in sorted(Path(shard_dir).glob("shard-*.parquet"))]
    if not parts:
        return pd.DataFrame(columns=list(PoseRecord("", "", "ok").to_row()))
    df = pd.concat(parts, ignore_index=True)
    df = df.drop_duplicates(subset=["frame_id", "obj_name"], keep="last")
    return df.sort_values(["scene_id", "im_id", "frame_id", "obj_name"], kind="stable").reset_index(drop=True)
