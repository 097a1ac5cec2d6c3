"""Fit and check the verification score (``min_verification``, :mod:`batchpose.method.score`).

For every untracked pose of finished runs that has a pose (ok and low_confidence), the mesh is rendered at it
and compared with the frame by the pipeline's own :func:`batchpose.method.score.comparisons` (outline,
gradient, texture, over the pixels the frame's other ok poses do not hide); the pose is *right* when its
ADD-S to the ground truth is under 0.2 of the object's diameter (``ok`` precision's rule), wrong otherwise
(an absent object's pose is wrong).

``--fit`` fits the score's logistic weights to those poses (maximum likelihood, scipy) and prints them for
:data:`batchpose.method.score.WEIGHTS`; fit on synthetic frames (``benchmarks/heldout.py``), never on the
frames you measure on. Without it, the runs are scored with the current weights: separation (AUROC) of each
term, of the score and of the pose's confidence; a reliability table (mean score against the share right,
by score bin); and, among the run's ok poses, precision and recall of right poses at several thresholds.
A run made with ``min_verification`` on has already dropped the poses it rejected: measure on runs made
with ``--set min_verification=0.000001`` (scored, nothing rejected).

Usage:
    .venv/bin/python benchmarks/verification.py RUN MANIFEST [RUN MANIFEST ...] [--cache DIR] [--fit]
        [--features OUT.parquet]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import code_version, machine, table  # noqa: E402

from batchpose.config import load_estimator_config, load_yaml  # noqa: E402
from batchpose.core.frames import decode_image  # noqa: E402
from batchpose.core.poses import PoseRecord, row_cam_from_model  # noqa: E402
from batchpose.io.manifest import load_manifest  # noqa: E402
from batchpose.io.mesh import load_mesh  # noqa: E402
from batchpose.io.sources import open_frames  # noqa: E402
from batchpose.method.objects import Objects  # noqa: E402
from batchpose.method.render import get_renderer  # noqa: E402
from batchpose.method.score import WEIGHTS, comparisons  # noqa: E402
from batchpose.report import metrics  # noqa: E402

TERMS = ("outline", "gradient", "texture")
THRESHOLDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def run_features(run: Path, manifest: Path, cache: Path | None) -> pd.DataFrame:
    """One row per untracked scored pose of ``run``: its terms, confidence, status, ADD-S / diameter, right."""
    conf = load_estimator_config(load_yaml(run / "config.yaml")["pipeline"])
    objects_json = json.loads((run / "objects.json").read_text())
    names = sorted(objects_json)
    models = {n: load_mesh(Path(objects_json[n]["mesh"]), conf.mesh, name=n, cache_dir=cache) for n in names}
    points = {n: np.loadtxt(objects_json[n]["points"]) for n in names}
    diameters = {n: float(objects_json[n]["diameter_m"]) for n in names}
    objects = Objects(conf, {}, models=models, renderer=get_renderer())
    poses, gt = pd.read_parquet(run / "poses.parquet"), pd.read_parquet(run / "gt.parquet")
    scored = metrics.pick_estimates(poses[poses["status"].isin(["ok", "low_confidence"])])
    man = load_manifest(manifest)
    rows = []
    for frame in open_frames(man.frames, man.path.parent):
        here = scored[scored["frame_id"] == frame.frame_id]
        if here.empty:
            continue
        truth = {g["obj_name"]: row_cam_from_model(g) for g in gt[gt["frame_id"] == frame.frame_id].to_dict("records")}
        records, kept = [], []
        for r in here.to_dict("records"):
            T = row_cam_from_model(r)
            if T is None:
                continue
            rec = PoseRecord(frame.frame_id, r["obj_name"], r["status"], cam_from_model=T, tracked=bool(r["tracked"]))
            records.append(rec)
            if not rec.tracked:
                kept.append((rec, r))
        found = comparisons(objects, frame, decode_image(frame), records, [rec for rec, _ in kept])
        for rec, r in kept:
            T, G, c = rec.cam_from_model, truth.get(r["obj_name"]), found[id(rec)]
            d = np.inf if G is None else metrics.adds(T[:3, :3], T[:3, 3], G[:3, :3], G[:3, 3], points[r["obj_name"]])
            terms = c.__dict__ if c is not None else {t: np.nan for t in TERMS}
            rows.append({
                "run": str(run), "frame_id": frame.frame_id, "obj_name": r["obj_name"], "status": r["status"],
                "confidence": float(r["confidence"]), "reason": r["reason"], **terms,
                "adds_d": d / diameters[r["obj_name"]], "present": G is not None,
            })  # fmt: skip
    df = pd.DataFrame(rows)
    df["right"] = df["adds_d"] < 0.2
    return df


def score_of(df: pd.DataFrame, weights=WEIGHTS) -> np.ndarray:
    x = np.c_[np.ones(len(df)), df[list(TERMS)].to_numpy(float)]
    z = x @ np.asarray(weights)
    return np.where(np.isnan(z), 0.0, 1.0 / (1.0 + np.exp(-np.nan_to_num(z))))


def auroc(right: np.ndarray, s: np.ndarray) -> float:
    s = np.nan_to_num(np.asarray(s, float), nan=-9.0)
    pos, neg = s[right], s[~right]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    return float((pos[:, None] > neg[None]).mean() + 0.5 * (pos[:, None] == neg[None]).mean())


def fit(df: pd.DataFrame) -> np.ndarray:
    """Logistic weights (1, outline, gradient, texture) by maximum likelihood, a weak L2 pull to 0."""
    d = df.dropna(subset=list(TERMS))
    x = np.c_[np.ones(len(d)), d[list(TERMS)].to_numpy(float)]
    y = d["right"].to_numpy(float)

    def loss(w):
        z = x @ w
        return float(np.sum(np.logaddexp(0, z) - y * z) + 0.01 * w[1:] @ w[1:])

    return minimize(loss, np.zeros(x.shape[1]), method="BFGS").x


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("pairs", nargs="+", help="RUN MANIFEST pairs (a finished run and the manifest it ran)")
    ap.add_argument("--cache", type=Path, help="the runs' --cache (their loaded meshes)")
    ap.add_argument("--fit", action="store_true", help="fit the weights to these runs and print them")
    ap.add_argument("--features", type=Path, help="also write the rows to this Parquet file")
    args = ap.parse_args()
    if len(args.pairs) % 2:
        ap.error("give RUN MANIFEST pairs")
    pairs = [(Path(a), Path(b)) for a, b in zip(args.pairs[::2], args.pairs[1::2], strict=True)]
    print(f"# verification: {machine()}; code {code_version()}; {len(pairs)} runs")
    df = pd.concat([run_features(run, man, args.cache) for run, man in pairs], ignore_index=True)
    if args.features:
        df.to_parquet(args.features)
    right = df["right"].to_numpy(bool)
    print(f"{len(df)} untracked poses ({int((df['status'] == 'ok').sum())} ok), {int((~right).sum())} wrong")
    if args.fit:
        w = fit(df)
        print(f"WEIGHTS = ({', '.join(f'{v:.2f}' for v in w)})  # (1, outline, gradient, texture)")
        df["score"] = score_of(df, w)
    else:
        df["score"] = score_of(df)
    cols = [*TERMS, "score", "confidence"]
    print(table([[c, f"{auroc(right, df[c]):.3f}"] for c in cols], ["term", "AUROC right vs wrong"]))
    bins = np.clip((df["score"] * 5).astype(int), 0, 4)
    rel = [
        [f"{b / 5:.1f}-{(b + 1) / 5:.1f}", int((bins == b).sum()), f"{df['score'][bins == b].mean():.2f}",
         f"{df['right'][bins == b].mean():.2f}"]
        for b in range(5) if (bins == b).any()
    ]  # fmt: skip
    print(table(rel, ["score", "poses", "mean score", "share right"]))
    ok = df[df["status"] == "ok"]
    n_right = int(ok["right"].sum())
    rows = [["the run's ok", len(ok), n_right, f"{ok['right'].mean():.4f}", "1.000"]]
    for t in THRESHOLDS:
        kept = ok[ok["score"] >= t]
        prec = kept["right"].mean() if len(kept) else float("nan")
        rows.append([f"score >= {t:g}", len(kept), int(kept["right"].sum()), f"{prec:.4f}",
                     f"{kept['right'].sum() / max(n_right, 1):.3f}"])  # fmt: skip
    print(table(rows, ["ok poses kept", "kept", "right", "precision", "right kept"]))
    wrong = df[(df["status"] == "ok") & ~df["right"]]
    if len(wrong):
        print(table(wrong[["frame_id", "obj_name", "confidence", *TERMS, "score", "adds_d"]].round(3).values.tolist(),
                    ["wrong ok pose", "object", "confidence", *TERMS, "score", "ADD-S / d"]))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
