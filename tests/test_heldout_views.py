"""benchmarks/heldout.py's views (``--views table``): the object on one of its resting faces, the camera looking
at it from within the elevation range above the table, wherever in the image the object is put."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from batchpose.io.mesh import load_mesh
from batchpose.method.support import stable_faces
from tests.conftest import CRACKER, K_SYN

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def heldout():
    sys.path.insert(0, str(_BENCHMARKS))  # heldout.py imports its neighbour _common
    spec = importlib.util.spec_from_file_location("heldout", _BENCHMARKS / "heldout.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["heldout"] = module
    spec.loader.exec_module(module)
    return module


def test_table_views_rest_the_object_and_look_down_at_it(heldout):
    model = load_mesh(CRACKER)
    stable = model.mesh.compute_stable_poses(n_samples=1)
    ups = -stable_faces(model.mesh)[0]  # each resting face's outward normal turned over: the table's up
    rng = np.random.default_rng(0)
    elevations, faces = [], set()
    for _ in range(60):
        R, up = heldout.table_rotation(rng, stable, (15.0, 65.0), 30.0)
        up_model = R.T @ up
        face = int(np.argmax(ups @ up_model))
        assert ups[face] @ up_model == pytest.approx(1.0, abs=1e-9)  # the object rests on that face
        faces.add(face)
        T = heldout.place(R, model.center_m, K_SYN, 640, 480, rng, on_ray=True)
        centre = T[:3, :3] @ model.center_m + T[:3, 3]
        assert centre[2] > 0.5  # in front of the camera
        # Seen from the elevation drawn, wherever in the image the object was put.
        elevations.append(np.degrees(np.arcsin(-(T[:3, :3] @ up_model) @ centre / np.linalg.norm(centre))))
    assert 15.0 - 1e-6 <= min(elevations) and max(elevations) <= 65.0 + 1e-6
    assert max(elevations) - min(elevations) > 30.0  # drawn from the range, not one view
    assert len(faces) >= 2  # more than one resting face
