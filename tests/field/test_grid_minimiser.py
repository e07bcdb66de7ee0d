"""autodecoder.field.grid_minimiser, the exact grid minimiser of the mean loss, against a closed form.

``python -m benchmarks fit --mode target-limit``'s figures (the exact minimiser of fit_cloud's mean loss against open3d's Chamfer) rest on
this solver, so it is checked here: for a target field that is exactly the gradient of phi(x) = (|x|^2 - R^2) / 2, a
function that vanishes on the sphere where the screened points lie, phi itself makes both terms of the loss zero, so
it is the minimiser; the grid solution must reproduce it up to the grid's interpolation error.
"""
from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from autodecoder.field.grid_minimiser import grid_minimiser, zero_level_mesh
from autodecoder.field.sampling import Box


def _sphere_targets(radius=0.3, n=400, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    points = radius * v / np.linalg.norm(v, axis=1, keepdims=True)
    posterior = SimpleNamespace(points=points, tree=cKDTree(points), radius=10.0,  # every node "within reach"
                                mean=lambda x: np.asarray(x, dtype=np.float64))  # grad phi = x
    return SimpleNamespace(box=Box(np.full(3, -0.5), np.full(3, 0.5)), posterior=posterior, lengthscale=0.05)


def test_grid_minimiser_recovers_the_closed_form_potential():
    targets = _sphere_targets()
    g, lo, delta, info = grid_minimiser(targets, 25)
    assert info["converged"] and info["residual"] < 1e-6
    axes = [lo[a] + delta * np.arange(25) for a in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    phi = 0.5 * ((x**2).sum(-1) - 0.3**2)
    # forward differences of a quadratic equal its derivative at the edge midpoints exactly, so only the screening's
    # trilinear interpolation of phi at the points (error <= 3 delta^2 / 8 for this phi) separates g from phi
    assert np.abs(g - phi).max() < 3 * delta**2 / 8
    assert np.abs(g - phi).max() < 0.01 * np.abs(phi).max()


def test_zero_level_mesh_is_the_sphere():
    from datasets.frame import Frame

    targets = _sphere_targets()
    g, lo, delta, _ = grid_minimiser(targets, 25)
    mesh = zero_level_mesh(g, lo, delta, Frame.identity())
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 0.3).max() < delta / 4
    assert mesh.volume > 0  # outward faces: g > 0 is outside
