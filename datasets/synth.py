"""Synthetic scan collections: virtual scans of a CAD part, good and with synthetic defects, in the collection frame."""
import numpy as np

from .defects import DEFECT_KINDS, defect_for_view
from .frame import Frame
from .scan import Scan
from .scanner import SENSORS, VirtualScanner, written_origin


def synthesise(mesh, n_train=32, n_test_good=16, n_test_defective=16, defects=DEFECT_KINDS, n_points=4000,
               noise=0.002, seed=0, jitter_deg=0.0, n_validation=0, part_id="", jitter_translation=0.0,
               radius_range=(1.5, 2.2), fov_deg=40.0, min_defect_fraction=0.015, min_defect_points=30,
               max_attempts=12, progress=True, sensor="pinhole", origin_standoff=None, origin_tilt_deg=0.0,
               defect_size=1.0, grazing_dropout=0.0, ragged=0.0):
    """Scan a part from random views, good and with synthetic defects, into scans in the collection frame.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, in its own units (watertight is best: missing / foreign defects are then exact booleans).
    n_train, n_validation, n_test_good : int
        Numbers of good scans in each split.
    n_test_defective : int
        Number of defective test scans PER defect kind.
    defects : sequence of str
        Defect kinds, from `datasets.defects.DEFECT_KINDS`.
    n_points : int
        Points per scan (exact).
    noise : float
        Depth-noise standard deviation RELATIVE to the part's size: the noise in mesh units is
        ``noise * bounding-box diagonal`` (0.002 of a 100 mm part is 0.2 mm), applied along each camera ray.
    seed : int
        Everything drawn (views, poses, defect sites and sizes, noise, point subsets) follows from it: the same seed
        gives the same scans. Each scan draws from its own child of ``np.random.SeedSequence(seed)``.
    jitter_deg, jitter_translation : float
        Random pose of the part in every scan (a part not held in a fixture): rotation up to ``jitter_deg`` degrees
        about its centre and a shift up to ``jitter_translation`` x the diagonal per axis. 0 = fixture.
    part_id : str
        Stored in every scan.
    radius_range : (2,) floats
        Camera distance from the part's centre, in multiples of its diagonal.
    fov_deg : float
        Horizontal field of view of the camera.
    min_defect_fraction, min_defect_points : float, int
        A defective scan must have at least this fraction of its points on the defect, and at least
        ``min(min_defect_points, 3 % of the points)`` of them; otherwise a new view and defect site are drawn, up to
        ``max_attempts`` times.
    progress : bool
        Show a tqdm progress bar over the scans.
    sensor : {'pinhole', 'line'}
        The virtual scanner (:meth:`datasets.scanner.VirtualScanner.scan`): a pinhole depth camera, or a line
        (profile) scanner sweeping a laser fan, whose ``sensor_origin`` is its head at mid-sweep.
    origin_standoff : (2,) floats, optional
        The sensor origin each scan records as a user writes it, not where the sensor was
        (:func:`datasets.scanner.written_origin`): its stand-off from the part's centre times a factor drawn
        log-uniformly in this range per scan (None: as measured).
    origin_tilt_deg : float
        And its axis turned by up to this many degrees (uniform, about a random axis across the view).
        The scans themselves do not change with either (their draws come after the scan's own).
    defect_size : float > 0
        Every defect's width and depth times this (:func:`datasets.defects.make_defect`'s ``size``).
    grazing_dropout : float >= 0
        Returns lost at grazing incidence (:meth:`datasets.scanner.VirtualScanner.scan`): a hit at incidence angle
        theta is kept with probability ``cos(theta) ** grazing_dropout`` (1: Lambertian). 0: none lost.
    ragged : float >= 0
        Ragged borders RELATIVE to the part's size, like ``noise``: every scan's silhouettes and occluding edges
        eaten back by up to ``ragged * bounding-box diagonal`` (:meth:`datasets.scanner.VirtualScanner.scan`). 0:
        clean borders.

    The sensor's options (``noise``, ``n_points``, ``radius_range``, ``fov_deg``, ``sensor``, ``grazing_dropout``,
    ``ragged``) describe one device. With the same ``seed`` and counts, each good scan sees the part from the same
    direction in the same pose whatever they are (its camera distance scaled with ``radius_range``), so two calls
    that differ only in them give the same good views through two sensors. At their defaults the scans are exactly
    those of the versions before ``grazing_dropout`` and ``ragged`` existed.

    Returns
    -------
    scans : list of Scan
        In the collection frame ``frame`` (points, sensor origins), named ``train/good/000``, ``test/dent/003``, ...;
        test scans carry per-point labels (all zeros for good ones) and per-point deviations
        (:func:`_point_deviation`: collection units; all zeros for good ones; training and validation scans have
        neither, None); ``extra`` holds the pose (4, 4) of the part in file units and, for defects, the defect's
        centre and radius in file units.
    frame : Frame
        ``Frame.fit(mesh.vertices)``: the part's bounding box mapped to a cube of side 1 centred at 0.

    Raises
    ------
    ValueError
        Unknown defect kind, bad counts, or a defect that no view could show after ``max_attempts`` tries.
    """
    from tqdm import tqdm

    defects = tuple(defects)
    unknown = [d for d in defects if d not in DEFECT_KINDS]
    if unknown:
        raise ValueError(f"unknown defect kind(s) {unknown}; expected some of {DEFECT_KINDS}")
    counts = dict(n_train=n_train, n_validation=n_validation, n_test_good=n_test_good,
                  n_test_defective=n_test_defective, n_points=n_points)
    for key, value in counts.items():
        low = 1 if key == "n_points" else 0
        if int(value) != value or value < low:
            raise ValueError(f"{key} must be an integer >= {low}, got {value!r}")
    if not 0 <= noise < np.inf:
        raise ValueError(f"noise must be >= 0 (relative to the bounding-box diagonal), got {noise!r}")
    if not 0 <= jitter_deg <= 180:
        raise ValueError(f"jitter_deg must be between 0 and 180 degrees, got {jitter_deg!r}")
    if not 0 <= jitter_translation < np.inf:
        raise ValueError(f"jitter_translation must be >= 0 (relative to the diagonal), got {jitter_translation!r}")

    if sensor not in SENSORS:
        raise ValueError(f"sensor must be one of {SENSORS}, got {sensor!r}")
    if origin_standoff is not None:
        origin_standoff = tuple(float(f) for f in origin_standoff)
        if len(origin_standoff) != 2 or not 0 < origin_standoff[0] <= origin_standoff[1] < np.inf:
            raise ValueError(f"origin_standoff must be two factors 0 < low <= high, got {origin_standoff!r}")
    if not 0 <= origin_tilt_deg < 90:
        raise ValueError(f"origin_tilt_deg must be in [0, 90) degrees, got {origin_tilt_deg!r}")
    if not 0 <= grazing_dropout < np.inf:
        raise ValueError(f"grazing_dropout must be >= 0 (an exponent on the cosine of incidence), got "
                         f"{grazing_dropout!r}")
    if not 0 <= ragged < np.inf:
        raise ValueError(f"ragged must be >= 0 (relative to the bounding-box diagonal), got {ragged!r}")
    scanner = VirtualScanner(mesh)
    frame = Frame.fit(mesh.vertices)
    jobs = ([("train", "good", i) for i in range(n_train)]
            + [("validation", "good", i) for i in range(n_validation)]
            + [("test", "good", i) for i in range(n_test_good)]
            + [("test", kind, i) for kind in defects for i in range(n_test_defective)])
    # One child seed per scan: a scan does not depend on how many retries the scans before it needed.
    children = np.random.SeedSequence(seed).spawn(len(jobs))
    if not 0 < defect_size < np.inf:
        raise ValueError(f"defect_size must be > 0 (a factor on the defects' sizes), got {defect_size!r}")
    options = dict(n_points=int(n_points), noise=noise * scanner.diagonal, fov_deg=fov_deg, sensor=sensor,
                   grazing_dropout=float(grazing_dropout), ragged=ragged * scanner.diagonal)
    view_options = dict(radius_range=radius_range, jitter_deg=jitter_deg, jitter_translation=jitter_translation)
    scans = []
    for (split, kind, i), child in tqdm(list(zip(jobs, children)), desc="synth scans", unit="scan",
                                        disable=not progress):
        rng = np.random.default_rng(child)
        name = f"{split}/{kind}/{i:03d}"
        if kind == "good":
            result = scanner.scan(scanner.random_view(seed=rng, **view_options), seed=rng, **options)
            labels = np.zeros(len(result.points), dtype=np.uint8) if split == "test" else None
            deviation = np.zeros(len(result.points), dtype=np.float32) if split == "test" else None
            extra = {"pose": result.pose}
        else:
            result, labels, defect = _defective_scan(mesh, scanner, kind, rng, view_options, options,
                                                     min_defect_fraction, min_defect_points, max_attempts, name,
                                                     defect_size)
            deviation = _point_deviation(mesh, result, labels, defect)
            extra = {"pose": result.pose, "defect_center": defect.center, "defect_radius": defect.radius}
        origin = result.sensor_origin
        if origin_standoff is not None or origin_tilt_deg > 0:
            origin = written_origin(origin, result.pose[:3, :3] @ scanner.center + result.pose[:3, 3],
                                    origin_standoff or (1.0, 1.0), origin_tilt_deg, rng)
        scan = Scan(name=name, points=result.points, normals=result.normals, split=split,
                    label="good" if kind == "good" else "defective", defect="" if kind == "good" else kind,
                    part_id=part_id, point_labels=labels, sensor_origin=origin, extra=extra,
                    point_deviation=deviation)
        scans.append(frame.apply(scan))  # the deviation, a length, scaled with the points
    return scans, frame


