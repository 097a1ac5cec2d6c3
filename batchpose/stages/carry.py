"""Stage: carry confident poses forwards and backwards through each sequence of frames (``carry.*``).

The estimate stage tracks forwards only, and within a worker task only. Here the whole run's estimates are
read at once: the frames are cut into sequences (each frame the next of the one before,
:func:`~batchpose.method.sequence.is_next`), and for each object every *gap* (a run of consecutive frames
whose pairs have a status it may be carried into: :func:`carry_statuses`) is closed from both ends: from the
confident ok pose just before it, forwards, and from the one just after it, backwards through the frames the
forward carry did not reach, each at most ``carry.max_steps`` frames (:func:`batchpose.method.carry.carry`).
A carried pose replaces the pair's row in ``poses.parquet``, marked ``carried`` (and ``tracked``), its
reason naming the frame it came from and what the estimate had said.

The log is read twice, and never held: once for where its sequences break, once for the frames of the gaps,
each group's frames handed to a worker as soon as they are read. Resumable item by item: gaps go to the
workers in groups of :data:`GROUP_GAPS` (in the order of the log); each group's carried rows
are written (atomically) to ``carry/<key>.parquet`` as soon as it is done, ``key`` hashing the group's gaps
(their frames, the poses they start from, the other objects' poses, the config). A rerun skips the groups
already written; ``carry.json`` records which estimates ``poses.parquet`` was carried from, so a finished
stage is skipped as a whole.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import joblib
import numpy as np
import pandas as pd
from tqdm import tqdm

from batchpose.config import EstimatorConfig, config_hash, load_estimator_config, to_dict
from batchpose.core.frames import Frame, FrameSource
from batchpose.core.poses import PoseRecord, row_cam_from_model
from batchpose.errors import BatchposeError
from batchpose.io.files import write_json_atomic, write_parquet_atomic
from batchpose.io.mesh import load_mesh, quiet_mesh_warnings
from batchpose.method.carry import View, carry, view_of
from batchpose.method.objects import Objects
from batchpose.method.records import NOT_FOUND
from batchpose.method.sequence import Stamp, is_next
from batchpose.stages import up_to_date
from batchpose.stages.estimate import estimated_rows
from batchpose.stages.workers import limit_threads, loky_options, relax_loky_leak_check

log = logging.getLogger("batchpose")

#: Gaps per worker task (and per ``carry/<key>.parquet``).
GROUP_GAPS = 4
#: Bumped when what a group's file holds changes: files of another format are not reused.
CARRY_FORMAT = 1


@dataclass(frozen=True)
class CarryInputs:
    """What the carry stage reads besides the config and the estimates.

    Attributes:
        source: the frames (:func:`batchpose.io.sources.open_frames`).
        obj_ids: object name -> data set id for the records.
        mesh_paths: object name -> mesh file (workers load it to render).
        limit: only the first ``limit`` frames.
        frame_ids: the frames this run covers (``frames.parquet``).
        mesh_cache: the cache folder workers load meshes through.
        jobs: parallel workers; backend: joblib backend ("loky" or "dask").
        threads: OpenCV / renderer threads per worker (None: their defaults).
    """

    source: FrameSource
    obj_ids: dict[str, int]
    mesh_paths: dict[str, Path]
    limit: int | None = None
    frame_ids: set[str] | None = None
    mesh_cache: Path | None = None
    jobs: int = 2
    backend: str = "loky"
    threads: int | None = None


@dataclass(frozen=True)
class Start:
    """Where a carry starts: the confident pose's frame, its (4, 4) cam_from_model and confidence."""

    frame_id: str
    cam_from_model: np.ndarray
    confidence: float


