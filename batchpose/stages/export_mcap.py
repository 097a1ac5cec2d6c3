"""Stage: write ``run_dir/poses.mcap`` (the input log or the frames, plus the pose topics) for Foxglove, and
``run_dir/foxglove_layout.json``, the layout that shows it (the run's own image and calibration topics and
camera frame)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from batchpose.config import EstimatorConfig
from batchpose.config.pipelines import layout_template
from batchpose.core.frames import FrameSource
from batchpose.core.model import ObjectModel
from batchpose.io.files import read_text, write_text_atomic
from batchpose.stages import up_to_date

log = logging.getLogger("batchpose")

LAYOUT_NAME = "foxglove_layout.json"


@dataclass(frozen=True)
class ExportInputs:
    """What the MCAP export reads: the merged estimates, the meshes (drawn in Foxglove), the manifest's
    ``frames:`` mapping (a log is copied with the poses added; folder frames are written as a log) and the
    frame source. ``ros_tf``: for a ROS log, also publish the poses on ``/tf`` (``tf2_msgs/TFMessage`` in the
    log's encoding); an export option, not an estimator setting, so it changes no config hash or cache.

    The run directory's ``gt.parquet`` and ``frames.parquet`` (ground truth, drawn beside the estimates) and
    ``objects.json`` (object ids) are read from the run directory."""

    poses_path: Path
    models: dict[str, ObjectModel]
    frames_spec: dict
    source: FrameSource
    ros_tf: bool = True


def _ground_truth(run_dir: Path) -> pd.DataFrame:
    """``gt.parquet`` rows with their image's ``stamp_ns`` (from ``frames.parquet``); empty without either."""
    gt_path, frames_path = run_dir / "gt.parquet", run_dir / "frames.parquet"
    if not (gt_path.is_file() and frames_path.is_file()):
        return pd.DataFrame(columns=["stamp_ns", "obj_name", "obj_id", "R", "t_m"])
    gt = pd.read_parquet(gt_path)
    stamps = pd.read_parquet(frames_path, columns=["frame_id", "stamp_ns"])
    return gt.merge(stamps, on="frame_id", how="inner")


def _obj_ids(run_dir: Path) -> dict[str, int]:
    """Object name -> id, from ``objects.json`` (empty when the run has none)."""
    path = run_dir / "objects.json"
    if not path.is_file():
        return {}
    return {name: int(o.get("obj_id", 0) or 0) for name, o in json.loads(read_text(path)).items()}


def _fresh(out: Path, layout: Path, poses_path: Path, ros_tf: bool) -> bool:
    """The export on disk is what the estimates and options make: both files there, the log newer than the
    estimates and written with the same ``ros_tf``."""
    from batchpose.io.mcap_poses import export_options

    if not (out.is_file() and layout.is_file()) or out.stat().st_mtime < Path(poses_path).stat().st_mtime:
        return False
    return export_options(out).get("ros_tf") == json.dumps(bool(ros_tf))


def main(conf: EstimatorConfig | None, inputs: ExportInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Write ``run_dir/poses.mcap`` and ``run_dir/foxglove_layout.json``; skipped when they are newer than the
    estimates and were written with the same options. Returns the path of ``poses.mcap``."""
    from batchpose.io.gltf import mesh_to_glb
    from batchpose.io.mcap_poses import write_poses_mcap
    from batchpose.io.mcap_topics import foxglove_layout

    run_dir = Path(run_dir)
    poses_path, models, frames_spec, source = inputs.poses_path, inputs.models, inputs.frames_spec, inputs.source
    out, layout_path = run_dir / "poses.mcap", run_dir / LAYOUT_NAME
    if up_to_date("MCAP export", out, overwrite, _fresh(out, layout_path, poses_path, inputs.ros_tf)):
        log.info("Foxglove layout: %s (Layouts > Import from file)", layout_path)
        return out
    poses = pd.read_parquet(poses_path)
    glbs = {name: mesh_to_glb(m.mesh) for name, m in models.items()}
    gt = _ground_truth(run_dir)
    if frames_spec.get("format") == "mcap":
        written = write_poses_mcap(
            out,
            poses,
            glbs,
            input_mcap=Path(frames_spec["path"]),
            image_topic=frames_spec.get("image_topic"),
            calibration_topic=frames_spec.get("calibration_topic"),
            rectified=frames_spec.get("rectified"),
            ground_truth=gt,
            ros_tf=inputs.ros_tf,
        )
    else:
        wanted = set(poses["frame_id"])
        frames = (f for f in source if f.frame_id in wanted)
        written = write_poses_mcap(
            out, poses, glbs, frames=frames, ground_truth=gt, obj_ids=_obj_ids(run_dir), ros_tf=inputs.ros_tf
        )
    if written.n_ros_tf:
        log.info("%s: the poses are also on /tf (tf2_msgs/TFMessage, %d messages)", out, written.n_ros_tf)
    template = json.loads(read_text(layout_template()))
    layout = foxglove_layout(
        template, written.image_topic, written.calibration_topic, written.camera_frame, written.scene_topics
    )
    write_text_atomic(layout_path, json.dumps(layout, indent=2) + "\n")
    log.info("Foxglove layout: %s (Layouts > Import from file)", layout_path)
    return out
