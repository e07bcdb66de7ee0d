"""Shared pytest fixtures.

The tests follow the packages' seams: ``tests/datasets/``, ``tests/field/``, ``tests/latent/``, ``tests/scanning/``,
``tests/inspection/`` (``autodecoder``'s three sub-packages and the two other packages), and cross-cutting checks at
the top (the console entry points). Every folder is a package (``tests.field.test_fit``...), so test files in
different folders may share a name, and helpers that several test files use live in plain modules beside them
(``tests/scanning/toy_fields.py``) or here as fixtures; no test imports another test module.
"""
import os
from pathlib import Path

import pytest

# Set before torch is imported: OpenMP threads that spin while waiting make small torch problems 20-60x slower
# whenever anything else runs on the machine's 2 cores (measured); passive waiting costs nothing measurable here.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


@pytest.fixture
def shared_meshes():
    """Folder of the real meshes (fandisk, bunny); skips the test when it is absent (e.g. a bare clone)."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"{SHARED_MESHES} not present: this test needs the shared real meshes")
    return SHARED_MESHES


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny tensors: intra-op threads only add overhead, and oversubscribe a shared CPU badly. Restored after."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def adam_steps(monkeypatch):
    """Records every torch.optim.Adam step as the id of the optimiser that took it (the real step still runs), so a
    test can count how many steps each of a run's optimisers took."""
    import torch

    taken = []
    real_step = torch.optim.Adam.step

    def counting_step(self, *args, **kwargs):
        taken.append(id(self))
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", counting_step)
    return taken
