"""Stage: write the estimates as tables: ``run_dir/poses.csv`` (the BOP results format, for any BOP scorer),
``run_dir/trajectory.csv`` (log time, object, position, quaternion, status, confidence, tracked) and
``run_dir/tum/<object>.txt`` (TUM trajectories of the ok poses, for ``evo`` and similar tools)."""

from __future__ import annotations

import logging
from pathlib import Path

import pandas as pd

from batchpose.config import EstimatorConfig
from batchpose.io.bop_csv import write_bop_csv
from batchpose.io.trajectory import trajectory, write_trajectory_csv, write_tum
from batchpose.stages import up_to_date

log = logging.getLogger("batchpose")


def main(conf: EstimatorConfig | None, poses_path: Path, run_dir: Path, overwrite: bool = False) -> Path:
    """Write ``poses.csv``, ``trajectory.csv`` and ``tum/`` from ``poses.parquet`` (``poses_path``); skipped
    when they are newer than the estimates. Returns the path of ``poses.csv``."""
    run_dir = Path(run_dir)
    out, traj = run_dir / "poses.csv", run_dir / "trajectory.csv"
    since = Path(poses_path).stat().st_mtime
    fresh = all(p.is_file() and p.stat().st_mtime >= since for p in (out, traj))
    if up_to_date("CSV export", out, overwrite, fresh):
        return out
    poses = pd.read_parquet(poses_path)
    table = trajectory(poses)
    write_tum(table, run_dir / "tum")
    write_trajectory_csv(table, traj)
    return write_bop_csv(poses, out)
