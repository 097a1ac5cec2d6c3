"""A run scored the BOP way: MSSD, MSPD and (where every frame has depth) VSD per ground-truth instance, and
their average recalls per object in ``summary.csv``.

The errors and recalls are :mod:`batchpose.report.bop_metrics`'; this module finds what they need in a run:
the ok estimate of each instance (a failed or missing one is a missed pose: recall 0), the frame's K and
width (``frames.parquet``), and for VSD the frame's depth image (read again through the manifest's
``frames:`` source) and the model rendered at both poses (:mod:`batchpose.method.render`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from batchpose.core.poses import row_cam_from_model
from batchpose.errors import BatchposeError, DataError
from batchpose.report import bop_metrics, metrics
from batchpose.report.runs import RunData, fetch_frames

log = logging.getLogger("batchpose")

#: Per-instance columns added to ``frames.csv`` (``ar_vsd`` only when VSD could be computed).
INSTANCE_COLUMNS = ("mssd_mm", "mspd_px", "ar_vsd", "ar_mssd", "ar_mspd", "ar")
#: Summary columns (fractions in [0, 1], the BOP leaderboard's scale).
AR_COLUMNS = ("ar_vsd", "ar_mssd", "ar_mspd", "ar")
#: VSD is left out (with a note) for runs with more ground-truth instances than this: it reads every frame
#: again and renders the model twice per instance, about 65 ms an instance here (ycbv_dev, 640x480,
#: OSMesa), so 2000 instances add about two minutes to the report.
VSD_MAX_INSTANCES = 2000


def _ok_poses(est: pd.DataFrame) -> dict[tuple[str, str], np.ndarray]:
    """(frame_id, obj_name) -> 4x4 model->camera of each pair's picked estimate, where it is ok and finite."""
    picked = metrics.pick_estimates(est)
    out = {}
    for r in picked[picked["status"] == "ok"].to_dict("records"):
        T = row_cam_from_model(r)
        if T is not None:
            out[(r["frame_id"], r["obj_name"])] = T
    return out


def _cameras(frames: pd.DataFrame | None) -> dict[str, tuple[np.ndarray, int, int]]:
    """frame_id -> (K (3, 3), width, height) from ``frames.parquet`` (frames without a finite K left out)."""
    if frames is None or not {"frame_id", "K", "width", "height"} <= set(frames.columns):
        return {}
    out = {}
    for f in frames.drop_duplicates("frame_id").to_dict("records"):
        K = np.asarray(f["K"], dtype=np.float64).reshape(-1)
        if K.size == 9 and np.all(np.isfinite(K)) and int(f["width"]) > 0:
            out[f["frame_id"]] = (K.reshape(3, 3), int(f["width"]), int(f["height"]))
    return out


def instance_errors(
    est: pd.DataFrame,
    gt: pd.DataFrame,
    points: Mapping[str, np.ndarray],
    diameters: Mapping[str, float],
    frames: pd.DataFrame | None,
) -> pd.DataFrame:
    """MSSD and MSPD of each ground-truth instance, and their recalls.

    Args:
        est: ``poses.parquet`` rows; a pair's estimate counts when its picked row is ok.
        gt: ground truth, one row per instance (frame_id, obj_name, R, t_m).
        points: obj_name -> (N, 3) model points, metres.
        diameters: obj_name -> diameter, metres.
        frames: ``frames.parquet`` (frame_id, K, width, height), or None (then MSPD is NaN).

    Returns:
        One row per row of ``gt``, in its order: mssd_mm, mspd_px (+inf for a missed pose, NaN for MSPD
        without the frame's K), ar_mssd, ar_mspd (fractions of the thresholds passed; NaN without K).
    """
    ok = _ok_poses(est)
    cams = _cameras(frames)
    rows = []
    for g in gt.to_dict("records"):
        key = (g["frame_id"], g["obj_name"])
        T_gt, T_est = row_cam_from_model(g), ok.get(key)
        cam = cams.get(g["frame_id"])
        diam = float(diameters[g["obj_name"]])
        e_mssd = e_mspd = np.inf
        if T_gt is not None and T_est is not None:
            syms = bop_metrics.symmetry_transforms(g["obj_name"])
            pose = (T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3])
            e_mssd = bop_metrics.mssd(*pose, points[g["obj_name"]], syms)
            if cam is not None:
                e_mspd = bop_metrics.mspd(*pose, cam[0], points[g["obj_name"]], syms)
        if cam is None:
            e_mspd = np.nan
        rows.append(
            {
                "mssd_mm": e_mssd * 1000.0,
                "mspd_px": e_mspd,
                "ar_mssd": bop_metrics.ar_mssd(e_mssd, diam),
                "ar_mspd": bop_metrics.ar_mspd(e_mspd, cam[1]) if cam is not None else np.nan,
            }
        )
    return pd.DataFrame(rows, columns=["mssd_mm", "mspd_px", "ar_mssd", "ar_mspd"], index=gt.index)


