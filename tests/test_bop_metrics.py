"""BOP 2019 pose errors (MSSD, MSPD, VSD) and recalls on hand-made cases, the symmetry table against the real
meshes, and the precision / recall of ok on a hand-built table."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import trimesh
from scipy.spatial import cKDTree

from batchpose.core.model import diameter
from batchpose.io.sources import open_frames
from batchpose.report import bop_metrics as bm
from batchpose.report import bop_scoring, metrics, precision
from batchpose.report.runs import RunData
from tests.conftest import DEMO, SHARED_DATA, rotation

#: The shared data (``../shared/data`` beside the repository, or ``$BATCHPOSE_SHARED_DATA``).
DATA = Path(os.environ.get("BATCHPOSE_SHARED_DATA", SHARED_DATA))
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def _cylinder(radius: float = 0.05, height: float = 0.14, n: int = 720) -> np.ndarray:
    """(n, 3) points on a can's side about z, seeded."""
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 2 * np.pi, n)
    return np.c_[radius * np.cos(a), radius * np.sin(a), rng.uniform(-height / 2, height / 2, n)]


CAN = _cylinder()
CAN_SYMS = bm.symmetry_transforms("002_master_chef_can")
T_GT = np.array([0.02, -0.01, 0.7])
R_GT = rotation(0, 30) @ rotation(1, -20)


def test_identity_pose_has_no_error():
    syms = bm.symmetry_transforms("no_such_object")
    assert syms.shape == (1, 4, 4) and np.allclose(syms[0], np.eye(4))
    assert bm.mssd(R_GT, T_GT, R_GT, T_GT, CAN, syms) < 1e-12
    assert bm.mspd(R_GT, T_GT, R_GT, T_GT, K, CAN, syms) < 1e-9
    assert bm.mssd(R_GT, T_GT, R_GT, T_GT, CAN, CAN_SYMS) < 1e-12  # the identity is among the symmetries
    assert bm.ar_mssd(0.0, 0.15) == 1.0 and bm.ar_mspd(0.0, 640) == 1.0


def test_turn_about_the_cans_axis_is_no_mssd_error_but_is_an_add_error():
    assert CAN_SYMS.shape == (36, 4, 4)
    R_est = R_GT @ rotation(2, 40.0)  # a multiple of the 10-degree steps
    assert bm.mssd(R_est, T_GT, R_GT, T_GT, CAN, CAN_SYMS) < 1e-9
    assert bm.mspd(R_est, T_GT, R_GT, T_GT, K, CAN, CAN_SYMS) < 1e-6
    assert metrics.add(R_est, T_GT, R_GT, T_GT, CAN) > 0.03
    # Between two steps the error is at most the chord of half a step; without symmetries it is the full turn.
    R_mid = R_GT @ rotation(2, 45.0)
    assert bm.mssd(R_mid, T_GT, R_GT, T_GT, CAN, CAN_SYMS) <= 2 * 0.05 * math.sin(math.radians(2.5)) + 1e-9
    no_syms = bm.symmetry_transforms("003_cracker_box")
    assert bm.mssd(R_mid, T_GT, R_GT, T_GT, CAN, no_syms) > 0.035
    # A turn about another axis is not a symmetry of the can.
    assert bm.mssd(R_GT @ rotation(0, 40.0), T_GT, R_GT, T_GT, CAN, CAN_SYMS) > 0.03


def test_known_translation_gives_known_mssd_and_mspd():
    shift = np.array([0.01, 0.0, 0.0])
    assert bm.mssd(R_GT, T_GT + shift, R_GT, T_GT, CAN, CAN_SYMS) == pytest.approx(0.01)
    # Points on a plane facing the camera at z = 0.5 m: a 10 mm sideways shift moves each 600 * 0.01 / 0.5 px.
    plane = np.c_[np.random.default_rng(1).uniform(-0.05, 0.05, (50, 2)), np.zeros(50)]
    t = np.array([0.0, 0.0, 0.5])
    assert bm.mspd(np.eye(3), t + shift, np.eye(3), t, K, plane, np.eye(4)[None]) == pytest.approx(12.0)


def test_recalls_at_thresholds():
    # MSSD: 0.05 d .. 0.5 d with d = 0.1 m; an error of 14.9 mm is below 8 of the 10 (15 mm .. 50 mm).
    assert bm.ar_mssd(0.0149, 0.1) == pytest.approx(0.8)
    assert bm.ar_mssd(0.051, 0.1) == 0.0 and bm.ar_mssd(np.inf, 0.1) == 0.0 and bm.ar_mssd(np.nan, 0.1) == 0.0
    # MSPD: 5 .. 50 px at 640 wide, twice that at 1280.
    assert bm.ar_mspd(7.0, 640) == pytest.approx(0.9)
    assert bm.ar_mspd(7.0, 1280) == 1.0
    assert bm.ar_mspd(np.inf, 640) == 0.0
    # VSD: 6 of the 10 taus with error 0 pass every theta, the others (error 1) none.
    assert bm.ar_vsd(np.r_[np.ones(4), np.zeros(6)]) == pytest.approx(0.6)
    assert bm.ar_vsd(None) == 0.0


