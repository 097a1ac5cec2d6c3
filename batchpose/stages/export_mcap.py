"""Stage: write ``run_dir/poses.mcap`` (the input log or the frames, plus the pose topics) for Foxglove."""

from __future__ import annotations

import logging
from pathlib import Path

import pandas as pd

from batchpose.core.model import ObjectModel

log = logging.getLogger("batchpose")


def main(
    run_dir: Path,
    poses_path: Path,
    models: dict[str, ObjectModel],
    frames_spec: dict,
    source,
    overwrite: bool = False,
) -> Path:
    """Write ``run_dir/poses.mcap``; skipped when it is newer than ``poses_path``. Returns its path."""
    from batchpose.io.gltf import mesh_to_glb
    from batchpose.io.mcap_poses import write_poses_mcap

    out = Path(run_dir) / "poses.mcap"
    if out.is_file() and not overwrite and out.stat().st_mtime >= Path(poses_path).stat().st_mtime:
        log.info("Skipping MCAP export: %s is up to date", out)
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
