"""fit_cloud's two representations on single real range scans (the Stanford bunny's Cyberware views).

Run by hand from the repository root (not a test):

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/real_scan_fit.py [--views bun000,bun090]

Each view of ``../shared/realscans/bunny/`` (metres, no normals) is cleaned of stray returns
(``datasets.outliers.stray_points``), given normals by ``datasets.normals.estimate_normals`` (oriented toward a
viewpoint 1 m along +z from the centroid, the Cyberware views' viewing direction), and fitted with
``fit_cloud(..., representation=R)`` for R = grid (the default) and siren at their defaults. A real scan has no true
surface to compare with, so the measure is how far the scan's own points lie from the fitted mean surface (marched at
160^3, 400,000 points sampled on it): mean and 95th percentile, in the scan's median point spacings; beside it the
fit time and the field's noise level (RMS of the mean at the points, in spacings).
"""
import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import trimesh
from scipy.spatial import cKDTree

BUNNY = Path(__file__).resolve().parents[2] / "shared" / "realscans" / "bunny"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", default="bun000,bun090", help="comma-separated file stems in --source")
    p.add_argument("--source", default=str(BUNNY))
    args = p.parse_args(argv)
    from autodecoder import fit_cloud
    from datasets.normals import estimate_normals
    from datasets.outliers import stray_points

    print(f"load average at start: {os.getloadavg()}")
    for view in args.views.split(","):
        path = Path(args.source) / f"{view}.ply"
        if not path.is_file():
            raise SystemExit(f"{path}: no such scan (the real scans are shared data, not in the repository)")
        points = np.asarray(trimesh.load(path).vertices, dtype=np.float64)
        points = points[~stray_points(points)]
        normals = estimate_normals(points, sensor_origin=points.mean(0) + np.array([0.0, 0.0, 1.0]))
        spacing = float(np.median(cKDTree(points).query(points, 2)[0][:, 1]))
        for representation in ("grid", "siren"):
            t0 = time.perf_counter()
            field = fit_cloud(points, normals, representation=representation, quiet=True)
            seconds = time.perf_counter() - t0
            surface = trimesh.sample.sample_surface(field.mesh(160), 400_000, seed=0)[0]
            d = cKDTree(surface).query(points)[0] / spacing
            print(f"{view} {representation:5s}: {len(points)} points, fit {seconds:.1f} s, scan points to the mean "
                  f"surface: mean {d.mean():.2f}, 95 % {np.quantile(d, 0.95):.2f} spacings; field noise "
                  f"{field.noise / spacing:.2f} spacings", flush=True)
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
