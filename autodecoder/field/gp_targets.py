"""Gaussian-process posterior of the normal field (the training targets of the two Poisson problems).

The oriented points are noisy observations of a vector field v with independent components, each a GP with the
compact kernel k of :mod:`autodecoder.field.kernel`. Given points P (n, 3) and normals N (n, 3),

    mu(x)        = K2(x) K3^-1 N                         (posterior mean of v, (3,))
    Sigma(x, y)  = k(x, y) - K2(x) K3^-1 K2(y)^T         (posterior covariance, the same scalar for each component)

with K2(x) = [k(x, p_i)]_i and K3 = [k(p_i, p_j)]_ij + sigma_n^2 I. Solving with K3 is out of the question for
100k points, so K3 is *lumped*: replaced by the diagonal D with D_ii = sum_j k(p_i, p_j) + sigma_n^2 (row-sum or
"mass" lumping, the same approximation Stochastic PSR makes with its splatted sampling density).

Why row-sum lumping: K3 has non-negative entries, so D - K3 is weakly diagonally dominant with a non-negative
diagonal, hence positive semi-definite (Gershgorin). Therefore D >= K3, D^-1 <= K3^-1, and the lumped posterior
covariance is never smaller than the exact one: it stays a valid (PSD) covariance and errs on the side of more
uncertainty. The lumped mean is a normalised kernel (Shepard) average of the normals, of unit magnitude on a densely
sampled surface whatever the sampling density, which is what the gradient of the implicit function should be there.

All kernel sums are evaluated only on KD-tree neighbour pairs: k vanishes beyond Chebyshev distance 2h.
"""
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from autodecoder.field.kernel import kernel, support_radius


class GPPosterior:
    """Lumped GP posterior of the vector field from an oriented point cloud.

    Parameters
    ----------
    points : (n, 3) array
        Point positions (any frame; all queries use the same frame).
    normals : (n, 3) array
        Unit outward normals.
    lengthscale : float
        Kernel lengthscale h (support 2h per axis).
    normal_noise : float, optional
        Standard deviation sigma_n of the normal observations, added to the lumped diagonal.
    amplitude : float, optional
        Prior scale of the kernel.
    """

    def __init__(self, points, normals, lengthscale, normal_noise=0.0, amplitude=1.0):
        points = np.ascontiguousarray(points, dtype=np.float64)
        normals = np.ascontiguousarray(normals, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
            raise ValueError(f"points and normals must both be (n, 3); got {points.shape} and {normals.shape}")
        if len(points) == 0:
            raise ValueError("the point cloud is empty")
        if not lengthscale > 0:
            raise ValueError(f"lengthscale must be > 0, got {lengthscale}")
        self.points = points
        self.normals = normals
        self.lengthscale = float(lengthscale)
        self.amplitude = float(amplitude)
        self.normal_noise = float(normal_noise)
        self.radius = support_radius(self.lengthscale)
        self.tree = cKDTree(points)
        self.lumped = self._lumped_diagonal()  # (n,)
        self.weighted_normals = normals / self.lumped[:, None]  # D^-1 N, (n, 3)

    def _lumped_diagonal(self):
        pairs = self.tree.query_pairs(self.radius, p=np.inf, output_type="ndarray")  # i < j
        k_off = kernel(self.points[pairs[:, 0]] - self.points[pairs[:, 1]], self.lengthscale, self.amplitude)
        rows = np.full(len(self.points), kernel(np.zeros(3), self.lengthscale, self.amplitude))
        np.add.at(rows, pairs[:, 0], k_off)
        np.add.at(rows, pairs[:, 1], k_off)
        return rows + self.normal_noise**2

    def cross_kernel(self, x):
        """The sparse matrix K2 = [k(x_a, p_i)], (m, n) CSR, from KD-tree neighbour pairs."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        if len(x) == 0:
            return sp.csr_matrix((0, len(self.points)))
        pairs = cKDTree(x).sparse_distance_matrix(self.tree, self.radius, p=np.inf, output_type="ndarray")
        vals = kernel(x[pairs["i"]] - self.points[pairs["j"]], self.lengthscale, self.amplitude)
        return sp.csr_matrix((vals, (pairs["i"], pairs["j"])), shape=(len(x), len(self.points)))

    def mean(self, x):
        """Posterior mean mu(x) of the vector field.

        Parameters
        ----------
        x : (m, 3) array

        Returns
        -------
        (m, 3) float64 array
        """
        return np.asarray(self.cross_kernel(x) @ self.weighted_normals)

    def mean_and_support(self, x):
        """Posterior mean and the number of cloud points inside each query's kernel support.

        Returns
        -------
        mu : (m, 3) float64 array
        count : (m,) int array
            How many points lie within Chebyshev distance 2h of each query (used for importance weights).
        """
        k2 = self.cross_kernel(x)
        return np.asarray(k2 @ self.weighted_normals), np.diff(k2.indptr)

    def covariance(self, x1, x2):
        """Posterior covariance Sigma(x1_a, x2_a) for pairs taken row by row.

        Parameters
        ----------
        x1, x2 : (m, 3) arrays

        Returns
        -------
        (m,) float64 array
        """
        x1 = np.asarray(x1, dtype=np.float64)
        x2 = np.asarray(x2, dtype=np.float64)
        if x1.shape != x2.shape:
            raise ValueError(f"x1 and x2 must have the same shape, got {x1.shape} and {x2.shape}")
        prior = kernel(x1 - x2, self.lengthscale, self.amplitude)
        explained = np.asarray(self.cross_kernel(x1).multiply(self.cross_kernel(x2)) @ (1.0 / self.lumped)).ravel()
        return prior - explained

    def covariance_matrix(self, x):
        """Posterior covariance between all pairs of queries, as a sparse matrix.

        Only pairs within Chebyshev distance 4h can be non-zero (2h for the prior term); all others are exactly
        zero and are not stored.

        Parameters
        ----------
        x : (m, 3) array

        Returns
        -------
        (m, m) scipy.sparse CSR matrix, symmetric.
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        tree_x = cKDTree(x)
        near = tree_x.sparse_distance_matrix(tree_x, self.radius, p=np.inf, output_type="ndarray")
        prior = sp.csr_matrix(
            (kernel(x[near["i"]] - x[near["j"]], self.lengthscale, self.amplitude), (near["i"], near["j"])),
            shape=(len(x), len(x)),
        )
        k2 = self.cross_kernel(x)
        explained = k2 @ sp.diags(1.0 / self.lumped) @ k2.T
        return (prior - explained).tocsr()

    def prior_variance(self):
        """k(x, x): the covariance far from every point."""
        return float(kernel(np.zeros(3), self.lengthscale, self.amplitude))
