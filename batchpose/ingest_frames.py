"""Stage: index the frames of a data set (``frames.parquet``) and its ground truth (``gt.parquet``)."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from batchpose.errors import DataError

log = logging.getLogger("batchpose")


def write_parquet_atomic(df: pd.DataFrame, path: Path) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    df.to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return path


def _utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:  # a file name's undecodable bytes, kept as surrogates
        return False
    return True


def _printable(text: str) -> str:
    return os.fsencode(text).decode("utf-8", "backslashreplace")


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def main(source, objects: list[str], run_dir: Path, overwrite: bool = False, limit: int | None = None) -> Path:
    """Write ``run_dir/frames.parquet`` and ``run_dir/gt.parquet``; returns the frames index path.

    Args:
        source: a frame source (``batchpose.datasets.open_frames``).
        objects: object names of interest (ground truth of other objects is not kept).
        limit: index only the first ``limit`` frames.
    """
    out = Path(run_dir) / "frames.parquet"
    gt_out = Path(run_dir) / "gt.parquet"
    # What the index covers: a rerun with another --limit indexes the frames again (and estimates only
    # the pairs it has not yet).
    stamp, covers = Path(run_dir) / "ingest.json", {"limit": limit}
    if out.is_file() and gt_out.is_file() and not overwrite and _read_json(stamp) == covers:
        log.info("Skipping ingest: %s exists", out)
        return out
    stamp.unlink(missing_ok=True)
    rows, gt_rows = [], []
    wanted = set(objects)
    total = source.count()
    if limit is not None:
        total = min(total, limit)
    for i, f in enumerate(tqdm(source, total=total, desc="ingest", unit="frame", leave=False, disable=None)):
        if limit is not None and i >= limit:
            break
        for text in (f.frame_id, f.source):
            if not _utf8(text):
                raise DataError(f"{_printable(text)}: the name is not valid UTF-8 text; rename it")
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
    tmp = stamp.with_name(stamp.name + ".tmp")
    tmp.write_text(json.dumps(covers))
    os.replace(tmp, stamp)
    log.info("ingested %d frames, %d ground-truth poses of %s", len(frames), len(gt), ", ".join(objects))
    return out
