"""How well a model fits a product family's members (issue 32, item 1): the distance of a scan's projected mean
surface from the true surface of the member the scan is of, for the unseen member's good test scans against the
trained members' held-back scans.

For each scan: the member's mesh (:func:`benchmarks.cache.member_mesh` of the part by the factor in the scan's name,
``.../stretch0.900_003``), in the collection frame and moved as the model moves the scan (its family registration,
:meth:`autodecoder.latent.model.LatentModel.normalise`; none for a model of one size); the scan projected as
inspection projects it; the first-order distance |g| / |grad g| of the projected mean at points of the true surface
the scan saw (area-uniform samples within 2 % of the frame's unit of a scan point), median. In the collection frame's
units (the training scans' box is about 1 long).

Two comparisons: :func:`family_fit`, the collection's own scans (the unseen member's good test scans against the
trained members' held-back scans: different views), and :func:`paired_family_fit`, new scans of the unseen member
and of the trained members nearest to it on either side, each from the same camera positions (the same synthesis
seed), so that a difference is the member's and not the view's: how hard a view is to fit varies more between views
(median distances 0.0013-0.0082 over one member's 16 views of the fandisk) than between members.
"""
import re

import numpy as np

FACTOR = re.compile(r"(stretch|bend|hole|wall)(-?[0-9.]+)_")


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

    from .cache import VARIATIONS, member_mesh, part_mesh

    model = load_model(model_path)
    mesh = None if kind not in VARIATIONS else part if hasattr(part, "vertices") else part_mesh(part)
    out = {}
    with ScanCollection(collection_path) as c:
        names = c.names
        groups = {"unseen": [n for n in names if n.startswith("test/good/")][:max_scans],
                  "trained": [n for n in model.calibration_names if n in set(names)][:max_scans]}
        for role, chosen in groups.items():
            errors = []
            for name in chosen:
                factor = float(FACTOR.search(name).group(2))
                member = member_mesh(part, kind, factor, mesh)
                errors.append(member_surface_error(model, c[names.index(name)], member, c.frame))
            out[role] = float(np.median(errors)) if errors else float("nan")
    out["scans"] = max_scans
    return out



def paired_member_scans(part, kind, factors, frame, views=16, seed=7919, n_points=4000):
    """Good scans of members of ``part``'s family (a part's name, or a mesh for the kinds that transform one) from
    the same camera positions.

    Each member (:func:`benchmarks.cache.member_mesh` ``(part, kind, factor)``) is synthesised with the same ``seed``
    (its cameras depend on the seed alone, at distances in multiples of its own diagonal:
    :func:`datasets.synth.synthesise`), and its scans moved from file units into ``frame`` (the collection's) as
    :func:`benchmarks.cache.family_collection` moves a collection's; named ``paired/good/<kind><factor>_<view>``.
    Returns {factor: (the member's mesh in file units, its scans)}.
    """
    from dataclasses import replace

    from datasets.synth import synthesise

    from .cache import VARIATIONS, member_mesh, part_mesh

    mesh = None if kind not in VARIATIONS else part if hasattr(part, "vertices") else part_mesh(part)
    out = {}
    for factor in factors:
        member = member_mesh(part, kind, float(factor), mesh)
        scans, own = synthesise(member, n_train=0, n_test_good=int(views), n_test_defective=0, n_points=n_points,
                                seed=seed, progress=False)
        out[float(factor)] = member, [
            frame.apply(replace(s, name=f"paired/good/{kind}{float(factor):.3f}_{s.name.rsplit('/', 1)[1]}",
                                points=own.to_file(s.points),
                                sensor_origin=None if s.sensor_origin is None else own.to_file(s.sensor_origin)))
            for s in scans]
    return out


def paired_family_fit(model_path, collection_path, part, kind, test_factor, scale=1.0, views=16, seed=7919):
    """:func:`member_surface_error` of new good scans of the unseen member ``test_factor`` and of the two trained
    members nearest to it (the inner ends of the family's ranges, :func:`benchmarks.cache.family_ranges`), all from
    the same ``views`` camera positions (:func:`paired_member_scans`).

    Returns
    -------
    dict
        ``members``: {factor: median over the views}; ``unseen``: the unseen member's median; ``trained``: the
        median over both trained members' scans; ``paired_ratio``: the median over views of the unseen member's
        distance over the mean of the two trained members' from the same view (1: fitted as well); ``views``.
    """
    from autodecoder.latent.model import load_model
    from datasets import ScanCollection

    from .cache import COLLECTION_DEFAULTS, family_ranges

    ranges = family_ranges(kind, float(scale))
    lows, highs = [r for r in ranges if max(r) <= test_factor], [r for r in ranges if min(r) >= test_factor]
    trained = ([max(max(r) for r in lows)] if lows else []) + ([min(min(r) for r in highs)] if highs else [])
    model = load_model(model_path)
    with ScanCollection(collection_path) as c:
        common = c.frame
    members = paired_member_scans(part, kind, [float(test_factor)] + trained, common, views, seed,
                                  COLLECTION_DEFAULTS["n_points"])
    errors = {f: np.array([member_surface_error(model, s, member, common) for s in scans])
              for f, (member, scans) in members.items()}
    unseen = errors[float(test_factor)]
    others = np.mean([errors[f] for f in trained], axis=0) if trained else np.full(len(unseen), np.nan)
    return {"members": {f"{f:g}": float(np.median(e)) for f, e in errors.items()},
            "unseen": float(np.median(unseen)),
            "trained": float(np.median(np.concatenate([errors[f] for f in trained]))) if trained else float("nan"),
            "paired_ratio": float(np.median(unseen / others)), "views": int(views)}
