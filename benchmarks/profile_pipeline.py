"""Profile the pipeline where the targets are missed: ``run.main --jobs 1`` (in-process) under pyinstrument.

Prints the functions with the most self time (C calls such as ``knnSearch`` or ``detectAndCompute`` count
as their own entries) and the batchpose functions with the most inclusive time, each with its share of the
profiled run. Template libraries are built first (not profiled). Needs pyinstrument, a profiling-only tool
that is not a batchpose dependency: ``.venv/bin/pip install pyinstrument``.

Usage:
    .venv/bin/python benchmarks/profile_pipeline.py [--manifest M.yaml] [--pipeline P.yaml] [--limit N]
        [--set key=value ...] [--top 15] [--html OUT.html]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO, code_version, default_manifest, machine, run_in_child, table  # noqa: E402
from floor_and_stages import warm_cache  # noqa: E402

from batchpose import run as run_mod  # noqa: E402
from batchpose.io import library


def _walk(frame, stack: tuple, self_t: dict, incl_t: dict) -> None:
    if getattr(frame, "is_synthetic", False) or (frame.function or "").startswith("["):
        return  # pyinstrument's "[self]" children: already in their parent's total_self_time
    key = (frame.function or "?", frame.file_path_short or "")
    self_t[key] += frame.total_self_time
    if key not in stack:  # count recursion once
        incl_t[key] += frame.time
    for child in frame.children:
        _walk(child, stack + (key,), self_t, incl_t)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__
    )
    ap.add_argument("--manifest", default=str(default_manifest()))
    ap.add_argument("--pipeline", default=str(REPO / "pipelines" / "gnc_pose.yaml"))
    ap.add_argument("--cache", default=str(library.default_cache_dir()))
    ap.add_argument("--limit", type=int, default=None, help="first N frames only")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="pipeline override")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--html", help="also write pyinstrument's interactive HTML here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    try:
        from pyinstrument import Profiler  # noqa: PLC0415
    except ImportError:
        print("skipped: pyinstrument is not installed (.venv/bin/pip install pyinstrument)")
        return 0

    print(f"machine : {machine()}")
    print(f"code    : {code_version()}")
    print(f"profile : {args.manifest}, {args.pipeline} {' '.join('--set ' + s for s in args.set)}, --jobs 1")
    run_in_child(warm_cache, args.manifest, args.pipeline, args.set, args.cache)
    profiler = Profiler(interval=0.001)
    with tempfile.TemporaryDirectory(prefix="bp-bench-profile-") as tmp:
        t0 = time.perf_counter()
        profiler.start()
        run_mod.main(
            Path(args.pipeline),
            Path(args.manifest),
            Path(tmp) / "run",
            cache_dir=Path(args.cache),
            overrides=args.set,
            jobs=1,
            limit=args.limit,
            report=False,
        )
        profiler.stop()
        wall = time.perf_counter() - t0
    session = profiler.last_session
    root = session.root_frame()
    self_t: dict = defaultdict(float)
    incl_t: dict = defaultdict(float)
    _walk(root, (), self_t, incl_t)
    total = root.time
    print(f"\nprofiled {total:.1f} s of a {wall:.1f} s run (main thread, 1 ms samples)")

    rows = sorted(self_t.items(), key=lambda kv: -kv[1])[: args.top]
    print("\n## Self time (where the CPU is)")
    print(table([[f, p, f"{t:.2f}", f"{100 * t / total:.1f}"] for (f, p), t in rows], ["function", "file", "s", "%"]))

    rows = [(k, t) for k, t in incl_t.items() if "batchpose" in k[1] and k[0] != "main"]
    rows = sorted(rows, key=lambda kv: -kv[1])[: args.top]
    print("\n## batchpose functions, inclusive time")
    print(table([[f, p, f"{t:.2f}", f"{100 * t / total:.1f}"] for (f, p), t in rows], ["function", "file", "s", "%"]))
    if args.html:
        Path(args.html).write_text(profiler.output_html())
        print(f"\nwrote {args.html}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