def _defective_scan(mesh, scanner, kind, rng, view_options, options, min_fraction, min_points, max_attempts, name,
                    size=1.0):
    """Draw views and defect sites until the scan shows the defect. Returns (ScanResult, (n,) uint8, Defect)."""
    # The count floor matters at thousands of points; with few points it would ask for a large share of them.
    share = int(np.ceil(min_fraction * options["n_points"]))
    needed = max(share, min(min_points, int(np.ceil(0.03 * options["n_points"]))))
    best = 0
    for _ in range(max_attempts):
        view = scanner.random_view(seed=rng, **view_options)
        defect = defect_for_view(mesh, scanner, view, kind, seed=rng, fov_deg=options["fov_deg"],
                                 sensor=options["sensor"], size=size)
        result = VirtualScanner(defect.mesh).scan(view, seed=rng, **options)
        # Label the noise-free hits, by the triangles they hit: noise must not move a point on or off the defect.
        clean = result.to_mesh_frame(result.clean_points)
        labels = defect.region(clean, result.triangle_ids)
        if kind == "missing":
            # a hole through a thin wall has almost no surface of its own: what the sensor saw through it counts
            labels |= defect.seen_through(mesh, result.to_mesh_frame(result.ray_origins), clean)
        if labels.sum() >= needed:
            return result, labels.astype(np.uint8), defect
        best = max(best, int(labels.sum()))
    raise ValueError(f"{name}: no view out of {max_attempts} showed the {kind} defect on at least {needed} points "
                     f"(best {best}); use a larger defect or more points")


