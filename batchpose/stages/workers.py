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
    """
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
