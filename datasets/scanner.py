"""Virtual depth scanning over a triangle mesh (open3d RaycastingScene): a pinhole depth camera, or a line (profile)
scanner that sweeps a laser fan across the part.

The two sensors differ in where their rays start, which is what the inspection's free-space test along the sensor's
rays must live with: a pinhole camera's rays all leave one centre (the ``sensor_origin``); a line scanner's leave a
head that moves along a sweep, so its rays are parallel along the sweep and fan out only across it, and it has no
single centre (its ``sensor_origin`` is the head's position at mid-sweep, which is what a user writes in a sidecar:
the view's axis and a stand-off). ``ScanResult.ray_origins`` holds each point's true ray origin either way.
"""
from dataclasses import dataclass

import numpy as np

SENSORS = ("pinhole", "line")
# Below this many rays the scanner never goes, above this it stops raising the resolution and samples with
# replacement instead (a part that small in the image is a badly chosen view, not a reason to cast 100M rays).
_MIN_RAYS = 64 * 48
_MAX_RAYS = 4096 * 4096


@dataclass
class ScanResult:
    """One depth-camera scan of a mesh.

    All positions are in the world frame: the mesh's own coordinates moved by ``pose`` (identity without jitter).

    Attributes
    ----------
    points : (n, 3) float32 array
        Measured points, with the depth noise applied along each ray.
    normals : (n, 3) float32 array
        Unit normals of the hit triangles, flipped to face the camera.
    triangle_ids : (n,) int64 array
        Index of the hit triangle in the scanned mesh's ``faces``.
    sensor_origin : (3,) float64 array
        Camera position (a line scanner: its head at mid-sweep).
    clean_points : (n, 3) float64 array
        The exact ray hits before noise (ground truth for labelling and tests).
    pose : (4, 4) float64 array
        Rigid transform that was applied to the mesh before scanning (mesh coordinates -> world).
    ray_origins : (n, 3) float64 array
        Where each point's ray started (a pinhole camera: ``sensor_origin`` for every point; a line scanner: the
        head's position when it saw the point).
    """

    points: np.ndarray
    normals: np.ndarray
    triangle_ids: np.ndarray
    sensor_origin: np.ndarray
    clean_points: np.ndarray
    pose: np.ndarray
    ray_origins: np.ndarray = None

    def to_mesh_frame(self, x):
        """(m, 3) world-frame positions -> (m, 3) positions in the scanned mesh's own coordinates."""
        rotation, translation = self.pose[:3, :3], self.pose[:3, 3]
        return (np.asarray(x, dtype=np.float64) - translation) @ rotation


@dataclass
class View:
    """A camera placement plus the pose of the part in front of it.

    Attributes
    ----------
    camera_position : (3,) float64 array
    look_at : (3,) float64 array
    pose : (4, 4) float64 array
        Rigid transform applied to the part before scanning (identity when there is no jitter).
    """

    camera_position: np.ndarray
    look_at: np.ndarray
    pose: np.ndarray


def random_view(center, radius_range, elevation_range_deg=(-20.0, 70.0), size=1.0, jitter_deg=0.0,
                jitter_translation=0.0, seed=None):
    """Draw a camera position on a spherical shell around a part, looking at its centre, and a random part pose.

    Parameters
    ----------
    center : (3,) array
        Centre of the part (the camera looks at it).
    radius_range : (2,) floats
        Camera distance from ``center``, in multiples of ``size`` (drawn uniformly).
    elevation_range_deg : (2,) floats
        Elevation above the x-y plane in degrees (drawn uniformly in sin(elevation), i.e. uniform on the sphere band);
        the azimuth is uniform.
    size : float
        Length scale of the part (the scanner passes its bounding-box diagonal), so that one ``radius_range``
        works for parts of any size and units.
    jitter_deg : float
        Maximum rotation of the part about its centre, about a uniformly random axis (0 = part held in a fixture).
    jitter_translation : float
        Maximum translation of the part along each axis, as a fraction of ``size``.
    seed : int, numpy Generator or None

    Returns
    -------
    View
    """
    rng = np.random.default_rng(seed)
    center = np.asarray(center, dtype=np.float64).reshape(3)
    lo, hi = np.sin(np.radians(np.asarray(elevation_range_deg, dtype=np.float64)))
    sin_el = rng.uniform(lo, hi)
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    radius = rng.uniform(*radius_range) * size
    cos_el = np.sqrt(max(0.0, 1.0 - sin_el ** 2))
    direction = np.array([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), sin_el])
    # Draw the jitter even when it is zero so that a view's camera does not depend on whether jitter is on.
    axis = rng.normal(size=3)
    angle = np.radians(jitter_deg) * rng.uniform(-1.0, 1.0)
    shift = jitter_translation * size * rng.uniform(-1.0, 1.0, size=3)
    pose = np.eye(4)
    if jitter_deg > 0 or jitter_translation > 0:
        rotation = _axis_angle(axis / np.linalg.norm(axis), angle)
        pose[:3, :3] = rotation
        # Rotate about the part's centre, then shift.
        pose[:3, 3] = center - rotation @ center + shift
    return View(center + radius * direction, center.copy(), pose)


