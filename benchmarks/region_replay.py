"""Replay one image region, one object (``region.max_overlap``) over a finished run, and score its verdicts.

The check (:func:`batchpose.method.region.claim_regions`) needs the frame and the ok poses with their evidence
(inlier pixels), all of which ``poses.parquet`` holds. This script takes a run made without it (``--set
region.max_overlap=0``), puts each frame's ok SIFT and tracked poses back (the searches' poses are left out:
the check runs before the searches), runs the check with the run's settings and ``--set``'s, and compares each
conflict with the ground truth: a pose is ``right`` when its ADD-S is under 0.1 of the object's diameter,
``wrong`` when farther, ``absent`` when the ground truth does not list the object in that frame. A conflict is
resolved right when the loser is wrong or absent and the winner right; wrongly when the loser was right.

The replay is not the run: a weak SIFT pose that a search replaced is not in ``poses.parquet``, so its
conflicts are missed, and a conflict's loser is not searched for again; rerun with the check on for those.

Usage:
    .venv/bin/python benchmarks/region_replay.py RUN --manifest MANIFEST [--cache DIR] \\
        [--set region.max_overlap=0.5 ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.config import apply_overrides, load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.core.poses import PoseRecord, row_cam_from_model  # noqa: E402
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.objects import Objects  # noqa: E402
from batchpose.method.region import claim_regions  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.method.sequence import Sequence  # noqa: E402
from batchpose.report.metrics import adds  # noqa: E402

#: Reasons of the searches' poses (the check runs before the searches, so it never sees them).
SEARCH_REASONS = ("plane search", "depth search")


def ok_records(rows: pd.DataFrame) -> list[PoseRecord]:
    """The frame's ok SIFT and tracked poses as the check sees them, with their inlier pixels."""
    out = []
    for r in rows.to_dict("records"):
        if r["status"] != "ok" or any(s in r["reason"] for s in SEARCH_REASONS):
            continue
        rec = PoseRecord(r["frame_id"], r["obj_name"], "ok", r["reason"], cam_from_model=row_cam_from_model(r))
        rec.confidence, rec.tracked = float(r["confidence"]), bool(r["tracked"])
        rec.inliers_px = np.asarray(r["inliers_px"], float).reshape(-1, 2)
        out.append(rec)
    return out


def verdict(rec: PoseRecord, truth: dict, points: dict, diameters: dict) -> str:
    """right / wrong (ADD-S against 0.1 d) / absent (not in the frame's ground truth)."""
    G = truth.get(rec.obj_name)
    if G is None:
        return "absent"
    T = rec.cam_from_model
    d = adds(T[:3, :3], T[:3, 3], G[:3, :3], G[:3, 3], points[rec.obj_name])
    return "right" if d < 0.1 * diameters[rec.obj_name] else "wrong"


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run", type=Path, help="a finished `batchpose run` folder (poses.parquet, gt.parquet)")
    ap.add_argument("--manifest", type=Path, required=True, help="the manifest the run was made from")
    ap.add_argument("--cache", type=Path, help="the run's --cache (its loaded meshes; default: parse the files)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    pipeline = load_yaml(args.run / "config.yaml")["pipeline"]
    conf = load_estimator_config(apply_overrides(pipeline, ["region.max_overlap=0.5", *args.overrides]))
    objects_json = json.loads((args.run / "objects.json").read_text())
    names = sorted(objects_json)
    models = {n: load_mesh(Path(objects_json[n]["mesh"]), conf.mesh, name=n, cache_dir=args.cache) for n in names}
    points = {n: np.loadtxt(objects_json[n]["points"]) for n in names}
    diameters = {n: float(objects_json[n]["diameter_m"]) for n in names}
    objects = Objects(conf, {}, models=models, renderer=get_renderer())
    poses, gt = pd.read_parquet(args.run / "poses.parquet"), pd.read_parquet(args.run / "gt.parquet")
    print(f"# region_replay: {machine()}; code {code_version()}; run {args.run}; region {conf.region}")
    man = load_manifest(args.manifest)
    rows, n_ok, spent, n_frames = [], {"right": 0, "wrong": 0, "absent": 0}, 0.0, 0
    for frame in open_frames(man.frames, man.path.parent):
        records = ok_records(poses[poses["frame_id"] == frame.frame_id])
        truth = {g["obj_name"]: row_cam_from_model(g) for g in gt[gt["frame_id"] == frame.frame_id].to_dict("records")}
        kinds = {id(r): verdict(r, truth, points, diameters) for r in records}
        for r in records:
            n_ok[kinds[id(r)]] += 1
        if len(records) < 2:
            continue
        rgb = decode_image(frame)
        if n_frames == 0:  # the GL context and the meshes' upload are not the check's
            for n in names:
                objects.render(n, records[0].cam_from_model, frame.camera)
        t0 = time.perf_counter()
        claim_regions(objects, frame, rgb, records, Sequence())
        spent, n_frames = spent + time.perf_counter() - t0, n_frames + 1
        for r in records:
            if r.status == "conflict":
                winner = next(w for w in records if r.reason.startswith(f"claims the pixels of {w.obj_name} "))
                rows.append([frame.frame_id, r.obj_name, kinds[id(r)], winner.obj_name, kinds[id(winner)], r.reason])
    print(f"ok poses replayed: {sum(n_ok.values())} ({', '.join(f'{k} {v}' for k, v in n_ok.items())})")
    print(f"the check: {1e3 * spent / max(n_frames, 1):.1f} ms a frame with two or more ok poses ({n_frames} frames)")
    if not rows:
        print("no conflict")
        return 0
    print(table(rows, ["frame", "loser", "loser is", "winner", "winner is", "reason"]))
    df = pd.DataFrame(rows, columns=["frame", "loser", "lk", "winner", "wk", "reason"])
    good = int((df["lk"].isin(["wrong", "absent"]) & (df["wk"] == "right")).sum())
    lost_right = int((df["lk"] == "right").sum())
    others = len(df) - good - lost_right
    print(f"\n{len(df)} conflicts: {good} resolved right (a wrong or absent pose lost to a right one), "
          f"{lost_right} wrongly (a right pose lost), {others} between two wrong poses")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
