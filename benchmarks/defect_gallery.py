"""Defect gallery: one good and one defective virtual scan per defect kind of the built-in part and of fandisk.

Each panel is the scan seen from its own sensor (points projected on the image plane). Per part, the first row is
shaded by the angle between normal and ray with the labelled defect points in red; the second colours each point by
its distance to the undamaged part, so a defect shows up where it really is, whatever the labels say. Also times the synthesis of the default fandisk collection.

    .venv/bin/python benchmarks/defect_gallery.py [--out results/defect_gallery.png] [--no-timing]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FANDISK = ROOT.parent / "shared" / "meshes" / "fandisk.obj"


def _project(scan):
    """(n, 3) points -> (n, 2) image-plane coordinates and (n,) shading, seen from the scan's sensor."""
    eye = scan.sensor_origin.astype(np.float64)
    forward = np.mean(scan.points, axis=0) - eye
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rays = scan.points - eye
    depth = rays @ forward
    xy = np.stack([rays @ right, rays @ up], axis=1) / depth[:, None]
    shade = np.abs(np.sum(scan.normals * rays, axis=1)) / np.linalg.norm(rays, axis=1)
    return xy, shade


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "results" / "defect_gallery.png"))
    parser.add_argument("--points", type=int, default=4000)
    parser.add_argument("--noise", type=float, default=0.002)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-timing", action="store_true", help="skip timing the default fandisk collection")
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from datasets.defects import DEFECT_KINDS
    from datasets.parts import builtin_part, load_part
    from datasets.synth import synthesise

    parts = [("builtin bracket", builtin_part())]
    if FANDISK.is_file():
        parts.append(("fandisk", load_part(FANDISK)))
    else:
        print(f"{FANDISK} not found: gallery of the built-in part only")
    # Two rows per part: the labels (red), and each point's distance to the undamaged part (the defect as measured).
    fig, axes = plt.subplots(2 * len(parts), 1 + len(DEFECT_KINDS),
                             figsize=(4 * (1 + len(DEFECT_KINDS)), 8 * len(parts)), squeeze=False)
    for row, (title, mesh) in enumerate(parts):
        import trimesh

        scans, frame = synthesise(mesh, n_train=0, n_test_good=1, n_test_defective=1, n_points=args.points,
                                  noise=args.noise, seed=args.seed, progress=False)
        diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        for col, scan in enumerate(scans):
            xy, shade = _project(scan)
            labels = np.zeros(len(scan), bool) if scan.point_labels is None else scan.point_labels.astype(bool)
            ax = axes[2 * row, col]
            ax.scatter(xy[~labels, 0], xy[~labels, 1], s=2, c=shade[~labels], cmap="Greys_r", vmin=-0.3, vmax=1.2)
            ax.scatter(xy[labels, 0], xy[labels, 1], s=3, c="red")
            ax.set_title(f"{title}: {scan.defect or 'good'} ({labels.sum()} / {len(scan)} defect pts)", fontsize=9)
            ax = axes[2 * row + 1, col]
            distance = trimesh.proximity.closest_point(mesh, frame.to_file(scan.points))[1] / diagonal
            image = ax.scatter(xy[:, 0], xy[:, 1], s=2, c=distance, cmap="viridis", vmin=0, vmax=0.02)
            ax.set_title(f"distance to undamaged part / diagonal (noise std {args.noise})", fontsize=9)
            for a in axes[2 * row: 2 * row + 2, col]:
                a.set_aspect("equal")
                a.set_xticks([])
                a.set_yticks([])
        fig.colorbar(image, ax=axes[2 * row + 1, -1], fraction=0.05)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")

    if not args.no_timing and FANDISK.is_file():
        mesh = load_part(FANDISK)
        start = time.perf_counter()
        scans, _ = synthesise(mesh, n_train=32, n_test_good=16, n_test_defective=16, n_points=4000, noise=0.002,
                              seed=args.seed, progress=True)
        seconds = time.perf_counter() - start
        print(f"default fandisk collection: {len(scans)} scans x 4000 points synthesised in {seconds:.1f} s")


if __name__ == "__main__":
    main()