def written_origin(origin, center, standoff=(1.0, 1.0), tilt_deg=0.0, seed=None):
    """The sensor origin as a user writes it in a sidecar, not where the sensor was: the view's axis and a nominal
    stand-off, not a calibrated optical centre.

    Parameters
    ----------
    origin : (3,) array
        Where the sensor was (a line scanner: its head at mid-sweep).
    center : (3,) array
        The point the view looks at (the part's centre), same frame.
    standoff : (2,) floats
        The written stand-off is the true one times a factor drawn log-uniformly in this range (1, 1: exact).
    tilt_deg : float
        The written axis is the true one turned by an angle drawn uniformly in [0, tilt_deg] about a random axis
        across it.
    seed : int, numpy Generator or None

    Returns
    -------
    (3,) float64 array
    """
    rng = np.random.default_rng(seed)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    center = np.asarray(center, dtype=np.float64).reshape(3)
    low, high = np.log(np.asarray(standoff, dtype=np.float64))
    factor = float(np.exp(rng.uniform(low, high)))
    axis = origin - center
    across = np.cross(axis, rng.normal(size=3))
    turn = _axis_angle(across / np.linalg.norm(across), np.radians(tilt_deg) * rng.uniform(0.0, 1.0))
    return center + factor * (turn @ axis)


