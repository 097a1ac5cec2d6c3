"""Scale: a generated 640x480 JPEG MCAP (default 2,000 frames) through the whole pipeline with --jobs 2.

The log shows the bundled cracker box (demo_data/models/003_cracker_box) rendered with
``batchpose.method.render`` along a smooth trajectory (a full turn in azimuth, rising and falling elevation,
changing distance, in-plane roll, drifting across the image) over five procedurally textured backgrounds
that pan, with a slow brightness change on the object, per-frame sensor noise, JPEG quality 90, and the
true pose as ground truth in each frame. Every quarter of the log runs through the same cycle of views and
backgrounds (only the noise differs), so the work per quarter is the same and a slower last quarter means
the pipeline slowed down, not that the content got harder.

Reported: generation time, stage wall times, throughput per quarter of the run (from shard completion
times, after every worker's first shard; flat is the goal) and per-pair compute time per quarter (from
poses.parquet), RSS of every worker per quarter (peak and median; the median must not grow), accuracy
(ADD < 0.1 d) and PASS/MISS per target.

Usage:
    .venv/bin/python benchmarks/scale.py [--frames 2000] [--jobs 2] [--keep DIR] [--cache DIR]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import MB, REPO, RssSampler, StageTimer, code_version, machine, run_in_child, table, target  # noqa: E402

from batchpose import run as run_mod  # noqa: E402
from batchpose.io import bop_csv as bop  # noqa: E402
from batchpose.io import library
from batchpose.stages import build_templates, export_mcap  # noqa: E402
from batchpose.stages import estimate as estimate_poses
from batchpose.stages import ingest as ingest_frames
from batchpose.stages import report as report_stage

W, H = 640, 480
K = np.array([[620.0, 0.0, 319.5], [0.0, 620.0, 239.5], [0.0, 0.0, 1.0]])
OBJECT = "003_cracker_box"
SECOND = "009_gelatin_box"  # --two-objects: in view for 100 frames, out for the next 100, and so on
SECOND_ON_OFF = 100
MODELS = REPO / "demo_data" / "models"
FRAME_PERIOD_NS = 33_333_333
RSS_LIMIT = 1.5 * 1024**3
FLAT_MIN = 0.9  # last-quarter throughput / first-quarter throughput
GROWTH_MAX = 0.05  # last-quarter median RSS / first-quarter median RSS - 1, the steepest worker


# ---------------------------------------------------------------------------------------------- generate


def backgrounds(n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` textured 1280x960 BGR images: smooth colour noise, random shapes and fine grain."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        img = cv2.resize(
            rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (2 * W, 2 * H), interpolation=cv2.INTER_CUBIC
        )
        for _ in range(120):
            color = tuple(int(c) for c in rng.integers(0, 256, 3))
            x, y = int(rng.integers(0, 2 * W)), int(rng.integers(0, 2 * H))
            kind = rng.integers(0, 3)
            if kind == 0:
                cv2.rectangle(img, (x, y), (x + int(rng.integers(10, 120)), y + int(rng.integers(10, 120))), color, -1)
            elif kind == 1:
                cv2.circle(img, (x, y), int(rng.integers(5, 60)), color, -1)
            else:
                cv2.line(
                    img,
                    (x, y),
                    (int(rng.integers(0, 2 * W)), int(rng.integers(0, 2 * H))),
                    color,
                    int(rng.integers(1, 6)),
                )
        img = cv2.add(img, rng.integers(0, 24, img.shape, dtype=np.uint8))
        out.append(img)
    return out


def trajectory(i: int, period: int, center_m: np.ndarray, diameter_m: float) -> np.ndarray:
    """cam_from_model (4, 4) of frame ``i``: smooth, and periodic with ``period`` frames (a quarter of the log)."""
    from batchpose.method.views import look_at  # noqa: PLC0415

    ph = 2 * np.pi * i / period
    az = ph  # one turn per period
    el = np.deg2rad(25.0 + 20.0 * np.sin(2 * ph))
    f = K[0, 0]
    d = f * diameter_m / (0.4 * H) * (1.0 + 0.2 * np.sin(ph))
    eye = center_m + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = look_at(eye, center_m, np.array([0.0, 0.0, 1.0]))
    roll = np.deg2rad(15.0 * np.sin(3 * ph))
    Rr = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    shift = np.array([d * 110 / f * np.sin(2 * ph), d * 60 / f * np.sin(ph + 1), 0])
    out = np.eye(4)
    out[:3, :3] = Rr @ T[:3, :3]
    out[:3, 3] = Rr @ T[:3, 3] + shift
    return out


def second_pose(i: int, period: int, center_m: np.ndarray, diameter_m: float) -> np.ndarray:
    """The second object's pose: its own phase of the trajectory, shifted 190 px to the left."""
    T = trajectory(i + period // 3, period, center_m, diameter_m)
    T[0, 3] -= T[2, 3] * 190 / K[0, 0]
    return T


def generate(path: str, n: int, quality: int = 90, two_objects: bool = False) -> dict:
    """Write the log (run in a child process: the renderer's memory stays out of the measured processes)."""
    from batchpose.core.frames import Camera, Frame, ObjectPose  # noqa: PLC0415
    from batchpose.io.mcap_write import write_frames_mcap  # noqa: PLC0415
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415
    from batchpose.method.render import get_renderer  # noqa: PLC0415

    model = load_mesh(MODELS / OBJECT / "textured.obj", name=OBJECT)
    second = load_mesh(MODELS / SECOND / "textured.obj", name=SECOND) if two_objects else None
    renderer = get_renderer()
    bgs = backgrounds(5)
    cam = Camera(K=K, width=W, height=H)
    times = {"render": 0.0, "compose": 0.0, "jpeg": 0.0}
    n_bytes = 0

    period = max(n // 4, 1)

    def frames():
        nonlocal n_bytes
        for i in range(n):
            T = trajectory(i, period, model.center_m, model.diameter_m)
            t0 = time.perf_counter()
            rgb, depth = renderer.render(model.content_hash, model.mesh, T, K, W, H, "flat")
            gt = [ObjectPose(OBJECT, T)]
            if second is not None and (i // SECOND_ON_OFF) % 2 == 0:
                T2 = second_pose(i, period, second.center_m, second.diameter_m)
                rgb2, depth2 = renderer.render(second.content_hash, second.mesh, T2, K, W, H, "flat")
                front = (depth2 > 0) & ((depth == 0) | (depth2 < depth))
                rgb[front], depth[front] = rgb2[front], depth2[front]
                gt.append(ObjectPose(SECOND, T2))
            t1 = time.perf_counter()
            ph = 2 * np.pi * (i % period) / period
            bg = bgs[(i % period) * len(bgs) // period]
            x = int((bg.shape[1] - W) * (0.5 + 0.5 * np.sin(ph)))
            y = int((bg.shape[0] - H) * (0.5 + 0.5 * np.cos(2 * ph)))
            img = bg[y : y + H, x : x + W].copy()
            gain = 0.85 + 0.15 * np.sin(4 * ph)  # slow lighting change on the object
            mask = depth > 0
            img[mask] = np.clip(rgb[mask][:, ::-1] * gain, 0, 255).astype(np.uint8)
            noise = np.random.default_rng(i).integers(0, 6, img.shape, dtype=np.uint8)
            img = cv2.add(img, noise)  # sensor noise: no two quarters hold the same images
            t2 = time.perf_counter()
            data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
            t3 = time.perf_counter()
            times["render"] += t1 - t0
            times["compose"] += t2 - t1
            times["jpeg"] += t3 - t2
            n_bytes += len(data)
            yield Frame(f"{i:06d}", 0, i, i * FRAME_PERIOD_NS, cam, "jpeg", data, gt=tuple(gt))

    t0 = time.perf_counter()
    write_frames_mcap(frames(), Path(path), obj_ids={OBJECT: 2, SECOND: 8})
    times["total"] = time.perf_counter() - t0
    times["mb"] = n_bytes / 1e6
    return times


def warm_cache(manifest: str, pipeline: str, cache: str) -> float:
    """Build the template library in a child process (see ``generate``); returns seconds."""
    from batchpose.config import load_estimator_config, load_yaml  # noqa: PLC0415
    from batchpose.io.manifest import load_manifest  # noqa: PLC0415
    from batchpose.io.mesh import load_mesh  # noqa: PLC0415

    conf = load_estimator_config(load_yaml(Path(pipeline)))
    man = load_manifest(Path(manifest))
    t0 = time.perf_counter()
    for spec in man.objects:
        build_templates.build_library(load_mesh(spec.mesh, conf.mesh, name=spec.name), conf, K, W, H, Path(cache))
    return time.perf_counter() - t0


# ------------------------------------------------------------------------------------------------ report


def quarters(run_dir: Path, est_start: float) -> pd.DataFrame:
    """Shards in completion order with cumulative frames: t_s (since estimation start), frames, cum."""
    rows = []
    for p in (run_dir / "shards").glob("shard-*.parquet"):
        rows.append(
            {
                "t_s": p.stat().st_mtime - est_start,
                "frames": pd.read_parquet(p, columns=["frame_id"])["frame_id"].nunique(),
            }
        )
    df = pd.DataFrame(rows).sort_values("t_s", kind="stable").reset_index(drop=True)
    df["cum"] = df["frames"].cumsum()
    return df


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    ap.add_argument("--frames", type=int, default=2000, help="frames to generate (default 2000)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--pipeline", default=str(REPO / "pipelines" / "gnc_pose.yaml"))
    ap.add_argument(
        "--cache",
        default=str(library.default_cache_dir()),
        help="template cache, warmed before timing (default: $BATCHPOSE_CACHE or ~/.cache/batchpose)",
    )
    ap.add_argument("--keep", help="write the log and the run here instead of a temporary folder")
    ap.add_argument(
        "--two-objects",
        action="store_true",
        help=f"also render {SECOND}, in view in alternate blocks of {SECOND_ON_OFF} frames; each frame's "
        "ground truth lists the objects in view and the run estimates those (targets: annotations)",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    if args.frames < 8:
        ap.error("--frames must be at least 8")
    print(f"machine : {machine()}")
    print(f"code    : {code_version()}")
    print(f"pipeline: {args.pipeline}, --jobs {args.jobs}")

    with tempfile.TemporaryDirectory(prefix="bp-bench-scale-") as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        log_path = base / "frames.mcap"
        manifest = base / "scale.yaml"
        manifest.write_text(
            "name: scale\n"
            f"frames: {{format: mcap, path: {log_path.name}}}\n"
            f'models: {{root: {MODELS}, mesh: "{{name}}/textured.obj", points: "{{name}}/points.xyz"}}\n'
            f"objects: [{OBJECT}{', ' + SECOND if args.two_objects else ''}]\n"
            f"targets: {'annotations' if args.two_objects else 'all'}\n"
        )
        gen = run_in_child(generate, str(log_path), args.frames, 90, args.two_objects)
        t_cache = run_in_child(warm_cache, str(manifest), args.pipeline, args.cache)
        print(
            f"generated {args.frames} frames {W}x{H} in {gen['total']:.1f} s ({args.frames / gen['total']:.0f} "
            f"frames/s: render {gen['render']:.1f} s, compose {gen['compose']:.1f} s, JPEG {gen['jpeg']:.1f} s); "
            f"log {log_path.stat().st_size / 1e6:.0f} MB"
        )
        print(f"template cache ready in {t_cache:.1f} s (not timed below)")

        run_dir = base / "run"
        timer = StageTimer()
        timer.wrap(ingest_frames, "main", "ingest")
        timer.wrap(build_templates, "main", "templates")
        timer.wrap(estimate_poses, "main", "estimate")
        timer.wrap(bop, "write_bop_csv", "write poses.csv")
        timer.wrap(export_mcap, "main", "write poses.mcap")
        t0 = time.perf_counter()
        with timer, RssSampler(0.5) as rss:
            run_mod.main(
                Path(args.pipeline),
                manifest,
                run_dir,
                cache_dir=Path(args.cache),
                jobs=args.jobs,
                overwrite=True,
                report=False,
            )
        wall = time.perf_counter() - t0
        poses = pd.read_parquet(run_dir / "poses.parquet")
        est_start = timer.starts["estimate"][0]
        shards = quarters(run_dir, est_start)
        acc_dir = base / "compare"
        report_stage.compare([run_dir], acc_dir)
        acc = pd.read_csv(acc_dir / "compare.csv").iloc[0]

    n = int(shards["cum"].iloc[-1])
    print(f"\n## Stages (run.main wall {wall:.1f} s)")
    print(
        table(
            [[k, f"{v:.1f}", f"{1e3 * v / n:.1f}"] for k, v in timer.total.items()],
            ["stage", "wall s", "ms / frame"],
        )
    )
    est = timer.total["estimate"]
    print(
        f"estimation: {n} frames in {est:.1f} s = {n / est:.2f} frames/s overall; first shard after "
        f"{shards['t_s'].iloc[0]:.1f} s (worker start-up)"
    )

    # throughput and compute time per quarter; memory per quarter
    bounds = [n * q / 4 for q in range(5)]
    rows, rss_q, med_q = [], [], []
    # Quarter 1 starts when every worker has finished its first shard: each first shard carries that
    # worker's start-up, and they finish together, so counting the later ones would inflate quarter 1.
    first = min(args.jobs, len(shards)) - 1
    t_prev, f_prev = shards["t_s"].iloc[first], shards["cum"].iloc[first]
    poses = poses.sort_values("im_id", kind="stable").reset_index(drop=True)
    pair_q = np.minimum((np.arange(len(poses)) * 4) // len(poses), 3)
    for q in range(1, 5):
        end = shards[shards["cum"] >= bounds[q]].iloc[0]
        frames_q = end["cum"] - f_prev
        fps = frames_q / (end["t_s"] - t_prev) if end["t_s"] > t_prev else float("nan")
        sel = poses[pair_q == q - 1]
        t_from = (est_start - rss.t0_epoch) + t_prev
        t_to = (est_start - rss.t0_epoch) + end["t_s"]
        workers = rss.peak_by_pid("worker", t_from, t_to)
        rss_q.append((max(workers.values(), default=0), rss.peak("main", t_from, t_to), workers))
        by_pid: dict[int, list[int]] = {}
        for t, pid, r, role in rss.samples:
            if role == "worker" and t_from <= t < t_to:
                by_pid.setdefault(pid, []).append(r)
        med_q.append({pid: float(np.median(v)) for pid, v in by_pid.items()})
        ok = sel["status"] == "ok"
        rows.append(
            [
                f"Q{q}",
                int(frames_q),
                f"{t_prev:.0f}-{end['t_s']:.0f}",
                f"{fps:.2f}",
                f"{1e3 * sel['time_total_s'].mean():.0f}",
                f"{1e3 * sel['time_match_s'].mean():.0f}",
                f"{100 * ok.mean():.0f}",
                f"{100 * sel['tracked'].mean():.0f}" if "tracked" in sel else "-",
                f"{rss_q[-1][0] / MB:.0f}",
                f"{rss_q[-1][1] / MB:.0f}",
            ]
        )
        t_prev, f_prev = end["t_s"], end["cum"]
    print("\n## Per quarter of the run")
    print(
        table(
            rows,
            [
                "quarter",
                "frames",
                "t s (since estimate start)",
                "frames/s",
                "compute ms / pair",
                "of which matching ms",
                "ok %",
                "tracked %",
                "peak worker RSS MB",
                "main RSS MB",
            ],
        )
    )
    pids = sorted({p for _, _, w in rss_q for p in w})
    # worker RSS trend after the first quarter (start-up and warm-up done): least squares over all samples
    q2_from = (est_start - rss.t0_epoch) + shards[shards["cum"] >= bounds[1]]["t_s"].iloc[0]
    slopes = []
    for pid in pids:
        pts = [(t, r) for t, p, r, role in rss.samples if p == pid and role == "worker" and t >= q2_from]
        if len(pts) > 10:
            slopes.append(float(np.polyfit([t for t, _ in pts], [r for _, r in pts], 1)[0]))
    slope = max(slopes, default=float("nan"))  # bytes per second, the steepest worker
    per_1000 = slope / MB * 1000 / (n / est)  # MB per 1000 frames at this run's frame rate
    print(
        "worker RSS by quarter (MB): "
        + "; ".join(f"pid {p}: " + " / ".join(f"{w.get(p, 0) / MB:.0f}" for _, _, w in rss_q) for p in pids)
    )

    print(
        "worker RSS median by quarter (MB): "
        + "; ".join(f"pid {p}: " + " / ".join(f"{m.get(p, 0) / MB:.0f}" for m in med_q) for p in pids)
    )
    print(f"worker RSS trend after Q1: {per_1000:+.0f} MB per 1000 frames (steepest worker, least squares)")
    print(f"other processes kept {rss.other_load():.2f} cores busy during the run (comparable only when ~0)")
    print(
        f"\naccuracy: ADD < 0.1 d {acc['add_recall_01d']:.1f} %, ADD-S < 0.1 d {acc['adds_recall_01d']:.1f} %, "
        f"ADD AUC {acc['add_auc_mean']:.1f}, median rotation error {acc['median_rot_err_deg']:.2f} deg, "
        f"median translation error {acc['median_trans_err_mm']:.1f} mm, {int(acc['n_ok'])} / "
        f"{int(acc['n_pairs'])} pairs ok"
    )

    fps_q = [float(r[3]) for r in rows]
    peak_worker = max(r[0] for r in rss_q)
    # Growth from the quarters' median RSS, worker by worker: a full estimate's buffers lift a worker's RSS by
    # ~50 MB for a moment, so whether a quarter's *peak* holds one is chance (+0.3 % and +11.7 % Q4 vs Q1 in
    # two runs of the same code); a leak lifts the median.
    growth = max((med_q[-1].get(p, 0) / med_q[0][p] - 1 for p in med_q[0] if med_q[0][p]), default=float("nan"))
    peak_growth = rss_q[-1][0] / rss_q[0][0] - 1 if rss_q[0][0] else float("nan")
    print("\n## Targets")
    print(
        target(
            fps_q[3] >= FLAT_MIN * fps_q[0],
            f"throughput flat: last quarter {fps_q[3]:.2f} vs first "
            f"{fps_q[0]:.2f} frames/s ({fps_q[3] / fps_q[0]:.2f}x; target >= {FLAT_MIN}x)",
        )
    )
    print(target(peak_worker <= RSS_LIMIT, f"peak RSS per worker: {peak_worker / MB:.0f} MB (target <= 1536 MB)"))
    print(
        target(
            growth <= GROWTH_MAX,
            f"no memory growth: worker median RSS last quarter vs first {100 * growth:+.1f} % "
            f"(target <= +{100 * GROWTH_MAX:.0f} %; peaks {100 * peak_growth:+.1f} %)",
        )
    )
    if args.frames != 2000:
        print(f"note: {args.frames} frames, not the 2,000 of the full benchmark")
    return 0


if __name__ == "__main__":
    sys.exit(main())
