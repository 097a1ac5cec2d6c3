"""Shared fixtures: bundled data paths and a session-wide template cache."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from batchpose.core.frames import Frame
from batchpose.io.folders import YcbvFrameSource

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "demo_data"
SHARED_DATA = ROOT.parent / "shared" / "data"
#: The shared data the tests read: ``SHARED_DATA``, or ``$BATCHPOSE_SHARED_DATA``.
DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", SHARED_DATA))
CRACKER = DEMO / "models" / "003_cracker_box" / "textured.obj"
GELATIN = DEMO / "models" / "009_gelatin_box" / "textured.obj"


def rotation(axis: int, deg: float) -> np.ndarray:
    """(3, 3) rotation by ``deg`` degrees about coordinate axis ``axis`` (0: x, 1: y, 2: z)."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def load_benchmark(name: str) -> ModuleType:
    """The script ``benchmarks/<name>.py`` imported as module ``name`` (its neighbours, e.g. ``_common``,
    importable too), once per test session."""
    if name in sys.modules:
        return sys.modules[name]
    folder = ROOT / "benchmarks"
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def ycbv_dev_frame(frame_id: str) -> Frame:
    """The frame ``frame_id`` of the shared ycbv_dev data set; the test is skipped where the data is not."""
    root = DATA / "ycbv_dev"
    if not root.is_dir():
        pytest.skip(f"shared YCB-Video dev data not at {root} (set BATCHPOSE_SHARED_DATA)")
    return next(f for f in YcbvFrameSource(root) if f.frame_id == frame_id)


# A canonical 640x480 camera for synthetic tests.
K_SYN = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def cracker_model():
    from batchpose.io.mesh import load_mesh

    return load_mesh(CRACKER)


@pytest.fixture(scope="session")
def cracker_library(cracker_model, cache_dir):
    """Template library of the bundled cracker box for K_SYN, built once per test session."""
    from batchpose.config import EstimatorConfig
    from batchpose.io import library
    from batchpose.stages import build_templates

    lib_dir = build_templates.build_library(cracker_model, EstimatorConfig(), K_SYN, 640, 480, cache_dir)
    return library.load(lib_dir)


class RunStopped(Exception):
    """Raised by :func:`stop_run` where a killed run would have stopped."""


@pytest.fixture()
def stop_run():
    """``stop_run(after=N)``: the next in-process run (``--jobs 1``) stops, as a kill would, right after the
    estimate stage has saved its N-th chunk; ``stop_run(after=N, at="save")`` right after its N-th checkpoint
    inside a chunk (checkpoints then after every frame); the run raises ``stop_run.Stopped``.
    ``stop_run.disarm()`` lets the next run finish."""
    mp = pytest.MonkeyPatch()

    class Arm:
        #: What a stopped run raises (use this attribute: conftest may be imported under two module names).
        Stopped = RunStopped

        def __call__(self, after: int, at: str = "finish") -> None:
            from batchpose.stages import checkpoints

            original = getattr(checkpoints.ChunkFiles, at)
            calls = []

            def stopping(files, *args, **kwargs):
                original(files, *args, **kwargs)
                calls.append(files.chunk_id)
                if len(calls) >= after:
                    raise RunStopped(f"stopped after {at} #{len(calls)} ({files.chunk_id})")

            mp.setattr(checkpoints.ChunkFiles, at, stopping)
            if at == "save":
                mp.setattr(checkpoints, "CHECKPOINT_S", 0.0)

        def disarm(self) -> None:
            mp.undo()

    yield Arm()
    mp.undo()
