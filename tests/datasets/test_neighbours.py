"""datasets.neighbours: exact k nearest neighbours against scipy's cKDTree and brute force."""
import pickle

import numpy as np
import pytest
from scipy.spatial import cKDTree

from datasets.neighbours import NearestNeighbours


def test_the_same_neighbours_as_ckdtree_and_brute_force():
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(2000, 3)) * [1.0, 1.0, 0.01]  # a noisy sheet, as scans are
    query = rng.normal(size=(300, 3)) * [1.0, 1.0, 0.01]
    distance, index = NearestNeighbours(cloud).query(query, 9)
    ref_distance, ref_index = cKDTree(cloud).query(query, 9)
    np.testing.assert_array_equal(index, ref_index)
    np.testing.assert_allclose(distance, ref_distance, rtol=1e-12)
    brute = np.linalg.norm(query[:, None] - cloud[None], axis=2)
    np.testing.assert_allclose(distance, np.sort(brute, axis=1)[:, :9], rtol=1e-12)
    assert index.dtype == np.intp and distance.shape == index.shape == (300, 9)


def test_shapes_errors_and_pickling():
    rng = np.random.default_rng(1)
    nn = NearestNeighbours(rng.random((50, 3)).astype(np.float32))
    assert nn.n == 50 and nn.data.dtype == np.float64
    d, i = nn.query(rng.random((4, 3)), 1)
    assert d.shape == i.shape == (4, 1)
    assert nn.query(np.zeros((0, 3)), 3)[1].shape == (0, 3)
    with pytest.raises(ValueError, match="k must be"):
        nn.query(rng.random((2, 3)), 51)
    with pytest.raises(ValueError, match="at least one point"):
        NearestNeighbours(np.zeros((0, 3)))
    again = pickle.loads(pickle.dumps(nn))
    q = rng.random((5, 3))
    np.testing.assert_array_equal(again.query(q, 4)[1], nn.query(q, 4)[1])


def test_non_finite_points_are_one_clear_error():
    cloud = np.random.default_rng(2).random((20, 3))
    bad = cloud.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        NearestNeighbours(bad)
    with pytest.raises(ValueError, match="finite"):
        NearestNeighbours(cloud).query(bad, 2)


def test_nearest_within_is_ckdtrees_distance_bounded_query():
    """The registration's correspondences: which query points have an indexed point within the bound, and which
    one, exactly as cKDTree's distance-bounded query (and brute force) gives them."""
    rng = np.random.default_rng(4)
    data = rng.uniform(size=(3000, 3))
    x = np.r_[rng.uniform(-0.2, 1.2, size=(700, 3)), data[:50] + 1e-4]
    index = NearestNeighbours(data)
    for bound in (0.005, 0.02, 0.3):
        found, rows = index.nearest_within(x, bound)
        distance, expected_rows = cKDTree(data).query(x, distance_upper_bound=bound)
        assert found.dtype == bool and found.shape == (len(x),)
        np.testing.assert_array_equal(found, np.isfinite(distance))
        np.testing.assert_array_equal(rows[found], expected_rows[found])
        assert (rows[~found] == len(data)).all()
        brute = np.linalg.norm(x[:, None] - data[None], axis=-1)
        np.testing.assert_array_equal(found, brute.min(1) < bound)
        if bound == 0.02:  # some query points with a neighbour within it, some without
            assert 0 < found.sum() < len(x)
    empty_found, empty_rows = index.nearest_within(np.zeros((0, 3)), 0.1)
    assert empty_found.shape == (0,) and empty_rows.shape == (0,)
    with pytest.raises(ValueError, match="finite"):
        index.nearest_within(np.array([[np.nan, 0, 0]]), 0.1)