def _axis_angle(axis, angle):
    """(3,) unit axis, angle in radians -> (3, 3) rotation matrix (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


class VirtualScanner:
    """A depth camera over one triangle mesh; the ray-casting scene is built once and reused for every scan.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, in its own units. It need not be watertight.
    """

    def __init__(self, mesh):
        import open3d as o3d

        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if len(faces) == 0:
            raise ValueError("VirtualScanner: the mesh has no faces")
        lower, upper = vertices.min(axis=0), vertices.max(axis=0)
        self.mesh = mesh
        self.center = (lower + upper) / 2.0
        self.diagonal = float(np.linalg.norm(upper - lower))
        # open3d casts in float32: shift the mesh to its box centre so parts far from the origin (CAD coordinates in
        # mm) keep their precision; hits are shifted back in float64.
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor((vertices - self.center).astype(np.float32)),
                                  o3d.core.Tensor(faces.astype(np.uint32)))

    def random_view(self, radius_range=(1.5, 2.2), elevation_range_deg=(-20.0, 70.0), jitter_deg=0.0,
                    jitter_translation=0.0, seed=None):
        """`random_view` around this mesh's box centre, with distances in multiples of its box diagonal."""
        return random_view(self.center, radius_range, elevation_range_deg, size=self.diagonal, jitter_deg=jitter_deg,
                           jitter_translation=jitter_translation, seed=seed)

    def scan(self, camera_position, look_at=None, fov_deg=40.0, resolution=None, noise=0.0, n_points=4000,
             pose=None, seed=None, sensor="pinhole", grazing_dropout=0.0, ragged=0.0):
        """Scan the mesh from one camera position.

        Parameters
        ----------
        camera_position : (3,) array or View
            Camera position in the world frame; a `View` also supplies ``look_at`` and ``pose``.
        look_at : (3,) array, optional
            Point the optical axis goes through; defaults to the mesh's box centre.
        fov_deg : float
            Horizontal field of view of the pinhole camera; a line scanner's fan angle.
        resolution : (W, H) ints, optional
            Image size. Raised automatically (same aspect) when the part covers fewer than ``n_points`` pixels;
            by default it starts at 4:3 with about ``6 * n_points`` pixels. A line scanner: W rays per line, H
            lines over the sweep.
        noise : float
            Standard deviation of the Gaussian depth noise, in mesh units, applied along each ray.
        n_points : int
            Exact number of points returned (a seeded subset of the hit pixels).
        pose : (4, 4) array, optional
            Rigid transform applied to the mesh before scanning (mesh coordinates -> world).
        seed : int, numpy Generator or None
        sensor : {'pinhole', 'line'}
            'pinhole': every ray leaves ``camera_position``. 'line': a profile scanner whose head moves along a sweep
            through ``camera_position``, perpendicular to the optical axis and to the fan, over the part's whole
            extent (its diagonal); each line is a fan of ``fov_deg`` from the head's position at that moment, so the
            rays are parallel along the sweep (:func:`_line_rays`).
        grazing_dropout : float >= 0
            Returns lost at grazing incidence, as a sensor whose return weakens with the angle loses them: a hit at
            incidence angle theta (between its ray and the surface normal) is kept with probability
            ``cos(theta) ** grazing_dropout`` (1: a Lambertian return, 1/2 kept at 60 degrees; 2: 1/4 kept there).
            0 (the default): every hit kept, the scan exactly as without this option.
        ragged : float >= 0
            Ragged borders, in mesh units: the scan's borders (hits next to a missed ray: the silhouette; or across a
            depth discontinuity: an occluding edge and the surface it hides) eaten back by up to this distance, as
            real sensors lose returns there. The depth of the bite varies along the border: border stretches about
            ``2 * ragged`` long each draw a depth uniform in [0, ``ragged``] (:func:`_ragged_keep`). The edges of the
            field of view are not borders (a crop stays straight). 0 (the default): no hit lost.

        The returned points are an exact ``n_points`` drawn from the hits these two options keep (the resolution is
        raised until enough are kept), so they change where the points lie, not how many there are. Either option
        draws one number from the scan's generator before the points are chosen; at 0 none is drawn.

        Returns
        -------
        ScanResult

        Raises
        ------
        ValueError
            When no ray hits the part (or none is kept), an unknown ``sensor``, or a negative ``grazing_dropout`` or
            ``ragged``.
        """
        if sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {SENSORS}, got {sensor!r}")
        if not 0 <= grazing_dropout < np.inf:
            raise ValueError(f"grazing_dropout must be >= 0 (an exponent on the cosine of incidence), got "
                             f"{grazing_dropout!r}")
        if not 0 <= ragged < np.inf:
            raise ValueError(f"ragged must be >= 0 (a distance in mesh units), got {ragged!r}")
        if isinstance(camera_position, View):
            view = camera_position
            camera_position, look_at, pose = view.camera_position, view.look_at, view.pose
        rng = np.random.default_rng(seed)
        n_points = int(n_points)
        if n_points < 1:
            raise ValueError(f"n_points must be >= 1, got {n_points}")
        pose = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
        rotation, translation = pose[:3, :3], pose[:3, 3]
        eye_world = np.asarray(camera_position, dtype=np.float64).reshape(3)
        target_world = self.center if look_at is None else np.asarray(look_at, dtype=np.float64).reshape(3)
        # Moving the part by the pose is the same as moving the camera by its inverse: cast in the mesh's frame so the
        # scene is never rebuilt, then carry the hits forward.
        eye = (eye_world - translation) @ rotation
        target = (target_world - translation) @ rotation
        if resolution is None:
            height = int(np.ceil(np.sqrt(6.0 * n_points * 3.0 / 4.0)))
            resolution = (int(np.ceil(height * 4.0 / 3.0)), height)
        width, height = (max(2, int(r)) for r in resolution)
        # the losses' own draws: one seed from the scan's generator, a generator of their own at each resolution
        losses = grazing_dropout > 0 or ragged > 0
        loss_seed = int(rng.integers(2 ** 63)) if losses else None
        while True:
            if sensor == "pinhole":
                directions = _pinhole_directions(eye, target, fov_deg, width, height)
                origins = np.broadcast_to(eye, directions.shape)
            else:
                origins, directions = _line_rays(eye, target, fov_deg, width, height, self.diagonal)
            t_hit, ray_index, triangle_ids, normals = self._cast(origins, directions)
            if losses and len(t_hit):
                keep = _lost_returns(origins, directions, t_hit, ray_index, normals, width, height, grazing_dropout,
                                     ragged, np.random.default_rng(loss_seed))
                t_hit, ray_index, triangle_ids, normals = (a[keep] for a in (t_hit, ray_index, triangle_ids, normals))
            n_hits = len(t_hit)
            if n_hits == 0:
                raise ValueError(f"the part is not visible from camera position {eye_world.tolist()} "
                                 f"looking at {target_world.tolist()} (fov {fov_deg} deg)"
                                 + (" once grazing and border returns are lost" if losses else ""))
            if n_hits >= n_points or width * height >= _MAX_RAYS:
                break
            # Hits grow with the pixel count: aim 20% above what is needed.
            factor = np.sqrt(1.2 * n_points / n_hits)
            factor = min(factor, np.sqrt(_MAX_RAYS / (width * height)))
            width, height = int(np.ceil(width * factor)) + 1, int(np.ceil(height * factor)) + 1
        hit_directions, hit_origins = directions[ray_index], origins[ray_index]
        # Subset first, noise second, so that the same seed picks the same pixels with or without noise.
        chosen = np.sort(rng.choice(n_hits, size=n_points, replace=n_hits < n_points))
        t, d, tri, nrm = t_hit[chosen], hit_directions[chosen], triangle_ids[chosen], normals[chosen]
        start = hit_origins[chosen]
        clean = start + t[:, None] * d
        depth_noise = rng.normal(0.0, noise, size=n_points) if noise > 0 else np.zeros(n_points)
        noisy = clean + depth_noise[:, None] * d
        # Flip triangle normals that point away from the camera (back-facing hits, inconsistent winding).
        nrm = np.where((np.sum(nrm * d, axis=1) > 0)[:, None], -nrm, nrm)
        return ScanResult(
            points=(noisy @ rotation.T + translation).astype(np.float32),
            normals=(nrm @ rotation.T).astype(np.float32),
            triangle_ids=tri.astype(np.int64),
            sensor_origin=eye_world.copy(),
            clean_points=clean @ rotation.T + translation,
            pose=pose.copy(),
            ray_origins=start @ rotation.T + translation,
        )

    def _cast(self, origins, directions):
        """Cast rays from ``origins`` ((3,) or (k, 3), mesh frame) along ``directions`` (k, 3); per hit: t (h,), ray
        index (h,), triangle id (h,), unit normal (h, 3)."""
        import open3d as o3d

        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origins - self.center
        rays[:, 3:] = directions
        hit = self._scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy()
        index = np.flatnonzero(np.isfinite(t))
        normals = hit["primitive_normals"].numpy()[index].astype(np.float64)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
        return t[index].astype(np.float64), index, hit["primitive_ids"].numpy()[index].astype(np.int64), normals


