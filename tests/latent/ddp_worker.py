"""Worker of tests/latent/test_ddp.py, started by torchrun as ``-m tests.latent.ddp_worker`` from the repository
root (so that it imports the checkout's ``train_latent``): trains through train_latent.run and saves this rank's
state."""
import sys
from pathlib import Path

import torch

import train_latent


def main(data, out_dir):
    import os

    out_dir = Path(out_dir)
    args = train_latent.build_parser().parse_args(
        ["--data", data, "--out", str(out_dir / "model.pt"), "--latent-dim", "2", "--width", "16", "--depth", "1",
         "--epochs", "3", "--batch", "2", "--device", "cpu", "--quiet", "--calibration-fraction", "0"])
    model = train_latent.run(args)
    rank = int(os.environ["RANK"])
    torch.save({"mean": model.mean_net.state_dict(), "cov": model.cov_net.state_dict(), "codes": model.codes,
                "world": int(os.environ["WORLD_SIZE"])}, out_dir / f"rank{rank}.pt")


if __name__ == "__main__":
    main(*sys.argv[1:3])
