"""HD frames: what a camera larger than 640x480 costs, and what ``max_image_side_px`` gives back.

The bundled demo's YCB-Video frames are upscaled by ``--factor`` (3: 1920x1440; the camera scaled with
them, depth left out), then the whole job runs once per ``--sides`` value of ``max_image_side_px`` (0: full
resolution), ``--jobs 1``, each in a fresh process with a fresh template cache: cold template build time,
estimation time per (frame, object) pair, the process's peak RSS, and ADD-S / ADD AUC. Upscaled frames hold
no detail a 640x480 frame lacks, so the accuracy column checks that resizing loses nothing it should not;
what a real HD camera's finer texture is worth at full resolution cannot be measured on them.

Usage:
    .venv/bin/python benchmarks/hd_frames.py [--factor 3] [--sides 0 1280 960 640] [--keep DIR]
"""

from __future__ import annotations

import argparse
import logging
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import pandas as pd
import scipy.io

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, StageTimer, code_version, machine, run_in_child, table  # noqa: E402

from batchpose import run  # noqa: E402
from batchpose.stages import build_templates  # noqa: E402
from batchpose.stages import estimate as estimate_poses


def upscale_demo(factor: float, out: Path) -> Path:
    """The demo's YCB-Video folder with colour images and K scaled by ``factor`` (no depth); its manifest."""
    src = REPO / "demo_data" / "ycbv"
    for p in sorted(src.rglob("*")):
        q = out / "ycbv" / p.relative_to(src)
        if p.is_dir() or p.name.endswith(("-depth.png", "-label.png")):
            continue
        q.parent.mkdir(parents=True, exist_ok=True)
        if p.name.endswith("-color.png"):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(q), cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC))
        elif p.name.endswith("-meta.mat"):
            meta = {k: v for k, v in scipy.io.loadmat(str(p)).items() if not k.startswith("__")}
            K = meta["intrinsic_matrix"].astype(float).copy()
            K[:2, :2] *= factor
            K[:2, 2] = factor * (K[:2, 2] + 0.5) - 0.5
            scipy.io.savemat(str(q), meta | {"intrinsic_matrix": K})
        else:
            shutil.copy(p, q)
    manifest = out / "hd.yaml"
    models = REPO / "demo_data" / "models"
    manifest.write_text(
        f"name: hd_x{factor:g}\nframes: {{format: ycbv, root: {out / 'ycbv'}}}\n"
        f"models: {{root: {models}, mesh: '{{name}}/textured.obj', points: '{{name}}/points.xyz'}}\n"
        "objects: [003_cracker_box, 009_gelatin_box]\ntargets: annotations\n"
    )
    return manifest


def one_run(manifest: Path, side: int, out: Path) -> dict:
    """The whole job at ``max_image_side_px = side`` (in a child process: its peak RSS is this run's)."""
    logging.basicConfig(level=logging.WARNING)
    timer = StageTimer()
    timer.wrap(build_templates, "build_all", "templates")
    timer.wrap(estimate_poses, "main", "estimate")
    t0 = time.perf_counter()
    with timer:
        run_dir = run.main(
            REPO / "pipelines" / "gnc_pose.yaml",
            str(manifest),
            out / f"run_{side}",
            cache_dir=out / f"cache_{side}",
            overrides=[f"max_image_side_px={side}"],
            jobs=1,
        )
    poses = pd.read_parquet(run_dir / "poses.parquet")
    summary = pd.read_csv(run_dir / "report" / "summary.csv")
    pooled = summary.set_index("obj_name").loc["pooled"]
    return {
        "side": side,
        "templates_s": timer.total["templates"],
        "per_pair_s": timer.total["estimate"] / max(len(poses), 1),
        "total_s": time.perf_counter() - t0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "ok": int((poses["status"] == "ok").sum()),
        "pairs": len(poses),
        "adds_auc": float(pooled["adds_auc"]),
        "add_auc": float(pooled["add_auc"]),
    }


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    ap.add_argument("--factor", type=float, default=3.0, help="upscaling of the 640x480 demo frames (default 3)")
    ap.add_argument("--sides", type=int, nargs="+", default=[0, 1280, 960, 640], help="max_image_side_px values")
    ap.add_argument("--keep", help="folder for the frames, runs and caches (default: a temporary one, removed)")
    args = ap.parse_args()
    out = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bp_hd_"))
    out.mkdir(parents=True, exist_ok=True)
    try:
        manifest = upscale_demo(args.factor, out)
        w, h = round(640 * args.factor), round(480 * args.factor)
        print(f"machine : {machine()}\ncode    : {code_version()}\nframes  : the demo's 5 pairs at {w}x{h}\n")
        rows = []
        for side in args.sides:
            r = run_in_child(one_run, manifest, side, out)
            rows.append(
                [
                    side or f"0 (full, {w}x{h})",
                    f"{r['templates_s']:.1f}",
                    f"{r['per_pair_s']:.2f}",
                    f"{r['peak_rss_mb']:.0f}",
                    f"{r['ok']}/{r['pairs']}",
                    f"{r['adds_auc']:.1f} / {r['add_auc']:.1f}",
                ]
            )
        print(
            table(
                rows,
                [
                    "max_image_side_px",
                    "templates cold (s)",
                    "estimate s/pair",
                    "peak RSS (MB)",
                    "ok",
                    "ADD-S / ADD AUC",
                ],
            )
        )
    finally:
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
