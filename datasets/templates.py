"""Partial training views of complete template clouds: what a depth sensor would see of each from around it.

Real3D-AD and Anomaly-ShapeNet give 4 complete (360 degree) clouds per class for training and test on partial scans.
The latent model is a space of partial scans, so each template is turned into partial views: the template points a
sensor at a given position would return, with that position recorded as the view's sensor origin. Views for training
and held-back views for calibration come from different sensor positions of the same templates, so no template has to
be held back.

Which points a sensor returns is decided by casting a ray from the sensor to each template point through a surface
reconstructed from the template (:class:`TemplateSurface`, screened Poisson): a point is returned when the ray meets
the surface no earlier than the template's own noise allows, and its normal faces the sensor. Hidden-point removal
(Katz, Tal and Basri 2007), the rule before, lost much of the grazing and concave surface that real test scans
show; held-back views rendered that way scored lower than good test scans, and their threshold flagged good ones
(figures: docs/results.md#four-complete-templates; ``python -m benchmarks data --mode views`` compares the two
rules with a ray caster on the true mesh).
"""
import numpy as np

from .scan import Scan

MIN_VIEW_POINTS = 3
VISIBILITY_RULE = "ray-cast"  # which rule decided a view's points (benchmark caches key on it)
# A point counts as returned while the ray to it meets the reconstructed surface at most NOISE_TOLERANCE template
# noise deviations before it, that tolerance divided by the ray's cosine with the normal (floored at GRAZING_FLOOR):
# at grazing incidence a point's offset from the surface stretches along the ray.
NOISE_TOLERANCE = 3.0
GRAZING_FLOOR = 0.2
# Vertices of the Poisson surface with the lowest support (this quantile of its density) are removed: where the
# template has a gap, Poisson closes it with a membrane no sensor would see, and the membrane would hide real points.
DENSITY_TRIM = 0.02


def sensor_positions(center, diagonal, n, seed, distance=2.0):
    """``n`` sensor positions uniformly distributed in direction around ``center``, ``distance`` diagonals from it.

    Parameters
    ----------
    center : (3,) float array
    diagonal : float > 0
        The template's bounding-box diagonal, in its units.
    n : int >= 0
    seed : int, sequence of int or numpy Generator
    distance : float > 0

    Returns
    -------
    (n, 3) float64 array, in the template's units.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center, dtype=np.float64) + distance * float(diagonal) * d


class TemplateSurface:
    """A surface reconstructed from one complete template cloud, to decide which of its points a sensor returns.

    Screened Poisson reconstruction (open3d, one thread, so the same template gives the same surface), octree depth
    from its point count (:func:`poisson_depth`), its least supported vertices trimmed (``DENSITY_TRIM``). The template's noise, sigma,
    is the robust spread (1.4826 MAD) of the points' signed distances to that surface, in the template's units.

    Parameters
    ----------
    points : (N, 3) float array
        The complete template, N >= 10.
    normals : (N, 3) float array
        Its unit outward normals.
    """

    def __init__(self, points, normals):
        import open3d as o3d

        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape or len(points) < 10:
            raise ValueError(f"a template surface needs (N, 3) points and normals with N >= 10, got {points.shape} "
                             f"and {normals.shape}")
        if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
            raise ValueError("the template has non-finite points or normals")
        if np.count_nonzero(np.ptp(points, axis=0) > 0) < 2:
            raise ValueError("the template's points all lie on one line or point: no surface to see")
        self._offset = points.mean(0)  # the surface and rays in float32 about the template's centre: file units can
        # lie far from 0
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - self._offset))
        pcd.normals = o3d.utility.Vector3dVector(normals)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pcd, depth=poisson_depth(len(points)), n_threads=1)  # one thread: open3d's threaded solve sums in
            # a varying order, so the same template gave views a point apart from run to run
        density = np.asarray(density)
        mesh.remove_vertices_by_mask(density < np.quantile(density, DENSITY_TRIM))
        if len(mesh.triangles) == 0:
            raise ValueError("the template's Poisson surface is empty")
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        signed = self._scene.compute_signed_distance(
            o3d.core.Tensor((points - self._offset).astype(np.float32))).numpy().astype(np.float64)
        self.sigma = float(1.4826 * np.median(np.abs(signed - np.median(signed))))

    def first_hits(self, origin, points):
        """Distance from ``origin`` (3,) along the ray to each of ``points`` (m, 3) to the first surface hit (inf:
        none), and the rays' unit directions (m, 3)."""
        import open3d as o3d

        origin = np.asarray(origin, dtype=np.float64).reshape(3) - self._offset
        d = np.asarray(points, dtype=np.float64) - self._offset - origin
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        rays = np.hstack([np.broadcast_to(origin, u.shape), u]).astype(np.float32)
        return self._scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64), u