# two neighbouring hits of the ray grid lie across a depth discontinuity when they are farther apart than this many
# times the median distance between neighbours along that grid axis (a surface steeper than about 83 degrees to the
# rays, or an occluding edge)
_DEPTH_JUMP = 8.0


def _lost_returns(origins, directions, t_hit, ray_index, normals, width, height, grazing_dropout, ragged, rng):
    """Which hits a real sensor returns (:meth:`VirtualScanner.scan`'s ``grazing_dropout`` and ``ragged``).

    Parameters
    ----------
    origins, directions : (k, 3) arrays
        The rays of a ``height`` x ``width`` grid (k = width * height), row-major, mesh frame.
    t_hit, ray_index : (h,) arrays
        The hits: distance along the ray, index of the ray.
    normals : (h, 3) array
        Unit normals of the hit triangles.
    width, height : int
    grazing_dropout, ragged : float
    rng : numpy Generator

    Returns
    -------
    (h,) bool array
        True for a hit that is returned.
    """
    keep = np.ones(len(t_hit), dtype=bool)
    d = directions[ray_index]
    if grazing_dropout > 0:
        cosine = np.abs(np.sum(normals * d, axis=1))
        keep &= rng.uniform(size=len(t_hit)) < cosine ** grazing_dropout
    if ragged > 0:
        points = origins[ray_index] + t_hit[:, None] * d
        keep &= _ragged_keep(points, ray_index, width, height, ragged, rng)
    return keep


