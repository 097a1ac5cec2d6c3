"""benchmarks/line_of_sight.py: the split of a translation error along and across the viewing ray, the scale
ratio, and the along-ray spread SIFT's inliers predict."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def los():
    return load_benchmark("line_of_sight")


def _ray_frame(t_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unit ray through ``t_gt`` and a unit vector across it."""
    u = t_gt / np.linalg.norm(t_gt)
    v = np.cross(u, [1.0, 0.0, 0.0])
    return u, v / np.linalg.norm(v)


def test_a_known_error_splits_into_its_along_and_across_parts(los):
    t_gt = np.array([0.12, -0.05, 0.85])
    u, v = _ray_frame(t_gt)
    t_est = t_gt + 0.015 * u + 0.004 * v  # 15 mm too far, 4 mm to the side
    s = los.decompose(t_est, t_gt)
    assert s["along_m"][0] == pytest.approx(0.015, abs=1e-12)
    assert s["across_m"][0] == pytest.approx(0.004, abs=1e-12)
    assert s["along_pct"][0] == pytest.approx(100 * 0.015 / np.linalg.norm(t_gt), rel=1e-12)
    near = los.decompose(t_gt - 0.02 * u, t_gt)  # too near: negative, nothing across
    assert near["along_m"][0] == pytest.approx(-0.02, abs=1e-12)
    assert near["across_m"][0] == pytest.approx(0.0, abs=1e-12)
    assert near["ratio"][0] < 1.0


def test_a_scale_error_is_one_constant_ratio_and_nothing_across(los):
    rng = np.random.default_rng(3)
    t_gt = rng.uniform([-0.3, -0.2, 0.5], [0.3, 0.2, 1.5], size=(50, 3))
    s = los.decompose(1.03 * t_gt, t_gt)  # e.g. a focal length 3 % too long
    np.testing.assert_allclose(s["ratio"], 1.03, rtol=1e-12)
    np.testing.assert_allclose(s["along_pct"], 3.0, rtol=1e-10)
    np.testing.assert_allclose(s["across_m"], 0.0, atol=1e-12)
    # a lateral slip of the same size changes the ratio only to second order
    u, v = _ray_frame(t_gt[0])
    lateral = los.decompose(t_gt[0] + 0.03 * np.linalg.norm(t_gt[0]) * v, t_gt[0])
    assert abs(lateral["ratio"][0] - 1) < 1e-3 and abs(lateral["along_m"][0]) < 1e-12


def test_bad_shapes_and_a_zero_ray_are_refused(los):
    with pytest.raises(ValueError, match="must both be"):
        los.decompose(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="zero"):
        los.decompose(np.ones(3), np.zeros(3))


def test_the_predicted_spread_matches_a_simulated_scale_fit(los):
    rng = np.random.default_rng(0)
    x = rng.uniform(-80, 80, size=(60, 2))  # inliers about their centre, pixels
    x -= x.mean(axis=0)
    sigma = 0.7
    median_norm = sigma * np.sqrt(2 * np.log(2))  # the median residual norm such noise gives
    pred = los.predicted_along_pct(x, median_norm)
    noisy = x + rng.normal(0, sigma, size=(4000, *x.shape))
    c = noisy - noisy.mean(axis=1, keepdims=True)
    scales = np.einsum("tij,ij->t", c, x) / (x**2).sum()  # least-squares image scale of each trial
    assert pred == pytest.approx(100 * scales.std(), rel=0.08)
    assert np.isnan(los.predicted_along_pct(x[:2], median_norm))


def test_video_of(los):
    assert los.video_of("0049/000012") == "0049"
    assert los.video_of("data_syn/000003") == "data_syn"
    assert los.video_of("mcap:170") == "-"
