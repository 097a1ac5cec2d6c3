"""Where a run's misses are lost: in the template library, or in the frame's keypoints themselves?

For each (frame, object) pair of a finished run that has ground truth, the frame's SIFT keypoints (the
run's feature settings) on the object's ground-truth silhouette are matched, by nearest descriptor, against

- ``library``: the run's template library (every view, both distances), and
- ``exact``: a template rendered at the ground-truth pose itself (the run's shading, the frame's camera)
  and lifted to 3D the way the library's templates are: the best view a library could hold;

and a match counts as right when its 3D point projects, at the ground truth, within 4 px of the frame
keypoint. If ``exact`` finds many more right matches than ``library`` on the missed pairs, denser views
or other template distances would help; if they find as few, the frame's keypoints are the limit (blur,
noise, too little print at that size) and no template can do better.

Usage:
    .venv/bin/python benchmarks/matchability.py RUN_DIR --manifest M.yaml [--objects NAME ...] [--limit N]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.config import load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.io import library
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.features import detect_shapes, make_sift, to_gray  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.method.templates import lift_keypoints  # noqa: E402

RIGHT_PX = 4.0


def right_matches(desc_q: np.ndarray, xy_q: np.ndarray, desc_t: np.ndarray, xy_t_at_gt: np.ndarray) -> int:
    """Frame keypoints whose nearest template descriptor (exact search) projects within RIGHT_PX of them."""
    if len(desc_q) == 0 or len(desc_t) == 0:
        return 0
    d2 = (desc_q**2).sum(1)[:, None] + (desc_t**2).sum(1)[None, :] - 2.0 * desc_q @ desc_t.T
    nearest = d2.argmin(1)
    return int((np.linalg.norm(xy_t_at_gt[nearest] - xy_q, axis=1) < RIGHT_PX).sum())


def project(pts: np.ndarray, T: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = (pts @ T[:3, :3].T + T[:3, 3]) @ K.T
    return p[:, :2] / p[:, 2:]


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run", type=Path, help="a finished `batchpose run` folder (with report/frames.csv)")
    ap.add_argument("--manifest", type=Path, required=True, help="the manifest the run was made from")
    ap.add_argument("--objects", nargs="+", help="only these objects (default: every object with ground truth)")
    ap.add_argument("--limit", type=int, default=0, help="at most this many pairs per object (0: all)")
    args = ap.parse_args()

    conf = load_estimator_config(load_yaml(args.run / "config.yaml")["pipeline"])
    objects = json.loads((args.run / "objects.json").read_text())
    scored = pd.read_csv(args.run / "report" / "frames.csv")
    gt = pd.read_parquet(args.run / "gt.parquet")
    names = args.objects or sorted(set(scored["obj_name"]))
    sift = make_sift(conf.features)
    renderer = get_renderer()
    libs = {n: library.load(Path(objects[n]["library"])) for n in names}
    models = {n: load_mesh(Path(objects[n]["mesh"]), conf.mesh, name=n) for n in names}
    print(f"# matchability: {machine()}; code {code_version()}; run {args.run}")

    counts: dict[tuple[str, bool], list[np.ndarray]] = {}
    pairs = dict.fromkeys(names, 0)
    man = load_manifest(args.manifest)
    for frame in open_frames(man.frames, man.path.parent):
        here = gt[(gt["frame_id"] == frame.frame_id) & gt["obj_name"].isin(names)]
        if here.empty:
            continue
        gray = None
        for g in here.itertuples():
            row = scored[(scored["frame_id"] == frame.frame_id) & (scored["obj_name"] == g.obj_name)]
            if row.empty or (args.limit and pairs[g.obj_name] >= args.limit):
                continue
            row = row.iloc[0]
            found = row["status"] == "ok" and row["adds_m"] <= 0.1 * row["diameter_m"]
            if gray is None:
                rgb = decode_image(frame)
                gray = to_gray(rgb)
                xy, desc, _ = detect_shapes(gray, conf.features, sift=sift)
            T = np.eye(4)
            T[:3, :3] = np.asarray(g.R).reshape(3, 3)
            T[:3, 3] = np.asarray(g.t_m)
            K, lib, model = frame.camera.K, libs[g.obj_name], models[g.obj_name]
            h, w = gray.shape
            render, depth = renderer.render(
                model.content_hash, model.mesh, T, K, w, h, conf.render.shading, conf.render.znear_m, conf.render.zfar_m
            )
            if not (depth > 0).any():
                continue
            col = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
            line = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
            on = depth[line, col] > 0  # keypoints on the object's ground-truth silhouette
            xy_r, desc_r, _ = detect_shapes(to_gray(render), conf.features, sift=sift)
            keep, _ = lift_keypoints(xy_r, depth, K, np.linalg.inv(T))
            n = np.array(
                [
                    on.sum(),
                    right_matches(desc[on], xy[on], lib.desc, project(lib.pts3d, T, K)),
                    right_matches(desc[on], xy[on], desc_r[keep], xy_r[keep]),
                ]
            )
            counts.setdefault((g.obj_name, bool(found)), []).append(n)
            pairs[g.obj_name] += 1

    rows = []
    for (name, found), ns in sorted(counts.items()):
        a = np.array(ns)
        rows.append(
            [
                name,
                "found" if found else "missed",
                len(a),
                f"{np.median(a[:, 0]):.0f}",
                f"{np.median(a[:, 1]):.0f} ({a[:, 1].sum()})",
                f"{np.median(a[:, 2]):.0f} ({a[:, 2].sum()})",
            ]
        )
    headers = ["object", "pairs", "n", "keypoints on it", "right: library", "right: exact-pose template"]
    print("\nmedian per pair (sum over pairs)")
    print(table(rows, headers))
    return 0


if __name__ == "__main__":
    sys.exit(main())
