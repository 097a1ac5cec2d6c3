"""BOP results CSV: exact format, byte-exact round trip, errors naming file and line, scoring a file."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from batchpose.core.poses import PoseRecord
from batchpose.errors import DataError
from batchpose.io import bop_csv as bop
from batchpose.report import scoring


def _T(R: np.ndarray, t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _poses() -> pd.DataFrame:
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = Q * np.sign(np.linalg.det(Q))  # a proper rotation with "ugly" decimals
    recs = [
        # Written out of order on purpose: the file is sorted by scene_id, im_id, obj_id.
        PoseRecord(
            "48/2",
            "b",
            "ok",
            scene_id=48,
            im_id=2,
            obj_id=5,
            cam_from_model=_T(R, [0.01, -0.02, 0.9]),
            confidence=0.25,
            timings={"sift": 0.125, "gnc": 0.5},
        ),
        PoseRecord(
            "48/1",
            "b",
            "ok",
            scene_id=48,
            im_id=1,
            obj_id=5,
            cam_from_model=_T(R, [0.05, 0.06, 0.7]),
            confidence=0.5,
            timings={"sift": 0.25},
        ),
        PoseRecord(
            "48/1",
            "a",
            "ok",
            scene_id=48,
            im_id=1,
            obj_id=2,
            cam_from_model=_T(np.eye(3), [0.1, 0.2, 0.3]),
            confidence=0.75,
            timings={"sift": 0.5, "gnc": 0.25},
        ),
        PoseRecord(
            "48/1",
            "c",
            "too_few_matches",
            reason="3 matches",
            scene_id=48,
            im_id=1,
            obj_id=9,
            timings={"sift": 1.0},
        ),
    ]
    return pd.DataFrame([r.to_row() for r in recs])


def test_write_exact_lines(tmp_path):
    path = bop.write_bop_csv(_poses(), tmp_path / "res" / "gnc_ycbv-test.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert len(lines) == 4  # the failed row is left out
    # Image 48/1 took 0.75 + 0.25 + 1.0 = 2.0 s over all its rows (failed ones too), on every line of it,
    # as bop_toolkit requires one time per image.
    assert lines[1] == "48,1,2,0.75,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,100.0 200.0 300.0,2.0"
    assert [ln.split(",")[:3] for ln in lines[1:]] == [["48", "1", "2"], ["48", "1", "5"], ["48", "2", "5"]]
    assert lines[2].endswith(",2.0") and lines[3].endswith(",0.625")
    assert not list(tmp_path.rglob("*.tmp"))

    per_row = bop.write_bop_csv(_poses(), tmp_path / "row.csv", time_per="row").read_text().splitlines()
    assert per_row[1].endswith(",0.75") and per_row[2].endswith(",0.25")


def test_round_trip_byte_exact(tmp_path):
    poses = _poses()
    first = bop.write_bop_csv(poses, tmp_path / "a.csv")
    table = bop.read_bop_csv(first)
    assert list(table.columns) == list(bop.BOP_COLUMNS)
    assert table["obj_id"].tolist() == [2, 5, 5]
    ok = poses[poses["status"] == "ok"].sort_values(["scene_id", "im_id", "obj_id"])
    for (_, r), (_, e) in zip(table.iterrows(), ok.iterrows(), strict=True):
        np.testing.assert_array_equal(r["R"], e["R"])  # repr() round-trips floats exactly
        np.testing.assert_allclose(r["t_mm"], np.asarray(e["t_m"]) * 1000.0, rtol=0, atol=1e-12)
        assert r["score"] == e["confidence"]
    second = bop.write_bop_csv(table, tmp_path / "b.csv")
    assert second.read_bytes() == first.read_bytes()
    assert bop.read_bop_csv(second).equals(table)


def test_empty_results(tmp_path):
    path = bop.write_bop_csv(_poses().iloc[3:], tmp_path / "empty.csv")
    assert path.read_text() == "scene_id,im_id,obj_id,score,R,t,time\n"
    assert bop.read_bop_csv(path).empty


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("scene,im,obj\n", r"bad\.csv:1: expected the header"),
        ("", r"bad\.csv:1: expected the header.*empty file"),
        (
            "scene_id,im_id,obj_id,score,R,t,time\n48,1,2,0.5,1 0 0 0 1 0 0 0 1,1 2 3\n",
            r"bad\.csv:2: expected 7 comma-separated fields.*got 6",
        ),
        (
            (
                "scene_id,im_id,obj_id,score,R,t,time\n48,1,2,0.5,1 0 0 0 1 0 0 0 1,1 2 3,1\n"
                "48,1,2,0.5,1 0 0 0 1 0 0 0,1 2 3,1\n"
            ),
            r"bad\.csv:3: field R needs 9 .* got 8",
        ),
        (
            "scene_id,im_id,obj_id,score,R,t,time\n48,x,2,0.5,1 0 0 0 1 0 0 0 1,1 2 3,1\n",
            r"bad\.csv:2: field im_id must be a non-negative integer, got 'x'",
        ),
        (
            "scene_id,im_id,obj_id,score,R,t,time\n48,1,2,0.5,1 0 0 0 1 0 0 0 1,1 nan 3,1\n",
            r"bad\.csv:2: field t contains NaN",
        ),
        (
            "scene_id,im_id,obj_id,score,R,t,time\n48,1,2,high,1 0 0 0 1 0 0 0 1,1 2 3,1\n",
            r"bad\.csv:2: field score is not numeric",
        ),
    ],
)
def test_read_malformed_names_file_and_line(tmp_path, body, message):
    path = tmp_path / "bad.csv"
    path.write_text(body)
    with pytest.raises(DataError, match=message):
        bop.read_bop_csv(path)


def test_read_missing_file(tmp_path):
    with pytest.raises(DataError, match=r"nope\.csv: BOP results file not found"):
        bop.read_bop_csv(tmp_path / "nope.csv")


def test_score_bop_csv(tmp_path):
    poses = _poses()
    path = bop.write_bop_csv(poses, tmp_path / "res.csv")
    # Ground truth equal to the estimates for a and b, plus an instance of c (failed -> not in the file).
    gt = poses[["frame_id", "obj_name", "obj_id", "R", "t_m"]].copy()
    gt.loc[gt["obj_name"] == "c", "R"] = pd.Series([np.eye(3).ravel().tolist()], index=[3])
    gt.loc[gt["obj_name"] == "c", "t_m"] = pd.Series([[0.0, 0.0, 1.0]], index=[3])
    frames = poses[["frame_id", "scene_id", "im_id"]].drop_duplicates()
    pts = np.random.default_rng(2).normal(scale=0.03, size=(100, 3))
    points = {n: pts for n in "abc"}
    diam = {n: 0.1 for n in "abc"}
    names = {2: "a", 5: "b", 9: "c"}

    with pytest.raises(DataError, match="cannot match BOP image ids"):
        scoring.score_bop_csv(path, gt, points, diam, names)
    inst, summary = scoring.score_bop_csv(path, gt, points, diam, names, frames=frames)
    s = summary.set_index("obj_name")
    assert s.loc["a", "add_auc"] == pytest.approx(100.0) and s.loc["b", "adds_auc"] == pytest.approx(100.0)
    assert s.loc["c", "add_auc"] == 0.0 and s.loc["c", "n_missing"] == 1
    np.testing.assert_allclose(inst.loc[inst["obj_name"] != "c", "add_m"], 0.0, atol=1e-9)
    # obj_id 5 unknown: b's estimates are dropped, so b becomes missing.
    _, summary = scoring.score_bop_csv(path, gt, points, diam, {2: "a", 9: "c"}, frames=frames)
    assert summary.set_index("obj_name").loc["b", "n_missing"] == 2
    assert math.isclose(summary.set_index("obj_name").loc["pooled", "add_auc"], 100 * 1 / 4)