def _ragged_keep(points, ray_index, width, height, ragged, rng):
    """Hits kept by ragged borders: (h,) bool, False within the bite of the border nearest to the hit.

    Border hits are those of the ``height`` x ``width`` ray grid next to a ray that missed (a silhouette) or across a
    depth discontinuity (:data:`_DEPTH_JUMP`). The border is cut into stretches: the border hits are binned into cubes
    of side ``2 * ragged`` and one of each cube's hits, drawn at random, is its stretch's centre; each border hit
    belongs to its nearest centre's stretch and each stretch draws a bite depth uniform in [0, ``ragged``]. A hit
    whose distance to its nearest border hit is below that border hit's bite is lost.
    """
    from scipy.spatial import cKDTree

    grid = np.full(width * height, -1, dtype=np.int64)
    grid[ray_index] = np.arange(len(ray_index))
    grid = grid.reshape(height, width)
    border = np.zeros(len(ray_index), dtype=bool)
    for a, b in ((grid[:, :-1], grid[:, 1:]), (grid[:-1, :], grid[1:, :])):  # neighbours across, then down
        a, b = a.ravel(), b.ravel()
        one = (a >= 0) != (b >= 0)  # one of the two rays missed: the hit one is on the silhouette
        border[a[one & (a >= 0)]] = True
        border[b[one & (b >= 0)]] = True
        both = (a >= 0) & (b >= 0)
        if both.any():
            gap = np.linalg.norm(points[a[both]] - points[b[both]], axis=1)
            jump = gap > _DEPTH_JUMP * np.median(gap)
            border[a[both][jump]] = True
            border[b[both][jump]] = True
    if not border.any():
        return np.ones(len(ray_index), dtype=bool)
    edge = points[border]
    cells = np.floor(edge / (2.0 * ragged)).astype(np.int64)
    order = rng.permutation(len(edge))
    _, first = np.unique(cells[order], axis=0, return_index=True)
    centres = order[np.sort(first)]
    depth = rng.uniform(0.0, ragged, size=len(centres))
    bite = depth[cKDTree(edge[centres]).query(edge)[1]]  # (b,) each border hit's stretch's depth
    distance, nearest = cKDTree(edge).query(points)
    return distance >= bite[nearest]


def _camera_axes(eye, target):
    """Unit forward, right and up vectors (3,) each of a camera at ``eye`` looking at ``target``."""
    forward = target - eye
    norm = np.linalg.norm(forward)
    if norm == 0:
        raise ValueError("camera position and look_at coincide")
    forward = forward / norm
    # Any up vector not parallel to the optical axis will do: the image is only used as a set of rays.
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def _line_rays(eye, target, fov_deg, width, height, extent):
    """Ray origins and unit directions (width*height, 3) each of a line scanner: ``height`` lines, the head moved
    along the camera's up axis from ``eye`` - extent/2 to ``eye`` + extent/2, each line a fan of ``width`` rays over
    ``fov_deg`` in the plane of the optical axis and the right axis."""
    forward, right, up = _camera_axes(eye, target)
    half = np.tan(np.radians(fov_deg) / 2.0)
    u = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * half
    sweep = ((np.arange(height) + 0.5) / height - 0.5) * extent
    uu, ss = np.meshgrid(u, sweep)
    directions = forward + uu.reshape(-1, 1) * right
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return eye + ss.reshape(-1, 1) * up, directions


def _pinhole_directions(eye, target, fov_deg, width, height):
    """Unit ray directions (width*height, 3) of a pinhole camera at ``eye`` looking at ``target``, row-major."""
    forward, right, up = _camera_axes(eye, target)
    half_w = np.tan(np.radians(fov_deg) / 2.0)
    half_h = half_w * height / width
    u = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * half_w
    v = ((np.arange(height) + 0.5) / height * 2.0 - 1.0) * half_h
    uu, vv = np.meshgrid(u, v)
    directions = forward + uu.reshape(-1, 1) * right - vv.reshape(-1, 1) * up
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)
