"""How well a model fits a product family's members (issue 32, item 1): the distance of a scan's projected mean
surface from the true surface of the member the scan is of, for the unseen member's good test scans against the
trained members' held-back scans.

For each scan: the member's mesh (:data:`benchmarks.cache.VARIATIONS` of the part by the factor in the scan's name,
``.../stretch0.900_003``), in the collection frame and moved as the model moves the scan (its family registration,
:meth:`autodecoder.latent.model.LatentModel.normalise`; none for a model of one size); the scan projected as
inspection projects it; the first-order distance |g| / |grad g| of the projected mean at points of the true surface
the scan saw (area-uniform samples within 2 % of the frame's unit of a scan point), median. In the collection frame's
units (the training scans' box is about 1 long).
"""
import re

import numpy as np

FACTOR = re.compile(r"(stretch|bend)(-?[0-9.]+)_")


def member_surface_error(model, scan, mesh_file, frame, samples=20000, seen=0.02, seed=0):
    """The median first-order distance of ``scan``'s projected mean surface at the true surface it saw.

    Parameters
    ----------
    model : autodecoder.latent.model.LatentModel
    scan : datasets.Scan
        Collection frame.
    mesh_file : trimesh.Trimesh
        The scan's member in file units.
    frame : datasets.frame.Frame
        The collection's frame.
    """
    import trimesh
    from scipy.spatial import cKDTree

    from datasets.registration import apply_transform

    moved = model.normalise(scan)
    extra = getattr(moved, "extra", None) or {}
    T = extra.get("align") if model.family is not None else None
    truth = frame.to_collection(trimesh.sample.sample_surface(mesh_file, samples, seed=seed)[0])
    if T is not None:
        truth = apply_transform(T, truth)[0]
    points = np.asarray(moved.points, dtype=np.float64)
    near = cKDTree(points).query(truth, distance_upper_bound=seen)[0] < np.inf
    field = model.project(points.astype(np.float32), np.asarray(moved.normals, dtype=np.float32), seed=0).field
    mean, grad = field.mean_and_gradient(truth[near].astype(np.float32))
    return float(np.median(np.abs(mean) / np.maximum(np.linalg.norm(grad, axis=1), 1e-12)))


def family_fit(model_path, collection_path, part, kind, max_scans=8):
    """Median over scans of :func:`member_surface_error`, for up to ``max_scans`` good test scans (the unseen
    member) and as many of the model's held-back scans (trained members). Returns {'unseen': float,
    'trained': float, 'scans': int}."""
    from autodecoder.latent.model import load_model
    from datasets import ScanCollection

    from .cache import VARIATIONS, part_mesh

    model = load_model(model_path)
    mesh = part_mesh(part)
    out = {}
    with ScanCollection(collection_path) as c:
        names = c.names
        groups = {"unseen": [n for n in names if n.startswith("test/good/")][:max_scans],
                  "trained": [n for n in model.calibration_names if n in set(names)][:max_scans]}
        for role, chosen in groups.items():
            errors = []
            for name in chosen:
                factor = float(FACTOR.search(name).group(2))
                errors.append(member_surface_error(model, c[names.index(name)], VARIATIONS[kind](mesh, factor),
                                                   c.frame))
            out[role] = float(np.median(errors)) if errors else float("nan")
    out["scans"] = max_scans
    return out
