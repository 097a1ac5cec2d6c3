"""Held-out accuracy against the pose the colour image shows: what the estimator loses, and what no image can give.

``benchmarks/heldout.py`` renders each object with the camera's focal lengths scaled by a factor s just
under 1 (``--scale-error``, 0.5–3.7 % by default: real YCB-Video colour frames show their objects that much
smaller than the ground truth, reports/ACCURACY.md "Along the line of sight"). Such a frame shows the object
where the ground truth's pose would stand with its distance along the optical axis divided by s (exact for the
object's centre; its other points move by their depth offset times 1/s − 1, under 2 mm). No colour image holds
the ground truth's distance then, and an estimator exactly right about the image is still up to 3.7 % too far.

This script scores finished heldout.py runs (their ``--keep`` folders, with the data set's
``shown_scale.json``) three ways, per object, pooled over the runs given:

- **truth**: the estimates against the ground truth, as the runs' reports score them;
- **image**: the estimates against the pose the image shows;
- **ceiling**: the pose the image shows, scored against the ground truth as if it were an estimate of every
  instance: the most an RGB estimator can score on these frames.

and the precision of ``ok`` (ADD-S < 0.2 d) against the truth and against the image, with the ok poses that
would fail 0.2 d against the truth even at the image's pose exactly ("unavoidable").

Usage:
    .venv/bin/python benchmarks/as_shown.py HELDOUT_DIR [HELDOUT_DIR ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import table  # noqa: E402

from batchpose.report.metrics import score, vocap_auc  # noqa: E402
from batchpose.report.runs import load_run  # noqa: E402

RIGHT = 0.2  # ok is right when ADD-S < 0.2 d (the precision bar)


def shown_truth(data: Path, gt: pd.DataFrame) -> pd.DataFrame:
    """``gt`` (a run's ``gt.parquet`` rows, frame_id ``scene/im_id``) moved to the pose each frame's image
    shows: the distance along the optical axis divided by the frame's scale (``data/<scene>/shown_scale.json``)."""
    scales: dict[str, dict[str, float]] = {}
    t_shown = []
    for frame_id, t in zip(gt["frame_id"], gt["t_m"], strict=True):
        scene, im = str(frame_id).split("/")
        if scene not in scales:
            path = data / scene / "shown_scale.json"
            if not path.is_file():
                sys.exit(f"error: {path} does not exist (made by a heldout.py older than this script? rerun it)")
            scales[scene] = json.loads(path.read_text())
        t = np.asarray(t, dtype=float).copy()
        t[2] /= scales[scene][str(int(im))]
        t_shown.append(t)
    return gt.assign(t_m=t_shown)


def instances(folder: Path) -> pd.DataFrame:
    """One row per ground-truth instance of the heldout.py folder's run: status, diameter, and ADD-S / ADD
    against the truth, against the image and of the ceiling (metres)."""
    run = load_run(folder / "run")
    if run.gt is None or run.gt.empty:
        sys.exit(f"error: {folder / 'run'} has no ground truth (gt.parquet): not a heldout.py run?")
    points, diameters = run.model_points(run.gt["obj_name"])
    image = shown_truth(folder / "data", run.gt)
    truth, _ = score(run.poses, run.gt, points, diameters)
    seen, _ = score(run.poses, image, points, diameters)
    exact = image.assign(status="ok", confidence=1.0)
    ceiling, _ = score(exact, run.gt, points, diameters)
    out = truth[["frame_id", "obj_name", "status", "diameter_m", "adds_m", "add_m"]].copy()
    for name, part in (("image", seen), ("ceiling", ceiling)):
        out[f"adds_{name}"] = part["adds_m"].to_numpy()
        out[f"add_{name}"] = part["add_m"].to_numpy()
    return out.assign(run=str(folder))


def summarize(pairs: pd.DataFrame) -> tuple[list[list[str]], dict[str, int]]:
    """Table rows per object and their mean, and the pooled ok counts (see the module docstring)."""
    rows, aucs = [], []
    for name, g in pairs.groupby("obj_name", sort=True):
        a = [vocap_auc(g[c].to_numpy(float)) for c in ("adds_m", "add_m", "adds_image", "add_image")]
        a += [vocap_auc(g[c].to_numpy(float)) for c in ("adds_ceiling", "add_ceiling")]
        aucs.append(a)
        rows.append([str(name), f"{int((g.status == 'ok').sum())}/{len(g)}", *_counts(g), *(f"{x:.1f}" for x in a)])
    mean = np.mean(aucs, axis=0)
    rows.append(["mean over objects", f"{int((pairs.status == 'ok').sum())}/{len(pairs)}", *_counts(pairs),
                 *(f"{x:.1f}" for x in mean)])  # fmt: skip
    ok = pairs[pairs.status == "ok"]
    bar = RIGHT * ok["diameter_m"]
    totals = {
        "ok": len(ok),
        "wrong_truth": int((ok["adds_m"] >= bar).sum()),
        "wrong_image": int((ok["adds_image"] >= bar).sum()),
        "unavoidable": int((ok["adds_ceiling"] >= bar).sum()),
    }
    return rows, totals


def _counts(g: pd.DataFrame) -> list[str]:
    """An object's ok poses over 0.2 d against the truth, against the image, and at the image's pose."""
    ok = g[g.status == "ok"]
    bar = RIGHT * ok["diameter_m"]
    return [str(int((ok[c] >= bar).sum())) for c in ("adds_m", "adds_image", "adds_ceiling")]


HEADER = [
    "object",
    "ok",
    "ok > 0.2 d: truth",
    "image",
    "unavoidable",
    "ADD-S truth",
    "ADD truth",
    "ADD-S image",
    "ADD image",
    "ADD-S ceiling",
    "ADD ceiling",
]


def report(folders: list[Path]) -> str:
    """The table and the precision lines for heldout.py ``folders``, pooled."""
    pairs = pd.concat([instances(f) for f in folders], ignore_index=True)
    rows, t = summarize(pairs)
    n = max(t["ok"], 1)
    return "\n".join(
        [
            f"{len(folders)} run(s), {len(pairs)} pairs; AUCs pooled over the runs per object, then averaged",
            "",
            table(rows, HEADER),
            "",
            f"ok precision (ADD-S < {RIGHT} d): against the truth {1 - t['wrong_truth'] / n:.3f} "
            f"({t['wrong_truth']} of {t['ok']} over), against the image {1 - t['wrong_image'] / n:.3f} "
            f"({t['wrong_image']} over); {t['unavoidable']} of the ok pairs are over even at the image's pose",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("folders", nargs="+", type=Path, help="heldout.py --keep folders (data/ and run/)")
    args = ap.parse_args(argv)
    for f in args.folders:
        if not (f / "run" / "poses.parquet").is_file() or not (f / "data").is_dir():
            sys.exit(f"error: {f} is not a finished heldout.py --keep folder (needs data/ and run/poses.parquet)")
    print(report(args.folders))
    return 0


if __name__ == "__main__":
    sys.exit(main())
