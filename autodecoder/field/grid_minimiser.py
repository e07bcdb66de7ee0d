"""The exact minimiser of ``fit_cloud``'s mean loss over all functions on a regular grid: a reference for the fit.

``fit_cloud``'s mean net minimises the paper's mean loss

    E(g) = integral_B |mu(x) - grad g(x)|^2 dx + lambda_S mean_p g(p)^2

over SIRENs by Adam. ``grid_minimiser`` minimises the same E over all functions on a regular grid of the same box B
(the model frame and the GP posterior mean mu of ``CloudTargets``, exactly as ``fit_cloud`` builds them): forward
differences along every grid edge against mu at the edge's midpoint, g(p) by trilinear interpolation. E is then a
positive-definite quadratic; its normal equations

    (delta sum_a D_a^T D_a + lambda_S / n W^T W) g = delta^2 sum_a D_a^T m_a

(delta the grid spacing, D_a the differences along axis a, m_a the edge values of mu_a, W the interpolation
matrix) are solved by conjugate gradients, preconditioned by the exact inverse of the first term (a Neumann
Laplacian, diagonal in the type-II DCT). The zero level set of the solution (``zero_level_mesh``) is what an
infinitely expressive, perfectly trained mean net would give, up to the grid's discretisation (compare two
resolutions): it separates what the GP target itself costs from what the network and its training add
(``python -m benchmarks fit --mode target-limit``; figures in docs/results.md#what-limits-the-mean-surface).
"""
import math
import time

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.fft import dctn, idctn
from scipy.sparse.linalg import LinearOperator, cg
from skimage.measure import marching_cubes

from autodecoder.field.losses import SCREENING_WEIGHT


def _difference_adjoint(v, axis):
    """D^T v for D g = g[i + 1] - g[i] along ``axis``: (D^T v)[i] = v[i - 1] - v[i], zero beyond the ends."""
    pad_before = [(0, 0)] * v.ndim
    pad_after = [(0, 0)] * v.ndim
    pad_before[axis] = (1, 0)
    pad_after[axis] = (0, 1)
    return np.pad(v, pad_before) - np.pad(v, pad_after)


def _neumann_laplacian(g):
    """sum_a D_a^T D_a g (the graph Laplacian of the grid, no boundary condition beyond the grid: Neumann)."""
    return sum(_difference_adjoint(np.diff(g, axis=a), a) for a in range(3))


def _interpolation_matrix(x, lo, delta, shape):
    """Trilinear interpolation of grid values at points x (n, 3) -> sparse (n, prod(shape)) W."""
    u = (x - lo) / delta
    base = np.clip(np.floor(u).astype(np.int64), 0, np.array(shape) - 2)
    frac = u - base
    rows, cols, vals = [], [], []
    for corner in range(8):
        offset = np.array([(corner >> a) & 1 for a in range(3)])
        weight = np.prod(np.where(offset, frac, 1 - frac), axis=1)
        idx = np.ravel_multi_index((base + offset).T, shape)
        rows.append(np.arange(len(x)))
        cols.append(idx)
        vals.append(weight)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(len(x), int(np.prod(shape))))


