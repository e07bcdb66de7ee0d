"""Benchmark inputs built once and reused: scan collections and trained models, cached by their parameters.

Every cached thing is a folder ``<root>/<kind>/<label>_<key>/``, ``key`` a short sha256 of the canonical JSON of the
kind and its parameters, holding what the build wrote and ``params.json`` (the parameters). A folder is built in a
hidden temporary folder beside it and renamed into place when the build has finished (``datasets.atomic``): an
interrupted or failing build leaves nothing, and a folder that exists is complete.
"""
import hashlib
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = "results/cache"
SHARED = ROOT.parent / "shared"
MESHES = SHARED / "meshes"
REAL_SCANS = SHARED / "realscans"
MESH_FILES = {"fandisk": MESHES / "fandisk.obj", "bunny": MESHES / "stanford-bunny.obj", "ogre": MESHES / "ogre.obj"}

# the collection of a new user's first run: 32 good training scans, 16 good test scans, 16 per defect type, 4,000
# points, in a fixture (datasets.synth.synthesise's keyword arguments)
COLLECTION_DEFAULTS = dict(n_train=32, n_test_good=16, n_test_defective=16, n_points=4000, jitter_deg=0.0)


def cache_key(kind, params):
    """The short sha256 (12 hex digits) of the canonical JSON of ``kind`` and ``params``."""
    text = json.dumps({"kind": kind, "params": params}, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def cached_path(kind, params, build, root=CACHE, label=""):
    """The folder of ``kind`` with ``params``, built by ``build(tmp_folder)`` when it does not exist yet.

    Parameters
    ----------
    kind : str
        What is cached (``'collection'``, ``'model'``, ...): a sub-folder of ``root``.
    params : dict
        Everything the result depends on (JSON-serialisable; paths are keyed as strings). Stored as params.json.
    build : callable (Path) -> None
        Fills the empty temporary folder it is given; an exception leaves nothing behind and propagates.
    root : str or Path
    label : str
        Readable prefix of the folder's name (e.g. the part); not part of the key.

    Returns
    -------
    Path
        The complete folder.
    """
    from datasets.atomic import atomic_directory

    key = cache_key(kind, params)
    path = Path(root) / kind / (f"{label}_{key}" if label else key)
    if (path / "params.json").is_file():
        return path
    with atomic_directory(path) as tmp:
        build(tmp)
        (tmp / "params.json").write_text(json.dumps({"kind": kind, "params": params}, indent=1, sort_keys=True,
                                                    default=str) + "\n")
    return path


def part_mesh(part):
    """The mesh of ``part``: ``fandisk`` and ``bunny`` (../shared/meshes), a built-in part's name
    (``datasets.parts.BUILTIN_PARTS``: builtin, enclosure, cup) or a mesh file."""
    from datasets.parts import load_part

    return load_part(str(MESH_FILES.get(part, part)))


def synth_collection(part, seed=0, root=CACHE, progress=False, **params):
    """The synthetic scan collection of ``part`` (``datasets.synth.synthesise``), cached. Returns its ``tree.h5``.

    Parameters
    ----------
    part : str
        See :func:`part_mesh`.
    seed : int
    **params
        ``synthesise``'s keyword arguments (defaults: :data:`COLLECTION_DEFAULTS`), and ``sensor_origins=False``
        for the same scans without sensor origins (a scanner that does not record where it stood).
    """
    params = {**COLLECTION_DEFAULTS, **params}
    origins = params.pop("sensor_origins", True)
    keyed = {"part": part, "seed": seed, **params, **({} if origins else {"sensor_origins": False})}

    def build(folder):
        from datasets import ScanCollection
        from datasets.synth import synthesise

        scans, frame = synthesise(part_mesh(part), seed=seed, progress=progress, **params)
        if not origins:
            for scan in scans:
                scan.sensor_origin = None
        ScanCollection.create(folder / "tree.h5", scans, frame=frame, provenance={"benchmark": "cache", **keyed})

    return cached_path("collection", keyed, build, root, label=Path(str(part)).stem) / "tree.h5"


# the Real3D-AD-like class folders of the template regime: 4 complete clouds sampled on the part's mesh, depth noise
# TEMPLATE_NOISE x its diagonal along the normal
TEMPLATES = 4
TEMPLATE_NOISE = 0.002


def template_collection(part, test, seed=0, template_points=10000, views=16, validation_views=4, root=CACHE):
    """The template regime's collection of ``part``, cached: :data:`TEMPLATES` complete clouds sampled on its mesh
    (:func:`write_templates`) and the test scans of the collection ``test`` (file units: Real3D-AD ``.pcd`` files
    without sensor origins, ground truth in ``gt/``), written as a Real3D-AD class folder and imported by the datasets
    importer (the templates become ``views`` partial training views and ``validation_views`` held-back views each;
    the frame is fitted to the training views, so that every ``test`` of the same part, seed and template options
    gives a collection in the same frame with the same training and held-back scans). Returns its ``data.h5``.

    Parameters
    ----------
    part : str
        See :func:`part_mesh`.
    test : Path
        A :func:`synth_collection` of the part (its scans are the test scans; ``n_train=0``). Keyed by its folder's
        name, which holds its parameters' key.
    seed : int
        The templates' and the views' seed.
    template_points, views, validation_views : int
    """
    from datasets.templates import VISIBILITY_RULE

    test = Path(test)
    params = {"part": part, "test": str(test.parent.name), "template_points": template_points, "seed": seed,
              "views": views, "validation_views": validation_views, "visibility": VISIBILITY_RULE}

    def build(folder):
        from datasets import ScanCollection
        from datasets.importer import import_tree

        tree = folder / "tree"
        write_templates(part_mesh(part), tree / "train", template_points, seed)
        with ScanCollection(test) as c:
            frame, scans = c.frame, c.read_many(range(len(c)))
        for i, s in enumerate(scans):
            points = frame.to_file(s.points)
            stem = f"{i + 1}_{'good' if s.label == 'good' else s.defect}"
            write_pcd(tree / "test" / f"{stem}.pcd", points)
            if s.label != "good":
                (tree / "gt").mkdir(exist_ok=True)
                np.savetxt(tree / "gt" / f"{stem}.txt", np.column_stack([points, s.point_labels]),
                           fmt=["%.6f"] * 3 + ["%d"])
        import_tree(tree, folder / "data.h5", seed=seed, views=views, validation_views=validation_views,
                    progress=False)

    return cached_path("templates", params, build, root, label=part) / "data.h5"


def write_templates(mesh, folder, n_points, seed):
    """:data:`TEMPLATES` complete clouds of ``n_points`` sampled on ``mesh`` (its units), depth noise
    :data:`TEMPLATE_NOISE` x its diagonal along the normal, as ``folder/<k>_template.pcd``."""
    import trimesh

    diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    for k in range(TEMPLATES):
        rng = np.random.default_rng([seed, 1000 + k])
        pts, faces = trimesh.sample.sample_surface(mesh, n_points, seed=int(rng.integers(2**31)))
        pts = pts + mesh.face_normals[faces] * rng.normal(0, TEMPLATE_NOISE * diag, (len(pts), 1))
        write_pcd(folder / f"{k + 1}_template.pcd", pts)


def write_pcd(path, points):
    """(n, 3) points as a ``.pcd`` file (open3d), its folder made."""
    import open3d as o3d

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if not o3d.io.write_point_cloud(str(path), pcd):
        raise RuntimeError(f"{path}: open3d could not write it")


# a product family (issue 32): training scans of variants stretched along the part's longest axis by these factors
# (evenly spread over both ranges), test scans of one variant that no training scan showed
FAMILY_STRETCH = ((0.8, 0.9), (1.1, 1.2))
# a second kind of variation (issue 32): the part bent along its longest axis by this many degrees end to end
FAMILY_BEND = ((-12.0, -6.0), (6.0, 12.0))
# families whose features move or change (issue 52, item 2): a built-in part's holes moved by this many mm
# (datasets.parts: the bracket's bolt holes towards its mid-line, the enclosure's round top hole along x), and its
# sheet this many mm thick (the cup, the enclosure; nominal 1.5)
FAMILY_HOLE = ((-4.0, -2.0), (2.0, 4.0))
FAMILY_WALL = ((1.0, 1.25), (1.75, 2.0))
FAMILY_RANGES = {"stretch": FAMILY_STRETCH, "bend": FAMILY_BEND, "hole": FAMILY_HOLE, "wall": FAMILY_WALL}
# each kind's nominal member (the value a family's spread is measured from, family_ranges' scale)
FAMILY_NOMINAL = {"stretch": 1.0, "bend": 0.0, "hole": 0.0, "wall": 1.5}
FAMILY_VARIANTS = 8


def stretched(mesh, factor):
    """A copy of ``mesh`` stretched by ``factor`` along its bounding box's longest axis, about the box's centre."""
    out = mesh.copy()
    lo, hi = out.bounds
    axis = int(np.argmax(hi - lo))
    centre = (lo[axis] + hi[axis]) / 2
    vertices = out.vertices.copy()
    vertices[:, axis] = centre + float(factor) * (vertices[:, axis] - centre)
    out.vertices = vertices
    return out


def bent(mesh, degrees):
    """A copy of ``mesh`` bent along its bounding box's longest axis, in the plane of that axis and the shortest one,
    by ``degrees`` end to end (negative: the other way): the box's mid-plane across the longest axis stays in place,
    each slice across it turns about an axis at radius length / angle, so lengths along the mid-surface are kept
    (a pure bend). The mesh is first subdivided to edges of at most 1/64 of its length, so that long flat faces bend
    too (subdivision leaves the surface where it is). 0 is the mesh itself."""
    import trimesh

    angle = np.radians(float(degrees))
    if angle == 0:
        return mesh.copy()
    lo, hi = mesh.bounds
    extent = hi - lo
    along, across = int(np.argmax(extent)), int(np.argmin(extent))
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=extent[along] / 64)
    out = trimesh.Trimesh(vertices, faces, process=False)
    centre = (lo + hi) / 2
    radius = extent[along] / angle  # signed: the centre of curvature on the side of the sign
    u = out.vertices[:, along] - centre[along]
    v = out.vertices[:, across] - centre[across]
    phi = u / radius
    vertices = out.vertices.copy()
    vertices[:, along] = centre[along] + (radius - v) * np.sin(phi)
    vertices[:, across] = centre[across] + radius - (radius - v) * np.cos(phi)
    out.vertices = vertices
    return out


