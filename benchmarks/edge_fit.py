"""Whose depth do the images agree with? Silhouette-to-edge fit of the estimated and the ground-truth poses.

For every ok pose of a run on a YCB-Video manifest, the mesh is rendered at the estimate, at the ground
truth, and at the ground truth moved 1.5 % and 3 % nearer and farther along its translation; each
render's silhouette contour is scored against the frame's Canny edges (mean distance to the nearest edge
pixel, capped at 10 px: lower fits better). If the ground truth fits worse than the estimate and
improves when moved to the estimate's depth, the depth difference is in the data (image vs annotation or
intrinsics), not in the estimator. Prints one line per pose and the median per video.

Usage:
    .venv/bin/python benchmarks/edge_fit.py RUN_DIR [--scenes 1 ...] [--skip OBJ ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO  # noqa: E402,F401  (puts the repo on sys.path)

from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.core.poses import row_cam_from_model  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402

SHIFTS = (-0.03, -0.015, 0.015, 0.03)


def chamfer(depth: np.ndarray, dist_to_edge: np.ndarray) -> float:
    """Mean distance (px, capped at 10) from the rendered silhouette's contour to the nearest image edge."""
    mask = (depth > 0).astype(np.uint8)
    contour = cv2.morphologyEx(mask, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    return float(np.mean(np.minimum(dist_to_edge[contour], 10.0))) if contour.any() else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--scenes", type=int, nargs="*", help="only these scene ids (default: all real videos)")
    ap.add_argument("--skip", nargs="*", default=[], help="objects to leave out")
    args = ap.parse_args()
    run_dir = args.run_dir
    objs = json.loads((run_dir / "objects.json").read_text())
    manifest = yaml.safe_load((run_dir / "manifest.yaml").read_text())
    poses = pd.read_parquet(run_dir / "poses.parquet")
    models = {n: load_mesh(Path(o["mesh"]), name=n) for n, o in objs.items() if n not in args.skip}
    renderer = get_renderer()
    source = open_frames(manifest["frames"], run_dir)  # the run's manifest.yaml holds absolute paths
    rows = []
    for frame in source:
        if frame.scene_id >= 10000 or (args.scenes and frame.scene_id not in args.scenes):
            continue
        rgb = decode_image(frame)
        gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (3, 3), 0)
        edges = cv2.Canny(gray, 40, 100)
        dist_to_edge = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
        cam = frame.camera
        for gt in frame.gt:
            if gt.obj_name not in models:
                continue
            sel = poses[(poses["frame_id"] == frame.frame_id) & (poses["obj_name"] == gt.obj_name)]
            if sel.empty or sel.iloc[0]["status"] != "ok":
                continue
            est = row_cam_from_model(sel.iloc[0])
            m = models[gt.obj_name]

            def fit(T, m=m, cam=cam, dist_to_edge=dist_to_edge):
                _, depth = renderer.render(m.content_hash, m.mesh, T, cam.K, cam.width, cam.height)
                return chamfer(depth, dist_to_edge)

            row = {
                "frame_id": frame.frame_id,
                "scene_id": frame.scene_id,
                "obj_name": gt.obj_name,
                "z_est_over_gt": est[2, 3] / gt.cam_from_model[2, 3],
                "est": fit(est),
                "gt": fit(gt.cam_from_model),
            }
            for s in SHIFTS:
                T = gt.cam_from_model.copy()
                T[:3, 3] *= 1.0 + s
                row[f"gt{s:+.3f}"] = fit(T)
            rows.append(row)
            print(
                f"{frame.frame_id} {gt.obj_name:22s} z est/gt {row['z_est_over_gt']:.3f}  edge fit (px): "
                f"estimate {row['est']:.2f}, ground truth {row['gt']:.2f}; ground truth moved "
                + ", ".join(f"{s:+.1%} {row[f'gt{s:+.3f}']:.2f}" for s in SHIFTS)
            )
    if not rows:
        print("no ok poses with ground truth in real videos")
        return 0
    df = pd.DataFrame(rows)
    print("\nmedian per video:")
    cols = ["z_est_over_gt", "est", "gt", *[f"gt{s:+.3f}" for s in SHIFTS]]
    print(df.groupby("scene_id")[cols].median().round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
