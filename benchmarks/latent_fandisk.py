"""Benchmark: latent training on partial scans of fandisk, test-time projection vs per-scan fit_cloud.

    .venv/bin/python benchmarks/latent_fandisk.py [--epochs 150] [--fit-scans 2] [--out results/latent_fandisk]

Synthesises 32 training and 16 held-out good partial scans of /work/shared/meshes/fandisk.obj (4,000 points each,
datasets.synth), trains the latent model, projects the held-out scans, and prints: training wall time, projection
seconds per scan (median), the projected mean surface's symmetric mean point-to-surface distance to the true mesh (the benchmarks' Chamfer,
``surface_metrics.py``; collection frame), and the same for fit_cloud from scratch on held-out scans, as ratios. Saves a PNG of one held-out
scan, its projected mean surface and its variance on a slice. Prints ``uptime`` (the CPU is shared).
"""
import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see train_latent.main

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
MESH = ROOT.parent / "shared" / "meshes" / "fandisk.obj"


def uptime():
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "uptime unavailable"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: LatentOptions)")
    p.add_argument("--latent-dim", type=int, default=None)
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--depth", type=int, default=None)
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--steps", type=int, default=None, help="projection steps (default: ProjectionOptions)")
    p.add_argument("--fit-scans", type=int, default=2, help="held-out scans also fitted with fit_cloud (slow)")
    p.add_argument("--fit-steps", type=int, default=None, help="fit_cloud steps (default: FitOptions)")
    p.add_argument("--samples", type=int, default=20000, help="surface samples per side of the Chamfer distance")
    p.add_argument("--resolution", type=int, default=128, help="marching-cubes grid of the mean surfaces")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a loaded 2-core box)")
    p.add_argument("--out", default=str(ROOT / "results" / "latent_fandisk"))
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import numpy as np
    import torch
    import trimesh

    from autodecoder.field.fit import fit_cloud
    from surface_metrics import mean_surface_distance  # same folder
    from autodecoder.latent.train import train_latent
    from datasets.parts import load_part
    from datasets.synth import synthesise

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"load before: {uptime()}")
    mesh = load_part(MESH)
    t0 = time.perf_counter()
    scans, frame = synthesise(mesh, n_train=32, n_test_good=16, n_test_defective=0, defects=(), n_points=4000,
                              seed=args.seed, progress=False)
    train = [s for s in scans if s.split == "train"]
    held = [s for s in scans if s.split == "test"]
    print(f"synthesised {len(train)} training + {len(held)} held-out partial scans of {MESH.name} "
          f"(4000 points each) in {time.perf_counter() - t0:.1f} s")
    true_mesh = trimesh.Trimesh(frame.to_collection(mesh.vertices), mesh.faces, process=False)

    overrides = {k: v for k, v in dict(epochs=args.epochs, latent_dim=args.latent_dim, width=args.width,
                                       depth=args.depth, batch=args.batch).items() if v is not None}
    t0 = time.perf_counter()
    model = train_latent(train, out / "model.pt", frame=frame, seed=args.seed, **overrides)
    train_s = time.perf_counter() - t0
    c = model.config
    print(f"training: {train_s:.1f} s wall ({c['epochs']} epochs, latent {c['latent_dim']}, width {c['width']}, "
          f"depth {c['depth']}, batch {c['batch']}; GP targets {model.info['targets_seconds']:.1f} s; "
          f"final loss {model.info['history'][-1]['loss']:.4g}; noise {model.noise:.2e})")

    popts = {} if args.steps is None else {"steps": args.steps}
    model.project(held[0].points, held[0].normals, steps=5)  # warm-up (first-call allocations)
    singles = []
    for s in held[:4]:
        t0 = time.perf_counter()
        model.project(s.points, s.normals, seed=args.seed, **popts)
        singles.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    projections = model.project_many(held, seed=args.seed, batch=16, **popts)
    batch_s = (time.perf_counter() - t0) / len(held)
    proj_s = float(np.median(singles))
    print(f"projection: {proj_s:.3f} s per scan alone (median of {len(singles)}), {batch_s:.3f} s per scan "
          f"batched (16 at once)")

    chamfer_proj = []
    for k, (s, pr) in enumerate(zip(held, projections)):
        chamfer_proj.append(mean_surface_distance(pr.field.mesh(args.resolution), true_mesh, args.samples, k))
    print(f"projected mean surface vs true mesh: Chamfer median {np.median(chamfer_proj):.5f}, mean "
          f"{np.mean(chamfer_proj):.5f} (collection units; {args.samples} samples per side; {len(held)} scans)")
    # a scan's own points against the true mesh: the floor set by sensor noise
    floor = np.median([trimesh.proximity.closest_point(true_mesh, s.points[:1000])[1].mean() for s in held[:4]])
    print(f"  (scan points to true mesh: {floor:.5f} mean distance)")

    fit_opts = {} if args.fit_steps is None else {"steps": args.fit_steps}
    fit_s, chamfer_fit, chamfer_same = [], [], []
    for k, s in enumerate(held[:args.fit_scans]):
        t0 = time.perf_counter()
        f = fit_cloud(s.points, s.normals, representation="siren", seed=args.seed, quiet=True, **fit_opts)
        fit_s.append(time.perf_counter() - t0)
        chamfer_fit.append(mean_surface_distance(f.mesh(args.resolution), true_mesh, args.samples, k))
        chamfer_same.append(chamfer_proj[k])
        print(f"  fit_cloud scan {k}: {fit_s[-1]:.1f} s, Chamfer {chamfer_fit[-1]:.5f} "
              f"(projection: {chamfer_proj[k]:.5f})")
    if fit_s:
        print(f"fit_cloud from scratch ({len(fit_s)} held-out scans, {f.info['steps']} steps): "
              f"{np.median(fit_s):.1f} s per scan, Chamfer median {np.median(chamfer_fit):.5f}")
        print(f"RATIOS: projection speed-up {np.median(fit_s) / proj_s:.0f}x (batched "
              f"{np.median(fit_s) / batch_s:.0f}x); Chamfer projected / fit_cloud on the same scans "
              f"{np.median(chamfer_same) / np.median(chamfer_fit):.2f}")

    _figure(held[0], projections[0], out / "projection.png")
    print(f"wrote {out / 'projection.png'} and {out / 'model.pt'}")
    print(f"load after: {uptime()}")
    return 0