def _square(depth_m: float, x0: int, size: int = 40) -> np.ndarray:
    d = np.zeros((480, 640))
    d[220 : 220 + size, x0 : x0 + size] = depth_m
    return d


def test_vsd_of_shifted_and_deeper_renders():
    gt = _square(0.5, 300)
    assert np.all(bm.vsd(gt, gt, gt, K, 0.1) == 0.0)
    # Shifted by 10 px: the 40x40 masks share 30x40 pixels, and the union is 50x40.
    shifted = _square(0.5, 310)
    np.testing.assert_allclose(bm.vsd(shifted, gt, gt, K, 0.1), 1.0 - 30 / 50)
    # 22 mm deeper, same pixels: every pixel differs by 22-23 mm, above the taus of 5 .. 20 mm only.
    deeper = _square(0.522, 300)
    np.testing.assert_allclose(bm.vsd(deeper, gt, gt, K, 0.1), np.r_[np.ones(4), np.zeros(6)])
    # Missing scene depth counts as visible (BOP 2019); nothing visible at all is an error of 1.
    np.testing.assert_allclose(bm.vsd(gt, gt, np.zeros_like(gt), K, 0.1), 0.0)
    np.testing.assert_allclose(bm.vsd(np.zeros_like(gt), np.zeros_like(gt), gt, K, 0.1), 1.0)
    d = bm.distance_map(np.full((480, 640), 2.0), K)
    assert d[239, 319] == pytest.approx(2.0 * math.sqrt(1 + (0.5 / 600) ** 2)) and d[0, 0] > 2.0


@pytest.mark.skipif(not (DATA / "ycb_models").is_dir(), reason=f"shared YCB meshes not at {DATA}")
@pytest.mark.parametrize("name", sorted(bm.SYMMETRIES))
def test_symmetries_map_the_real_mesh_onto_itself(name):
    """Each discretised symmetry moves the model points onto the mesh (nearest dense-surface sample within
    5 % of the diameter); the same turns about the other two axes do not (a check that the axis is right)."""
    folder = DATA / "ycb_models" / name
    mesh = trimesh.load(folder / "textured.obj", force="mesh", process=False, skip_materials=True)
    surface = cKDTree(trimesh.sample.sample_surface(mesh, 20000, seed=0)[0])
    pts = np.loadtxt(folder / "points.xyz")[:, :3]
    diam = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def worst(syms: np.ndarray) -> float:
        moved = np.einsum("sij,nj->sni", syms[:, :3, :3], pts) + syms[:, None, :3, 3]
        return float(surface.query(moved.reshape(-1, 3))[0].max())

    assert worst(bm.symmetry_transforms(name)) < 0.05 * diam
    axis = np.asarray(bm.SYMMETRIES[name]["continuous"][0][0])
    for other in np.eye(3)[np.abs(np.eye(3) @ axis) < 0.5]:
        table = {name: {"continuous": [(tuple(other), (0.0, 0.0, 0.0))]}}
        assert worst(bm.symmetry_transforms(name, table=table)) > 0.1 * diam


# ------------------------------------------------------------------------------------ precision / recall


def _rows(items) -> pd.DataFrame:
    return pd.DataFrame(
        [
            {
                "frame_id": f,
                "obj_name": o,
                "status": s,
                "confidence": c,
                "R": np.eye(3).ravel().tolist(),
                "t_m": list(t),
            }
            for f, o, s, c, t in items
        ]
    )


