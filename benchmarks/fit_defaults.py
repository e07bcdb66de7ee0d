"""Sweep fit_cloud's network size and step count on fandisk: fit time and Chamfer distance of the mean surface.

The figures behind fit_cloud's defaults (width, depth, steps). Run by hand:

    .venv/bin/python benchmarks/fit_defaults.py [--widths 64,128] [--depths 3] [--steps 1000,3000]
        [--batches 256,512,4096] [--jobs 1]

``--jobs N`` runs N fits side by side (each with 2 torch threads): only for quality sweeps on a big machine; fit
times are only comparable between runs with ``--jobs 1`` on an otherwise idle machine.
"""
import argparse
import itertools
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import trimesh

from fandisk import SHARED  # same folder
from surface_metrics import mean_surface_distance


def run_one(job):
    import torch

    from autodecoder import fit_cloud

    torch.set_num_threads(job["threads"])
    mesh = trimesh.load(job["mesh"], force="mesh")
    points, faces = trimesh.sample.sample_surface(mesh, job["points"], seed=0)
    t0 = time.perf_counter()
    from autodecoder.field.targets import point_spacing

    lengthscale = job["h_factor"] * point_spacing(points)
    field = fit_cloud(points, mesh.face_normals[faces], representation="siren",
                      seed=0, quiet=True, width=job["width"], depth=job["depth"],
                      steps=job["steps"], lengthscale=lengthscale, **job["extra"])
    seconds = time.perf_counter() - t0
    diag = float(np.linalg.norm(mesh.extents))
    return {**job, "seconds": seconds, "chamfer": mean_surface_distance(field.mesh(job["resolution"]), mesh) / diag}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(SHARED / "fandisk.obj"))
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--widths", default="64,128")
    parser.add_argument("--depths", default="3")
    parser.add_argument("--steps", default="1000,3000")
    parser.add_argument("--h-factors", default="2", help="kernel lengthscale / point spacing")
    parser.add_argument("--omega0s", default=None,
                        help="SIREN first-layer frequencies to sweep (default: fit_cloud's own choice)")
    parser.add_argument("--batches", default=None,
                        help="mean-loss samples per step to sweep (the screening batch follows; default: FitOptions')")
    parser.add_argument("--resolution", type=int, default=256, help="marching-cubes grid")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None, help="torch threads per fit (default: 2 if --jobs>1)")
    args = parser.parse_args(argv)
    import torch

    threads = args.threads or (2 if args.jobs > 1 else torch.get_num_threads())
    omegas = [None] if args.omega0s is None else [float(o) for o in args.omega0s.split(",")]
    batches = [None] if args.batches is None else [int(b) for b in args.batches.split(",")]
    grid = itertools.product(map(int, args.widths.split(",")), map(int, args.depths.split(",")),
                             map(int, args.steps.split(",")), map(float, args.h_factors.split(",")), omegas, batches)
    jobs = [{"mesh": args.mesh, "points": args.points, "width": w, "depth": d, "steps": s, "h_factor": h,
             "threads": threads, "resolution": args.resolution,
             "extra": {**({} if o is None else {"omega0": o}),
                       **({} if b is None else {"mean_batch": b, "screen_batch": b})}}
            for w, d, s, h, o, b in grid]
    print(f"{Path(args.mesh).name}, {args.points} points, {len(jobs)} fits, {args.jobs} at a time, "
          f"{threads} torch threads each")
    print(f"{'width':>5} {'depth':>5} {'steps':>5} {'h/spacing':>9} {'omega0':>7} {'batch':>6} {'fit s':>8} "
          f"{'Chamfer/diag':>13}")
    with ProcessPoolExecutor(args.jobs) as pool:
        for r in pool.map(run_one, jobs):
            print(f"{r['width']:5d} {r['depth']:5d} {r['steps']:5d} {r['h_factor']:9.2f} "
                  f"{str(r['extra'].get('omega0', 'default')):>7} "
                  f"{str(r['extra'].get('mean_batch', 'default')):>6} {r['seconds']:8.1f} "
                  f"{r['chamfer']:13.3e}",
                  flush=True)


if __name__ == "__main__":
    main()
