"""Metrics against hand-computed values and the YCB-Video toolbox's AUC definition (AUC.md)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from batchpose.errors import DataError
from batchpose.report import metrics


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _vocap_reference(distances: list[float], max_distance: float = 0.1) -> float:
    """A literal, loop-by-loop port of the toolbox's plot_accuracy_keyframe.m + VOCap (AUC.md)."""
    D = [math.inf if (math.isnan(d) or d > max_distance) else d for d in distances]
    d = sorted(D)
    n = len(d)
    accuracy = [(k + 1) / n for k in range(n)]
    rec = [x for x in d if math.isfinite(x)]
    prec = [a for x, a in zip(d, accuracy, strict=True) if math.isfinite(x)]
    if not rec:
        return 0.0
    mrec = [0.0] + rec + [max_distance]
    mpre = [0.0] + prec + [prec[-1]]
    for i in range(1, len(mpre)):
        mpre[i] = max(mpre[i], mpre[i - 1])
    ap = 0.0
    for i in range(1, len(mrec)):
        if mrec[i] != mrec[i - 1]:
            ap += (mrec[i] - mrec[i - 1]) * mpre[i]
    return ap / max_distance * 100.0


# --- VOCap AUC -------------------------------------------------------------------------------------


def test_vocap_auc_hand_computed():
    # n = 4, sorted d = .02 .04 .06 inf, accuracies .25 .5 .75 (1.0 is the failure, dropped).
    # rec = [0, .02, .04, .06, .1], prec = [0, .25, .5, .75, .75] (already non-decreasing).
    # area = .02*.25 + .02*.5 + .02*.75 + .04*.75 = .005 + .01 + .015 + .03 = .06 -> .06/.1*100 = 60.
    # (The continuous mean(max(0, .1 - d))/.1 would be (.08+.06+.04+0)/4/.1 = 45: the step is upper.)
    assert metrics.vocap_auc(np.array([0.06, 0.02, np.inf, 0.04])) == pytest.approx(60.0, abs=1e-12)


def test_vocap_auc_over_max_distance_is_failure():
    # 0.15 > 0.1 becomes inf: n = 2, rec = [0, .02, .1], prec = [0, .5, .5] -> (.02*.5 + .08*.5)/.1 = 50.
    assert metrics.vocap_auc(np.array([0.02, 0.15])) == pytest.approx(50.0, abs=1e-12)


def test_vocap_auc_ties_follow_the_toolbox():
    # rec = [0, .05, .05, .1], prec = [0, .5, 1, 1]; the tie's zero-width interval is skipped, so the
    # first interval uses .5: .05*.5 + .05*1 = .075 -> 75 (not 50: the toolbox's right-end rule).
    assert metrics.vocap_auc(np.array([0.05, 0.05])) == pytest.approx(75.0, abs=1e-12)


def test_vocap_auc_perfect_missing_and_empty():
    assert metrics.vocap_auc(np.zeros(7)) == pytest.approx(100.0)
    # Each missing estimate caps the accuracy: 3 perfect + 1 missing -> 3/4 of the area.
    assert metrics.vocap_auc(np.array([0.0, 0.0, 0.0, np.inf])) == pytest.approx(75.0)
    assert metrics.vocap_auc(np.array([0.0, 0.0, 0.0, np.nan])) == pytest.approx(75.0)
    assert metrics.vocap_auc(np.array([np.inf, np.nan])) == 0.0
    assert math.isnan(metrics.vocap_auc(np.zeros(0)))


def test_vocap_auc_matches_literal_toolbox_port():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 40))
        d = rng.uniform(0.0, 0.15, n).round(3)  # rounding makes ties
        d[rng.random(n) < 0.2] = np.inf
        d[rng.random(n) < 0.05] = np.nan
        assert metrics.vocap_auc(d) == pytest.approx(_vocap_reference(d.tolist()), abs=1e-9)


def test_vocap_auc_rejects_bad_shape():
    with pytest.raises(ValueError, match=r"shape \(n,\).*\(2, 2\)"):
        metrics.vocap_auc(np.zeros((2, 2)))


# --- recall and curve ------------------------------------------------------------------------------


def test_recall_strictly_below_threshold():
    d = np.array([0.005, 0.01, 0.02, np.inf])
    assert metrics.recall(d, 0.01) == pytest.approx(25.0)  # 0.01 is not < 0.01
    assert metrics.recall(d, np.array([0.01, 0.02, 0.03, 1.0])) == pytest.approx(75.0)  # inf never passes
    with pytest.raises(ValueError, match="threshold"):
        metrics.recall(d, np.ones(3))


def test_accuracy_curve():
    d = np.array([0.01, 0.03, np.inf, np.nan])
    curve = metrics.accuracy_curve(d, np.array([0.0, 0.01, 0.02, 0.05]))
    np.testing.assert_allclose(curve, [0.0, 25.0, 25.0, 50.0])


