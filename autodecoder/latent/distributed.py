"""The processes and threads a training run runs on: torchrun's process group, gathering across ranks, torch CPU
threads.

Distributed data parallel (``torchrun --nproc_per_node=N train_latent.py ...``): :func:`setup_distributed` joins the
process group from torchrun's environment; :func:`rank_and_world` tells a process its share, :func:`all_gather`
collects a Python object from every rank (one process: no collective at all).
"""
import contextlib
import os

import torch

from autodecoder.latent.options import TrainingInputError


def rank_and_world():
    """(rank, world size, initialised?) of torch.distributed."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), True
    return 0, 1, False


def all_gather(obj, world):
    """Every rank's ``obj``, in rank order (a collective call: every rank makes it)."""
    if world == 1:
        return [obj]
    import torch.distributed as dist

    out = [None] * world
    dist.all_gather_object(out, obj)
    return out


def setup_distributed(device="auto"):
    """Initialise torch.distributed from torchrun's environment (``WORLD_SIZE`` > 1; gloo on CPU, nccl on CUDA).

    Returns (torch.device, initialised here?): the caller destroys the process group it initialised.
    ``device``: 'auto' (cuda when available), 'cpu' or 'cuda'.
    """
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise TrainingInputError("device cuda: no CUDA device is available")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return torch.device(device), False
    import torch.distributed as dist

    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device == "cuda":
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return device, True
    return device, False


# torch CPU threads of a training run (train_latent.py --threads, inspection.training.train_model): a step is many
# small tensor operations, which one thread ran faster than two on the 2-core machine (103 s against 139 s for the
# default run on fandisk's 26 scans, docs/results.md#latent-training-in-two-minutes-issue-19); more cores are used by
# torchrun processes, one thread each. Beside them: one thread draws each step's targets while the step before runs
# (autodecoder.latent.loop._train_epoch), and the family and pose decisions register scans on every core
# (datasets.parallel).
TRAINING_THREADS = 1


@contextlib.contextmanager
def training_threads(threads=None):
    """Run the block with ``threads`` torch CPU threads (None: ``TRAINING_THREADS``; 0: leave torch's setting),
    restored afterwards."""
    threads = TRAINING_THREADS if threads is None else int(threads)
    if threads < 0:
        raise ValueError(f"threads must be >= 0, got {threads}")
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
