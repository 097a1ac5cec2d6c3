"""Several accuracy runs pooled into one sample, with bootstrap intervals: how sure is a mean AUC?

A held-out seed of 16 frames per object is a small sample: one pair moves an object's AUC by up to
100/16 points and the mean over 12 objects by about half a point, so seeds of the same code differ by
several points (reports/ACCURACY.md). This script reads the per-pair tables (``report/frames.csv``) of
runs over independent draws of the same kind of data (e.g. ``benchmarks/heldout.py`` at several seeds),
pools their pairs per object and prints, per object and for the mean over objects, the ADD-S and ADD AUC
(``batchpose.report.metrics.vocap_auc``, as the reports compute them) with a 95 % bootstrap interval: pairs
redrawn with replacement within each object (``--boot`` times), so each object keeps its number of pairs.
The target lines say whether the mean passes the paper's figures (85.7 / 72.2) and how often the
resampled means do. The interval assumes the pairs are independent draws, as held-out frames are;
consecutive frames of one video (ycbv_dev) are not, and their intervals come out too narrow.

Usage:
    .venv/bin/python benchmarks/pooled.py RUN [RUN ...] [--boot 2000] [--seed 0] [--objects NAME ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import table, target  # noqa: E402

from batchpose.report.metrics import vocap_auc  # noqa: E402

PAPER = {"adds_m": 85.7, "add_m": 72.2}  # GNC-Pose's mean over the 12 objects (SPEC.md / the issue)
COLUMNS = ("adds_m", "add_m")


def load(runs: list[Path]) -> pd.DataFrame:
    """The runs' per-pair rows, each tagged with its run; one-line errors for a run without a table."""
    frames = []
    for run in runs:
        path = run / "report" / "frames.csv"
        if not path.is_file():
            sys.exit(f"error: {path} does not exist (is {run} a finished `batchpose run` output directory?)")
        f = pd.read_csv(path)
        missing = {"obj_name", *COLUMNS} - set(f.columns)
        if missing:
            sys.exit(f"error: {path} has no column(s) {', '.join(sorted(missing))}: no ground truth in that run?")
        frames.append(f.assign(run=str(run)))
    return pd.concat(frames, ignore_index=True)


def bootstrap(pairs: pd.DataFrame, n_boot: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per column, (n_boot, n_objects + 1) AUCs of resampled data: each object's pairs redrawn with
    replacement within the object; the last column is the mean over objects."""
    groups = [g for _, g in pairs.groupby("obj_name", sort=True)]
    out = {}
    for col in COLUMNS:
        aucs = np.empty((n_boot, len(groups) + 1))
        for j, g in enumerate(groups):
            d = g[col].to_numpy(float)
            idx = rng.integers(0, len(d), size=(n_boot, len(d)))
            aucs[:, j] = [vocap_auc(d[i]) for i in idx]
        aucs[:, -1] = aucs[:, :-1].mean(axis=1)
        out[col] = aucs
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="batchpose run output directories (with report/frames.csv)")
    ap.add_argument("--boot", type=int, default=2000, help="bootstrap resamples (default 2000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    ap.add_argument(
        "--objects", nargs="+", help="pool only these objects (e.g. benchmarks/tabletop.py's inserted ones)"
    )
    args = ap.parse_args(argv)
    if args.boot < 100:
        sys.exit(f"error: --boot {args.boot} is too few resamples for a 95 % interval (use at least 100)")
    pairs = load(args.runs)
    if args.objects:
        unknown = sorted(set(args.objects) - set(pairs.obj_name))
        if unknown:
            sys.exit(f"error: --objects {', '.join(unknown)}: not in these runs")
        pairs = pairs[pairs.obj_name.isin(args.objects)]
    objects = sorted(pairs.obj_name.unique())
    boot = bootstrap(pairs, args.boot, np.random.default_rng(args.seed))

    def cell(col: str, j: int, value: float) -> str:
        lo, hi = np.percentile(boot[col][:, j], [2.5, 97.5])
        return f"{value:.1f} [{lo:.1f}, {hi:.1f}]"

    rows, point = [], {c: [] for c in COLUMNS}
    for j, name in enumerate(objects):
        g = pairs[pairs.obj_name == name]
        vals = {c: vocap_auc(g[c].to_numpy(float)) for c in COLUMNS}
        for c in COLUMNS:
            point[c].append(vals[c])
        ok = int((g.status == "ok").sum()) if "status" in g else len(g)
        rows.append([name, len(g), ok, *(cell(c, j, vals[c]) for c in COLUMNS)])
    means = {c: float(np.mean(point[c])) for c in COLUMNS}
    rows.append(["mean over objects", len(pairs), "", *(cell(c, len(objects), means[c]) for c in COLUMNS)])
    print(f"{len(args.runs)} run(s), {len(pairs)} pairs, {len(objects)} objects; {args.boot} resamples")
    for run, g in pairs.groupby("run", sort=False):
        per_obj = {c: np.mean([vocap_auc(h[c].to_numpy(float)) for _, h in g.groupby("obj_name")]) for c in COLUMNS}
        print(f"  {run}: {len(g)} pairs, mean ADD-S / ADD AUC {per_obj['adds_m']:.1f} / {per_obj['add_m']:.1f}")
    print()
    print(table(rows, ["object", "pairs", "ok", "ADD-S AUC [95 %]", "ADD AUC [95 %]"]))
    print()
    for c, label in (("adds_m", "ADD-S"), ("add_m", "ADD")):
        share = float((boot[c][:, -1] >= PAPER[c]).mean())
        print(
            target(
                means[c] >= PAPER[c],
                f"pooled mean {label} AUC {means[c]:.1f} >= {PAPER[c]} (the paper); "
                f"{100 * share:.0f} % of resampled means reach it",
            )
        )


if __name__ == "__main__":
    main()