# --- per-instance errors ---------------------------------------------------------------------------

# Four points on a square of half-width a: symmetric under a 90 degree turn about z.
A = 0.05
SQUARE = np.array([[A, 0, 0], [0, A, 0], [-A, 0, 0], [0, -A, 0]], dtype=float)


def test_add_adds_translation_offset():
    R = _rot_z(30)
    t = np.array([0.1, -0.05, 0.8])
    off = np.array([0.003, 0.0, 0.004])  # 5 mm
    assert metrics.add(R, t + off, R, t, SQUARE) == pytest.approx(0.005)
    # Points are 70 mm apart, so each nearest neighbour is the same point moved by 5 mm.
    assert metrics.adds(R, t + off, R, t, SQUARE) == pytest.approx(0.005)
    assert metrics.translation_error_mm(t + off, t) == pytest.approx(5.0)
    assert metrics.rotation_error_deg(R, R) == pytest.approx(0.0, abs=1e-6)


def test_add_adds_symmetric_rotation():
    # A 90 degree turn about z maps the square onto itself: every point lands on its neighbour
    # (distance a*sqrt(2)) for ADD, but on another model point (distance 0) for ADD-S.
    t = np.array([0.0, 0.0, 1.0])
    R_gt = np.eye(3)
    R_est = _rot_z(90)
    assert metrics.add(R_est, t, R_gt, t, SQUARE) == pytest.approx(A * math.sqrt(2))
    assert metrics.adds(R_est, t, R_gt, t, SQUARE) == pytest.approx(0.0, abs=1e-12)
    assert metrics.rotation_error_deg(R_est, R_gt) == pytest.approx(90.0)
    assert metrics.rotation_error_deg(_rot_z(180), R_gt) == pytest.approx(180.0)


def test_shape_checks_name_expected_and_actual():
    with pytest.raises(ValueError, match=r"pts must have shape \(N, 3\).*\(4, 2\)"):
        metrics.add(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"R_est must have shape \(3, 3\).*\(9,\)"):
        metrics.adds(np.eye(3).ravel(), np.zeros(3), np.eye(3), np.zeros(3), SQUARE)
    with pytest.raises(ValueError, match=r"t_gt must have shape"):
        metrics.translation_error_mm(np.zeros(3), np.zeros(4))


# --- table-level score -----------------------------------------------------------------------------


def _gt_row(frame_id: str, obj: str, R: np.ndarray, t: np.ndarray) -> dict:
    return {
        "frame_id": frame_id,
        "obj_name": obj,
        "obj_id": 1 if obj == "a" else 2,
        "R": R.ravel().tolist(),
        "t_m": t.tolist(),
    }


def _est_row(frame_id: str, obj: str, R, t, status: str = "ok", confidence: float = 0.9) -> dict:
    nan9, nan3 = [math.nan] * 9, [math.nan] * 3
    return {
        "frame_id": frame_id,
        "obj_name": obj,
        "status": status,
        "confidence": confidence,
        "R": nan9 if R is None else np.asarray(R).ravel().tolist(),
        "t_m": nan3 if t is None else np.asarray(t).tolist(),
    }


@pytest.fixture
def scored():
    R = _rot_z(30)
    t = np.array([0.0, 0.0, 0.7])
    gt = pd.DataFrame(
        [
            _gt_row("f1", "a", R, t),
            _gt_row("f2", "a", R, t),
            _gt_row("f3", "a", R, t),
            _gt_row("f1", "b", R, t),
            _gt_row("f2", "b", R, t),
        ]
    )
    est = pd.DataFrame(
        [
            _est_row("f1", "a", R, t),
            _est_row("f1", "a", None, None, status="pnp_failed", confidence=0.99),  # duplicate: ok row wins
            _est_row("f2", "a", R, t + np.array([0.01, 0.0, 0.0]), confidence=0.5),  # 10 mm off
            # f3 / a: no row at all -> missing
            _est_row("f1", "b", None, None, status="too_few_matches", confidence=0.0),
            _est_row("f2", "b", R, t),
            _est_row("f9", "b", R, t),  # no ground truth: ignored
        ]
    )
    points = {"a": SQUARE, "b": SQUARE * 2}
    diameters = {"a": 0.2, "b": 0.1}
    return metrics.score(est, gt, points, diameters)


def test_score_per_instance(scored):
    inst, _ = scored
    assert list(inst["frame_id"]) == ["f1", "f2", "f3", "f1", "f2"]
    assert list(inst["status"]) == ["ok", "ok", "missing", "too_few_matches", "ok"]
    assert "obj_id" in inst.columns  # extra gt columns are carried over
    np.testing.assert_allclose(inst["add_m"], [0.0, 0.01, np.inf, np.inf, 0.0], atol=1e-12)
    np.testing.assert_allclose(inst["adds_m"], [0.0, 0.01, np.inf, np.inf, 0.0], atol=1e-12)
    np.testing.assert_allclose(inst["trans_err_mm"], [0.0, 10.0, np.nan, np.nan, 0.0], atol=1e-9)
    np.testing.assert_allclose(inst["confidence"], [0.9, 0.5, np.nan, 0.0, 0.9])


