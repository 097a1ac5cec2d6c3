"""Stage: write ``run_dir/poses.mcap`` (the input log or the frames, plus the pose topics) for Foxglove."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from batchpose.config import EstimatorConfig
from batchpose.core.frames import FrameSource
from batchpose.core.model import ObjectModel
from batchpose.stages import up_to_date

log = logging.getLogger("batchpose")


@dataclass(frozen=True)
class ExportInputs:
    """What the MCAP export reads: the merged estimates, the meshes (drawn in Foxglove), the manifest's
    ``frames:`` mapping (a log is copied with the poses added; folder frames are written as a log) and the
    frame source."""

    poses_path: Path
    models: dict[str, ObjectModel]
    frames_spec: dict
    source: FrameSource


def main(conf: EstimatorConfig | None, inputs: ExportInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Write ``run_dir/poses.mcap``; skipped when it is newer than the estimates. Returns its path."""
    from batchpose.io.gltf import mesh_to_glb
    from batchpose.io.mcap_poses import write_poses_mcap

    poses_path, models, frames_spec, source = inputs.poses_path, inputs.models, inputs.frames_spec, inputs.source
    out = Path(run_dir) / "poses.mcap"
    fresh = out.is_file() and out.stat().st_mtime >= Path(poses_path).stat().st_mtime
    if up_to_date("MCAP export", out, overwrite, fresh):
        return out
    poses = pd.read_parquet(poses_path)
    glbs = {name: mesh_to_glb(m.mesh) for name, m in models.items()}
    if frames_spec.get("format") == "mcap":
        write_poses_mcap(
            out,
            poses,
            glbs,
            input_mcap=Path(frames_spec["path"]),
            image_topic=frames_spec.get("image_topic"),
            calibration_topic=frames_spec.get("calibration_topic"),
            rectified=frames_spec.get("rectified"),
        )
    else:
        wanted = set(poses["frame_id"])
        frames = (f for f in source if f.frame_id in wanted)
        write_poses_mcap(out, poses, glbs, frames=frames)
    return out