def _load_geometry(mesh_path: Path, run: RunData):
    """The mesh without texture, scaled to metres as the estimator did (for depth renders)."""
    import trimesh

    from batchpose.errors import MeshError
    from batchpose.io.mesh import unit_scale

    try:
        mesh = trimesh.load(mesh_path, force="mesh", process=False, skip_materials=True)
    except (OSError, ValueError, KeyError, IndexError, AttributeError, TypeError) as e:
        raise MeshError(f"{mesh_path}: cannot load mesh for VSD ({e})") from None
    scale = unit_scale(mesh_path, mesh.bounds, run.mesh_conf)
    if scale != 1.0:
        mesh.apply_scale(scale)
    return mesh


def vsd_recalls(run: RunData, gt: pd.DataFrame, diameters: Mapping[str, float]) -> tuple[np.ndarray | None, str]:
    """Each ground-truth instance's VSD recall, or (None, why not) when some frame has no depth image, a mesh
    cannot be rendered, or the frames cannot be read again.

    Returns:
        ((n,) ar_vsd per row of ``gt`` in its order, ""), or (None, reason).
    """
    if len(gt) > VSD_MAX_INSTANCES:
        return None, f"VSD left out: {len(gt)} instances, more than the {VSD_MAX_INSTANCES} it is computed for"
    frame_ids = set(gt["frame_id"])
    found, note = fetch_frames(run, frame_ids)
    if len(found) < len(frame_ids):
        return None, f"VSD left out: {note or 'frames not found'}"
    no_depth = sorted(f for f, fr in found.items() if not fr.has_depth)
    if no_depth:
        return (
            None,
            f"VSD left out: {len(no_depth)} of {len(frame_ids)} frames have no depth image (e.g. {no_depth[0]})",
        )
    try:
        return _vsd_all(run, gt, diameters, found), ""
    except BatchposeError as e:
        return None, f"VSD left out: {e}"


def _vsd_all(run: RunData, gt: pd.DataFrame, diameters: Mapping[str, float], found: Mapping) -> np.ndarray:
    from batchpose.core.frames import decode_depth
    from batchpose.method.render import get_renderer

    renderer = get_renderer()
    ok = _ok_poses(run.poses)
    cams = _cameras(run.frames)
    meshes: dict[str, object] = {}
    depths: dict[str, np.ndarray | None] = {}
    out = np.zeros(len(gt))
    for i, g in enumerate(gt.to_dict("records")):
        name, fid = g["obj_name"], g["frame_id"]
        T_gt, T_est = row_cam_from_model(g), ok.get((fid, name))
        if T_gt is None or T_est is None:
            continue  # a missed pose: recall 0
        if name not in meshes:
            meshes[name] = _load_geometry(Path(run.objects[name]["mesh"]), run)
        if fid not in depths:
            depths[fid] = decode_depth(found[fid])
        depth = depths[fid]
        if depth is None:  # not after vsd_recalls' has_depth check
            raise DataError(f"{fid}: no depth image for VSD")
        K = cams[fid][0] if fid in cams else np.asarray(found[fid].camera.K, dtype=np.float64)
        h, w = depth.shape
        _, d_gt = renderer.render(f"vsd:{name}", meshes[name], T_gt, K, w, h)
        _, d_est = renderer.render(f"vsd:{name}", meshes[name], T_est, K, w, h)
        errors = bop_metrics.vsd(d_est, d_gt, depth, K, float(diameters[name]))
        out[i] = bop_metrics.ar_vsd(errors)
    return out


def _group_mean(summary: pd.DataFrame, per_instance: pd.DataFrame, column: str) -> list[float]:
    """Per summary row: the mean of an instance column over the object's instances; all instances on
    ``pooled``; the mean of the objects' means on ``mean``."""
    by_obj = per_instance.groupby("obj_name")[column].mean()
    values = []
    for name in summary["obj_name"]:
        if name == "pooled":
            values.append(float(per_instance[column].mean()) if len(per_instance) else np.nan)
        elif name == "mean":
            values.append(float(by_obj.mean()) if len(by_obj) else np.nan)
        else:
            values.append(float(by_obj.get(name, np.nan)))
    return values


def with_bop_columns(
    run: RunData, per_instance: pd.DataFrame, summary: pd.DataFrame
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``per_instance`` with :data:`INSTANCE_COLUMNS` and ``summary`` with :data:`AR_COLUMNS` (``ar_vsd``
    only where every frame of the run has a depth image and the meshes render; why not goes to
    ``run.notes``). ``ar`` is the mean of the available ARs, per instance and so per row."""
    assert run.gt is not None
    gt = run.gt.reset_index(drop=True)
    if len(gt) != len(per_instance):  # metrics.score makes one row per ground-truth row, in order
        raise ValueError(f"{len(per_instance)} scored instances for {len(gt)} ground-truth rows")
    points, diameters = run.model_points(gt["obj_name"])
    errors = instance_errors(run.poses, gt, points, diameters, run.frames)
    vsd, why = vsd_recalls(run, gt, diameters)
    if vsd is not None:
        errors.insert(2, "ar_vsd", vsd)
    elif why:
        log.info("report: %s", why)
        run.notes.append(why)
    ars = [c for c in AR_COLUMNS[:-1] if c in errors.columns and errors[c].notna().any()]
    errors["ar"] = errors[ars].mean(axis=1, skipna=False)
    per_instance = pd.concat([per_instance.reset_index(drop=True), errors.reset_index(drop=True)], axis=1)
    summary = summary.copy()
    for c in [*ars, "ar"]:
        summary[c] = _group_mean(summary, per_instance, c)
    return per_instance, summary