def test_score_summary(scored):
    _, s = scored
    s = s.set_index("obj_name")
    assert list(s.index) == ["a", "b", "mean", "pooled"]
    # a: d = [0, .01, inf], n = 3: rec = [0, 0, .01, .1], prec = [0, 1/3, 2/3, 2/3]
    #    -> (.01*2/3 + .09*2/3)/.1*100 = 66.67; recall < 0.1*0.2 m: {0, .01} -> 66.67 %.
    assert s.loc["a", "add_auc"] == pytest.approx(200 / 3)
    assert s.loc["a", "adds_auc"] == pytest.approx(200 / 3)
    assert s.loc["a", "add_recall_01d"] == pytest.approx(200 / 3)
    assert s.loc["a", "median_trans_err_mm"] == pytest.approx(5.0)
    # b: d = [inf, 0], n = 2: rec = [0, 0, .1], prec = [0, .5, .5] -> 50.
    assert s.loc["b", "add_auc"] == pytest.approx(50.0)
    assert s.loc["b", "adds_recall_01d"] == pytest.approx(50.0)
    # mean of per-object values.
    assert s.loc["mean", "add_auc"] == pytest.approx((200 / 3 + 50) / 2)
    # pooled: d = [0, 0, .01, inf, inf], n = 5: rec = [0, 0, 0, .01, .1], prec = [0, .2, .4, .6, .6]
    #    -> (.01*.6 + .09*.6)/.1*100 = 60; recall with per-instance 0.1 d: 0, .01 (a) and 0 (b) -> 60 %.
    assert s.loc["pooled", "add_auc"] == pytest.approx(60.0)
    assert s.loc["pooled", "add_recall_01d"] == pytest.approx(60.0)
    assert s.loc["pooled", "n"] == 5 and s.loc["mean", "n"] == 5
    assert s.loc["pooled", "n_ok"] == 3
    assert s.loc["pooled", "n_missing"] == 1 and s.loc["pooled", "n_too_few_matches"] == 1
    assert s.loc["a", "n_missing"] == 1 and s.loc["b", "n_missing"] == 0


def test_score_ground_truth_gives_100():
    rng = np.random.default_rng(1)
    pts = rng.normal(scale=0.05, size=(200, 3))
    gt = pd.DataFrame([_gt_row(f"f{i}", "a", _rot_z(10 * i), np.array([0, 0, 0.5 + 0.1 * i])) for i in range(5)])
    est = gt.assign(status="ok", confidence=1.0)
    _, s = metrics.score(est, gt, {"a": pts}, {"a": 0.2})
    pooled = s.set_index("obj_name").loc["pooled"]
    assert pooled["adds_auc"] == pytest.approx(100.0) and pooled["add_auc"] == pytest.approx(100.0)
    assert pooled["add_recall_01d"] == 100.0
    # Dropping one of five estimates caps every accuracy at 4/5.
    _, s = metrics.score(est.iloc[1:], gt, {"a": pts}, {"a": 0.2})
    assert s.set_index("obj_name").loc["pooled", "add_auc"] == pytest.approx(80.0)


def test_score_names_missing_points():
    gt = pd.DataFrame([_gt_row("f1", "a", np.eye(3), np.ones(3))])
    est = pd.DataFrame([_est_row("f1", "a", np.eye(3), np.ones(3))])
    with pytest.raises(DataError, match="'a' has no model points"):
        metrics.score(est, gt, {}, {"a": 0.1})
    with pytest.raises(DataError, match="estimates table: missing column.*confidence"):
        metrics.score(est.drop(columns="confidence"), gt, {"a": SQUARE}, {"a": 0.1})


def test_score_refuses_points_and_diameter_in_different_units():
    # Millimetre model points with a metre diameter turn a 1 degree error into metres of ADD: refuse them.
    gt = pd.DataFrame([_gt_row("f1", "a", np.eye(3), np.array([0.0, 0.0, 0.5]))])
    est = pd.DataFrame([_est_row("f1", "a", _rot_z(1), np.array([0.0, 0.0, 0.5]))])
    _, s = metrics.score(est, gt, {"a": SQUARE}, {"a": 0.1})
    assert s.set_index("obj_name").loc["a", "add_auc"] > 99.0
    with pytest.raises(DataError, match=r"'a': the model points span 141\.4 but the diameter is 0\.1 m"):
        metrics.score(est, gt, {"a": SQUARE * 1000}, {"a": 0.1})
    with pytest.raises(DataError, match="'a': diameter must be a positive number of metres, got nan"):
        metrics.score(est, gt, {"a": SQUARE}, {"a": float("nan")})
