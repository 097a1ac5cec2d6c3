"""Accuracy beside speed: the five pipelines on ycbv_dev, one compare table with the time per pair.

Runs ``gnc_pose``, ``paper``, ``ransac_only``, ``no_geom_weights`` and ``tp_ub`` (``batchpose.run.main``,
``--jobs 2``, fresh run folders, template libraries built first and not timed) and prints
``batchpose.stages.report.compare``'s table: detection, ADD-S / ADD AUC, recalls at 0.1 d, median errors,
compute time per (frame, object) and estimation wall time per pair. With a baseline (default
``benchmarks/accuracy_baseline.csv``, written by ``--save-baseline``) it flags any pipeline whose ADD-S or
ADD AUC fell by more than ``--tolerance`` points, so a speed-up that costs accuracy shows.
Skips (exit 0) when ../shared/data is missing.

Usage:
    .venv/bin/python benchmarks/accuracy.py [--pipelines gnc_pose paper ...] [--jobs 2] [--cache DIR]
        [--set key=value ...] [--keep DIR] [--baseline CSV] [--save-baseline] [--tolerance 1.0]
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, SHARED_DATA, StageTimer, code_version, machine, run_in_child, table, target  # noqa: E402

from batchpose import run as run_mod  # noqa: E402
from batchpose.io import library
from batchpose.stages import build_templates  # noqa: E402
from batchpose.stages import estimate as estimate_poses
from batchpose.stages import report as report_stage

PIPELINES = ("gnc_pose", "paper", "ransac_only", "no_geom_weights", "tp_ub")
BASELINE = Path(__file__).resolve().parent / "accuracy_baseline.csv"
COLUMNS = [
    ("detection_rate_pct", "detected %", 1),
    ("adds_auc_mean", "ADD-S AUC", 1),
    ("add_auc_mean", "ADD AUC", 1),
    ("adds_recall_01d", "ADD-S<0.1d %", 1),
    ("add_recall_01d", "ADD<0.1d %", 1),
    ("median_rot_err_deg", "med rot deg", 2),
    ("median_trans_err_mm", "med trans mm", 1),
]


def warm_cache(manifest: str, pipeline: str, overrides: list[str], cache: str) -> float:
    """Build the pipeline's template libraries (in a child process); returns seconds."""
    from batchpose.config import apply_overrides, load_estimator_config, load_yaml  # noqa: PLC0415
    from batchpose.io.manifest import load_manifest  # noqa: PLC0415
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415
    from batchpose.io.sources import open_frames  # noqa: PLC0415

    conf = load_estimator_config(apply_overrides(load_yaml(Path(pipeline)), list(overrides)))
    man = load_manifest(Path(manifest))
    cam = next(iter(open_frames(man.frames, man.path.parent))).camera
    t0 = time.perf_counter()
    for spec in man.objects:
        model = load_mesh(spec.mesh, conf.mesh, name=spec.name)
        build_templates.build_library(model, conf, cam.K, cam.width, cam.height, Path(cache))
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    ap.add_argument("--manifest", default=str(REPO / "data_manifest" / "ycbv_dev.yaml"))
    ap.add_argument("--pipelines", nargs="+", default=list(PIPELINES), help="names in pipelines/ or YAML paths")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument(
        "--cache",
        default=str(library.default_cache_dir()),
        help="template cache (default: $BATCHPOSE_CACHE or ~/.cache/batchpose)",
    )
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every pipeline")
    ap.add_argument("--keep", help="write the runs and the compare page here instead of a temporary folder")
    ap.add_argument("--baseline", default=str(BASELINE), help="compare.csv of an earlier run to check against")
    ap.add_argument("--save-baseline", action="store_true", help="write this run's table as the new baseline")
    ap.add_argument("--tolerance", type=float, default=1.0, help="allowed AUC drop vs the baseline, in points")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")

    if not (SHARED_DATA / "ycbv_dev").is_dir():
        print(f"skipped: {SHARED_DATA / 'ycbv_dev'} is missing (the ycbv_dev accuracy table needs it)")
        return 0
    print(f"machine : {machine()}")
    print(f"code    : {code_version()}")
    print(f"data    : {args.manifest}, --jobs {args.jobs} {' '.join('--set ' + s for s in args.set)}")

    paths = {
        Path(p).stem: (Path(p) if p.endswith(".yaml") else REPO / "pipelines" / f"{p}.yaml") for p in args.pipelines
    }
    rows, timing = [], {}
    with tempfile.TemporaryDirectory(prefix="bp-bench-accuracy-") as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        run_dirs = []
        for name, pipeline in paths.items():
            t_templates = run_in_child(warm_cache, args.manifest, str(pipeline), args.set, args.cache)
            run_dir = base / name
            shutil.rmtree(run_dir, ignore_errors=True)
            with StageTimer() as tm:
                tm.wrap(estimate_poses, "main", "estimate")
                t0 = time.perf_counter()
                run_mod.main(
                    pipeline,
                    Path(args.manifest),
                    run_dir,
                    cache_dir=Path(args.cache),
                    overrides=args.set,
                    jobs=args.jobs,
                    report=False,
                )
                wall = time.perf_counter() - t0
            timing[name] = (t_templates, tm.total["estimate"], wall)
            run_dirs.append(run_dir)
        report_stage.compare(run_dirs, base / "compare")
        df = pd.read_csv(base / "compare" / "compare.csv")
        df["run"] = list(paths)

    for r in df.to_dict("records"):
        t_templates, est, wall = timing[r["run"]]
        rows.append(
            [r["run"], int(r["n_pairs"])]
            + [f"{r[c]:.{d}f}" for c, _, d in COLUMNS]
            + [
                f"{1e3 * r['time_per_pair_s']:.0f}",
                f"{1e3 * est / r['n_pairs']:.0f}",
                f"{wall:.1f}",
                f"{t_templates:.1f}",
            ]
        )
    print(f"\n## ycbv_dev: {int(df['n_frames'].iloc[0])} frames, {int(df['n_pairs'].iloc[0])} (frame, object) pairs")
    print(
        table(
            rows,
            ["pipeline", "pairs"]
            + [h for _, h, _ in COLUMNS]
            + ["compute ms / pair", "estimate wall ms / pair", "run s", "templates s (not in run)"],
        )
    )
    print(
        "compute = sum of the per-stage times in poses.parquet (one worker); estimate wall = estimation stage / "
        f"pairs with --jobs {args.jobs} (includes worker start-up)"
    )

    print("\n## Targets")
    baseline = Path(args.baseline)
    if baseline.is_file():
        old = pd.read_csv(baseline).set_index("run")
        for r in df.to_dict("records"):
            if r["run"] not in old.index:
                print(target(None, f"{r['run']}: not in the baseline {baseline.name}"))
                continue
            o = old.loc[r["run"]]
            drops = {c: o[c] - r[c] for c in ("adds_auc_mean", "add_auc_mean")}
            ok = all(d <= args.tolerance for d in drops.values())
            print(
                target(
                    ok,
                    f"{r['run']}: ADD-S AUC {r['adds_auc_mean']:.1f} (baseline {o['adds_auc_mean']:.1f}), "
                    f"ADD AUC {r['add_auc_mean']:.1f} (baseline {o['add_auc_mean']:.1f}); "
                    f"time / pair {1e3 * r['time_per_pair_s']:.0f} ms (baseline "
                    f"{1e3 * o['time_per_pair_s']:.0f} ms); allowed drop {args.tolerance} points",
                )
            )
    else:
        print(target(None, f"no accuracy baseline at {baseline} (write one with --save-baseline)"))
    if args.save_baseline:
        keep = ["run", "n_frames", "n_pairs", "n_ok", "time_per_pair_s"] + [c for c, _, _ in COLUMNS]
        df[keep].to_csv(baseline, index=False)
        print(f"baseline written: {baseline}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
