"""The small data the inspection command-line tests share (one copy): half-sphere scans in a collection frame, and an
untrained tiny field model saved with that collection's frame, fingerprint and scan names."""
import numpy as np

from datasets import Frame, Scan, ScanCollection

FRAME = Frame(np.array([1.0, 2.0, 3.0]), 0.5)


def half_sphere(name, split="train", label="good", defect="", seed=0, n=300, dent=0.0):
    """A half-sphere of radius 0.4 seen from +z (model frame), dented by ``dent`` at its pole; test scans carry
    per-point labels (the pole of a defective one)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 0.4 - dent * (d[:, 2] > 0.9)
    labels = None if split == "train" else (d[:, 2] > 0.9).astype(np.uint8) * (label == "defective")
    return Scan(name=name, points=d * r[:, None], normals=d, split=split, label=label, defect=defect,
                point_labels=labels)


def tiny_field_model(root, scans, n_train=3, n_heldback=3):
    """Write ``root/tree.h5`` (``scans``, in :data:`FRAME`) and ``root/model.pt``: an untrained tiny
    :class:`StochasticField` (seeded) saved with the collection's frame and fingerprint, its first ``n_train`` scans
    recorded as training scans and the next ``n_heldback`` as held back. Returns ``root``."""
    import torch

    from autodecoder.field.networks import build_networks
    from autodecoder.field.stochastic_field import StochasticField
    from inspection.model_io import save_reference_field

    ScanCollection.create(root / "tree.h5", scans, frame=FRAME)
    with ScanCollection(root / "tree.h5") as c:
        fingerprint = c.fingerprint()
    config = {"width": 16, "depth": 1, "latent_dim": 0, "covariance": "feature", "features": 8, "omega0": 5.0,
              "lengthscale": 0.05, "box_lo": [-0.6] * 3, "box_hi": [0.6] * 3}
    torch.manual_seed(0)
    mean_net, cov_net = build_networks(config)
    field = StochasticField(mean_net, cov_net, Frame.identity(), config, noise=0.01)
    save_reference_field(field, root / "model.pt", frame=FRAME, fingerprint=fingerprint,
                         train_names=[s.name for s in scans[:n_train]],
                         heldback_names=[s.name for s in scans[n_train:n_train + n_heldback]])
    return root
