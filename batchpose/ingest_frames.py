"""Stage: index the frames of a data set (``frames.parquet``) and its ground truth (``gt.parquet``)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

log = logging.getLogger("batchpose")


def write_parquet_atomic(df: pd.DataFrame, path: Path) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    df.to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return path


def main(source, objects: list[str], run_dir: Path, overwrite: bool = False, limit: int | None = None) -> Path:
    """Write ``run_dir/frames.parquet`` and ``run_dir/gt.parquet``; returns the frames index path.

    Args:
        source: a frame source (``batchpose.datasets.open_frames``).
        objects: object names of interest (ground truth of other objects is not kept).
        limit: index only the first ``limit`` frames.
    """
    out = Path(run_dir) / "frames.parquet"
    gt_out = Path(run_dir) / "gt.parquet"
    if out.is_file() and gt_out.is_file() and not overwrite:
        log.info("Skipping ingest: %s exists", out)
        return out
    rows, gt_rows = [], []
    wanted = set(objects)
    total = source.count()
    if limit is not None:
        total = min(total, limit)
    for i, f in enumerate(tqdm(source, total=total, desc="ingest", unit="frame", leave=False, disable=None)):
        if limit is not None and i >= limit:
            break
        rows.append(
            {
                "frame_id": f.frame_id,
                "scene_id": f.scene_id,
                "im_id": f.im_id,
                "stamp_ns": f.stamp_ns,
                "width": f.camera.width,
                "height": f.camera.height,
                "K": np.asarray(f.camera.K, float).reshape(-1).tolist(),
                "source": f.source,
            }
        )
        for p in f.gt:
            if p.obj_name in wanted:
                gt_rows.append(
                    {
                        "frame_id": f.frame_id,
                        "obj_name": p.obj_name,
                        "obj_id": source.obj_id(p.obj_name),
                        "R": np.asarray(p.cam_from_model[:3, :3], float).reshape(-1).tolist(),
                        "t_m": np.asarray(p.cam_from_model[:3, 3], float).tolist(),
                    }
                )
    frames = pd.DataFrame(rows, columns=["frame_id", "scene_id", "im_id", "stamp_ns", "width", "height", "K", "source"])
    gt = pd.DataFrame(gt_rows, columns=["frame_id", "obj_name", "obj_id", "R", "t_m"])
    write_parquet_atomic(gt, gt_out)
    write_parquet_atomic(frames, out)
    log.info("ingested %d frames, %d ground-truth poses of %s", len(frames), len(gt), ", ".join(objects))
    return out
