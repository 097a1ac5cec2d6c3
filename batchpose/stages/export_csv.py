"""Stage: write ``run_dir/poses.csv``, the estimates in the BOP results format, for any BOP scorer."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from batchpose.config import EstimatorConfig
from batchpose.io.bop_csv import write_bop_csv
from batchpose.stages import up_to_date


def main(conf: EstimatorConfig | None, poses_path: Path, run_dir: Path, overwrite: bool = False) -> Path:
    """Write ``run_dir/poses.csv`` from ``poses.parquet`` (``poses_path``); skipped when it is newer than the
    estimates. Returns its path."""
    out = Path(run_dir) / "poses.csv"
    fresh = out.is_file() and out.stat().st_mtime >= Path(poses_path).stat().st_mtime
    if up_to_date("BOP export", out, overwrite, fresh):
        return out
    return write_bop_csv(pd.read_parquet(poses_path), out)
