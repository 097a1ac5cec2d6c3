"""Depth alignment of RGB poses that sit too far along the viewing ray, on real frames with depth.

Monocular poses on real YCB-Video frames are typically a few centimetres off along the viewing ray with
the rotation right. This replays the ``ok`` poses of a finished RGB run on a ``format: ycbv`` data set
through the depth step (:func:`batchpose.method.depth.align_to_depth`, as ``depth.enabled`` calls it: every
``depth.level``-th pixel), each first pushed ``--push-cm`` farther along the ray through the object's centre
(negative: nearer), with ``depth.ray_align`` off and on. A pose the depth contradicts counts as a failure,
like the pnp_failed row the pipeline writes. Only real frames (not ``data_syn``) are replayed.

Prints, per push and variant ("rgb": the pushed pose, no depth), the poses kept of the instances, mean
ADD-S / ADD AUC over the objects and the median translation error of the kept poses, then the same per
object for the push given by ``--per-object``.

Usage:
    .venv/bin/python benchmarks/depth_ray.py RUN_DIR [--push-cm 0 2 4 6] [--per-object 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import scipy.io

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.config import DepthConfig, EstimatorConfig, MeshConfig  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.method.depth import Surface, align_to_depth  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.report.metrics import score  # noqa: E402
from batchpose.report.runs import load_run  # noqa: E402

VARIANTS = ("rgb", "depth, ray_align off", "depth, ray_align on")


def _pose(row) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(row["R"], float).reshape(3, 3)
    T[:3, 3] = np.asarray(row["t_m"], float)
    return T


def _pushed(T: np.ndarray, centre_model: np.ndarray, push_m: float) -> np.ndarray:
    """``T`` with the object's centre moved ``push_m`` along its viewing ray (its projection kept)."""
    c = T[:3, :3] @ centre_model + T[:3, 3]
    out = T.copy()
    out[:3, 3] += c * (push_m / np.linalg.norm(c))
    return out


def _frame(root: Path, frame_id: str, level: int):
    """(depth (H/level, W/level) metres, K of that grid, full K, width, height) of a real YCB-Video frame."""
    base = root / "data" / frame_id
    meta = scipy.io.loadmat(str(base) + "-meta.mat", variable_names=["intrinsic_matrix", "factor_depth"])
    K = np.asarray(meta["intrinsic_matrix"], float)
    depth = cv2.imread(str(base) + "-depth.png", cv2.IMREAD_UNCHANGED).astype(np.float32)
    depth /= float(np.asarray(meta["factor_depth"]).item())
    K_level = K.copy()
    K_level[:2] /= level
    return np.ascontiguousarray(depth[::level, ::level]), K_level, K, depth.shape[1], depth.shape[0]


def replay(run_dir: Path, pushes_cm: list[float]) -> pd.DataFrame:
    """One estimate row per (push, variant, ok pose of a real frame): frame_id, obj_name, status, R, t_m."""
    run = load_run(run_dir)
    root = Path(run.manifest["frames"]["root"])
    poses = run.poses[(run.poses.status == "ok") & ~run.poses.frame_id.str.startswith("data_syn")]
    meshes = {n: load_mesh(Path(o["mesh"]), MeshConfig(), name=n) for n, o in run.objects.items()}
    surfaces = {n: Surface.of(m.mesh) for n, m in meshes.items()}
    renderer, rows = get_renderer(), []
    confs = {v: dataclasses.replace(DepthConfig(enabled=True), ray_align=v.endswith("on")) for v in VARIANTS[1:]}
    level, near, far = DepthConfig().level, EstimatorConfig().render.znear_m, EstimatorConfig().render.zfar_m
    for frame_id, group in poses.groupby("frame_id"):
        depth, K_level, K, w, h = _frame(root, str(frame_id), level)
        for _, p in group.iterrows():
            m = meshes[p.obj_name]

            def render(T, m=m, K=K, w=w, h=h):
                return renderer.render(m.content_hash, m.mesh, T, K, w, h, "flat", near, far)[1][::level, ::level]

            for push in pushes_cm:
                T0 = _pushed(_pose(p), surfaces[p.obj_name].points.mean(axis=0), push / 100)
                for variant in VARIANTS:
                    T, status = T0, "ok"
                    if variant != "rgb":
                        fit = align_to_depth(
                            T0, depth, render, K_level, surfaces[p.obj_name], m.diameter_m, confs[variant]
                        )
                        T, status = fit.cam_from_model, "pnp_failed" if fit.contradicted else "ok"
                    rows.append(
                        {"push": push, "variant": variant, "frame_id": frame_id, "obj_name": p.obj_name,
                         "status": status, "R": T[:3, :3].ravel(), "t_m": T[:3, 3], "confidence": 1.0}
                    )  # fmt: skip
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path, help="a finished RGB run on a format: ycbv manifest")
    ap.add_argument("--push-cm", type=float, nargs="+", default=[0.0, 2.0, 4.0, 6.0])
    ap.add_argument("--per-object", type=float, default=4.0, help="the push whose per-object table is printed")
    args = ap.parse_args()
    run = load_run(args.run_dir)
    if (run.manifest or {}).get("frames", {}).get("format") != "ycbv" or run.gt is None:
        sys.exit(f"{args.run_dir}: depth_ray needs a run with ground truth on a format: ycbv data set")
    est = replay(args.run_dir, args.push_cm)
    gt = run.gt[~run.gt.frame_id.str.startswith("data_syn")]
    points, diameters = run.model_points(gt.obj_name.unique())
    print(f"machine : {machine()}\ncode    : {code_version()}\nrun     : {args.run_dir}, {len(gt)} instances\n")
    summary_rows, per_object = [], {}
    for (push, variant), e in est.groupby(["push", "variant"], sort=False):
        _, s = score(e.drop(columns=["push", "variant"]), gt, points, diameters)
        mean = s[s.obj_name == "mean"].iloc[0]
        summary_rows.append(
            [f"{push:+.0f}", variant, f"{int(mean.n_ok)} / {int(mean.n)}", f"{mean.adds_auc:.1f}",
             f"{mean.add_auc:.1f}", f"{mean.median_trans_err_mm:.1f}"]
        )  # fmt: skip
        if push == args.per_object:
            per_object[variant] = s
    print(table(summary_rows, ["push cm", "variant", "ok", "ADD-S AUC", "ADD AUC", "median t err mm"]))
    if per_object:
        print(f"\nper object, pushed {args.per_object:+.0f} cm (ok, ADD-S / ADD AUC, median t err mm):")
        names = [n for n in per_object["rgb"].obj_name if n != "pooled"]
        out = []
        for n in names:
            cells = [n]
            for v in VARIANTS:
                r = per_object[v][per_object[v].obj_name == n].iloc[0]
                cells.append(
                    f"{int(r.n_ok)}/{int(r.n)}, {r.adds_auc:.1f} / {r.add_auc:.1f}, {r.median_trans_err_mm:.0f}"
                )
            out.append(cells)
        print(table(out, ["object", *VARIANTS]))


if __name__ == "__main__":
    main()