# kinds that transform any part's mesh, and kinds that build a built-in part anew with one of its parameters
VARIATIONS = {"stretch": stretched, "bend": bent}
FEATURE_VARIATIONS = {"hole": ("hole_shift", ("builtin", "enclosure")), "wall": ("wall", ("cup", "enclosure"))}
FAMILY_KINDS = tuple(FAMILY_RANGES)


def member_mesh(part, kind, value, mesh=None):
    """The mesh of ``part``'s family member ``value`` of ``kind``: ``part``'s mesh (``mesh``, or
    :func:`part_mesh`) stretched or bent (:data:`VARIATIONS`), or the built-in part built with its feature's
    parameter at ``value`` (:data:`FEATURE_VARIATIONS`: a ValueError for a part without that feature)."""
    if kind in VARIATIONS:
        return VARIATIONS[kind](part_mesh(part) if mesh is None else mesh, float(value))
    if kind not in FEATURE_VARIATIONS:
        raise ValueError(f"family kind must be one of {list(FAMILY_KINDS)}, got {kind!r}")
    from datasets.parts import BUILTIN_PARTS

    parameter, parts = FEATURE_VARIATIONS[kind]
    if part not in parts:
        raise ValueError(f"a {kind!r} family needs a built-in part with that feature ({', '.join(parts)}), got "
                         f"{part!r}")
    return BUILTIN_PARTS[part](**{parameter: float(value)})