@dataclass
class Gap:
    """One object's run of consecutive frames without a pose, and what closes it from either end.

    Attributes:
        obj_name: the object.
        forward: frame ids: the frame of the confident pose before the gap, then the gap's first
            ``max_steps`` frames (empty: no confident pose before it).
        backward: the frame of the confident pose after it, then the gap's last ``max_steps`` frames, last
            first.
        starts: the poses the carries start from (forward's, then backward's).
        was: frame_id -> "status: reason" of the pair the estimate made there.
        weak: frame_id -> the verification score of the estimate's weak ok pose there (``carry.over_weak``):
            a carried pose replaces it only when it scores higher.
        others: frame_id -> obj_name -> (4, 4) the other objects' ok poses in the gap's frames and its ends.
    """

    obj_name: str
    forward: list[str] = field(default_factory=list)
    backward: list[str] = field(default_factory=list)
    starts: list[Start] = field(default_factory=list)
    was: dict[str, str] = field(default_factory=dict)
    weak: dict[str, float] = field(default_factory=dict)
    others: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def key(self) -> str:
        """The gap's content, hashed: its frames, starts and the other poses its carries see."""
        blob = {
            "obj": self.obj_name,
            "f": self.forward,
            "b": self.backward,
            "s": [(s.frame_id, np.round(s.cam_from_model, 9).tolist(), round(s.confidence, 9)) for s in self.starts],
            "o": {k: {n: np.round(T, 9).tolist() for n, T in v.items()} for k, v in self.others.items()},
            "w": {k: round(v, 9) for k, v in self.weak.items()},
        }
        return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]

    def frames(self) -> set[str]:
        """The ids of every frame its carries read."""
        return {*self.forward, *self.backward}


def carry_statuses(conf: EstimatorConfig) -> tuple[str, ...]:
    """The statuses a pose is carried into: an object looked for and not found (``NOT_FOUND``), one tracking
    left ``hidden``, and ``absent`` with ``carry.into_absent``."""
    return (*NOT_FOUND, "hidden", *(("absent",) if conf.carry.into_absent else ()))


def weak_score(conf: EstimatorConfig, row: dict) -> float | None:
    """``carry.over_weak``: the verification score of the row's pose when it is a weak ok one (untracked, under
    ``carry.min_confidence``, scored); None otherwise."""
    if not conf.carry.over_weak or conf.min_verification <= 0 or row["status"] != "ok":
        return None
    if bool(row.get("tracked")) or bool(row.get("carried")) or float(row["confidence"]) >= conf.carry.min_confidence:
        return None
    v = float(row.get("verification", np.nan))
    return v if np.isfinite(v) else None


def sequences(frames: Iterable[Frame], max_gap_s: float) -> list[list[str]]:
    """The frames' ids, cut where a frame is not the next of the one before (:func:`is_next`)."""
    out: list[list[str]] = []
    last = None
    for frame in frames:
        if last is not None and is_next(last, frame, max_gap_s):
            out[-1].append(frame.frame_id)
        else:
            out.append([frame.frame_id])
        last = Stamp.of(frame)
    return out


def plan(conf: EstimatorConfig, estimated: pd.DataFrame, seqs: list[list[str]]) -> list[Gap]:
    """Every gap (see :class:`Gap`: pairs without a pose, or with a weak one, :func:`weak_score`) of every object
    in the sequences ``seqs`` (:func:`sequences`) with a confident ok pose (``carry.min_confidence``) at either
    end, from the estimate's rows; in the order of their last frame in the log."""
    cc, into = conf.carry, set(carry_statuses(conf))
    rows = {(r["frame_id"], r["obj_name"]): r for r in estimated.to_dict("records")}
    ok_poses: dict[str, dict[str, np.ndarray]] = {}
    for (fid, name), r in rows.items():
        pose = row_cam_from_model(r) if r["status"] == "ok" else None
        if pose is not None:
            ok_poses.setdefault(fid, {})[name] = pose

    def opens(r: dict | None) -> bool:
        return r is not None and (r["status"] in into or weak_score(conf, r) is not None)

    def confident(fid: str, name: str) -> Start | None:
        pose = ok_poses.get(fid, {}).get(name)
        r = rows.get((fid, name))
        if pose is None or r is None or float(r["confidence"]) < cc.min_confidence:
            return None
        return Start(fid, pose, float(r["confidence"]))

    gaps = []
    for name in sorted(estimated["obj_name"].unique()):
        for seq in seqs:
            i = 0
            while i < len(seq):
                if not opens(rows.get((seq[i], name))):
                    i += 1
                    continue
                j = i
                while j + 1 < len(seq) and opens(rows.get((seq[j + 1], name))):
                    j += 1
                gap = _gap(name, seq, i, j, confident, cc.max_steps)
                if gap is not None:
                    gap.was = {f: _was(rows[(f, name)]) for f in seq[i : j + 1]}
                    scores = {f: weak_score(conf, rows[(f, name)]) for f in seq[i : j + 1]}
                    gap.weak = {f: v for f, v in scores.items() if v is not None}
                    ends = sorted({*gap.forward, *gap.backward})
                    gap.others = {k: {n: T for n, T in ok_poses.get(k, {}).items() if n != name} for k in ends}
                    gaps.append(gap)
                i = j + 1
    at = {f: k for k, f in enumerate(f for seq in seqs for f in seq)}
    return sorted(gaps, key=lambda g: max(at[f] for f in g.frames()))


