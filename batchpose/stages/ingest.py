"""Stage: index the frames of a data set (``frames.parquet``) and its ground truth (``gt.parquet``)."""

from __future__ import annotations

import json
import logging
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from batchpose.config import EstimatorConfig
from batchpose.core.frames import FrameSource
from batchpose.errors import DataError
from batchpose.io.files import write_parquet_atomic, write_text_atomic
from batchpose.stages import up_to_date

log = logging.getLogger("batchpose")


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


@dataclass(frozen=True)
class IngestInputs:
    """What ingest reads: the frames (:func:`batchpose.io.sources.open_frames`), the objects of interest
    (ground truth of other objects is not kept), ``limit`` (index only the first ``limit`` frames) and the
    objects' ids (``obj_id`` in ``gt.parquet``; the data set's own where not given)."""

    source: FrameSource
    objects: list[str]
    limit: int | None = None
    obj_ids: dict[str, int] | None = None


def main(conf: EstimatorConfig | None, inputs: IngestInputs, run_dir: Path, overwrite: bool = False) -> Path:
    """Write ``run_dir/frames.parquet`` and ``run_dir/gt.parquet``; returns the frames index path. The
    estimator config does not change the index (the stage contract passes it to every stage).

    The data set is read again on every run and compared with the index a previous run left: unchanged,
    nothing is written; frames added or removed (or another ``--limit``), the index is rewritten and the
    merged ``poses.parquet`` removed, so the estimate stage covers exactly the frames indexed now (finished
    pairs are kept in their shards); a frame whose content changed under the same id is an error, since its
    finished pairs would be stale.

    Raises:
        DataError: a frame's name is not UTF-8 text, or a frame changed since the run that estimated it.
    """
    source, objects, limit = inputs.source, inputs.objects, inputs.limit
    run_dir = Path(run_dir)
    out, gt_out, stamp = run_dir / "frames.parquet", run_dir / "gt.parquet", run_dir / "ingest.json"
    covers = {"limit": limit}
    frames, gt = _index(source, objects, limit, inputs.obj_ids or {})
    old = None if overwrite else _read_index(out, gt_out)
    if old is not None:
        _check_unchanged(old[0], frames, source)
        fresh = _read_json(stamp) == covers and _same(old[0], frames) and _same(old[1], gt)
        if up_to_date("ingest", out, overwrite, fresh, f"{len(frames)} frames"):
            return out
    stamp.unlink(missing_ok=True)
    (run_dir / "poses.parquet").unlink(missing_ok=True)  # merged for another set of frames
    write_parquet_atomic(gt, gt_out)
    write_parquet_atomic(frames, out)
    write_text_atomic(stamp, json.dumps(covers), encoding=None)
    log.info("ingested %d frames, %d ground-truth poses of %s", len(frames), len(gt), ", ".join(objects))
    return out


def _read_index(out: Path, gt_out: Path) -> tuple[pd.DataFrame, pd.DataFrame] | None:
    """The index a previous run wrote; None when there is none or it is unreadable (written again)."""
    if not (out.is_file() and gt_out.is_file()):
        return None
    try:
        return pd.read_parquet(out), pd.read_parquet(gt_out)
    except (OSError, ValueError) as e:  # pyarrow's errors derive from these
        log.warning("%s: unreadable (%s); indexing the frames again", out, e)
        return None


def _same(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Equal tables, list cells (K, R, t_m) compared by value: Parquet reads them back as arrays."""

    def plain(df: pd.DataFrame) -> pd.DataFrame:
        df = df.reset_index(drop=True).copy()
        for c in df.columns:
            if df[c].dtype == object and len(df) and not isinstance(df[c].iloc[0], str):
                df[c] = df[c].map(lambda v: tuple(np.asarray(v, float).ravel()))
        return df

    return list(a.columns) == list(b.columns) and plain(a).equals(plain(b))


def _check_unchanged(old: pd.DataFrame, new: pd.DataFrame, source) -> None:
    if "crc" not in old.columns:
        return  # written by an earlier version: no content to compare
    both = old.merge(new, on="frame_id", suffixes=("_old", ""))
    changed = both[both["crc_old"] != both["crc"]]
    if len(changed):
        raise DataError(
            f"{source.describe()}: frame {changed['frame_id'].iloc[0]} is not the one this run estimated "
            f"({len(changed)} frame(s) changed since); use --overwrite or another --out"
        )


def _index(source, objects: list[str], limit: int | None, obj_ids: dict[str, int]) -> tuple[pd.DataFrame, pd.DataFrame]:
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
                "crc": zlib.crc32(f.depth_data, zlib.crc32(f.image_data)),
            }
        )
        for p in f.gt:
            if p.obj_name in wanted:
                gt_rows.append(
                    {
                        "frame_id": f.frame_id,
                        "obj_name": p.obj_name,
                        "obj_id": obj_ids.get(p.obj_name) or source.obj_id(p.obj_name),
                        "R": np.asarray(p.cam_from_model[:3, :3], float).reshape(-1).tolist(),
                        "t_m": np.asarray(p.cam_from_model[:3, 3], float).tolist(),
                    }
                )
    columns = ["frame_id", "scene_id", "im_id", "stamp_ns", "width", "height", "K", "source", "crc"]
    frames = pd.DataFrame(rows, columns=columns)
    gt = pd.DataFrame(gt_rows, columns=["frame_id", "obj_name", "obj_id", "R", "t_m"])
    return frames, gt
