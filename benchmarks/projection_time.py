"""Projection time per scan of latent models, side by side: inspection's projection settings on a collection's test scans.

Run by hand from the repository root (not a test):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/projection_time.py --data results/verdicts/fandisk_3ece1194b5/tree.h5 \
        --models results/verdicts/fandisk_3ece1194b5/model.pt,results/verdicts/fandisk_3ece1194b5/model_grid.pt

Each model projects the same ``--scans`` test scans (``project_many`` with ``inspection.estimator.DEFAULT_PROJECTION``,
the batch inspection uses) ``--repeats`` times, the models taking turns so that a changing machine load falls on
all of them alike; printed: the fastest and the median seconds per scan of each model, and the load average. A warm-up
projection first pays the one-off costs (torch's optimiser imports) outside the timings.
"""
import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads crawl on a shared CPU
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="scan collection (its 'test' split is projected)")
    p.add_argument("--models", required=True, help="comma-separated latent model files")
    p.add_argument("--scans", type=int, default=32, help="test scans projected per repeat (default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    import torch

    from autodecoder.latent.model import load_model
    from datasets import ScanCollection
    from inspection.estimator import DEFAULT_PROJECTION

    torch.set_num_threads(1)
    with ScanCollection(args.data) as c:
        scans = c.read_many(c.select(split="test")[:args.scans])
    models = [load_model(m) for m in args.models.split(",")]
    print(f"load average at start: {os.getloadavg()}")
    for m in models:  # warm-up
        m.project_many(scans[:2], seed=0, **DEFAULT_PROJECTION)
    seconds = [[] for _ in models]
    for _ in range(args.repeats):
        for k, m in enumerate(models):
            t0 = time.perf_counter()
            m.project_many(scans, seed=0, **DEFAULT_PROJECTION)
            seconds[k].append((time.perf_counter() - t0) / len(scans))
    for m, s in zip(models, seconds):
        print(f"{m.source}: {m.representation}, {min(s):.3f} s/scan fastest, {np.median(s):.3f} median "
              f"({len(scans)} scans x {args.repeats})")
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
