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
