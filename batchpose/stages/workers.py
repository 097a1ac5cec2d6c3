"""Worker processes of a run: loky's options that tie them to the run that started them."""

from __future__ import annotations

import os
import threading
import time


def watch_parent(parent_pid: int, every_s: float = 1.0) -> None:
    """Worker initializer: leave when the run that started this worker is gone.

    A ``batchpose run`` killed outright (SIGKILL, the OOM killer) cannot stop its loky workers, which would
    otherwise finish their task and wait for the next one for good (loky's idle timeout does not fire:
    the dead run's queues never report empty). A daemon thread checks once a ``every_s`` whether the
    worker's parent is still ``parent_pid`` and ends the process when it is not; the dead run's unsaved
    results are lost either way and are computed again by a rerun.

    It also raises loky's memory-growth limit in the worker (:func:`relax_loky_leak_check`): building a
    template library grows a worker by more than loky's 300 MB, which it takes for a leak, restarting the
    worker with a warning that reads like a crash.
    """
    relax_loky_leak_check()
    if os.getppid() != parent_pid:
        try:
            os.kill(parent_pid, 0)
        except ProcessLookupError:  # the run died while this worker started
            os._exit(1)
        except OSError:
            pass
        return  # not started by the run itself (e.g. a dask nanny's worker): nothing to watch

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(every_s)
        os._exit(1)

    threading.Thread(target=watch, name="batchpose-watch-parent", daemon=True).start()


def loky_options() -> dict:
    """``joblib.parallel_config`` options for this process's loky workers (one set for every pool of a run,
    so that loky reuses its workers from one stage to the next)."""
    return {"initializer": watch_parent, "initargs": (os.getpid(),)}


def leak_limit_bytes() -> int:
    """How much a worker may grow past its size after its first task before loky takes it for a leak: a
    quarter of the machine's memory, at least 1.5 GB (our RSS budget a worker on the two-object logs)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        total = 0
    return max(int(1.5e9), total // 4)


def relax_loky_leak_check() -> None:
    """Raise loky's per-worker memory-growth limit (300 MB) to :func:`leak_limit_bytes`.

    loky measures a worker after its first task and restarts it, warning "A worker stopped while some jobs
    were given to the executor", once it has grown past that by the limit. A worker's first task can be
    building one template library; estimating it then loads every object's library and the presence
    index (about 3 GB for the 12 YCB objects), which is no leak: restarted, the worker would load them all
    again. The renderer bounds its own growth (``benchmarks/scale.py`` checks that a worker does not grow).
    """
    try:
        from joblib.externals.loky import process_executor  # noqa: PLC0415
    except ImportError:  # pragma: no cover
        return
    process_executor._MAX_MEMORY_LEAK_SIZE = max(process_executor._MAX_MEMORY_LEAK_SIZE, leak_limit_bytes())


_THREADS: dict[str, int] = {}


def limit_threads(threads: int | None) -> None:
    """Let this worker's OpenCV and software renderer use ``threads`` threads (None: their defaults).

    Both start one thread per core in every process, so two workers on two cores would run four of each
    and fight over the cores; joblib caps only OpenMP/BLAS pools, and OpenCV's wheels use pthreads.
    ``LP_NUM_THREADS`` (llvmpipe) is read when a GL context is made, so it is set before the first render.
    """
    if threads is None or _THREADS.get("threads") == threads:
        return
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(threads)
    os.environ["LP_NUM_THREADS"] = str(threads)
    _THREADS["threads"] = threads


def threads_per_worker(jobs: int) -> int | None:
    """Threads each of ``jobs`` workers on this machine gets (None for one worker: use every core)."""
    if jobs <= 1:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // jobs)
