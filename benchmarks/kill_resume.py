"""What a kill costs: a run SIGKILLed at half its wall time, then resumed, against one uninterrupted run.

    .venv/bin/python benchmarks/kill_resume.py [--manifest data_manifest/ycbv_dev.yaml] [--jobs 1]

1. warms the template cache (not timed);
2. runs ``batchpose run`` to the end in a fresh folder and times the whole process (T);
3. runs it again in another fresh folder, SIGKILLs the run and its workers at T / 2 (``--at``), then reruns the
   same command, which resumes from the saved chunks and checkpoints, and times that rerun (R);
4. prints R / T against the target (at most 0.6; the median of ``--repeat`` trials) and checks that the
   resumed run's ``poses.csv`` equals the uninterrupted run's in every column but ``time``.

Each run is a separate ``batchpose run`` process, as a user would start it.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, code_version, default_manifest, machine  # noqa: E402

TARGET = 0.6


def _cmd(manifest: Path, out: Path, cache: Path, jobs: int) -> list[str]:
    pipeline = REPO / "pipelines" / "gnc_pose.yaml"
    return [sys.executable, "-m", "batchpose", "run", str(pipeline), "--manifest", str(manifest), "--out", str(out),
            "--cache", str(cache), "--jobs", str(jobs)]  # fmt: skip


def _timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise SystemExit(f"batchpose run failed (exit {done.returncode}): {done.stderr.strip()[-2000:]}")
    return time.perf_counter() - t0


def _killed_at(cmd: list[str], seconds: float) -> None:
    """Start ``cmd`` in its own process group and SIGKILL the whole group after ``seconds``."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=seconds)
        raise SystemExit(f"the run finished in under {seconds:.1f} s, before the kill; use a larger --at")
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path).drop(columns=["time"])


def _trial(manifest: Path, tmp: Path, cache: Path, jobs: int, at: float) -> tuple[float, float, int, bool]:
    """One full run and one killed-and-resumed run: (full s, rerun s, pairs saved at the kill, same poses)."""
    full = _timed(_cmd(manifest, tmp / "full", cache, jobs))
    resumed = tmp / "resumed"
    _killed_at(_cmd(manifest, resumed, cache, jobs), at * full)
    saved = sorted((resumed / "shards").glob("shard-*.parquet"))
    kept = sum(len(pd.read_parquet(p, columns=["frame_id"])) for p in saved)
    rerun = _timed(_cmd(manifest, resumed, cache, jobs))
    same = _csv(resumed / "poses.csv").equals(_csv(tmp / "full" / "poses.csv"))
    return full, rerun, kept, same


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--manifest", type=Path, default=default_manifest())
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--at", type=float, default=0.5, help="kill at this fraction of the full run's time")
    ap.add_argument("--repeat", type=int, default=3, help="trials (this host's timings vary by ~10 %%)")
    ap.add_argument("--cache", type=Path, default=None, help="template cache (default: a new temporary one)")
    args = ap.parse_args()
    print(f"machine : {machine()}")
    print(f"code    : {code_version()}")
    print(f"manifest: {args.manifest.name}, --jobs {args.jobs}, killed at {args.at:g} of the full run's time")
    ratios, same_all = [], True
    with tempfile.TemporaryDirectory(prefix="batchpose-kill-") as tmp:
        cache = args.cache or Path(tmp) / "cache"
        _timed(_cmd(args.manifest, Path(tmp) / "warm", cache, args.jobs))  # template libraries and meshes cached
        for k in range(args.repeat):
            trial = Path(tmp) / f"trial{k}"
            full, rerun, kept, same = _trial(args.manifest, trial, cache, args.jobs, args.at)
            ratios.append(rerun / full)
            same_all &= same
            print(
                f"trial {k + 1}: full run {full:6.1f} s, killed at {args.at * full:5.1f} s ({kept} pairs saved), "
                f"resumed run {rerun:6.1f} s = {rerun / full:.2f} x; poses.csv {'identical' if same else 'DIFFERENT'}"
            )
    median = float(np.median(ratios))
    ok = median <= TARGET and same_all
    print(
        f"{'PASS' if ok else 'MISS'}: resumed in {median:.2f} x a full run (median of {len(ratios)}; "
        f"target <= {TARGET}); poses.csv identical to the uninterrupted run's: {same_all}"
    )


if __name__ == "__main__":
    main()