def family_ranges(kind, scale=1.0):
    """The variants' ranges of a family of ``kind``, their spread about the nominal part (``FAMILY_NOMINAL``) times
    ``scale``: the factors' distance from 1 (stretch), the angles (bend), the holes' shifts (hole), the sheet's
    thickness' distance from 1.5 mm (wall)."""
    if scale == 1:
        return FAMILY_RANGES[kind]
    nominal = FAMILY_NOMINAL[kind]
    return tuple(tuple(nominal + scale * (x - nominal) for x in r) for r in FAMILY_RANGES[kind])


def family_collection(part, seed=0, root=CACHE, progress=False, test_stretch=1.0, kind="stretch", scale=1.0,
                      **params):
    """A product family's scan collection, cached (returns its ``tree.h5``): ``n_train`` good training scans of
    :data:`FAMILY_VARIANTS` variants of ``part`` (factors evenly spread over the ranges of
    ``FAMILY_RANGES[kind]``, the scans shared out evenly) and test scans (good and defective, as
    :func:`synth_collection`'s) of the variant ``test_stretch``. ``kind`` 'stretch': stretched along the longest
    axis by that factor (:func:`stretched`; 1.0: the nominal part, inside the family's range and never trained on;
    1.3: just outside it); 'bend': bent by that many degrees (:func:`bent`; 0: the nominal part, inside; 18:
    outside). Each variant is synthesised in its own frame, its scans moved to file units and the whole collection
    into one frame fitted to the training scans; a scan's name holds its variant (``train/good/stretch0.800_001``,
    ``train/good/bend-12.000_001``).

    Parameters
    ----------
    part : str
        See :func:`part_mesh`.
    seed : int
    test_stretch : float
        The test variant's factor (stretch) or angle in degrees (bend).
    kind : {'stretch', 'bend', 'hole', 'wall'}
    scale : float > 0
        The variants' spread about the nominal part (:func:`family_ranges`; 1: ``FAMILY_RANGES[kind]``).
    **params
        ``synthesise``'s keyword arguments (defaults: :data:`COLLECTION_DEFAULTS`).
    """
    if kind not in FAMILY_RANGES:
        raise ValueError(f"family kind must be one of {list(FAMILY_KINDS)}, got {kind!r}")
    if not float(scale) > 0:
        raise ValueError(f"family scale must be > 0, got {scale!r}")
    params = {**COLLECTION_DEFAULTS, **params}
    ranges = family_ranges(kind, float(scale))
    keyed = {"part": part, "seed": seed, "family": [list(r) for r in ranges], "variants": FAMILY_VARIANTS,
             "test_stretch": float(test_stretch), **params}
    if kind != "stretch":  # the stretch families' cache keys stay as they were
        keyed["kind"] = kind

    def build(folder):
        from dataclasses import replace

        from datasets import ScanCollection
        from datasets.frame import Frame
        from datasets.synth import synthesise

        mesh = part_mesh(part) if kind in VARIATIONS else None
        factors = np.concatenate([np.linspace(lo, hi, FAMILY_VARIANTS // len(ranges)) for lo, hi in ranges])
        shares = np.diff(np.linspace(0, params["n_train"], len(factors) + 1).round().astype(int))
        groups = [(f, dict(params, n_train=int(n), n_test_good=0, n_test_defective=0))
                  for f, n in zip(factors, shares) if n > 0]
        groups.append((float(test_stretch), dict(params, n_train=0)))
        scans = []
        for k, (factor, options) in enumerate(groups):
            variant, frame = synthesise(member_mesh(part, kind, factor, mesh), seed=seed * 1000 + k,
                                        progress=progress, **options)
            for s in variant:  # to file units, named after the variant
                origin = None if s.sensor_origin is None else frame.to_file(s.sensor_origin)
                head, tail = s.name.rsplit("/", 1)
                scans.append(replace(s, name=f"{head}/{kind}{factor:.3f}_{tail}", points=frame.to_file(s.points),
                                     sensor_origin=origin))
        common = Frame.fit(np.concatenate([s.points for s in scans if s.split == "train"]))
        ScanCollection.create(folder / "tree.h5", (common.apply(s) for s in scans), frame=common,
                              provenance={"benchmark": "cache", **keyed})

    label = f"{Path(str(part)).stem}-family" + ("" if kind == "stretch" else f"-{kind}")
    return cached_path("collection", keyed, build, root, label=label) / "tree.h5"


def trained_model(collection_path, root=CACHE, **train_options):
    """A latent model trained on a collection (``inspection.training.train_model``: the trainer's defaults for
    everything not given), cached by the collection's fingerprint and the options. Returns its ``model.pt``
    (uncalibrated: copy it before calibrating).

    ``train_options``: ``train_model``'s keyword arguments (``seed`` default 0, ``epochs``, ``calibration_fraction``,
    ``representation`` and the other ``LatentOptions`` fields); None values mean the default and are not keyed.
    """
    from datasets import ScanCollection

    collection_path = Path(collection_path)
    with ScanCollection(collection_path) as c:
        fingerprint = c.fingerprint()
    options = {"seed": 0, **{k: v for k, v in train_options.items() if v is not None}}
    options.pop("quiet", None)

    folds = options.pop("calibration_folds", None)
    family = options.pop("family", "auto")  # the trainer's default: a family when fit_family decides it
    pose = options.pop("pose", "auto")  # the trainer's default: one common pose when the poses spread
    if family == "auto":
        family = family_decision(collection_path, fingerprint, options["seed"], root)
    if family:  # keyed only for a family: the models cached before families were sized stay valid for the rest
        options["family"] = FAMILY_KEY
    elif pose is True or (pose == "auto" and pose_decision(collection_path, fingerprint, options["seed"], root)):
        options["pose"] = POSE_KEY  # likewise: keyed only where the training scans are moved into one pose

    def build(folder):
        from inspection.training import train_model

        train_model(collection_path, folder / "model.pt", quiet=True, calibration_folds=0,
                    **{**options, "family": bool(family), "pose": pose})

    label = collection_path.parent.name.rsplit("_", 1)[0]
    model = cached_path("model", {"collection": fingerprint, **options}, build, root, label=label) / "model.pt"
    _ensure_folds(model, collection_path, folds)
    return model


FAMILY_KEY = "scaled-5"  # the rule by which a family's scans are brought to one size (autodecoder.latent.family)
FAMILY_DECISION_KEY = "scaled-5-first-round"  # the rule by which family='auto' decides it (fit_family)


POSE_KEY = "group-1"  # the rule by which training scans placed by hand are moved into one pose (fit_pose)


def pose_decision(collection_path, fingerprint, seed=0, root=CACHE):
    """Whether the trainer's ``pose='auto'`` moves this collection's training scans into one common pose
    (:func:`autodecoder.latent.family.pose_decision` on the scans it trains on), cached per collection and seed."""
    def build(folder):
        from autodecoder.latent.collection_split import CollectionScans, part_types, split_training_scans
        from autodecoder.latent.family import pose_decision as decide
        from datasets import ScanCollection

        with ScanCollection(collection_path) as c:
            train, _ = split_training_scans(c, "train", 0.2, seed)
            one_part = len(part_types(c, train)) <= 1  # as the trainer: never across several part types
            spread, moves = decide(CollectionScans(c, train), seed=seed) if one_part else (None, False)
        (folder / "decision.json").write_text(json.dumps({"pose": bool(moves), "spread": spread}) + "\n")

    folder = cached_path("pose", {"collection": fingerprint, "seed": seed, "rule": POSE_KEY}, build, root,
                         label=Path(collection_path).parent.name.rsplit("_", 1)[0])
    return bool(json.loads((folder / "decision.json").read_text())["pose"])


def family_decision(collection_path, fingerprint, seed=0, root=CACHE):
    """Whether the trainer's ``family='auto'`` brings this collection's training scans to one size
    (:func:`autodecoder.latent.family.fit_family` on the scans it trains on), cached per collection and seed (the
    decision registers 16 scans onto each other: half a minute)."""
    def build(folder):
        from autodecoder.latent.collection_split import CollectionScans, part_types, split_training_scans
        from autodecoder.latent.family import fit_family
        from datasets import ScanCollection

        with ScanCollection(collection_path) as c:
            train, _ = split_training_scans(c, "train", 0.2, seed)
            one_part = len(part_types(c, train)) <= 1
            frame, spread = fit_family(CollectionScans(c, train), "auto", seed=seed) if one_part else (None, None)
        (folder / "decision.json").write_text(json.dumps({"family": frame is not None, "spread": spread}) + "\n")

    folder = cached_path("family", {"collection": fingerprint, "seed": seed, "rule": FAMILY_DECISION_KEY}, build, root,
                         label=Path(collection_path).parent.name.rsplit("_", 1)[0])
    return bool(json.loads((folder / "decision.json").read_text())["family"])


def _ensure_folds(model, collection_path, k=None):
    """The cached model with ``k`` fold models of today's rule (None: the trainer's default, none; 0: none wanted, the
    file is left as it is: a copy calibrates without them when ``inspect_api.calibrate_and_score(folds=False)``) in its checkpoint, trained into it when it has other or none: the main model is cached apart from its fold
    models, so models cached before fold models existed keep their nets, and the fold models are exactly those
    ``train_latent.py`` would add."""
    from autodecoder.latent.folds import DEFAULT_FOLDS, FOLD_RULE, FOLDS_KEY, add_folds
    from autodecoder.latent.model import read_checkpoint

    k = DEFAULT_FOLDS if k is None else int(k)
    if k == 0:
        return
    folds = read_checkpoint(model).get(FOLDS_KEY) or []
    if len(folds) == k and all(f.get("rule") == FOLD_RULE for f in folds):
        return
    t0 = time.perf_counter()
    add_folds(model, collection_path, k)
    seconds = time.perf_counter() - t0
    params = model.parent / "fold_seconds.json"
    params.write_text(json.dumps({"folds": k, "seconds": seconds}))
    print(f"  {model}: {k} fold models trained in {seconds:.0f} s", flush=True)


def merged_collection(collections, root=CACHE):
    """One collection of several parts' collections, cached by their fingerprints. Returns its ``tree.h5``.

    ``collections`` {part: tree.h5}: the same scans, each named ``<part>/<name>`` with ``part_id`` = the part. Each
    part keeps the coordinates of its own collection's unit-cube frame (each sits in its own fixture frame, centred
    in the same cube; the part id tells them apart) and the merged collection records the identity frame.
    """
    from datasets import ScanCollection

    fingerprints = {}
    for part, path in collections.items():
        with ScanCollection(path) as c:
            fingerprints[part] = c.fingerprint()

    def build(folder):
        from dataclasses import replace

        from datasets.frame import Frame

        scans = []
        for part, path in collections.items():
            with ScanCollection(path) as c:
                scans += [replace(s, name=f"{part}/{s.name}", part_id=part) for s in c.read_many(range(len(c)))]
        ScanCollection.create(folder / "tree.h5", scans, frame=Frame.identity(),
                              provenance={"benchmark": "cache", "parts": {p: str(s) for p, s in collections.items()},
                                          "frame": "each part in its own collection's unit-cube frame"})

    return cached_path("merged", fingerprints, build, root, label="+".join(collections)) / "tree.h5"


def real_tree(seed, root=CACHE):
    """The collection file of the real suite's bunny tree of ``seed`` cached under ``root`` (the first by key).
    FileNotFoundError when there is none: the real suite builds it (``python -m benchmarks real --seed S``); other
    suites read it from here, as suites do not import each other."""
    import json

    trees = [p.parent / "bunny.h5" for p in sorted((Path(root) / "real").glob("bunny_*/params.json"))
             if json.loads(p.read_text())["params"].get("seed") == seed and (p.parent / "bunny.h5").exists()]
    if not trees:
        raise FileNotFoundError(f"no real bunny tree of seed {seed} in {root}/real: build it with "
                                f"`python -m benchmarks real --seed {seed}`")
    return trees[0]
