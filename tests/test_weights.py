"""Geometry-aware weights equal SPEC §3's formula on hand-built voxel layouts."""

import numpy as np
import pytest

from batchpose.method.weights import geom_weights, model_support, model_voxel_grid, support_to_weights


def test_weights_match_formula_exactly():
    v = 0.005
    # voxel (0,0,0): 3 points; voxel (1,0,0): 1 point; voxel (-1,2,0): 2 points.
    X = np.array(
        [
            [0.001, 0.001, 0.001],
            [0.004, 0.002, 0.003],
            [0.0025, 0.0049, 0.0001],
            [0.006, 0.001, 0.001],
            [-0.004, 0.011, 0.002],
            [-0.001, 0.012, 0.004],
        ]
    )
    w = geom_weights(X, voxel_m=v, w_min=0.2)
    s = np.array([3, 3, 3, 1, 2, 2])
    expected = 0.2 + 0.8 * s / 3
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-12)


def test_model_mode_counts_library_points():
    lib_pts = np.array([[0.001, 0.001, 0.001]] * 4 + [[0.011, 0.0, 0.0]] * 2)
    keys, counts = model_voxel_grid(lib_pts, 0.005)
    X = np.array([[0.002, 0.003, 0.004], [0.012, 0.001, 0.001], [0.5, 0.5, 0.5]])
    s = model_support(X, keys, counts, 0.005)
    np.testing.assert_array_equal(s, [4, 2, 0])
    np.testing.assert_allclose(support_to_weights(s, 0.2), [1.0, 0.2 + 0.8 * 0.5, 0.2])


def test_shape_error_names_expected_shape():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        geom_weights(np.zeros((4, 2)))