def poisson_depth(n_points):
    """Octree depth of the template's Poisson reconstruction: about 4^(depth - 1) points, 6 to 10 (8 for 10,000
    points: cells of about 1/256 of the template's extent)."""
    return int(np.clip(np.round(np.log(max(n_points, 1)) / np.log(4.0)) + 1, 6, 10))


def visible_points(points, normals, origin, surface):
    """Indices of the points of a complete template that a sensor at ``origin`` returns.

    A point is returned when its normal faces the sensor and the ray from the sensor to it meets ``surface`` no
    earlier than ``NOISE_TOLERANCE`` x sigma / max(|cos|, ``GRAZING_FLOOR``) before it (cos: between the ray and
    the point's normal; sigma: the template's noise, :class:`TemplateSurface`).

    Parameters
    ----------
    points, normals : (N, 3) float arrays
        The complete template and its unit outward normals.
    origin : (3,) float array, same units, outside the template
    surface : TemplateSurface
        Reconstructed from ``points`` and ``normals``.

    Returns
    -------
    (M,) int64 array, sorted.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    t_hit, u = surface.first_hits(origin, points)
    distance = np.linalg.norm(points - origin, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", u, normals))
    tolerance = NOISE_TOLERANCE * surface.sigma / np.maximum(cos, GRAZING_FLOOR)
    facing = np.einsum("ij,ij->i", normals, origin - points) > 0
    return np.flatnonzero(facing & (t_hit >= distance - tolerance)).astype(np.int64)


def render_views(name, points, normals, n_train, n_validation, seed=0, distance=2.0):
    """Partial views of one complete template cloud, as scans in the template's units.

    Parameters
    ----------
    name : str
        The template's name (its file stem); views are named ``train/<name>/view_000``, ``validation/<name>/...``.
    points : (N, 3) float array
        The complete template, in its file units.
    normals : (N, 3) float array
        Unit outward normals of the template. A view keeps the visible points whose normal faces its sensor (a depth
        sensor sees the outside of a surface and returns nothing from a back face), so every view's normals face
        its sensor.
    n_train, n_validation : int >= 0
        Views for training (split 'train') and held-back views for calibration (split 'validation', which the
        trainer and the calibration treat as not trained on), from different sensor positions.
    seed : int
        The sensor positions follow from (seed, name): the same seed gives the same views.
    distance : float
        Sensor distance from the template's bounding-box centre, in bounding-box diagonals.

    Returns
    -------
    list of Scan
        Label 'good', ``sensor_origin`` set, points float64 in file units (the collection frame is applied later).

    Raises
    ------
    ValueError
        A view that sees fewer than 3 points (names the template and the view).
    """
    import zlib

    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    lo, hi = points.min(0), points.max(0)
    center, diagonal = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    origins = sensor_positions(center, diagonal, n_train + n_validation, rng, distance)
    try:
        surface = TemplateSurface(points, normals)
    except ValueError as e:
        raise ValueError(f"template {name!r}: {e}") from None
    scans = []
    for k, origin in enumerate(origins):
        split, i = ("train", k) if k < n_train else ("validation", k - n_train)
        idx = visible_points(points, normals, origin, surface)
        if len(idx) < MIN_VIEW_POINTS:
            raise ValueError(f"template {name!r}: view {split} {i} from {origin.tolist()} sees {len(idx)} points")
        p, n = points[idx], normals[idx]
        scan = Scan(name=f"{split}/{name}/view_{i:03d}", points=p, normals=n, split=split, label="good",
                    sensor_origin=origin, extra={"template": name})
        scan.points = p  # keep file-unit precision until the frame is applied (as the importer does)
        scans.append(scan)
    return scans
