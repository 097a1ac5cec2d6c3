"""Shape probe (a prototype, not used by the pipeline): can an object SIFT cannot match be found by its edges?

For a low-texture object (the default: the mustard bottle in ycbv_dev's video 0001, which every SIFT pass
misses), renders the library's views at the nearer template distance (every ``--view-step``-th), makes each
view's gradient-magnitude image at ``--scales-per-octave`` image sizes from 48 px to 0.8 of the image's
shorter side and at every 15 degrees in the image plane (at 1/4 resolution: 24,960 templates for the
mustard bottle), and slides them over the frame's gradient-magnitude image with normalised
cross-correlation, ranked by significance atanh(r) * sqrt(n - 3) (n: template pixels; a small template
correlates well anywhere). The best few are refined by half a size and half an angle step, turned into
poses and printed with their ADD-S against the ground truth and a colour score (Bhattacharyya similarity of
the rendered mesh's hue-saturation histogram to the frame's inside the silhouette, minus to a 7-px ring
around it), next to the ground truth's own colour score. With ``--refine N`` the best N hits are refined
by a pattern search on the colour score and the one scoring highest is kept. reports/ACCURACY.md
("Session 7") has the figures and what they say.

Usage:
    .venv/bin/python benchmarks/shape_probe.py [--object 006_mustard_bottle] [--frames 0001/000001 ...]
        [--top 12] [--refine N] [--cache DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO  # noqa: E402  (puts the repo on sys.path)

from batchpose import build_templates  # noqa: E402
from batchpose.config import ShapeConfig, load_estimator_config, load_yaml  # noqa: E402
from batchpose.datasets import open_frames  # noqa: E402
from batchpose.features import to_gray  # noqa: E402
from batchpose.frames import decode_image  # noqa: E402
from batchpose.mesh import load_mesh  # noqa: E402
from batchpose.render import get_renderer  # noqa: E402
from batchpose.shape import ShapeBank, colour_score, edge_image, pose_from, refine_colour, search  # noqa: E402

DATA = REPO.parent / "shared" / "data"


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--object", default="006_mustard_bottle")
    ap.add_argument("--frames", nargs="+", default=["0001/000001", "0001/000003", "0001/000005"])
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--view-step", type=int, default=2)
    ap.add_argument("--scales-per-octave", type=int, default=4)
    ap.add_argument("--cache", default=str(build_templates.default_cache_dir()))
    ap.add_argument(
        "--refine", type=int, default=0, help="refine the best N hits by their colour score and keep the best"
    )
    args = ap.parse_args()
    if not (DATA / "ycbv_dev").is_dir():
        print(f"needs {DATA / 'ycbv_dev'}")
        return 0
    conf = load_estimator_config(load_yaml(REPO / "pipelines" / "gnc_pose.yaml"))
    frames = {
        f.frame_id: f
        for f in open_frames({"format": "ycbv", "root": str(DATA / "ycbv_dev")}, REPO)
        if f.frame_id in set(args.frames)
    }
    first = frames[args.frames[0]]
    model = load_mesh(DATA / "ycb_models" / args.object / "textured.obj", conf.mesh, name=args.object)
    lib = build_templates.load(
        build_templates.main(model, conf, first.camera.K, first.camera.width, first.camera.height, Path(args.cache))
    )
    renderer = get_renderer()
    pts = lib.pts3d.astype(np.float64)

    def render_in(K, w, h):
        return lambda T: renderer.render(model.content_hash, model.mesh, T, K, w, h, "flat")

    sc = ShapeConfig(view_step=args.view_step, scales_per_octave=args.scales_per_octave)
    cam = first.camera
    t0 = time.perf_counter()
    bank = ShapeBank(
        render_in(lib.K, lib.width, lib.height),
        lib,
        0.5 * (cam.K[0, 0] + cam.K[1, 1]),
        (cam.width, cam.height),
        model.diameter_m,
        sc,
    )
    print(f"{args.object}: {len(bank.templates)} edge templates in {time.perf_counter() - t0:.1f} s")
    for fid in args.frames:
        f = frames[fid]
        rgb, cam = decode_image(f), f.camera
        gts = [p.cam_from_model for p in f.gt if p.obj_name == args.object]
        if not gts:
            print(f"{fid}: {args.object} not annotated")
            continue
        gt, render = gts[0], render_in(cam.K, cam.width, cam.height)
        t0 = time.perf_counter()
        hits = search(bank, edge_image(to_gray(rgb), sc.level), args.top)
        g = pts @ gt[:3, :3].T + gt[:3, 3]
        print(
            f"{fid}: search {time.perf_counter() - t0:.1f} s; ground truth: depth {gt[2, 3]:.2f} m, "
            f"colour score {colour_score(render, rgb, gt):.3f}"
        )

        def adds_cm(T, g=g):
            return 100 * cKDTree(pts @ T[:3, :3].T + T[:3, 3]).query(g)[0].mean()

        refined = []
        for k, h in enumerate(hits):
            T = pose_from(lib, h, cam.K)
            line = (
                f"  significance {h.score:5.1f}  view {h.view_id:3d}  angle {np.degrees(h.angle_rad):5.1f}  "
                f"depth {h.depth_m:.2f} m  ADD-S {adds_cm(T):5.1f} cm  colour {colour_score(render, rgb, T):.3f}"
            )
            if k < args.refine:
                T2, s2, n = refine_colour(render, rgb, T, model.center_m)
                refined.append((s2, adds_cm(T2)))
                line += f"  -> refined: colour {s2:.3f}, ADD-S {adds_cm(T2):5.1f} cm ({n} renders)"
            print(line)
        if refined:
            s2, a2 = max(refined)
            print(
                f"  kept (highest colour score after refinement): ADD-S {a2:.1f} cm, colour {s2:.3f}; "
                f"{time.perf_counter() - t0:.1f} s with the search"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
