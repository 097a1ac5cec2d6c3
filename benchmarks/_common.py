"""Shared helpers for the benchmark scripts: stage timers, an RSS sampler, tables and target lines.

Not part of the package: benchmarks import batchpose and measure it from the outside (wrapping stage
functions for the length of one run), so they always time the pipeline as ``batchpose run`` executes it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import multiprocessing
import os
import platform
import subprocess
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path

import psutil

from batchpose.run_dir import versions

REPO = Path(__file__).resolve().parents[1]
#: The shared data: ``../shared/data`` beside the repository, or ``$BATCHPOSE_SHARED_DATA`` (as the tests read it).
SHARED_DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", REPO.parent / "shared" / "data"))
MB = 1024 * 1024


def default_manifest() -> Path:
    """``ycbv_dev`` when ../shared/data exists, else the bundled demo."""
    if (SHARED_DATA / "ycbv_dev").is_dir():
        return REPO / "data_manifest" / "ycbv_dev.yaml"
    return REPO / "data_manifest" / "demo.yaml"


# The libraries whose versions move the figures (pyproject.toml gives ranges, so a fresh set-up may differ).
_LIBS = {"numpy": "numpy", "opencv-python-headless": "OpenCV", "scipy": "scipy", "trimesh": "trimesh"}


def machine() -> str:
    """One line: date, CPU model and count, memory, load, Python and the versions of :data:`_LIBS`."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    found = versions()
    libs = ", ".join(f"{name} {found.get(pkg) or '-'}" for pkg, name in _LIBS.items())
    return (
        f"{_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} | {cpu} | {psutil.cpu_count()} logical cores | "
        f"{psutil.virtual_memory().total / 2**30:.0f} GiB RAM | load avg {load} | Python {platform.python_version()}"
        f" | {libs}"
    )


def code_version() -> str:
    """``git describe`` of the checkout plus the package files that differ from it (others edit concurrently)."""

    def git(*a: str) -> str:
        try:
            return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True, timeout=20).stdout.rstrip()
        except (OSError, subprocess.SubprocessError):
            return ""

    head = git("log", "-1", "--format=%h %s")[:90] or "unknown"
    dirty = [ln[3:] for ln in git("status", "--porcelain", "--", "batchpose", "pipelines").splitlines()]
    return f"{head}" + (f" + uncommitted: {', '.join(dirty)}" if dirty else " (clean)")


def _child(conn, fn, args) -> None:
    try:
        conn.send((True, fn(*args)))
    except BaseException as e:  # noqa: BLE001 - reported in the parent
        conn.send((False, f"{type(e).__name__}: {e}"))
    conn.close()
    # multiprocessing joins a child's children at exit, before atexit handlers run; joblib's idle loky
    # workers would never end, so shut their executor down first
    with contextlib.suppress(Exception):
        from joblib.externals.loky import reusable_executor  # noqa: PLC0415

        if reusable_executor._executor is not None:
            reusable_executor._executor.shutdown(wait=True, kill_workers=True)
    for p in multiprocessing.active_children():
        p.terminate()


def run_in_child(fn: Callable, *args):
    """``fn(*args)`` in a fresh (spawned) process, so its memory (renderer, meshes) is not this process's."""
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, fn, args))
    proc.start()
    child.close()
    ok, value = parent.recv()
    proc.join(timeout=120)
    if proc.is_alive():  # the result is in; do not hang on a child stuck in its exit
        proc.terminate()
        proc.join()
    if not ok:
        raise RuntimeError(f"{fn.__name__} failed in the child process: {value}")
    return value


# ------------------------------------------------------------------------------------------------ timing


class StageTimer:
    """Wraps module-level functions for the length of a ``with`` block and sums their wall time per label.

    ``timer.wrap(module, "main", "estimate")`` replaces ``module.main`` by a timing wrapper; callers that look
    the function up through the module at call time (``estimate_poses.main(...)``) are timed.
    """

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.log: dict[str, list[tuple[float, object]]] = defaultdict(list)
        self.starts: dict[str, list[float]] = defaultdict(list)  # epoch seconds of each call
        self._undo: list[tuple[object, str, object]] = []

    def wrap(self, owner: object, attr: str, label: str, keep: Callable | None = None) -> None:
        """Time ``owner.attr`` under ``label``; ``keep(args, result)`` picks what to log beside each time."""
        orig = getattr(owner, attr)

        def timed(*args, **kwargs):
            self.starts[label].append(time.time())
            t0 = time.perf_counter()
            out = orig(*args, **kwargs)
            dt = time.perf_counter() - t0
            self.total[label] += dt
            self.calls[label] += 1
            self.log[label].append((dt, keep(args, out) if keep else None))
            return out

        setattr(owner, attr, timed)
        self._undo.append((owner, attr, orig))

    def restore(self) -> None:
        for owner, attr, orig in reversed(self._undo):
            setattr(owner, attr, orig)
        self._undo.clear()

    def __enter__(self) -> StageTimer:
        return self

    def __exit__(self, *exc) -> None:
        self.restore()


