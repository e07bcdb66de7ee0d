"""Sphere collections for the latent model's tests: scans of spheres of known radii, and the radius a fitted mean
puts its zero level at (the closed form the tests compare against)."""
import numpy as np

from datasets.scan import Scan

RADII = (0.15, 0.2, 0.3, 0.35)


def sphere_scan(name, radius, n=500, seed=0, partial=False, split="train", center=(0.0, 0.0, 0.0)):
    """n points of a sphere (the cap z > -0.5 r when partial) with outward normals, in the unit cube."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if partial:
        d = d[d[:, 2] > -0.5]
    d = d[:n]
    return Scan(name, radius * d + np.asarray(center), d, split=split)


def sphere_scans(radii=RADII, partial=False):
    return [sphere_scan(f"train/{i:03d}", r, seed=i, partial=partial) for i, r in enumerate(radii)]


def zero_crossing_radius(field, n_rays=64, seed=0):
    """Median distance from the origin at which the mean turns positive, over random rays."""
    d = np.random.default_rng(seed).normal(size=(n_rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.linspace(0.02, 0.48, 461)
    values = field.mean((d[:, None, :] * t[None, :, None]).reshape(-1, 3)).reshape(n_rays, -1)
    first = np.argmax(values > 0, axis=1)
    ok = (values > 0).any(1) & (values[:, 0] < 0)
    return float(np.median(t[first[ok]])) if ok.any() else float("nan")