def _gap(name: str, seq: list[str], i: int, j: int, confident, max_steps: int) -> Gap | None:
    """The gap ``seq[i..j]`` of ``name`` with its carries' frames and starts; None when neither end has a
    confident pose."""
    gap = Gap(name)
    before = confident(seq[i - 1], name) if i > 0 else None
    after = confident(seq[j + 1], name) if j + 1 < len(seq) else None
    if before is not None:
        gap.forward = seq[i - 1 : min(j, i + max_steps - 1) + 1]
        gap.starts.append(before)
    if after is not None:
        gap.backward = seq[max(i, j - max_steps + 1) : j + 2][::-1]
        gap.starts.append(after)
    return gap if gap.starts else None


def _was(row: dict) -> str:
    was = f"{row['status']}: {row['reason']}" if row["reason"] else str(row["status"])
    v = float(row.get("verification", np.nan))
    return f"{was} (confidence {float(row['confidence']):.2f}, verification {v:.2f})" if row["status"] == "ok" else was


@dataclass(frozen=True)
class CarrySetup:
    """What a worker needs to render the objects (plain data: it is sent to each worker)."""

    conf_dict: dict
    obj_ids: dict[str, int]
    mesh_paths: dict[str, str]
    mesh_cache: str | None = None
    threads: int | None = None


_WORKER: dict = {}


def _objects(setup: CarrySetup) -> Objects:
    """The worker's objects (meshes and renderer; no libraries: nothing is matched), made on first use."""
    key = config_hash(setup.conf_dict, setup.mesh_paths, setup.obj_ids)
    if _WORKER.get("key") != key:
        from batchpose.method.render import get_renderer  # noqa: PLC0415 - GL only where it renders

        conf = load_estimator_config(setup.conf_dict)
        cache = Path(setup.mesh_cache) if setup.mesh_cache else None
        quiet_mesh_warnings(setup.mesh_paths.values())  # the run warned about the meshes' units
        models = {n: load_mesh(Path(p), conf.mesh, name=n, cache_dir=cache) for n, p in setup.mesh_paths.items()}
        _WORKER["key"], _WORKER["objects"] = key, Objects(conf, {}, setup.obj_ids, models, get_renderer())
    return _WORKER["objects"]


def carry_gaps(objects: Objects, gaps: list[Gap], frames: Mapping[str, Frame]) -> list[dict]:
    """Close each gap from its ends (forwards, then backwards through the frames the forward carry did not
    reach): the ``poses.parquet`` rows of the carried poses (timings: the carry's only). ``frames``: frame
    id -> frame, for every frame of the gaps (:meth:`Gap.frames`)."""
    cc, views = objects.conf.carry, _Views(objects, frames)
    rows: list[dict] = []
    for gap in gaps:
        reached: set[str] = set()
        starts = iter(gap.starts)
        for direction, ids in (("forwards", gap.forward), ("backwards", gap.backward)):
            if not ids:
                continue
            start = next(starts)
            ids = ids[: next((k for k, f in enumerate(ids) if k and f in reached), len(ids))]
            seen = views.get(ids, gap.others)
            if seen is None or len(seen) < 2:
                continue
            pose = PoseRecord(start.frame_id, gap.obj_name, "ok", cam_from_model=start.cam_from_model,
                              confidence=start.confidence)  # fmt: skip
            found = carry(objects, gap.obj_name, seen, pose, cc.max_steps, scored=frozenset(gap.weak))
            for k, rec in enumerate(found.records, 1):
                reached.add(rec.frame_id)
                if rec.frame_id in gap.weak and not rec.verification > gap.weak[rec.frame_id]:
                    continue  # the estimate's weak pose looks at least as much like the frame: it stays
                rec.reason = (
                    f"carried {direction} from {start.frame_id} ({k} frame{'s' if k > 1 else ''}); "
                    f"the estimate: {gap.was[rec.frame_id]}"
                )
                rows.append(rec.to_row())
            if found.stopped:
                log.debug("%s %s %s: %s", gap.obj_name, direction, start.frame_id, found.stopped)
    return rows


