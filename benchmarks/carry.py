"""What the carry stage adds to finished runs: each run (``carry.enabled``, with ground truth) scored as it is
and as the estimate left it (the estimate stage's rows in ``shards/``, which is what ``--set
carry.enabled=false`` writes: the estimate does not depend on the carry), side by side.

With ``--keep-every N`` it also asks how far the carry gets from sparse poses: in each run, every ok pose
of the estimate is hidden (made ``too_few_matches``) except in every N-th frame of each sequence, the carry
is run in-process on that (:func:`batchpose.stages.carry.plan`, :func:`~batchpose.stages.carry.carry_gaps`, the
run's own config), and the hidden pairs it gave a pose back are scored against the ground truth.

Usage::

    PYTHONPATH=$PWD python benchmarks/carry.py RUN_DIR [RUN_DIR ...] [--keep-every N]

Prints per run and variant: pairs, ok pairs, the objects' mean ADD-S / ADD AUC, pooled ok precision and
recall (ADD-S < 0.2 d), ok poses of absent objects, poses carried and how many of them are right, and the
seconds the carry stage took (``carry.json``); with ``--keep-every``, the same for the sparse poses before and
after the carry, and the restored poses within 0.1 d / 0.2 d ADD-S.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import table  # noqa: E402

from batchpose.config import load_estimator_config  # noqa: E402
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.report.precision import pose_table  # noqa: E402
from batchpose.report.runs import load_run  # noqa: E402
from batchpose.report.scoring import score_run  # noqa: E402
from batchpose.stages import carry  # noqa: E402
from batchpose.stages.estimate import estimated_rows  # noqa: E402


def _row(name: str, variant: str, run, seconds: float | None) -> dict:
    _, summary = score_run(run)
    s = summary.set_index("obj_name")
    ok = run.poses["status"] == "ok"
    carried = run.poses.get("carried", pd.Series(False, index=run.poses.index)).fillna(False).astype(bool)
    return {
        "run": name,
        "variant": variant,
        "pairs": len(run.poses),
        "ok": int(ok.sum()),
        "ADD-S AUC": round(float(s.loc["mean", "adds_auc"]), 1),
        "ADD AUC": round(float(s.loc["mean", "add_auc"]), 1),
        "ok precision": round(float(s.loc["pooled", "ok_precision"]), 3),
        "ok recall": round(float(s.loc["pooled", "ok_recall"]), 3),
        "ok absent": int(s.loc["pooled", "n_ok_absent"]),
        "carried": int((carried & ok).sum()),
        "carried right": int(s.loc["pooled", "n_carried_correct"]),
        "carry s": "" if seconds is None else round(seconds, 1),
    }


def _sparse(run, keep_every: int, cache: Path | None) -> tuple[list[dict], str]:
    """The run's estimate with the ok poses of all but every ``keep_every``-th frame of each sequence hidden,
    before and after an in-process carry; and a line on the restored poses."""
    run_dir = run.run_dir
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    conf = load_estimator_config(saved["pipeline"])
    man = load_manifest(run_dir / "manifest.yaml")
    ids = set(run.frames["frame_id"])
    frames = {f.frame_id: f for f in open_frames(man.frames, man.path.parent) if f.frame_id in ids}
    seqs = carry.sequences(frames.values(), conf.track.max_gap_s)
    kept = {f for seq in seqs for f in seq[::keep_every]}
    est = estimated_rows(run_dir, ids)
    hide = (est["status"] == "ok") & ~est["frame_id"].isin(kept)
    sparse = est.copy()
    sparse.loc[hide, "status"] = "too_few_matches"
    sparse.loc[hide, "reason"] = "hidden by benchmarks/carry.py"
    meshes = {n: e["mesh"] for n, e in run.objects.items()}
    obj_ids = {n: int(e["obj_id"]) for n, e in run.objects.items()}
    setup = carry.CarrySetup(saved["pipeline"], obj_ids, meshes, str(cache) if cache else None)
    carry._objects(setup)  # meshes loaded and the renderer made before the clock starts
    t0 = time.perf_counter()
    gaps = carry.plan(conf, sparse, seqs)
    found = pd.DataFrame(carry.carry_gaps(carry._objects(setup), gaps, frames))
    seconds = time.perf_counter() - t0
    after = carry.overlay(sparse, found)
    name = f"{run_dir.name}, 1 in {keep_every}"
    rows = [
        _row(name, "sparse estimate", dataclasses.replace(run, poses=sparse), None),
        _row(name, "sparse + carry", dataclasses.replace(run, poses=after), seconds),
    ]
    points, diameters = run.model_points(run.gt["obj_name"])
    table = pose_table(after, run.gt, points, diameters)
    table = table[table["carried"]]
    d = np.array([diameters[n] for n in table["obj_name"]])
    adds = table["adds_m"].to_numpy(float)
    line = (
        f"{name}: {int(hide.sum())} ok poses hidden, {len(table)} given back by the carry: "
        f"{int((adds < 0.1 * d).sum())} within 0.1 d ADD-S, {int((adds < 0.2 * d).sum())} within 0.2 d; "
        f"{len(gaps)} gaps, {seconds:.1f} s"
    )
    return rows, line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished run directories with ground truth")
    ap.add_argument("--keep-every", type=int, default=0, help="also carry from every N-th frame's poses only")
    ap.add_argument("--cache", type=Path, default=None, help="the runs' --cache (meshes load from it)")
    args = ap.parse_args()
    lines = []
    rows = []
    for run_dir in args.runs:
        run = load_run(run_dir)
        if run.gt is None or run.gt.empty:
            sys.exit(f"{run_dir}: no ground truth to score against")
        done = run_dir / "carry.json"
        seconds = json.loads(done.read_text())["seconds"] if done.is_file() else None
        ids = set(run.frames["frame_id"]) if run.frames is not None else None
        rows.append(
            _row(run_dir.name, "estimate only", dataclasses.replace(run, poses=estimated_rows(run_dir, ids)), None)
        )
        rows.append(_row(run_dir.name, "with carry", run, seconds))
        if args.keep_every > 1:
            more, line = _sparse(run, args.keep_every, args.cache)
            rows += more
            lines.append(line)
    print(table([list(r.values()) for r in rows], list(rows[0])))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
