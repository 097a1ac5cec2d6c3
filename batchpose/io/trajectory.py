"""Poses as trajectories: ``trajectory.csv`` (every (frame, object) pair with its log time, one row each) and
one TUM file per object (``stamp_s tx ty tz qx qy qz qw``, ok poses only), which ``evo`` and similar tools read.

Both give the object's pose in the camera frame (``cam_from_model``): position in metres, rotation as a unit
quaternion (x, y, z, w).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from batchpose.io.files import write_text_atomic

#: ``trajectory.csv``'s columns, in order.
TRAJECTORY_COLUMNS = (
    "stamp_ns",
    "frame_id",
    "object",
    "obj_id",
    "x_m",
    "y_m",
    "z_m",
    "qx",
    "qy",
    "qz",
    "qw",
    "status",
    "confidence",
    "verification",
    "tracked",
)


def trajectory(poses: pd.DataFrame) -> pd.DataFrame:
    """``poses.parquet``'s rows as the ``trajectory.csv`` table: position and quaternion of ``ok`` rows (empty
    otherwise: a ``low_confidence`` pose stays in ``poses.parquet`` for inspection), in the rows' order."""
    out = pd.DataFrame(
        {
            "stamp_ns": poses["stamp_ns"].astype("int64"),
            "frame_id": poses["frame_id"].astype(str),
            "object": poses["obj_name"].astype(str),
            "obj_id": poses["obj_id"].astype("int64"),
        }
    )
    ok = (poses["status"] == "ok").to_numpy()
    xyz = np.full((len(poses), 3), np.nan)
    quat = np.full((len(poses), 4), np.nan)
    if ok.any():
        R = np.stack([np.asarray(r, float).reshape(3, 3) for r in poses["R"][ok]])
        xyz[ok] = np.stack([np.asarray(t, float).reshape(3) for t in poses["t_m"][ok]])
        quat[ok] = Rotation.from_matrix(R).as_quat()  # (x, y, z, w)
    for i, col in enumerate(("x_m", "y_m", "z_m")):
        out[col] = xyz[:, i]
    for i, col in enumerate(("qx", "qy", "qz", "qw")):
        out[col] = quat[:, i]
    out["status"] = poses["status"].astype(str).to_numpy()
    out["confidence"] = poses["confidence"].astype(float).to_numpy()
    out["verification"] = poses["verification"].astype(float).to_numpy() if "verification" in poses else np.nan
    out["tracked"] = poses["tracked"].astype(bool).to_numpy() if "tracked" in poses else False
    return out[list(TRAJECTORY_COLUMNS)]


def write_trajectory_csv(table: pd.DataFrame, out: Path) -> Path:
    """Write a :func:`trajectory` table to ``out`` (atomically); returns ``out``."""
    return write_text_atomic(Path(out), table.to_csv(index=False, float_format="%.9g"), encoding="utf-8")


def write_tum(table: pd.DataFrame, out_dir: Path) -> list[Path]:
    """Write ``out_dir/<object>.txt`` in the TUM trajectory format (``stamp_s tx ty tz qx qy qz qw``, seconds
    and metres, time order) for every object with an ``ok`` pose of a :func:`trajectory` table; returns the
    files written."""
    table = table[table["status"] == "ok"].sort_values(["stamp_ns", "frame_id"], kind="stable")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    written = []
    for name, rows in table.groupby("object", sort=True):
        lines = [
            f"{r.stamp_ns / 1e9:.9f} {r.x_m:.9g} {r.y_m:.9g} {r.z_m:.9g} {r.qx:.9g} {r.qy:.9g} {r.qz:.9g} {r.qw:.9g}"
            for r in rows.itertuples()
        ]
        path = Path(out_dir) / f"{name}.txt"
        written.append(
            write_text_atomic(path, "# stamp_s tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n", encoding="utf-8")
        )
    return written