class _Views:
    """Decoded frames (:func:`view_of`) of a worker task, kept while its gaps are carried (gaps of one task
    share frames)."""

    def __init__(self, objects: Objects, frames: Mapping[str, Frame]) -> None:
        self.objects, self.frames = objects, frames
        self.cache: dict[str, View | None] = {}

    def get(self, ids: list[str], others: dict[str, dict[str, np.ndarray]]) -> list[View] | None:
        """The frames' views with ``others``' poses, up to the first frame that cannot be decoded; None
        when the first cannot."""
        out = []
        for i in ids:
            if i not in self.cache:
                try:
                    self.cache[i] = view_of(self.frames[i], {}, self.objects.conf.max_image_side_px)
                except BatchposeError as e:
                    log.debug("%s: not carried into (%s)", i, e)
                    self.cache[i] = None
            view = self.cache[i]
            if view is None:
                break
            out.append(dataclasses.replace(view, others=others.get(i, {})))
        return out or None


def _task(key: str, gaps: list[Gap], frames: dict[str, Frame], setup: CarrySetup) -> tuple[str, list[dict]]:
    relax_loky_leak_check()
    limit_threads(setup.threads)
    return key, carry_gaps(_objects(setup), gaps, frames)


def _groups(gaps: list[Gap], conf_key: str) -> list[tuple[str, list[Gap]]]:
    """The gaps in groups of :data:`GROUP_GAPS` (in their order), each with its key."""
    out = []
    for k in range(0, len(gaps), GROUP_GAPS):
        group = gaps[k : k + GROUP_GAPS]
        blob = json.dumps([CARRY_FORMAT, conf_key, [g.key() for g in group]])
        out.append((hashlib.sha256(blob.encode()).hexdigest()[:16], group))
    return out


def _done_key(done_file: Path) -> str | None:
    """The key ``carry.json`` records (None: no readable one; the stage then runs)."""
    try:
        return json.loads(done_file.read_text(encoding="utf-8")).get("key")
    except (OSError, ValueError, AttributeError):
        return None


def _estimates_key(conf: EstimatorConfig, estimated: pd.DataFrame) -> str:
    """What ``poses.parquet`` is carried from: the config and the estimate's rows, hashed."""
    cols = ["frame_id", "obj_name", "status", "confidence"]
    rows = pd.util.hash_pandas_object(estimated[cols], index=False).to_numpy()
    poses = np.asarray([np.r_[r, t] for r, t in zip(estimated["R"], estimated["t_m"], strict=True)], float)
    h = hashlib.sha256(rows.tobytes() + np.round(np.nan_to_num(poses), 9).tobytes())
    return config_hash(to_dict(conf), h.hexdigest())


