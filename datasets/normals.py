"""Normal estimation for clouds that come without normals (range scans, public benchmarks, bare test scans)."""
import logging

import numpy as np

log = logging.getLogger(__name__)

_NEIGHBOURS = 30  # max neighbours of the normal-estimation search
_SPACING_RADIUS = 4.0  # search radius in median nearest-neighbour spacings (~50 neighbours on a uniform surface)
_DECISIVE_COS = 0.3  # |cos(normal, ray to the sensor)| above which the sensor alone decides a normal's sign (~73 deg)
_VOTE_NEIGHBOURS = 12  # neighbours whose orientation decides a grazing normal's sign


def estimate_normals(points, sensor_origin=None, orient=True):
    """Unit normals of a cloud, oriented toward the sensor when known, else consistently and away from the centroid.

    The search is a hybrid KNN/radius search whose radius is a few times the cloud's median nearest-neighbour
    spacing, so it adapts to the scanner's resolution and the file's units.

    Parameters
    ----------
    points : (N, 3) float array, N >= 3, finite
    sensor_origin : (3,) float array, optional
        In the same units as ``points``.
    orient : bool
        False: the tangent planes' normals with arbitrary signs (for losses that ignore the sign, e.g. the
        projection of a scan without normals); ``sensor_origin`` is then ignored.

    Returns
    -------
    (N, 3) float64 array
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    nn = np.asarray(pcd.compute_nearest_neighbor_distance())
    nn = nn[nn > 0]
    spacing = float(np.median(nn)) if len(nn) else 0.0
    if spacing <= 0:  # every point duplicated: fall back to the spacing of a uniform cloud over the bounding box
        spacing = float(np.linalg.norm(np.ptp(pts, axis=0))) / max(len(pts), 1) ** 0.5
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=_SPACING_RADIUS * spacing,
                                                              max_nn=_NEIGHBOURS))
    if not orient:
        return np.asarray(pcd.normals, dtype=np.float64)
    if sensor_origin is not None:
        return _orient_toward_sensor(pts, np.asarray(pcd.normals, dtype=np.float64),
                                     np.asarray(sensor_origin, dtype=np.float64))
    return _orient_consistently(pcd, pts)


def orient_consistently(points, normals):
    """The signs :func:`estimate_normals` gives a cloud without a sensor origin, for normals already estimated.

    The normals are oriented consistently with one another along a minimum spanning tree of the cloud (open3d's
    ``orient_normals_consistent_tangent_plane``), then the global sign that makes most of them point away from the
    cloud's centroid is taken. The result depends on the normals' lines only, not on the signs they come with: the
    propagation keeps only whether neighbours agree, and the global sign is decided afresh (exact ties aside). So two
    copies of a cloud whose normals differ by any per-point signs end the same.

    Parameters
    ----------
    points : (N, 3) float array, N >= 3, finite
    normals : (N, 3) float array
        Unit normals, any signs.

    Returns
    -------
    (N, 3) float64 array
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return _orient_consistently(pcd, pts)


def _orient_consistently(pcd, pts):
    """:func:`orient_consistently` on an open3d cloud ``pcd`` (its normals set) of the points ``pts`` (N, 3)."""
    if len(pts) > 16:
        try:  # propagate one orientation along a minimum spanning tree so neighbours agree...
            pcd.orient_normals_consistent_tangent_plane(15)
        except RuntimeError as e:  # disconnected or degenerate graphs: fall back to per-point centroid test
            log.debug("consistent orientation failed (%s); orienting each normal away from the centroid", e)
            normals = np.asarray(pcd.normals, dtype=np.float64)
            away = np.einsum("ij,ij->i", normals, pts - pts.mean(0)) < 0
            normals[away] *= -1
            return normals
    normals = np.asarray(pcd.normals, dtype=np.float64)
    # ...then pick the global sign that makes most normals point away from the centroid (outward on closed parts)
    if np.count_nonzero(np.einsum("ij,ij->i", normals, pts - pts.mean(0)) < 0) > len(pts) / 2:
        normals = -normals
    return normals


def _orient_toward_sensor(points, normals, origin, decisive=_DECISIVE_COS, k=_VOTE_NEIGHBOURS, rounds=3):
    """Normals signed to face the sensor where the view decides, and like their neighbours where it does not.

    A depth sensor sees the outside of a surface, so every true normal of a scan faces the sensor. open3d's
    ``orient_normals_towards_camera_location`` applies that test to each estimated normal on its own, which is
    right wherever the surface faces the sensor clearly; on a grazing surface the true normal is nearly
    perpendicular to the ray and the noise of a real scan tilts the estimate across it, so the test flips some of
    some of them (on real Cyberware views, docs/results.md). There the sign is taken
    from the neighbours instead: a few rounds of a vote of sum_j (n_i . n_j) over the ``k`` nearest neighbours,
    the decisively oriented ones counted twice.

    Parameters
    ----------
    points, normals : (N, 3) float64 arrays
        Unit normals, any sign.
    origin : (3,) float64 array
        Sensor position, same units as ``points``.
    decisive : float
        |cos| between a normal and the ray to the sensor above which the sensor test alone decides.

    Returns
    -------
    (N, 3) float64 array
    """
    from scipy.spatial import cKDTree

    to_sensor = origin - points
    to_sensor /= np.maximum(np.linalg.norm(to_sensor, axis=1, keepdims=True), 1e-300)
    cos = np.einsum("ij,ij->i", normals, to_sensor)
    normals = np.where((cos < 0)[:, None], -normals, normals)
    unsure = np.flatnonzero(np.abs(cos) < decisive)
    if len(unsure) == 0 or len(points) <= k:
        return normals
    _, nb = cKDTree(points).query(points[unsure], k + 1)
    nb = nb[:, 1:]  # (U, k)
    weight = np.where(np.abs(cos[nb]) >= decisive, 2.0, 1.0)
    for _ in range(rounds):
        vote = np.sum(weight * np.einsum("uj,ukj->uk", normals[unsure], normals[nb]), axis=1)
        flip = unsure[vote < 0]
        if len(flip) == 0:
            break
        normals[flip] *= -1
    return normals