# -------------------------------------------------------------------------------------------------- memory


class RssSampler:
    """Samples the resident set size of this process and all its descendants in a background thread.

    Attributes:
        samples: (t_s since start, pid, rss_bytes, role) tuples; role is "main" or "worker".
    """

    def __init__(self, interval_s: float = 0.2) -> None:
        self.interval_s = interval_s
        self.samples: list[tuple[float, int, int, str]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._me = psutil.Process(os.getpid())
        self.t0 = time.perf_counter()
        self.t0_epoch = time.time()
        self._helpers: set[int] = set()
        self._procs: dict[int, psutil.Process] = {}
        self._cpu0: dict[int, tuple[str, float]] = {}
        self._cpu1: dict[int, float] = {}

    def _is_helper(self, p: psutil.Process) -> bool:
        """joblib/loky's resource tracker and similar helpers are not workers."""
        if p.pid in self._helpers:
            return True
        with contextlib.suppress(psutil.Error):
            cmd = " ".join(p.cmdline())
            if "resource_tracker" in cmd or "semaphore_tracker" in cmd:
                self._helpers.add(p.pid)
                return True
        return False

    def _record(self, t: float, p: psutil.Process, role: str) -> None:
        with contextlib.suppress(psutil.Error):
            with p.oneshot():
                rss = p.memory_info().rss
                c = p.cpu_times()
            if rss == 0:  # a zombie between exit and reaping
                return
            self.samples.append((t, p.pid, rss, role))
            self._cpu0.setdefault(p.pid, (role, c.user + c.system))
            self._cpu1[p.pid] = c.user + c.system

    def sample(self) -> None:
        t = time.perf_counter() - self.t0
        self._record(t, self._me, "main")
        with contextlib.suppress(psutil.Error):
            for child in self._me.children(recursive=True):
                if not self._is_helper(child):
                    self._record(t, self._procs.setdefault(child.pid, child), "worker")

    def cpu_seconds(self, role: str | None = None) -> float:
        """CPU time (user + system, all threads) used between the first and the last sample of each process."""
        return sum(self._cpu1[pid] - c0 for pid, (r, c0) in self._cpu0.items() if role is None or r == role)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    @staticmethod
    def _system_busy() -> float:
        c = psutil.cpu_times()
        return sum(c) - c.idle - getattr(c, "iowait", 0.0)

    def other_load(self) -> float:
        """Cores kept busy by processes outside this tree during the sampling (another user's job, say)."""
        span = self.samples[-1][0] - self.samples[0][0] if self.samples else 0.0
        return max(self._sys1 - self._sys0 - self.cpu_seconds(), 0.0) / span if span > 0 else float("nan")

    def __enter__(self) -> RssSampler:
        self.t0 = time.perf_counter()
        self.t0_epoch = time.time()
        self._sys0 = self._system_busy()
        self.sample()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.sample()
        self._sys1 = self._system_busy()

    def __getstate__(self) -> dict:
        """Pickle the measurements only (a sampler run in a child process is returned to the parent)."""
        keep = ("interval_s", "samples", "t0_epoch", "_cpu0", "_cpu1", "_sys0", "_sys1")
        return {k: v for k, v in self.__dict__.items() if k in keep}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._thread = None

    def peak_by_pid(self, role: str | None = None, t_from: float = 0.0, t_to: float = float("inf")) -> dict:
        """pid -> peak RSS in bytes over [t_from, t_to] (seconds since start)."""
        out: dict[int, int] = {}
        for t, pid, rss, r in self.samples:
            if (role is None or r == role) and t_from <= t <= t_to:
                out[pid] = max(out.get(pid, 0), rss)
        return out

    def peak(self, role: str | None = None, t_from: float = 0.0, t_to: float = float("inf")) -> int:
        return max(self.peak_by_pid(role, t_from, t_to).values(), default=0)


# ------------------------------------------------------------------------------------------------- output


def table(rows: Sequence[Sequence[object]], headers: Sequence[str]) -> str:
    """A plain-text table (also valid Markdown)."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]

    def line(r: list[str]) -> str:
        padded = (c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))
        return "| " + " | ".join(padded) + " |"

    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(cells[0]), sep] + [line(r) for r in cells[1:]])


def target(ok: bool | None, text: str) -> str:
    """``PASS  text`` / ``MISS  text`` / ``N/A   text`` (not measurable in this run)."""
    tag = "N/A " if ok is None else ("PASS" if ok else "MISS")
    return f"{tag}  {text}"


def ms(x: float) -> str:
    return f"{x * 1e3:.1f}"
