"""Monte-Carlo samples of the training box and their importance weights.

The losses of NSSPR are integrals over a box B (the mean loss) and over B x B (the covariance loss). With a compact
kernel the targets vanish on most of the box: mu(x) = 0 further than 2h from every point, and Sigma(x, y) = 0 for
|x - y|_inf >= 4h. Sampling uniformly wastes most of a batch on trivially-zero targets, so both samplers draw from a
mixture of a uniform proposal and a "near" proposal, and weight every sample with the multiple-importance-sampling
balance heuristic: a sample x_k drawn with any technique gets weight 1 / sum_s n_s q_s(x_k), where n_s and q_s are
the sample count and the density of technique s. Then sum_k w_k f(x_k) is an unbiased estimate of the integral of f,
whatever f is (Veach 1997): the estimators below stay Monte-Carlo estimates of the paper's integrals.
"""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """An axis-aligned box [lo, hi] in the normalised frame (the integration domain B)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def extent(self):
        return self.hi - self.lo

    @property
    def volume(self):
        return float(np.prod(self.extent))

    @classmethod
    def around(cls, points, margin):
        """The bounding cube of ``points`` (n, 3) grown by ``margin`` on every side."""
        lo, hi = points.min(0), points.max(0)
        centre, half = (lo + hi) / 2, (hi - lo).max() / 2 + margin
        return cls(centre - half, centre + half)

    def uniform(self, n, rng):
        return self.lo + rng.random((n, 3)) * self.extent

    def surface(self, n, rng):
        """n points uniform on the box's surface -> (n, 3) array (faces chosen in proportion to their area)."""
        x = self.uniform(n, rng)
        face_area = np.prod(self.extent) / self.extent  # the two faces normal to each axis
        axis = rng.choice(3, n, p=face_area / face_area.sum())
        side = rng.integers(0, 2, n).astype(bool)
        x[np.arange(n), axis] = np.where(side, self.hi[axis], self.lo[axis])
        return x


def sample_mean_targets(posterior, box, n_uniform, n_near, rng):
    """Samples of the mean-loss integrand with their MIS weights.

    The near proposal picks a cloud point p uniformly and adds U([-r, r]^3) with r = 2h, the kernel support, so its
    density is q_near(x) = count_r(x) / (n (2r)^3), count_r(x) being the number of points whose support contains x:
    exactly the number of non-zero kernel entries of the row K2(x), which the posterior computes anyway. Near
    samples that fall outside B are outside the integral and get weight 0.

    Estimator (s = n_uniform + n_near samples in all):

        (1/|B|) int_B |mu(x) - grad g(x)|^2 dx  ~=  (1/s) sum_k omega_k |mu(x_k) - grad g(x_k)|^2,
        omega_k = 1 / (f_u + f_n |B| q_near(x_k)),  f_u = n_uniform / s,  f_n = n_near / s

    so omega = 1 for purely uniform sampling, and the paper's loss |B|/s sum |mu - grad g|^2 is |B| times it.

    Parameters
    ----------
    posterior : GPPosterior
    box : Box
    n_uniform, n_near : int
    rng : numpy.random.Generator

    Returns
    -------
    x : (s, 3) float32 array
    mu : (s, 3) float32 array
    omega : (s,) float32 array
    """
    radius = posterior.radius
    picks = rng.integers(0, len(posterior.points), n_near)
    near = posterior.points[picks] + rng.uniform(-radius, radius, (n_near, 3))
    x = np.concatenate([box.uniform(n_uniform, rng), near])
    mu, count = posterior.mean_and_support(x)
    s = len(x)
    q_near = count / (len(posterior.points) * (2 * radius) ** 3)
    omega = 1.0 / (n_uniform / s + (n_near / s) * box.volume * q_near)
    inside = np.all((x >= box.lo) & (x <= box.hi), axis=1)
    omega = np.where(inside, omega, 0.0)
    return x.astype(np.float32), mu.astype(np.float32), omega.astype(np.float32)


def cluster_density(diff, radius):
    """Density of the offset between two members of one cluster (see :func:`sample_pair_clusters`).

    Two members are c + u1 and c + u2 with u1, u2 ~ U([-r, r]^3) independent, so their offset has the product
    triangular density prod_d (2r - |delta_d|)_+ / (2r)^2.

    Parameters
    ----------
    diff : (..., 3) array
        Offsets (torus differences).
    radius : float
        r.

    Returns
    -------
    (...,) array
    """
    return np.prod(np.clip(2 * radius - np.abs(diff), 0, None), axis=-1) / (2 * radius) ** 6


def torus_difference(a, b, box):
    """a - b wrapped into [-extent/2, extent/2) per axis (the box treated as a torus)."""
    d = a - b
    return d - box.extent * np.round(d / box.extent)


def sample_pair_clusters(box, n_clusters, cluster_size, radius, rng):
    """Points in clusters, whose all ordered pairs sample the covariance loss over B x B.

    Cluster centres are uniform on B and members are centre + U([-r, r]^3), wrapped back into B as on a torus, so
    every point is marginally uniform on B. Over the batch of m = C s points there are n_w = C s (s - 1) ordered
    within-cluster pairs, distributed with density q_w(x, y) = cluster_density(x - y) / |B| (torus difference), and
    n_c = m^2 - C s^2 cross-cluster pairs with density 1 / |B|^2. The balance-heuristic weight of every ordered
    pair (i != j) is

        w_ij = 1 / (n_w q_w(x_i, x_j) + n_c / |B|^2),

    and  sum_{i != j} w_ij ||Sigma(x_i, x_j) I - D c(x_i, x_j)||_F^2  is an unbiased estimate of the paper's
    double integral  int_B int_B ||Sigma(x, y) I - D c(x, y)||_F^2 dx dy.

    Parameters
    ----------
    box : Box
    n_clusters, cluster_size : int
        C and s (s >= 2).
    radius : float
        Half-width r of a cluster; 2h makes within-cluster offsets span Sigma's support (4h).
    rng : numpy.random.Generator

    Returns
    -------
    x : (m, 3) float32 array
    weights : (m, m) float32 array
        w_ij, zero on the diagonal.
    """
    if cluster_size < 2:
        raise ValueError(f"cluster_size must be >= 2, got {cluster_size}")
    centres = box.uniform(n_clusters, rng)
    x = np.repeat(centres, cluster_size, 0) + rng.uniform(-radius, radius, (n_clusters * cluster_size, 3))
    x = box.lo + np.mod(x - box.lo, box.extent)
    m = len(x)
    n_within = n_clusters * cluster_size * (cluster_size - 1)
    n_cross = m * m - n_clusters * cluster_size**2
    diff = torus_difference(x[:, None, :], x[None, :, :], box)  # (m, m, 3)
    q_within = cluster_density(diff, radius) / box.volume
    weights = 1.0 / (n_within * q_within + n_cross / box.volume**2)
    np.fill_diagonal(weights, 0.0)
    return x.astype(np.float32), weights.astype(np.float32)
