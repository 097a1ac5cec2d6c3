"""The main job: ingest -> template libraries -> estimate -> carry -> poses.csv / poses.mcap -> report.

The run directory is claimed and locked by :mod:`batchpose.run_dir`; each stage is a module of :mod:`batchpose.stages`.

Each stage is a module whose ``main`` returns the path it wrote; finished stages are skipped on a rerun.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.core.frames import Camera, FrameSource, working_camera
from batchpose.errors import CameraError, ConfigError
from batchpose.io.manifest import object_ids
from batchpose.io.mesh import load_mesh
from batchpose.io.sources import SelectedFrames, open_frames
from batchpose.run_dir import Job, claim, exclusive, prepare
from batchpose.stages import build_templates, carry, estimate, export_csv, export_mcap, ingest
from batchpose.stages.build_templates import TemplateInputs
from batchpose.stages.workers import threads_per_worker

log = logging.getLogger("batchpose")


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


def _check_frames(job: Job, source: FrameSource, frames_index: pd.DataFrame, targets: str) -> None:
    """Refuse a run with no frames to estimate, saying why (none chosen, none at all, none annotated)."""
    man = job.manifest
    if frames_index.empty:
        if isinstance(source, SelectedFrames):
            sel = source.selection
            chosen = sel.describe()
            if source.span_s is not None and (sel.from_s is not None or sel.to_s is not None):
                chosen += f"; its images span {source.span_s[0]:.3g}-{source.span_s[1]:.4g} s of the log"
            raise ConfigError(f"{man.path}: none of the data set's frames is chosen ({chosen})")
        raise ConfigError(f"{man.path}: the data set has no frames")
    if targets == "annotations":
        objects = [o.name for o in man.objects]
        _check_annotated(pd.read_parquet(job.run_dir / "gt.parquet"), objects, man.path, job.limit)


def _targets(job: Job) -> str:
    """The manifest's ``targets``, with ``auto`` resolved: the annotated objects where the data set has ground
    truth (in the frames this run uses), every object in every frame where it has none."""
    if job.manifest.targets != "auto":
        return job.manifest.targets
    has_gt = not pd.read_parquet(job.run_dir / "gt.parquet", columns=["frame_id"]).empty
    targets = "annotations" if has_gt else "all"
    log.info("targets: %s (the data set %s ground truth)", targets, "has" if has_gt else "has no")
    return targets


def _template_inputs(
    job: Job, frames_index: pd.DataFrame, obj_ids: dict[str, int], jobs: int, targets: str
) -> TemplateInputs:
    man, conf = job.manifest, job.conf
    K0, width, height = _template_camera(frames_index, man.path, conf.max_image_side_px)
    models = {o.name: load_mesh(o.mesh, conf.mesh, name=o.name, cache_dir=job.cache_dir) for o in man.objects}
    return build_templates.TemplateInputs(
        models,
        obj_ids,
        K0,
        width,
        height,
        job.cache_dir,
        jobs,
        mesh_paths={o.name: o.mesh for o in man.objects},
        points={o.name: o.points for o in man.objects},
        presence=targets != "annotations" and conf.match.presence_votes > 0,
    )


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
    report: bool = True,
    ros_tf: bool = True,
) -> Path:
    """Run the whole pipeline: each stage's ``main`` returns the artifact the next one reads. Returns
    ``run_dir``. ``ros_tf``: also write the poses on ``/tf`` (tf2_msgs) in ``poses.mcap`` of a ROS log."""
    t_start = time.perf_counter()
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    job = prepare(pipeline, manifest, run_dir, cache_dir, list(overrides), limit)
    conf, man = job.conf, job.manifest
    try:
        job.run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out {job.run_dir}: cannot write there ({e.strerror or e})") from None
    with exclusive(job.run_dir):
        claim(job, overwrite)
        source = open_frames(man.frames, man.path.parent)
        log.info("data: %s", source.describe())
        obj_ids = object_ids(man.objects, {o.name: source.obj_id(o.name) for o in man.objects})
        ingested = ingest.IngestInputs(source, [o.name for o in man.objects], limit, obj_ids)
        frames_path = ingest.main(conf, ingested, job.run_dir, overwrite)
        frames_index = pd.read_parquet(frames_path)
        targets = _targets(job)
        _check_frames(job, source, frames_index, targets)
        templates = _template_inputs(job, frames_index, obj_ids, jobs, targets)
        objects_path = build_templates.main(conf, templates, job.run_dir, overwrite)
        with _backend(backend, scheduler, jobs) as jl_backend:
            inputs = estimate.EstimateInputs(
                source,
                build_templates.library_dirs(objects_path),
                templates.obj_ids,
                {o.name: o.mesh for o in man.objects},
                targets,
                limit=limit,
                frame_ids=set(frames_index["frame_id"]),
                mesh_cache=job.cache_dir,
                jobs=jobs,
                backend=jl_backend,
                # workers on this machine share its cores; a remote cluster's workers keep their defaults
                threads=None if scheduler else threads_per_worker(jobs),
                retry_lib_dirs=build_templates.library_dirs(objects_path, "retry_library"),
            )
            poses_path = estimate.main(conf, inputs, job.run_dir, overwrite)
            carried = carry.CarryInputs(
                source,
                templates.obj_ids,
                inputs.mesh_paths,
                limit=limit,
                frame_ids=inputs.frame_ids,
                mesh_cache=job.cache_dir,
                jobs=jobs,
                backend=jl_backend,
                threads=inputs.threads,
            )
            poses_path = carry.main(conf, carried, job.run_dir, overwrite)
        csv_path = export_csv.main(conf, poses_path, job.run_dir, overwrite)
        exported = export_mcap.ExportInputs(poses_path, templates.models, man.frames, source, ros_tf=ros_tf)
        mcap_path = export_mcap.main(conf, exported, job.run_dir, overwrite)
        if report:
            from batchpose.stages import report as report_stage

            report_stage.main(None, None, job.run_dir, overwrite=True)
        outputs = [job.run_dir / "trajectory.csv", csv_path, mcap_path]
        log.info("done in %.1f s: %s", time.perf_counter() - t_start, ", ".join(map(str, outputs)))
        return job.run_dir
