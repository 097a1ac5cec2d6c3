"""Depth bias: are a run's poses too near or too far, and is the ground truth right? Checked against the
depth images of a YCB-Video-format data set (RGB is still all the estimator uses).

For each (frame, object) of a finished run on a ``format: ycbv`` manifest, the mesh is rendered at the
estimated pose and at the ground-truth pose with the frame's camera, and each rendered depth is compared to
the measured depth (``*-depth.png`` / ``factor_depth``) on the object's pixels in ``*-label.png``. Prints,
per instance, the median rendered-minus-measured depth for both poses and the estimate's translation error
along and across the viewing ray, then the median over instances. A pose that agrees with the sensor has a
median near 0 mm.

Usage:
    .venv/bin/python benchmarks/depth_bias.py RUN_DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import scipy.io
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.config import MeshConfig  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402


def _pose(row) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(row["R"], float).reshape(3, 3)
    T[:3, 3] = np.asarray(row["t_m"], float)
    return T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    args = ap.parse_args()
    run = args.run_dir
    manifest = yaml.safe_load((run / "manifest.yaml").read_text())  # paths resolved by the run
    if manifest["frames"].get("format") != "ycbv":
        sys.exit(f"{run}: depth_bias needs a run on a format: ycbv data set")
    root = Path(manifest["frames"]["root"])
    poses = pd.read_parquet(run / "poses.parquet")
    gt = pd.read_parquet(run / "gt.parquet")
    objects = json.loads((run / "objects.json").read_text())
    classes = (root / "classes.txt").read_text().split()
    meshes = {n: load_mesh(Path(o["mesh"]), MeshConfig(), name=n) for n, o in objects.items()}
    renderer = get_renderer()
    print(f"machine : {machine()}\ncode    : {code_version()}\nrun     : {run} ({root})\n")
    rows = []
    for _, g in gt.iterrows():
        fid, name = g["frame_id"], g["obj_name"]
        if "/" not in fid or fid.startswith("data_syn"):
            continue  # rendered frames: no sensor depth to compare with
        scene, im = fid.split("/")
        base = root / "data" / scene / im
        meta = scipy.io.loadmat(str(base) + "-meta.mat", variable_names=["intrinsic_matrix", "factor_depth"])
        K = np.asarray(meta["intrinsic_matrix"], float)
        scale = float(np.asarray(meta["factor_depth"]).item())
        depth = cv2.imread(str(base) + "-depth.png", cv2.IMREAD_UNCHANGED).astype(float) / scale
        label = cv2.imread(str(base) + "-label.png", cv2.IMREAD_UNCHANGED)
        h, w = depth.shape
        est = poses[(poses.frame_id == fid) & (poses.obj_name == name)]
        out = {"frame": fid, "object": name}
        T_gt = _pose(g)
        for which, T in (
            ("gt", T_gt),
            ("estimate", _pose(est.iloc[0]) if len(est) and est.iloc[0].status == "ok" else None),
        ):
            if T is None:
                out[f"{which} mm"] = "failed"
                continue
            m = meshes[name]
            _, d = renderer.render(m.content_hash, m.mesh, T, K, w, h, "flat", 0.05, 10.0)
            sel = (d > 0) & (depth > 0) & (label == classes.index(name) + 1)
            out[f"{which} mm"] = f"{np.median(d[sel] - depth[sel]) * 1000:+.1f}" if sel.sum() > 50 else "hidden"
            if which == "estimate":
                ray = T_gt[:3, 3] / np.linalg.norm(T_gt[:3, 3])
                dt = T[:3, 3] - T_gt[:3, 3]
                out["along ray mm"] = f"{dt @ ray * 1000:+.1f}"
                out["across mm"] = f"{np.linalg.norm(dt - (dt @ ray) * ray) * 1000:.1f}"
                out["z m"] = f"{T_gt[2, 3]:.2f}"
        rows.append(out)
    if not rows:
        sys.exit(f"{run}: no real (non-data_syn) frames with ground truth")
    cols = ["frame", "object", "z m", "gt mm", "estimate mm", "along ray mm", "across mm"]
    print("rendered minus measured depth on the object's labelled pixels (median), and the estimate's error")
    print(table([[r.get(c, "") for c in cols] for r in rows], cols))

    def med(key):
        vals = [float(r[key]) for r in rows if r.get(key, "").lstrip("+-").replace(".", "").isdigit()]
        return f"{np.median(vals):+.1f} mm over {len(vals)}" if vals else "n/a"

    print(f"\nmedian: ground truth {med('gt mm')}, estimate {med('estimate mm')}, along the ray {med('along ray mm')}")


if __name__ == "__main__":
    main()
