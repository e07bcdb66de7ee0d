"""The closed-form smallest eigenpair of 3 x 3 scatter matrices against LAPACK (numpy.linalg.eigh)."""
import numpy as np
import pytest

from datasets.local_planes import smallest_eigenpairs


def _scatter(rng, m, spreads, scale=1.0):
    """(m, 3, 3) scatter matrices of 16 random points each, spread (sx, sy, sz) along a random rotation."""
    d = rng.normal(size=(m, 16, 3)) * np.asarray(spreads) * scale
    q, _ = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    d = d @ q
    return np.matmul(d.transpose(0, 2, 1), d) / 16


@pytest.mark.parametrize("spreads", [(1, 1, 1), (1, 1, 0.05), (1, 0.3, 1e-4), (1, 1, 0.0)])
@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e3])
def test_matches_lapack(spreads, scale):
    rng = np.random.default_rng(0)
    cov = _scatter(rng, 2000, spreads, scale)
    value, vector = smallest_eigenpairs(cov)
    ref_values, ref_vectors = np.linalg.eigh(cov)
    top = ref_values[:, 2]
    np.testing.assert_allclose(value, ref_values[:, 0], rtol=0, atol=1e-12 * top.max())
    np.testing.assert_allclose(np.linalg.norm(vector, axis=1), 1.0, atol=1e-12)
    # the eigenvector equation itself, and the same direction as LAPACK's wherever that one is well defined
    residual = np.linalg.norm(np.einsum("mij,mj->mi", cov, vector) - value[:, None] * vector, axis=1)
    assert residual.max() <= 1e-9 * top.max()
    gap = (ref_values[:, 1] - ref_values[:, 0]) / top
    defined = gap > 1e-3
    cos = np.abs(np.einsum("mi,mi->m", vector, ref_vectors[:, :, 0]))
    np.testing.assert_allclose(cos[defined], 1.0, atol=1e-9)


def test_degenerate_matrices_fall_back():
    """A line of points, a point, an isotropic blob, a plane along the axes: still an eigenpair of the matrix."""
    line = np.zeros((3, 3))
    line[0, 0] = 2.0
    cases = np.stack([line, np.zeros((3, 3)), np.eye(3) * 0.5, np.diag([3.0, 2.0, 0.0])])
    value, vector = smallest_eigenpairs(cases)
    np.testing.assert_allclose(value, [0.0, 0.0, 0.5, 0.0], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(vector, axis=1), 1.0)
    residual = np.einsum("mij,mj->mi", cases, vector) - value[:, None] * vector
    np.testing.assert_allclose(residual, 0.0, atol=1e-15)
    np.testing.assert_allclose(np.abs(vector[3]), [0, 0, 1])


def test_plane_normal_of_points():
    """The normal of noisy points on a tilted plane is the plane's normal."""
    rng = np.random.default_rng(1)
    normal = np.array([1.0, 2.0, 2.0]) / 3.0
    u = np.cross(normal, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    pts = rng.normal(size=(50, 2)) @ np.stack([u, w]) + 1e-3 * rng.normal(size=(50, 1)) * normal
    d = pts - pts.mean(0)
    _, vector = smallest_eigenpairs((d.T @ d)[None])
    assert abs(vector[0] @ normal) > 1 - 1e-5


def test_shapes():
    value, vector = smallest_eigenpairs(np.zeros((0, 3, 3)))
    assert value.shape == (0,) and vector.shape == (0, 3)
    with pytest.raises(ValueError, match="3, 3"):
        smallest_eigenpairs(np.zeros((4, 2, 2)))


def test_non_finite_matrices_are_one_clear_error():
    bad = np.eye(3)[None].repeat(2, 0)
    bad[1, 0, 0] = np.inf
    with pytest.raises(ValueError, match="finite"):
        smallest_eigenpairs(bad)
