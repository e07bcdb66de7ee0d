"""What the fit suite's modes share: the sampled cloud, open3d's screened Poisson reconstruction of it, where a
reconstruction's error lies (bands by distance to a sharp edge), and the variance against gpytoolbox's stochastic
Poisson reconstruction."""
import time
from pathlib import Path

from benchmarks.cache import CACHE
from benchmarks.surface_metrics import SPSR_GRID

OUT = {"grid": "results/grid_fandisk", "siren": "results/fandisk"}  # written files, per mode


def sampled_cloud(args):
    """(mesh, points, normals, diagonal) of ``--points`` area-uniform samples of ``--mesh`` (seed ``--seed``)."""
    import numpy as np
    import torch
    import trimesh

    from benchmarks.cache import part_mesh

    mesh = part_mesh(args.mesh)
    points, faces = trimesh.sample.sample_surface(mesh, args.points, seed=args.seed)
    diag = float(np.linalg.norm(mesh.extents))
    print(f"{Path(args.mesh).stem}: {len(mesh.faces)} faces, {len(points)} points (seed {args.seed}), diagonal "
          f"{diag:.4g}, torch threads {torch.get_num_threads()}")
    return mesh, points, mesh.face_normals[faces], diag


def open3d_reference(mesh, points, normals):
    """open3d's depth-8 reconstruction, its Chamfer distance to ``mesh``, printed. Returns (its mesh, Chamfer)."""
    from benchmarks.surface_metrics import mean_surface_distance, open3d_poisson

    t0 = time.perf_counter()
    o3d_mesh = open3d_poisson(points, normals)
    seconds = time.perf_counter() - t0
    cd = mean_surface_distance(o3d_mesh, mesh)
    print(f"open3d Poisson d8: {seconds:5.1f} s, Chamfer {cd:.5f}")
    return o3d_mesh, cd


def chamfer_by_edge_distance(mesh_ours, mesh_true, lengthscale, n=30_000, seed=0, dihedral_deg=30.0):
    """Where the error is: the true surface's samples split by their distance to the nearest sharp edge (dihedral
    angle above ``dihedral_deg``), in kernel lengthscales.

    A kernel of lengthscale h rounds a sharp edge over about one h (the posterior mean is a smoothed normal field,
    so the Poisson solution is a smoothed indicator); ``--mode target-limit`` measures how much of the first band
    that rounding explains.

    Returns
    -------
    list of (band label, area share, mean distance to ``mesh_ours``, share of the one-sided (true -> ours) sum)
    """
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    samples = trimesh.sample.sample_surface(mesh_true, n, seed=seed)[0]
    dist = trimesh.proximity.closest_point(mesh_ours, samples)[1]
    sharp = mesh_true.face_adjacency_edges[mesh_true.face_adjacency_angles > np.radians(dihedral_deg)]
    if len(sharp) == 0:
        return []
    t = np.linspace(0, 1, 64)[None, :, None]
    seg = mesh_true.vertices[sharp]
    edge_points = (seg[:, :1] * (1 - t) + seg[:, 1:] * t).reshape(-1, 3)
    to_edge = cKDTree(edge_points).query(samples)[0] / lengthscale
    rows = []
    for lo, hi in ((0, 1), (1, 2), (2, 4), (4, np.inf)):
        band = (to_edge >= lo) & (to_edge < hi)
        label = f"[{lo}, {hi}) h" if np.isfinite(hi) else f">= {lo} h"
        rows.append((label, float(band.mean()), float(dist[band].mean()) if band.any() else float("nan"),
                     float(dist[band].sum() / dist.sum())))
    return rows


def has_gpytoolbox():
    import importlib.util

    return importlib.util.find_spec("gpytoolbox") is not None


def gpytoolbox_variance_correlation(field, points, normals, grid=SPSR_GRID, cache=CACHE):
    """Spearman correlation of the field's variance with gpytoolbox SPSR's on its grid over the field's box.

    gpytoolbox's solve takes minutes: it is cached in ``cache`` (``benchmarks.cache``, kind ``spsr``) by a digest of
    its inputs (the cloud, the box, the grid).

    Returns
    -------
    rho : float
    mean_rho : float
        Spearman of the two means: an ordering check (the grids' orders must match).
    seconds : float
        Of gpytoolbox's solve; 0 when it came from the cache.
    """
    import hashlib

    import numpy as np
    from scipy.stats import spearmanr

    from benchmarks.cache import cached_path
    from benchmarks.surface_metrics import spsr, spsr_grid

    lo, hi = field.bounds
    gs, _, _, grid_points = spsr_grid(lo, hi, grid)
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes()
                                     for a in (points, normals, lo, hi, gs))).hexdigest()[:16]
    solved = []

    def build(folder):
        t0 = time.perf_counter()
        mean, var = spsr(points, normals, lo, hi, grid)
        solved.append(time.perf_counter() - t0)
        np.savez(folder / "spsr.npz", mean=mean, var=var)

    folder = cached_path("spsr", {"inputs": digest, "grid": grid}, build, root=cache, label="gpytoolbox")
    with np.load(folder / "spsr.npz") as saved:
        mean, var = saved["mean"], saved["var"]
    rho = spearmanr(field.variance(grid_points), np.ravel(var)).statistic
    mean_rho = spearmanr(field.mean(grid_points), np.ravel(mean)).statistic
    return float(rho), float(mean_rho), solved[0] if solved else 0.0


def variance_correlation(field, points, normals, reference, cache):
    """Spearman of the field's variance with gpytoolbox SPSR's (when installed) or with ``reference``'s (a
    StochasticField, or None: nan), on gpytoolbox's grid over the field's box."""
    from scipy.stats import spearmanr

    from benchmarks.surface_metrics import spsr_grid

    if has_gpytoolbox():
        return gpytoolbox_variance_correlation(field, points, normals, cache=cache)[0]
    if reference is None:
        return float("nan")
    grid_points = spsr_grid(*field.bounds, SPSR_GRID)[3]
    return float(spearmanr(field.variance(grid_points), reference.variance(grid_points)).statistic)
