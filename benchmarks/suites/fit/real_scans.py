"""``fit --mode real-scans``: ``fit_cloud``'s grid and SIREN at their defaults on single real range scans (the
bunny's Cyberware views in ``../shared/realscans/bunny``, metres; stray returns removed, normals estimated toward a
viewpoint 1 m along +z from the centroid): fit time, the scan's own points' distance to the mean surface (marched at
160^3, 400,000 samples; mean and 95th percentile in median point spacings) and the field's noise level. A real scan
has no true surface to compare with. Skipped, with a message, where the shared scans are absent."""
import time
from pathlib import Path


def run(args):
    """The fits' table; returns the figures (or why the mode was skipped)."""
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    from benchmarks.cache import REAL_SCANS
    from benchmarks.table import format_table

    source = Path(args.source) if args.source else REAL_SCANS / "bunny"
    if not source.is_dir():
        print(f"fit --mode real-scans: skipped, {source} not found (the real scans are shared data, not in the "
              f"repository)")
        return {"skipped": f"{source} not found"}
    from autodecoder import fit_cloud
    from datasets.normals import estimate_normals
    from datasets.outliers import stray_points

    rows = []
    for view in args.views.split(","):
        path = source / f"{view}.ply"
        if not path.is_file():
            raise SystemExit(f"{path}: no such scan")
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
            rows.append({"view": view, "representation": representation, "points": len(points),
                         "fit_seconds": seconds, "mean_spacings": float(d.mean()),
                         "q95_spacings": float(np.quantile(d, 0.95)), "noise_spacings": field.noise / spacing})
            print(f"  {view} {representation}: fit {seconds:.1f} s", flush=True)
    print("scan points to the mean surface, in median point spacings:")
    print(format_table(rows, [("view", "view", ""), ("representation", "fit", ""), ("points", "points", "d"),
                              ("fit_seconds", "fit s", ".1f"), ("mean_spacings", "mean", ".2f"),
                              ("q95_spacings", "95 %", ".2f"), ("noise_spacings", "field noise", ".2f")]))
    return {"source": str(source), "rows": rows}