def _point_deviation(mesh, result, labels, defect=None):
    """(n,) float64: how far each labelled point lies off the good part ``mesh`` (mesh units, positive outside:
    ``Scan.point_deviation``), taken at its noise-free hit (the range noise is the sensor's, not the defect's); 0 on
    the points no defect touched. Draws nothing, so the scans are those of a synthesis without it.

    For a dent or a bump (``defect`` given), the point's offset from the tangent plane of the face it was moved
    from: the displacement (:func:`datasets.defects.make_defect`'s profile along the defect's normal) times the
    cosine between that normal and the face's. Not the distance to the nearest face of the good part: a dent deeper
    than a thin wall moves both of its faces (pressed sheet metal), and its points lie nearer the far face's old place
    than their own. Otherwise (missing, foreign) the signed distance to the good part: a labelled point the sensor
    saw through a hole (``missing`` on a thin wall) lies on a surface the good part has (its far side), about 0.
    """
    import trimesh

    deviation = np.zeros(len(labels))
    on = labels.astype(bool)
    if not on.any():
        return deviation
    points = result.to_mesh_frame(result.clean_points[on])
    if defect is not None and defect.kind in ("dent", "bump"):
        normal = np.asarray(defect.normal, dtype=np.float64)
        offset = points - defect.center
        along = offset @ normal
        lateral = np.linalg.norm(offset - along[:, None] * normal, axis=1)
        moved = np.zeros(len(points))
        for _ in range(8):  # the profile is of the point's distance from the centre before it moved: a fixed point
            before = np.sqrt(lateral ** 2 + (along - moved) ** 2)
            moved = defect.height * np.clip(1.0 - (before / defect.radius) ** 2, 0.0, None) ** 2
        _, _, faces = trimesh.proximity.closest_point(mesh, points - moved[:, None] * normal)
        deviation[on] = moved * (np.asarray(mesh.face_normals)[faces] @ normal)
        return deviation
    deviation[on] = -trimesh.proximity.signed_distance(mesh, points)  # trimesh's sign is positive inside
    return deviation