def _figure(scan, projection, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    field = projection.field
    mesh = field.mesh(96)
    fig = plt.figure(figsize=(15, 5))
    ax = fig.add_subplot(131, projection="3d")
    pts = scan.points[::4]
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1, c=pts[:, 2], cmap="viridis")
    ax.set_title(f"held-out partial scan {scan.name} ({len(scan.points)} points)")
    ax = fig.add_subplot(132, projection="3d")
    ax.plot_trisurf(mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.faces, mesh.vertices[:, 2], color="0.7",
                    linewidth=0)
    ax.set_title(f"projected mean surface (loss {projection.loss:.3g})")
    for a in fig.axes:
        a.set_xlim(-0.5, 0.5), a.set_ylim(-0.5, 0.5), a.set_zlim(-0.5, 0.5)
    ax = fig.add_subplot(133)
    t = np.linspace(-0.6, 0.6, 200)
    gy, gz = np.meshgrid(t, t, indexing="xy")
    x0 = float(np.median(scan.points[:, 0]))  # a vertical slice through the middle of the scan
    grid = np.stack([np.full(gy.size, x0), gy.ravel(), gz.ravel()], 1)
    var = field.variance(grid).reshape(gy.shape)
    mean = field.mean(grid).reshape(gy.shape)
    im = ax.imshow(np.log10(var + 1e-12), extent=(-0.6, 0.6, -0.6, 0.6), origin="lower", cmap="magma")
    ax.contour(gy, gz, mean, levels=[0.0], colors="cyan", linewidths=1)
    near = np.abs(scan.points[:, 0] - x0) < 0.01
    ax.scatter(scan.points[near, 1], scan.points[near, 2], s=3, c="white")
    ax.set_xlabel("y"), ax.set_ylabel("z")
    fig.colorbar(im, ax=ax, label="log10 variance")
    ax.set_title(f"variance on the slice x = {x0:.2f}\n(cyan: mean zero level; white: scan points within 0.01)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