def _edge_mean(targets, lo, delta, shape, axis, chunk=100_000):
    """mu_axis at the midpoints of the grid edges along ``axis`` (zero where no point is within the support)."""
    edge_shape = list(shape)
    edge_shape[axis] -= 1
    out = np.zeros(int(np.prod(edge_shape)))
    post = targets.posterior
    # only midpoints within the kernel's reach of some point can have mu != 0 (Chebyshev radius r <= Euclidean r
    # sqrt(3)); finding them first keeps the GP evaluations to the band around the surface
    reach = post.radius * math.sqrt(3) + 1e-12
    for start in range(0, len(out), 4 * chunk):
        flat = np.arange(start, min(start + 4 * chunk, len(out)))
        idx = np.stack(np.unravel_index(flat, edge_shape), 1).astype(np.float64)
        idx[:, axis] += 0.5
        x = lo + idx * delta
        near = np.isfinite(post.tree.query(x, distance_upper_bound=reach)[0])
        for part in np.array_split(np.flatnonzero(near), max(1, int(near.sum()) // chunk)):
            if len(part):
                out[flat[part]] = post.mean(x[part])[:, axis]
    return out.reshape(edge_shape)


def grid_minimiser(targets, resolution, screening_weight=SCREENING_WEIGHT, tol=1e-8, maxiter=500):
    """The grid function g minimising the mean loss on ``targets.box`` (see the module docstring).

    Parameters
    ----------
    targets : CloudTargets
    resolution : int
        Nodes along each side of the (cubic) box.
    screening_weight : float
    tol, maxiter : CG settings.

    Returns
    -------
    g : (resolution, resolution, resolution) array
    lo : (3,) array, delta : float
        Node (i, j, k) sits at lo + (i, j, k) * delta (model frame).
    info : dict
        CG iterations, relative residual, seconds for the targets and for the solve.
    """
    if int(resolution) < 3:
        raise ValueError(f"the grid needs at least 3 nodes per side, got resolution {resolution}")
    box = targets.box
    lo = np.asarray(box.lo, dtype=np.float64)
    delta = float((box.hi - box.lo).max()) / (resolution - 1)
    shape = (resolution,) * 3
    n_nodes = int(np.prod(shape))
    t0 = time.perf_counter()
    edges = [_edge_mean(targets, lo, delta, shape, a) for a in range(3)]
    t_targets = time.perf_counter() - t0
    W = _interpolation_matrix(targets.posterior.points, lo, delta, shape)
    screen = screening_weight / len(targets.posterior.points)
    WtW = (W.T @ W).tocsr()
    rhs = delta**2 * sum(_difference_adjoint(m, a) for a, m in enumerate(edges)).ravel()

    def apply(v):
        g = v.reshape(shape)
        return delta * _neumann_laplacian(g).ravel() + screen * (WtW @ v)

    # preconditioner: the inverse of delta * Laplacian, with the constant mode (which only the screening fixes)
    # given the screening's own weight on a constant, screen * n / n_nodes
    k = [np.arange(s) for s in shape]
    eig = sum((2 - 2 * np.cos(np.pi * kk / s)).reshape([-1 if i == a else 1 for i in range(3)])
              for a, (kk, s) in enumerate(zip(k, shape)))
    eig = delta * eig
    eig[0, 0, 0] = screen * len(targets.posterior.points) / n_nodes

    def precondition(r):
        return idctn(dctn(r.reshape(shape), type=2, norm="ortho") / eig, type=2, norm="ortho").ravel()

    iterations = []
    t1 = time.perf_counter()
    A = LinearOperator((n_nodes, n_nodes), matvec=apply, dtype=np.float64)
    M = LinearOperator((n_nodes, n_nodes), matvec=precondition, dtype=np.float64)
    g, status = cg(A, rhs, rtol=tol, maxiter=maxiter, M=M, callback=lambda _: iterations.append(1))
    residual = float(np.linalg.norm(apply(g) - rhs) / np.linalg.norm(rhs))
    info = {"iterations": len(iterations), "residual": residual, "converged": status == 0,
            "targets_seconds": t_targets, "solve_seconds": time.perf_counter() - t1}
    return g.reshape(shape), lo, delta, info


def zero_level_mesh(g, lo, delta, frame):
    """Marching cubes of g = 0 on the grid, in the cloud's own (world) coordinates."""
    verts, faces, _, _ = marching_cubes(g, level=0.0, spacing=(delta,) * 3)
    # marching cubes orients faces toward increasing values; g > 0 is outside, so this is already outward
    return trimesh.Trimesh(frame.to_file(verts + lo), faces, process=False)
