"""BOP results CSV (SPEC §6), so third-party scorers can read our poses and we can score theirs
(:func:`batchpose.report.scoring.score_bop_csv`).

Format (BOP Challenge 2019+): header ``scene_id,im_id,obj_id,score,R,t,time``; one line per estimate;
R row-major, 9 numbers separated by spaces; t in millimetres, 3 numbers separated by spaces; time in
seconds (-1 when unknown). bop_toolkit rejects a file whose estimates of one image have different times
("The running time ... is not the same for all estimates"), so by default the time written is the time
the pipeline spent on the whole image: the sum of ``time_total_s`` over all of that image's rows
(including failed objects). ``time_per="row"`` writes each row's own ``time_total_s`` instead.

Numbers are written as Python's shortest round-trip ``repr``, so ``write -> read -> write`` is byte-exact.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.errors import DataError
from batchpose.io.files import write_bytes_atomic

log = logging.getLogger("batchpose")

BOP_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
#: Columns of the table returned by :func:`read_bop_csv` (and accepted by :func:`write_bop_csv`).
BOP_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t_mm", "time_s")
_POSES_COLUMNS = ("scene_id", "im_id", "obj_id", "status", "confidence", "R", "t_m")


def _num(x: float) -> str:
    return repr(float(x))


def poses_to_bop(poses: pd.DataFrame, time_per: str = "image") -> pd.DataFrame:
    """Convert a ``poses.parquet`` table to the BOP table (ok rows with a finite pose only).

    Args:
        poses: table in the :mod:`batchpose.core.poses` format.
        time_per: "image" (sum of ``time_total_s`` over the image's rows, as bop_toolkit requires) or
            "row" (each row's own ``time_total_s``). Without a ``time_total_s`` column the time is -1.

    Returns:
        Table with :data:`BOP_COLUMNS` (t in millimetres, time in seconds), sorted by scene_id, im_id,
        obj_id, then descending score.
    """
    if time_per not in ("image", "row"):
        raise ValueError(f"time_per must be 'image' or 'row', got {time_per!r}")
    missing = [c for c in _POSES_COLUMNS if c not in poses.columns]
    if missing:
        raise DataError(f"poses table: missing column(s) {', '.join(missing)} for the BOP results file")
    if "time_total_s" in poses.columns:
        row_time = poses["time_total_s"].astype(float)
        if time_per == "image":
            row_time = row_time.groupby([poses["scene_id"], poses["im_id"]]).transform("sum")
    else:
        row_time = pd.Series(-1.0, index=poses.index)
    rows = []
    for (idx, r), time_s in zip(poses.iterrows(), row_time, strict=True):
        if r["status"] != "ok":
            continue
        R = np.asarray(r["R"], dtype=np.float64).reshape(-1)
        t = np.asarray(r["t_m"], dtype=np.float64).reshape(-1)
        if R.size != 9 or t.size != 3 or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            log.warning(
                "poses row %s (%s): status ok but no finite pose; left out of the BOP file",
                idx,
                r.get("frame_id", "?"),
            )
            continue
        rows.append(
            {
                "scene_id": int(r["scene_id"]),
                "im_id": int(r["im_id"]),
                "obj_id": int(r["obj_id"]),
                "score": float(r["confidence"]),
                "R": R.tolist(),
                "t_mm": (t * 1000.0).tolist(),
                "time_s": float(time_s),
            }
        )
    table = pd.DataFrame(rows, columns=list(BOP_COLUMNS))
    return _sorted(table)


def _sorted(table: pd.DataFrame) -> pd.DataFrame:
    return table.sort_values(
        ["scene_id", "im_id", "obj_id", "score"], ascending=[True, True, True, False], kind="stable"
    ).reset_index(drop=True)


def write_bop_csv(poses: pd.DataFrame, path: Path | str, time_per: str = "image") -> Path:
    """Write a BOP results CSV atomically (``<path>.tmp`` then ``os.replace``).

    Args:
        poses: a ``poses.parquet`` table (only ok rows are written; see :func:`poses_to_bop`), or a table
            with :data:`BOP_COLUMNS` as returned by :func:`read_bop_csv` (written as is).
        path: output file.
        time_per: for a poses table, "image" or "row" (see :func:`poses_to_bop`).

    Returns:
        The path written.
    """
    path = Path(path)
    if "status" not in poses.columns and set(BOP_COLUMNS) <= set(poses.columns):
        table = _sorted(poses)
    else:
        table = poses_to_bop(poses, time_per=time_per)
    lines = [BOP_HEADER]
    for r in table.itertuples(index=False):
        R = np.asarray(r.R, dtype=np.float64).reshape(-1)
        t = np.asarray(r.t_mm, dtype=np.float64).reshape(-1)
        if R.size != 9 or t.size != 3:
            raise DataError(
                f"BOP table row scene {r.scene_id} image {r.im_id} object {r.obj_id}: "
                f"R needs 9 numbers and t_mm 3, got {R.size} and {t.size}"
            )
        lines.append(
            ",".join(
                (
                    str(int(r.scene_id)),
                    str(int(r.im_id)),
                    str(int(r.obj_id)),
                    _num(r.score),
                    " ".join(_num(v) for v in R),
                    " ".join(_num(v) for v in t),
                    _num(r.time_s),
                )
            )
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(path, ("\n".join(lines) + "\n").encode("ascii"))
    log.info("wrote %d estimates to %s", len(table), path)
    return path


def _parse_floats(text: str, n: int, field: str, where: str) -> list[float]:
    parts = text.split()
    if len(parts) != n:
        raise DataError(f"{where}: field {field} needs {n} space-separated numbers, got {len(parts)}: {text!r}")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise DataError(f"{where}: field {field} is not numeric: {text!r}") from None
    if not all(np.isfinite(vals)):
        raise DataError(f"{where}: field {field} contains NaN or inf: {text!r}")
    return vals


def _parse_int(text: str, field: str, where: str) -> int:
    try:
        v = int(text.strip())
    except ValueError:
        raise DataError(f"{where}: field {field} must be a non-negative integer, got {text!r}") from None
    if v < 0:
        raise DataError(f"{where}: field {field} must be a non-negative integer, got {v}")
    return v


def read_bop_csv(path: Path | str) -> pd.DataFrame:
    """Read a BOP results CSV.

    Args:
        path: CSV with the header ``scene_id,im_id,obj_id,score,R,t,time``.

    Returns:
        Table with :data:`BOP_COLUMNS`: ids as int, score float, R list of 9 floats (row-major,
        model -> camera), t_mm list of 3 floats (millimetres), time_s float (seconds, -1 = unknown).

    Raises:
        DataError: naming the file and line, when the file is missing, has no header or a malformed line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{path}: BOP results file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read BOP results file ({e})") from None
    lines = text.splitlines()
    if not lines or lines[0].strip().replace(" ", "") != BOP_HEADER:
        got = lines[0][:80] if lines else "an empty file"
        raise DataError(f"{path}:1: expected the header {BOP_HEADER!r}, got {got!r}")
    rows = []
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        fields = line.split(",")
        if len(fields) != 7:
            raise DataError(f"{where}: expected 7 comma-separated fields ({BOP_HEADER}), got {len(fields)}")
        score = _parse_floats(fields[3], 1, "score", where)[0]
        time_s = _parse_floats(fields[6], 1, "time", where)[0]
        rows.append(
            {
                "scene_id": _parse_int(fields[0], "scene_id", where),
                "im_id": _parse_int(fields[1], "im_id", where),
                "obj_id": _parse_int(fields[2], "obj_id", where),
                "score": score,
                "R": _parse_floats(fields[4], 9, "R", where),
                "t_mm": _parse_floats(fields[5], 3, "t", where),
                "time_s": time_s,
            }
        )
    table = pd.DataFrame(rows, columns=list(BOP_COLUMNS))
    for c in ("scene_id", "im_id", "obj_id"):
        table[c] = table[c].astype(np.int64)
    for c in ("score", "time_s"):
        table[c] = table[c].astype(np.float64)
    return table


def bop_to_poses(
    table: pd.DataFrame,
    obj_names: Mapping[int, str],
    frame_ids: Mapping[tuple[int, int], str] | None = None,
    where: str = "BOP results",
) -> pd.DataFrame:
    """Turn a BOP table into ``poses.parquet``-style rows (status ok) that
    :func:`batchpose.report.metrics.score` accepts.

    Args:
        table: as returned by :func:`read_bop_csv`.
        obj_names: obj_id -> obj_name. Rows with an unknown obj_id are dropped with a warning.
        frame_ids: (scene_id, im_id) -> frame_id; images not in it get ``"<scene:06d>/<im:06d>"``.
        where: name used in log messages (e.g. the file).

    Returns:
        Table with frame_id, scene_id, im_id, obj_name, obj_id, status, reason, R, t_m (metres),
        confidence (= score), time_total_s (= time).
    """
    frame_ids = frame_ids or {}
    unknown = sorted({int(i) for i in table["obj_id"]} - {int(k) for k in obj_names})
    if unknown:
        log.warning("%s: obj_id(s) %s not in the object list; their estimates are ignored", where, unknown)
    rows = []
    for r in table.itertuples(index=False):
        if int(r.obj_id) not in obj_names:
            continue
        key = (int(r.scene_id), int(r.im_id))
        rows.append(
            {
                "frame_id": frame_ids.get(key, f"{key[0]:06d}/{key[1]:06d}"),
                "scene_id": key[0],
                "im_id": key[1],
                "obj_name": obj_names[int(r.obj_id)],
                "obj_id": int(r.obj_id),
                "status": "ok",
                "reason": "",
                "R": list(map(float, r.R)),
                "t_m": (np.asarray(r.t_mm, dtype=np.float64) / 1000.0).tolist(),
                "confidence": float(r.score),
                "time_total_s": float(r.time_s),
            }
        )
    cols = [
        "frame_id",
        "scene_id",
        "im_id",
        "obj_name",
        "obj_id",
        "status",
        "reason",
        "R",
        "t_m",
        "confidence",
        "time_total_s",
    ]
    return pd.DataFrame(rows, columns=cols)