def main(conf: EstimatorConfig, inputs: CarryInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Carry confident poses into the pairs next to them that have none; rewrites ``run_dir/poses.parquet``
    (the estimate stage's rows with the carried ones in place of theirs) and returns it."""
    run_dir = Path(run_dir)
    out, folder, done_file = run_dir / "poses.parquet", run_dir / "carry", run_dir / "carry.json"
    if not conf.carry.enabled:
        return out
    estimated = estimated_rows(run_dir, inputs.frame_ids)
    key = _estimates_key(conf, estimated)
    fresh = _done_key(done_file) == key
    if up_to_date("carry", done_file, overwrite, fresh=fresh, detail="every gap carried"):
        return out
    t0 = time.perf_counter()
    gaps = plan(conf, estimated, sequences(_frames(inputs), conf.track.max_gap_s))
    groups = _groups(gaps, config_hash(to_dict(conf)))
    folder.mkdir(exist_ok=True)
    if overwrite:
        for p in folder.glob("*.parquet"):
            p.unlink()
    for p in folder.glob("*.tmp"):  # half-written file of a killed run: never trusted
        p.unlink()
    pending = [(k, g) for k, g in groups if not (folder / f"{k}.parquet").is_file()]
    if len(pending) < len(groups):
        log.info("Resuming carry: %d of %d groups of gaps already carried", len(groups) - len(pending), len(groups))
    _run(conf, inputs, folder, pending)
    missing = [k for k, _ in groups if not (folder / f"{k}.parquet").is_file()]
    if missing:  # (only if the log gave other frames the second time it was read)
        log.warning("carry: %d groups of gaps not carried: their frames were not read again", len(missing))
    parts = [pd.read_parquet(folder / f"{k}.parquet") for k, _ in groups if k not in missing]
    carried = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    df = overlay(estimated, carried)
    write_parquet_atomic(df, out)
    seconds = time.perf_counter() - t0
    counts = Counter(r.split(" ", 2)[1] for r in carried["reason"]) if len(carried) else Counter()
    tried = sum(len({*g.forward[1:], *g.backward[1:]}) for g in gaps)
    summary = {"gaps": len(gaps), "pairs_tried": tried, "carried": len(carried), **counts}
    write_json_atomic(done_file, {"key": key, **summary, "seconds": seconds})
    log.info(
        "carried %d of the %d pairs without a pose within carry.max_steps of a confident one (%d forwards, "
        "%d backwards; %d gaps) in %.1f s; the other %d failed the checks and keep the estimate's record",
        len(carried), tried, counts["forwards"], counts["backwards"], len(gaps), seconds, tried - len(carried),
    )  # fmt: skip
    return out


def _frames(inputs: CarryInputs) -> Iterator[Frame]:
    """The run's frames, in the order of the log."""
    for i, frame in enumerate(inputs.source):
        if inputs.limit is not None and i >= inputs.limit:
            return
        if inputs.frame_ids is None or frame.frame_id in inputs.frame_ids:
            yield frame


def _with_frames(inputs: CarryInputs, groups: list[tuple[str, list[Gap]]]):
    """(key, gaps, their frames) of each group, as soon as the log has been read up to its last frame; a frame
    is held only until the last group that needs it is handed on (groups come in the order of their last
    frame)."""
    needs = Counter(f for _, gaps in groups for f in set().union(*(g.frames() for g in gaps)))
    held: dict[str, Frame] = {}
    pending = iter(groups)
    group = next(pending, None)
    for frame in _frames(inputs):
        if frame.frame_id in needs:
            held[frame.frame_id] = frame
        while group is not None and all(f in held for g in group[1] for f in g.frames()):
            ids = set().union(*(g.frames() for g in group[1]))
            yield group[0], group[1], {f: held[f] for f in ids}
            for f in ids:
                needs[f] -= 1
                if not needs[f]:
                    del held[f]
            group = next(pending, None)
        if group is None:
            return


def _run(conf: EstimatorConfig, inputs: CarryInputs, folder: Path, groups: list[tuple[str, list[Gap]]]) -> None:
    """Carry the groups on the workers; each group's rows are written as soon as it is done."""
    if not groups:
        return
    setup = CarrySetup(
        to_dict(conf),
        dict(inputs.obj_ids),
        {k: str(v) for k, v in inputs.mesh_paths.items()},
        str(inputs.mesh_cache) if inputs.mesh_cache else None,
        inputs.threads,
    )
    tasks = (joblib.delayed(_task)(k, g, frames, setup) for k, g, frames in _with_frames(inputs, groups))
    loky = loky_options() if inputs.backend == "loky" else {}
    n_jobs = min(inputs.jobs, len(groups)) if inputs.backend == "loky" else -1
    columns = list(PoseRecord("", "", "ok").to_row())
    with (
        tqdm(desc="carry", unit="gap", total=sum(len(g) for _, g in groups), leave=False, disable=None) as bar,
        joblib.parallel_config(backend=inputs.backend, n_jobs=n_jobs, **loky),
    ):
        parallel = joblib.Parallel(return_as="generator_unordered", pre_dispatch="2*n_jobs")
        sizes = dict((k, len(g)) for k, g in groups)
        for k, rows in parallel(tasks):
            write_parquet_atomic(pd.DataFrame(rows, columns=columns), folder / f"{k}.parquet")
            bar.update(sizes[k])


def overlay(estimated: pd.DataFrame, carried: pd.DataFrame) -> pd.DataFrame:
    """The estimate's rows with each carried row in place of its pair's, its timings added to the time the
    estimate spent on the pair (so a pair's time stays all it cost)."""
    keys = ["frame_id", "obj_name"]
    if carried.empty:
        return _flagged(estimated.copy())
    carried = carried.drop_duplicates(subset=keys, keep="first")
    before = estimated.set_index(keys).loc[pd.MultiIndex.from_frame(carried[keys])]
    carried = carried.copy()
    for col in [c for c in estimated.columns if c.startswith("time_") and c in carried.columns]:
        carried[col] = carried[col].to_numpy() + before[col].to_numpy()
    replaced = estimated.set_index(keys).index.isin(pd.MultiIndex.from_frame(carried[keys]))
    df = pd.concat([estimated[~replaced], carried[estimated.columns.intersection(carried.columns)]], ignore_index=True)
    return _flagged(df).sort_values(["scene_id", "im_id", "frame_id", "obj_name"], kind="stable").reset_index(drop=True)


def _flagged(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with a bool ``carried`` column (False where shards written before the column left it empty)."""
    df["carried"] = df["carried"].fillna(False).astype(bool) if "carried" in df else False
    return df
