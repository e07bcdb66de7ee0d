"""The one surface-accuracy metric of the benchmarks: the symmetric mean point-to-surface distance ("Chamfer").

Every figure the benchmarks and docs/results.md call a Chamfer distance is :func:`mean_surface_distance`: ``n``
area-uniform samples of each mesh, the exact distance of each to the *other mesh's surface* (point-to-triangle, not
to the other's samples, so there is no sampling floor: two samplings of the same mesh score 0), the mean of the two
one-sided means. Figures measured before it was the only definition (sample-to-sample distances in next_view.py and
latent_fandisk.py) are marked so in docs/results.md.
"""
import numpy as np
import trimesh


def surface_distance_samples(mesh_a, mesh_b, n=30_000, seed=0):
    """Per-sample distances: (from ``n`` samples of a to b's surface, from ``n`` samples of b to a's surface).

    b's samples depend only on b and ``seed``, so two meshes compared with the same b share them (a paired
    comparison, see :func:`mean_surface_distance_difference`).

    Returns
    -------
    a_to_b, b_to_a : (n,) float64 arrays, in the meshes' units
    """
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
