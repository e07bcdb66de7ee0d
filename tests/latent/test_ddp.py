"""Data-parallel training: two local CPU processes (gloo) under torchrun end with identical network weights."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from autodecoder.latent.model import load_model
from datasets.collection import ScanCollection
from datasets.scan import Scan

ROOT = Path(__file__).resolve().parents[2]


def _sphere(name, radius, seed, n=300):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Scan(name, radius * d, d)


def test_two_gloo_processes_hold_identical_weights(tmp_path):
    data = tmp_path / "spheres.h5"
    ScanCollection.create(data, [_sphere(f"train/{i}", r, i) for i, r in enumerate((0.15, 0.2, 0.25, 0.3, 0.35))])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
    # the worker runs as a module from the repository root (python -m semantics: the root leads sys.path)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m",
           "tests.latent.ddp_worker", str(data), str(tmp_path)]
    proc = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    assert r0["world"] == r1["world"] == 2
    for key in ("mean", "cov"):
        for name, value in r0[key].items():
            assert torch.equal(value, r1[key][name]), (key, name)
    assert torch.equal(r0["codes"], r1["codes"])  # gathered from both ranks
    model = load_model(tmp_path / "model.pt")  # written once, by rank 0
    assert model.epoch == 3 and len(model.train_names) == 5 and model.config["world_size"] == 2
    for name, value in r0["mean"].items():
        assert torch.equal(value, model.mean_net.state_dict()[name])
    # every code moved from its N(0, 0.01^2) start (seed 0): each rank trained the codes it owns
    start = torch.randn(5, 2, generator=torch.Generator().manual_seed(1)) * 0.01
    assert torch.all((model.codes - start).abs().amax(1) > 1e-4)
