"""The benchmarks' surface accuracy: the one metric, the symmetric mean point-to-surface distance ("Chamfer"), and
the reference reconstructions the fits are compared with (open3d's screened Poisson, gpytoolbox's stochastic Poisson
on its grid).

Every figure the benchmarks and docs/results.md call a Chamfer distance is :func:`mean_surface_distance`: ``n``
area-uniform samples of each mesh, the exact distance of each to the *other mesh's surface* (point-to-triangle, not
to the other's samples, so there is no sampling floor: two samplings of the same mesh score 0), the mean of the two
one-sided means. Figures measured before it was the only definition (sample-to-sample distances in next_view.py and
latent_fandisk.py) are marked so in docs/results.md.

Imports only numpy at the top (the suites read :data:`SPSR_GRID` at import time, and ``--help`` stays light).
"""
import numpy as np


def surface_distance_samples(mesh_a, mesh_b, n=30_000, seed=0):
    """Per-sample distances: (from ``n`` samples of a to b's surface, from ``n`` samples of b to a's surface).

    b's samples depend only on b and ``seed``, so two meshes compared with the same b share them (a paired
    comparison, see :func:`mean_surface_distance_difference`).

    Returns
    -------
    a_to_b, b_to_a : (n,) float64 arrays, in the meshes' units
    """
    import trimesh

    a = trimesh.sample.sample_surface(mesh_a, n, seed=seed)[0]
    b = trimesh.sample.sample_surface(mesh_b, n, seed=seed + 1)[0]
    return trimesh.proximity.closest_point(mesh_b, a)[1], trimesh.proximity.closest_point(mesh_a, b)[1]


def mean_surface_distance(mesh_a, mesh_b, n=30_000, seed=0):
    """Symmetric mean point-to-surface distance between two meshes (the benchmarks' Chamfer distance), float."""
    a_to_b, b_to_a = surface_distance_samples(mesh_a, mesh_b, n, seed)
    return float(0.5 * (a_to_b.mean() + b_to_a.mean()))


def mean_surface_distance_difference(samples_1, samples_2):
    """Distance(1) - distance(2) to the same true mesh from two :func:`surface_distance_samples` results (each with
    the true mesh second), and the standard error of that estimate (the true mesh's samples are shared, so that
    half is a paired difference; the other half's are independent)."""
    (own_1, true_1), (own_2, true_2) = samples_1, samples_2
    diff = 0.5 * (own_1.mean() - own_2.mean() + (true_1 - true_2).mean())
    var = 0.25 * (own_1.var() / len(own_1) + own_2.var() / len(own_2) + (true_1 - true_2).var() / len(true_1))
    return float(diff), float(np.sqrt(var))


# --- reference reconstructions ----------------------------------------------------------------------------------

SPSR_GRID = 20  # gpytoolbox's exact variance solve is dense in the grid size: 32^3 ran out of 24 GiB, 20^3 fits


def open3d_poisson(points, normals, depth=8):
    """open3d's screened Poisson reconstruction of an oriented cloud, the lowest-density 1 % trimmed (open3d closes
    the surface far beyond the data; trimming is customary). Returns a trimesh.Trimesh."""
    import open3d as o3d
    import trimesh

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, n_threads=1)
    # one thread: open3d's threaded solve differs from run to run
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.01))
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=False)


def spsr_grid(lo, hi, grid=SPSR_GRID):
    """gpytoolbox SPSR's regular grid of ``grid`` nodes per side over the box [lo, hi].

    Returns
    -------
    gs : (3,) int array, step : (3,) array
        Its ``gs`` and ``h`` arguments.
    axes : list of 3 arrays
        Node coordinates along each axis.
    points : (grid^3, 3) array
        The nodes in gpytoolbox's order (first coordinate fastest: 'ij' grids flattened in Fortran order).
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    gs = np.array([grid] * 3)
    step = (hi - lo) / (gs - 1)
    axes = [np.linspace(lo[d], lo[d] + (gs[d] - 1) * step[d], gs[d]) for d in range(3)]
    points = np.stack([a.ravel(order="F") for a in np.meshgrid(*axes, indexing="ij")], -1)
    return gs, step, axes, points


def spsr(points, normals, lo, hi, grid=SPSR_GRID):
    """gpytoolbox's stochastic Poisson surface reconstruction of an oriented cloud on :func:`spsr_grid` (lo, hi,
    grid): the exact variance solve (minutes at 20^3; needs gpytoolbox).

    Returns
    -------
    mean, var : (grid^3,) arrays
        In the grid's order (:func:`spsr_grid`'s ``points``).
    """
    from gpytoolbox import stochastic_poisson_surface_reconstruction

    gs, step, _, _ = spsr_grid(lo, hi, grid)
    mean, var, _ = stochastic_poisson_surface_reconstruction(points, normals, gs=gs, h=step,
                                                             corner=np.asarray(lo, dtype=np.float64),
                                                             output_variance=True, solve_subspace_dim=0)
    return np.ravel(mean), np.ravel(var)
