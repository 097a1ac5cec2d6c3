"""Replay a finished run's plane search under other settings, without SIFT: a plane change measured in minutes.

The plane search (``plane.enabled``, :mod:`batchpose.method.plane`) looks for an object SIFT missed on the surface
the found objects rest on. Its inputs are the frame and the other objects' poses, and a finished run holds
both. This script takes a run, puts back every pose it reported for the objects not looked at, takes away
the plane search's own poses of the objects looked at (``--objects``: they are searched again, as are
those with no pose), runs the plane search once with the run's settings and once with ``--set``'s, and
compares both with the ground truth:

- ``right``: ADD-S under 0.1 of the object's diameter; ``near``: under 10 cm (the AUC's range); ``wrong``:
  farther; ``none``: no pose;
- ``credit``: the pairs' summed AUC credit, 1 - ADD-S / 10 cm for a pose (0 beyond, and with no pose),
  before and after — what the change is worth to the mean ADD-S AUC, pair for pair.

The replay is not the run: a weak SIFT pose a placement had to beat is gone, so the "before" column can
differ from the run's own rows in a pair or two; compare the two replayed columns with each other.

Usage (a tabletop run of benchmarks/tabletop.py, the eight inserted objects):
    .venv/bin/python benchmarks/plane_replay.py runs/tt/run --manifest runs/tt/tabletop_annotations.yaml \\
        --objects 005_tomato_soup_can 007_tuna_fish_can 008_pudding_box 009_gelatin_box 010_potted_meat_can \\
        021_bleach_cleanser 035_power_drill 040_large_marker --set plane.min_colour=0.2
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

from batchpose.config import apply_overrides, load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.core.poses import PoseRecord  # noqa: E402
from batchpose.io import library
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.estimator import PoseEstimator  # noqa: E402
from batchpose.method.on_plane import use_plane  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.method.sequence import Sequence  # noqa: E402
from batchpose.report.metrics import adds  # noqa: E402

#: Reasons of the poses the plane search made (taken away from the objects looked at).
PLANE_REASONS = ("found by the plane search", "followed from the previous frame's plane search")
KINDS = ("right", "near", "wrong", "none")


def pose(R, t) -> np.ndarray | None:
    T = np.eye(4)
    T[:3, :3] = np.reshape(R, (3, 3))
    T[:3, 3] = t
    return T if np.all(np.isfinite(T)) else None


def records_before_plane(rows: pd.DataFrame, looked_at: set[str]) -> list[PoseRecord]:
    """The frame's records as the plane search found them: every pose the run reported, except the plane
    search's own of the objects looked at (those become "no pose"); the objects not looked at without a pose
    are left out (they are not searched)."""
    out = []
    for r in rows.itertuples():
        if r.obj_name in looked_at and (r.status != "ok" or r.reason.startswith(PLANE_REASONS)):
            out.append(PoseRecord(r.frame_id, r.obj_name, "pnp_failed"))
        elif r.status == "ok":
            out.append(PoseRecord(r.frame_id, r.obj_name, "ok", r.reason, cam_from_model=pose(r.R, r.t_m),
                                  confidence=r.confidence))  # fmt: skip
    return out


def kind(T: np.ndarray | None, G: np.ndarray, pts: np.ndarray, diameter: float) -> tuple[str, float]:
    """(kind, AUC credit) of pose T against ground truth G."""
    if T is None:
        return "none", 0.0
    d = adds(T[:3, :3], T[:3, 3], G[:3, :3], G[:3, 3], pts)
    label = "right" if d < 0.1 * diameter else ("near" if d < 0.1 else "wrong")
    return label, max(0.0, 1.0 - d / 0.1)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run", type=Path, help="a finished `batchpose run` folder (with poses.parquet, gt.parquet)")
    ap.add_argument("--manifest", type=Path, required=True, help="the manifest the run was made from")
    ap.add_argument("--objects", nargs="+", required=True, help="the objects looked for (the others stay as found)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="the changed setting(s), as `batchpose run --set`")  # fmt: skip
    args = ap.parse_args()

    pipeline = load_yaml(args.run / "config.yaml")["pipeline"]
    confs = {
        "run": load_estimator_config(pipeline),
        "set": load_estimator_config(apply_overrides(pipeline, args.overrides)),
    }
    objects = json.loads((args.run / "objects.json").read_text())
    poses, gt = pd.read_parquet(args.run / "poses.parquet"), pd.read_parquet(args.run / "gt.parquet")
    names = sorted(objects)
    libs = {n: library.load(Path(objects[n]["library"])) for n in names}
    models = {n: load_mesh(Path(objects[n]["mesh"]), confs["run"].mesh, name=n) for n in names}
    pts = {n: np.loadtxt(objects[n]["points"]) for n in args.objects}
    renderer = get_renderer()
    estimators = {k: PoseEstimator(c, libs, models=models, renderer=renderer) for k, c in confs.items()}
    sequences = {k: Sequence() for k in confs}  # each keeps its placements for the next frame
    looked_at = set(args.objects)
    print(f"# plane_replay: {machine()}; code {code_version()}; run {args.run}; --set {' '.join(args.overrides)}")

    rows = []
    man = load_manifest(args.manifest)
    for frame in open_frames(man.frames, man.path.parent):
        here = poses[poses["frame_id"] == frame.frame_id]
        truth = gt[(gt["frame_id"] == frame.frame_id) & gt["obj_name"].isin(looked_at)]
        if here.empty or truth.empty:
            continue
        rgb, found = None, {}
        for key, est in estimators.items():
            records = records_before_plane(here, looked_at)
            weak = est.conf.plane.min_confidence
            lost = [r for r in records if r.obj_name in looked_at and (not r.ok or r.confidence < weak)]
            if not lost:
                break
            rgb = decode_image(frame) if rgb is None else rgb
            use_plane(est.objects, frame, rgb, records, sequences[key])
            for r in lost:
                found.setdefault(r.obj_name, {})[key] = r.cam_from_model if r.ok else None
        for g in truth.itertuples():
            if g.obj_name not in found:
                continue
            G = pose(g.R, g.t_m)
            row = {"frame_id": frame.frame_id, "obj_name": g.obj_name}
            for key, T in found[g.obj_name].items():
                row[key], row[f"{key}_credit"] = kind(T, G, pts[g.obj_name], objects[g.obj_name]["diameter_m"])
            rows.append(row)
    if not rows:
        print("no pair of the objects looked at was searched")
        return 0
    df = pd.DataFrame(rows)
    per = []
    for name, d in df.groupby("obj_name"):
        counts = [f"{(d['run'] == k).sum()} → {(d['set'] == k).sum()}" for k in KINDS]
        per.append([name, len(d), *counts, f"{d['run_credit'].sum():.2f} → {d['set_credit'].sum():.2f}"])
    total = [f"{(df['run'] == k).sum()} → {(df['set'] == k).sum()}" for k in KINDS]
    per.append(["all", len(df), *total, f"{df['run_credit'].sum():.2f} → {df['set_credit'].sum():.2f}"])
    print(table(per, ["object", "pairs searched", *KINDS, "credit"]))
    gain = df["set_credit"].sum() - df["run_credit"].sum()
    print(f"\n{int((df['run'] != df['set']).sum())} of {len(df)} pairs change kind; credit {gain:+.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