def test_precision_recall_and_absent_objects():
    gt = _rows([("f0", "a", "", 0, (0, 0, 1)), ("f1", "a", "", 0, (0, 0, 1)), ("f0", "b", "", 0, (0, 0, 1))])
    gt = gt.drop(columns=["status", "confidence"])
    poses = _rows(
        [
            ("f0", "a", "ok", 0.9, (0, 0, 1.001)),  # correct
            ("f1", "a", "ok", 0.8, (0, 0, 1.5)),  # wrong: 0.5 m off
            ("f0", "b", "low_confidence", 0.2, (0, 0, 1.0)),  # correct, but rejected
            ("f1", "b", "ok", 0.7, (0, 0, 1.0)),  # b is absent from f1: a false positive
            ("f1", "c", "absent", 0.0, (np.nan, np.nan, np.nan)),  # c absent, and said so
            ("f2", "a", "ok", 0.95, (0, 0, 1.0)),  # nothing is in f2: a false positive too
        ]
    )
    pts = {n: np.random.default_rng(0).uniform(-0.05, 0.05, (100, 3)) for n in ("a", "b")}
    diam = {"a": 0.1, "b": 0.1}
    table = precision.pose_table(poses, gt, pts, diam)
    by_pair = table.set_index(["frame_id", "obj_name"])["correct"].to_dict()
    assert by_pair == {("f0", "a"): True, ("f1", "a"): False, ("f1", "b"): False, ("f0", "b"): True, ("f2", "a"): False}
    assert table.loc[table["frame_id"] == "f2", "adds_m"].tolist() == [np.inf]
    absent = precision.absent_pairs(poses, gt)
    assert sorted(zip(absent["frame_id"], absent["obj_name"], absent["ok"], strict=True)) == [
        ("f1", "b", True),
        ("f1", "c", False),
        ("f2", "a", True),
    ]
    t = precision.trust(table, absent, n_instances=3)
    # ok poses: a/f0 (correct), a/f1 (wrong), b/f1 and a/f2 (absent) -> 1 of 4 correct; 1 of the 3 instances
    # got a correct ok pose.
    assert (t.ok_precision, t.ok_recall) == (pytest.approx(1 / 4), pytest.approx(1 / 3))
    assert (t.n_ok_absent, t.n_absent_pairs) == (2, 3)
    curve = precision.pr_curve(table, 3, default_threshold=0.3)
    # Confidence 0.95, 0.9, 0.8, 0.7, 0.2: wrong, correct, wrong, wrong, correct.
    np.testing.assert_allclose(curve.thresholds, [0.95, 0.9, 0.8, 0.7, 0.2])
    np.testing.assert_allclose(curve.precision, [0.0, 0.5, 1 / 3, 0.25, 0.4])
    np.testing.assert_allclose(curve.recall, [0.0, 1 / 3, 1 / 3, 1 / 3, 2 / 3])
    assert curve.ok_point == (pytest.approx(1 / 3), pytest.approx(1 / 4))
    summary = pd.DataFrame({"obj_name": ["a", "b", "mean", "pooled"], "n": [2, 1, 3, 3]})
    s = precision.trust_columns(summary, table, absent).set_index("obj_name")
    assert s.loc["a", "ok_precision"] == pytest.approx(1 / 3) and s.loc["a", "ok_recall"] == 0.5
    assert s.loc["b", "ok_precision"] == 0.0 and s.loc["b", "ok_recall"] == 0.0 and s.loc["b", "n_ok_absent"] == 1
    assert s.loc["mean", "ok_precision"] == pytest.approx(1 / 6) and s.loc["pooled", "ok_precision"] == 0.25
    assert s.loc["pooled", "n_absent_pairs"] == 3
    assert precision.ok_threshold("pipeline:\n  min_confidence: 0.3\n") == 0.3
    assert precision.ok_threshold("pipeline:\n  min_verification: 0.4\n", "min_verification") == 0.4
    assert precision.ok_threshold("name: x\n") is None
    assert precision.pr_curve(table, 3, 0.5, by="verification") is None  # a run before the score: no curve
    # The verification curve: a/f1's wrong pose scores 0.1, the tracked a/f0 has no score and stays in.
    scored = poses.assign(verification=[np.nan, 0.1, 0.9, 0.6, np.nan, 0.3])
    by_score = precision.pr_curve(precision.pose_table(scored, gt, pts, diam), 3, 0.5, by="verification")
    np.testing.assert_allclose(by_score.thresholds, [np.inf, 0.9, 0.6, 0.3, 0.1])
    np.testing.assert_allclose(by_score.precision, [1.0, 1.0, 2 / 3, 0.5, 0.4])
    np.testing.assert_allclose(by_score.recall, [1 / 3, 2 / 3, 2 / 3, 2 / 3, 2 / 3])


# ---------------------------------------------------------------------------------- VSD through a run


def test_vsd_of_a_run_reads_depth_and_renders_the_model(tmp_path):
    """Two demo frames with depth: the true pose scores AR_VSD 1; one 30 mm too deep fails the taus up to 30
    mm (6 of 10, so about 0.4); without the pose the instance scores 0."""
    spec = {"format": "ycbv", "root": str(DEMO / "ycbv")}
    frames = [f for _, f in zip(range(2), open_frames(spec, tmp_path), strict=False)]
    gt = pd.DataFrame(
        [
            {
                "frame_id": f.frame_id,
                "obj_name": p.obj_name,
                "R": p.cam_from_model[:3, :3].ravel(),
                "t_m": p.cam_from_model[:3, 3],
            }
            for f in frames
            for p in f.gt
            if p.obj_name == "009_gelatin_box"
        ]
    )
    assert len(gt) == 2 and all(f.has_depth for f in frames)
    deeper = gt.assign(t_m=[gt["t_m"][0], gt["t_m"][1] * (1 + 0.03 / np.linalg.norm(gt["t_m"][1]))])
    poses = deeper.assign(status="ok", confidence=0.9)
    mesh = DEMO / "models" / "009_gelatin_box" / "textured.obj"
    objects = {"009_gelatin_box": {"mesh": str(mesh), "points": None, "diameter_m": None}}
    run = RunData(tmp_path, poses, gt, None, objects, manifest={"frames": spec})
    diam = {"009_gelatin_box": diameter(trimesh.load(mesh, force="mesh", process=False).vertices)}
    ar, why = bop_scoring.vsd_recalls(run, gt, diam)
    assert why == "" and ar is not None
    assert ar[0] == 1.0 and 0.3 <= ar[1] <= 0.5
    run.poses = poses.iloc[:1]  # the second instance without an estimate
    ar, _ = bop_scoring.vsd_recalls(run, gt, diam)
    assert ar is not None and ar.tolist() == [1.0, 0.0]
