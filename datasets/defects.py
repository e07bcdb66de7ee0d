"""Defect synthesis: dents, bumps, missing material and foreign objects made on a copy of a part's mesh, and the
defect sites both kinds of synthesis share (:func:`pick_site`, :func:`patch_normal`; defects made in a scan's own
points: :mod:`datasets.point_defects`)."""
from dataclasses import dataclass
from typing import Optional

import numpy as np

from datasets.validation import check_points

DEFECT_KINDS = ("dent", "bump", "missing", "foreign")

# Default sizes, as fractions of the part's bounding-box diagonal. At 4000 points and depth noise of 0.002 x the
# diagonal, a 4-6 % radius covers a few percent of a view's points, and a 2-3 % depth is 10-15 noise deviations at
# the centre, still ~3 over the median labelled point (the smooth profile fades out towards the rim).
RADIUS_RANGE = (0.04, 0.06)
HEIGHT_RANGE = (0.02, 0.03)
FOREIGN_SHAPES = ("sphere", "box", "cylinder")


@dataclass
class Defect:
    """A defective copy of a part and where its defect is.

    Attributes
    ----------
    kind : str
        One of `DEFECT_KINDS`.
    mesh : trimesh.Trimesh
        The defective part, in the original part's coordinates.
    center : (3,) float64 array
        The surface point the defect was made at.
    normal : (3,) float64 array
        Outward unit surface normal there.
    radius : float
        Radius of the affected region, in mesh units.
    height : float
        Displacement depth for dent / bump (mesh units), protrusion of a foreign object, depth of a missing pit.
    changed_faces : (F,) bool array
        Faces of ``mesh`` that are new or moved (the defect's surface), for labelling scan points by triangle id.
    tool : trimesh.Trimesh or None
        The convex solid that was subtracted (missing) or added (foreign).
    """

    kind: str
    mesh: object
    center: np.ndarray
    normal: np.ndarray
    radius: float
    height: float
    changed_faces: np.ndarray
    tool: Optional[object] = None

    def region(self, points, triangle_ids=None):
        """Which points lie on the defect.

        Parameters
        ----------
        points : (n, 3) array
            Points on ``self.mesh``, in its coordinates (noise-free hits label best).
        triangle_ids : (n,) int array, optional
            The faces of ``self.mesh`` the points lie on (a `ScanResult` has them); exact where given.

        Returns
        -------
        (n,) bool array
        """
        points = np.asarray(points, dtype=np.float64)
        if triangle_ids is not None:
            return self.changed_faces[np.asarray(triangle_ids)]
        if self.tool is not None:
            # The defect surface of a boolean lies on the tool's boundary and nothing else of the part lies inside it.
            return _convex_signed_distance(self.tool, points) <= 1e-3 * self.radius
        offset = points - self.center
        along = offset @ self.normal
        # A thin wall's far side lies within the radius too but was not moved: the depth test keeps it out.
        return (np.linalg.norm(offset, axis=1) < self.radius) & (np.abs(along) <= abs(self.height) + 1e-3 * self.radius)

    def seen_through(self, original, sensor, points, step_fraction=0.02):
        """Which points were seen through removed material: the sensor's ray to them crossed the original solid
        where a ``missing`` defect took it away (a hole through a thin wall shows the surfaces behind it).

        Parameters
        ----------
        original : trimesh.Trimesh
            The undamaged part (watertight), in the same coordinates as ``self.mesh``.
        sensor : (3,) or (n, 3) array
            The sensor position, mesh coordinates: one for every point (a pinhole camera), or each point's own ray
            origin (a line scanner, :attr:`datasets.scanner.ScanResult.ray_origins`).
        points : (n, 3) array
            Points the sensor returned from ``self.mesh``, mesh coordinates (noise-free hits label best).
        step_fraction : float
            Spacing of the samples along each ray's chord of the removed ball, as a fraction of its radius.

        Returns
        -------
        (n,) bool array
            All False for other kinds than ``missing``.
        """
        import open3d as o3d

        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(points), dtype=bool)
        if self.kind != "missing" or len(points) == 0:
            return out
        sensor = np.broadcast_to(np.asarray(sensor, dtype=np.float64).reshape(-1, 3), points.shape)
        offset = points - sensor
        length = np.linalg.norm(offset, axis=1)
        d = offset / np.maximum(length, 1e-300)[:, None]
        # the chord of each ray inside the removed ball, clipped to the segment [sensor, point)
        b = np.einsum("ij,ij->i", sensor - self.center, d)  # (n,)
        disc = b ** 2 - (np.sum((sensor - self.center) ** 2, axis=1) - self.radius ** 2)
        crossing = np.flatnonzero(disc > 0)
        root = np.sqrt(disc[crossing])
        t0 = np.maximum(-b[crossing] - root, 0.0)
        t1 = np.minimum(-b[crossing] + root, length[crossing])
        keep = t1 > t0
        crossing, t0, t1 = crossing[keep], t0[keep], t1[keep]
        if len(crossing) == 0:
            return out
        n_steps = int(np.ceil(2.0 / step_fraction)) + 1
        u = (np.arange(n_steps) + 0.5) / n_steps
        t = t0[:, None] + (t1 - t0)[:, None] * u  # (k, S), chord samples strictly inside the segment
        x = sensor[crossing, None, :] + t[..., None] * d[crossing, None, :]
        scene = o3d.t.geometry.RaycastingScene()
        shift = np.asarray(original.vertices, dtype=np.float64).mean(axis=0)  # open3d is float32: work near 0
        scene.add_triangles(o3d.core.Tensor((np.asarray(original.vertices) - shift).astype(np.float32)),
                            o3d.core.Tensor(np.asarray(original.faces, dtype=np.uint32)))
        inside = scene.compute_occupancy(o3d.core.Tensor((x.reshape(-1, 3) - shift).astype(np.float32))).numpy()
        # a ray passing through the removed material ran inside the old solid; the point's own surface (a lining
        # point lies on the ball) is the segment's end, which the open samples leave out
        out[crossing] = (inside.reshape(t.shape) > 0.5).any(axis=1)
        return out


def pick_spot(scan, radius, seed=None, max_normal_deg=25.0, min_facing=0.6):
    """Pick a defect site that a scan sees, away from sharp edges where possible.

    Parameters
    ----------
    scan : ScanResult
        A scan of the undamaged part (noise-free is best).
    radius : float
        Radius of the defect to be made, in mesh units: the site's neighbourhood of that radius should be smooth.
    seed : int, numpy Generator or None
    max_normal_deg : float
        A site qualifies when all the scan normals within ``radius`` are within this angle of its own normal.
    min_facing : float
        ... and the cosine between its normal and the direction to the camera is at least this.

    Returns
    -------
    center : (3,) float64 array
        The site, in the scanned mesh's coordinates.
    normal : (3,) float64 array
        Unit normal there, facing the camera (outward on a closed part seen from outside).
    """
    points = scan.to_mesh_frame(scan.clean_points)
    normals = np.asarray(scan.normals, dtype=np.float64) @ scan.pose[:3, :3]
    eye = scan.to_mesh_frame(scan.sensor_origin[None])[0]
    i = pick_site(points, normals, eye, radius, seed=seed, max_normal_deg=max_normal_deg, min_facing=min_facing)
    return points[i].copy(), normals[i] / np.linalg.norm(normals[i])


def pick_site(points, normals, sensor, radius, seed=None, max_normal_deg=25.0, min_facing=0.6, min_share=0.5):
    """Pick a defect site of a point cloud that a sensor sees well, on a smooth patch where possible.

    Of up to 256 random candidates, one that qualifies is drawn, else the best by flatness, facing and neighbours.

    Parameters
    ----------
    points, normals : (n, 3) arrays
        The cloud and its unit normals facing the sensor, in any frame (the sensor's too).
    sensor : (3,) array
        Where the cloud was seen from.
    radius : float
        Radius of the defect to be made (the points' units): the site's neighbourhood of that radius should be smooth.
    seed : int, numpy Generator or None
    max_normal_deg : float
        A site qualifies when all the normals within ``radius`` are within this angle of its own normal,
    min_facing : float
        ... the cosine between its normal and the direction to the sensor is at least this,
    min_share : float
        ... and it has at least this share of the largest neighbour count within ``radius`` among the candidates:
        sites whose whole disc is seen have the most neighbours, half over a silhouette fewer.

    Returns
    -------
    int
        The row of the site in ``points``.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    points, normals = check_points(points, "pick_site: points"), check_points(normals, "pick_site: normals")
    if len(normals) != len(points) or not float(radius) > 0:
        raise ValueError(f"pick_site: one normal per point and a radius > 0 are needed, got {len(normals)} normals "
                         f"for {len(points)} points and radius {radius!r}")
    to_eye = np.asarray(sensor, dtype=np.float64) - points
    facing = np.sum(normals * to_eye, axis=1) / np.linalg.norm(to_eye, axis=1)
    candidates = rng.permutation(len(points))[:256]
    tree = cKDTree(points)
    flatness = np.empty(len(candidates))
    counts = np.empty(len(candidates))
    for k, (i, near) in enumerate(zip(candidates, tree.query_ball_point(points[candidates], radius))):
        flatness[k] = np.min(normals[near] @ normals[i])
        counts[k] = len(near)
    good = (flatness >= np.cos(np.radians(max_normal_deg))) & (facing[candidates] >= min_facing)
    good &= counts >= min_share * np.max(counts)
    if good.any():
        return int(candidates[rng.choice(np.flatnonzero(good))])
    return int(candidates[np.argmax(flatness + facing[candidates] + counts / np.max(counts))])


def patch_normal(points, normals, center, radius):
    """The unit mean of the normals of the points within ``radius`` of ``center``: a site's normal, less noisy than
    one point's. ``points``, ``normals`` (n, 3), ``center`` (3,) in one frame; (3,) float64."""
    from scipy.spatial import cKDTree

    near = cKDTree(np.asarray(points, dtype=np.float64)).query_ball_point(np.asarray(center, dtype=np.float64),
                                                                          radius)
    n = np.asarray(normals, dtype=np.float64)[near].mean(0) if near else np.zeros(3)
    if not np.linalg.norm(n) > 0:  # no point near, or normals that cancel out
        raise ValueError(f"patch_normal: no normal within {radius!r} of {np.asarray(center).tolist()}")
    return n / np.linalg.norm(n)


def make_defect(mesh, kind, center, normal, radius=None, height=None, shape=None, seed=None, size=1.0):
    """Make one defect on a copy of a mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part (not modified).
    kind : {'dent', 'bump', 'missing', 'foreign'}
    center : (3,) array
        A point on the surface, in mesh coordinates.
    normal : (3,) array
        Outward surface normal at ``center``.
    radius : float, optional
        Radius of the defect as a fraction of the bounding-box diagonal; drawn from `RADIUS_RANGE` when omitted.
        dent / bump: radius of the displaced disc; missing: radius of the spherical pit (its depth too);
        foreign: the added object is about 1.6 x this across.
    height : float, optional
        dent / bump depth as a fraction of the diagonal; drawn from `HEIGHT_RANGE` when omitted.
    shape : {'sphere', 'box', 'cylinder'}, optional
        The foreign object's shape; drawn when omitted.
    seed : int, numpy Generator or None
    size : float > 0
        Both sizes, drawn or given, times this (0.5: defects half as wide and half as deep).

    Returns
    -------
    Defect
    """
    if kind not in DEFECT_KINDS:
        raise ValueError(f"unknown defect kind {kind!r}; expected one of {DEFECT_KINDS}")
    rng = np.random.default_rng(seed)
    diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    # Draw both sizes always so that the stream of draws does not depend on which were given.
    drawn_radius, drawn_height = rng.uniform(*RADIUS_RANGE), rng.uniform(*HEIGHT_RANGE)
    if not float(size) > 0:
        raise ValueError(f"size must be > 0 (a factor on the defect's sizes), got {size!r}")
    radius = (drawn_radius if radius is None else float(radius)) * diagonal * size
    height = (drawn_height if height is None else float(height)) * diagonal * size
    center = np.asarray(center, dtype=np.float64).reshape(3)
    normal = np.asarray(normal, dtype=np.float64).reshape(3)
    normal = normal / np.linalg.norm(normal)
    if kind in ("dent", "bump"):
        return _displace(mesh, kind, center, normal, radius, -height if kind == "dent" else height)
    if kind == "missing":
        return _missing(mesh, center, normal, radius)
    return _foreign(mesh, center, normal, radius, shape or FOREIGN_SHAPES[rng.integers(len(FOREIGN_SHAPES))], rng)


def defect_for_view(mesh, scanner, view, kind, radius=None, height=None, seed=None, fov_deg=40.0, sensor="pinhole",
                    size=1.0):
    """Make a defect at a site that a given camera sees well.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part; ``scanner`` must scan this same mesh.
    scanner : VirtualScanner
    view : View
        The camera (and part pose) the defective part will be scanned with.
    kind, radius, height : see `make_defect`
    seed : int, numpy Generator or None
    fov_deg : float
    sensor : {'pinhole', 'line'}
        The scanner's kind (:meth:`datasets.scanner.VirtualScanner.scan`), for the preview that picks the site.
    size : float > 0
        The defect's sizes times this (:func:`make_defect`).

    Returns
    -------
    Defect
    """
    rng = np.random.default_rng(seed)
    drawn_radius = rng.uniform(*RADIUS_RANGE)
    radius = drawn_radius if radius is None else radius
    preview = scanner.scan(view, fov_deg=fov_deg, n_points=2000, seed=rng, sensor=sensor)
    center, normal = pick_spot(preview, radius * size * scanner.diagonal, seed=rng)
    return make_defect(mesh, kind, center, normal, radius=radius, height=height, seed=rng, size=size)


def _displace(mesh, kind, center, normal, radius, height):
    """Smooth radial displacement (1 - (r/R)^2)^2 * height along ``normal`` on a locally refined copy."""
    import trimesh

    vertices, faces = _refine_near(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), center,
                                   radius, radius / 6.0)
    refined = trimesh.Trimesh(vertices, faces, process=False)
    offset = vertices - center
    distance = np.linalg.norm(offset, axis=1)
    facing = refined.vertex_normals @ normal
    # The surface the spot lies on moves, and so does the far side of a wall thinner than the radius (a dent in a
    # sheet moves the whole sheet, as pressing sheet metal does; moving one side alone would push it through the
    # other). A side wall met at a sharp edge is within the radius too, but its normals point elsewhere: it stays.
    near_side = (distance < radius) & (facing > 0.5)
    far_side = (distance < radius) & (facing < -0.5)
    moving = near_side | far_side
    # the far side follows the profile of the point of the near side opposite it (distance across the sheet)
    lateral = np.linalg.norm(offset - (offset @ normal)[:, None] * normal, axis=1)
    profile = (1.0 - (np.where(far_side, lateral, distance)[moving] / radius) ** 2) ** 2
    vertices = vertices.copy()
    vertices[moving] += (height * profile)[:, None] * normal
    changed = moving[faces].any(axis=1)
    return Defect(kind, trimesh.Trimesh(vertices, faces, process=False), center, normal, radius, height, changed)


def _refine_near(vertices, faces, center, radius, max_edge, max_rounds=16):
    """Split the faces near a ball until their edges are shorter than ``max_edge``, keeping the mesh conforming.

    Faces within ``radius`` (plus their own size) of ``center`` are split 1-to-4 (midpoints of all edges); a
    neighbour with one split edge is split 1-to-2 so no T-junction is left, and one with two or more split edges is
    split 1-to-4 too. A watertight mesh stays watertight.

    Returns
    -------
    vertices : (V', 3) float64 array
    faces : (F', 3) int64 array
    """
    for _ in range(max_rounds):
        corners = vertices[faces]  # (F, 3, 3)
        edge_length = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).max(axis=1)
        near = np.linalg.norm(corners.mean(axis=1) - center, axis=1) - edge_length < 1.1 * radius
        split_faces = near & (edge_length > max_edge)
        if not split_faces.any():
            break
        vertices, faces = _split(vertices, faces, split_faces)
    return vertices, faces


def _split(vertices, faces, red):
    """One round of red-green refinement: (V, 3), (F, 3), (F,) bool -> refined (V', 3), (F', 3)."""
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)  # edge k of a face: (f[k], f[k+1])
    # One int64 key per edge: a 1-D unique is many times faster than a row-wise one.
    keys, edge_id = np.unique(edges[:, 0] * np.int64(len(vertices)) + edges[:, 1], return_inverse=True)
    unique = np.stack(np.divmod(keys, np.int64(len(vertices))), axis=1)
    edge_id = edge_id.reshape(-1, 3)
    red = red.copy()
    split = np.zeros(len(unique), dtype=bool)
    while True:
        split[edge_id[red].ravel()] = True
        closed = red | (split[edge_id].sum(axis=1) >= 2)
        if (closed == red).all():
            break
        red = closed
    midpoint = np.full(len(unique), -1, dtype=np.int64)
    midpoint[split] = len(vertices) + np.arange(split.sum())
    new_vertices = np.concatenate([vertices, (vertices[unique[split, 0]] + vertices[unique[split, 1]]) / 2.0])
    a, b, c = faces[red].T
    ab, bc, ca = midpoint[edge_id[red]].T
    children = [np.stack(f, axis=1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    split_count = split[edge_id].sum(axis=1)
    green = ~red & (split_count == 1)
    for k in range(3):
        these = green & split[edge_id[:, k]]
        f = faces[these]
        m = midpoint[edge_id[these, k]]
        p, q, r = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        children += [np.stack((p, m, r), axis=1), np.stack((m, q, r), axis=1)]
    keep = faces[~red & ~green]
    return new_vertices, np.concatenate([keep, *children]).astype(np.int64)


# --------------------------------------------------------------------------------------------------------------------
# missing material / foreign object (booleans with a convex tool)


def _missing(mesh, center, normal, radius):
    """Remove a ball of material centred on the surface (a pit as deep as ``radius``, a hole through a thin wall)."""
    import trimesh

    tool = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    tool.apply_translation(center)
    result = _boolean(mesh, tool, "difference")
    if result is None:
        # Not a closed solid (or the boolean failed): cut the ball's faces away and line the hole with the half of
        # the ball below the surface, which is what a difference would leave on a locally flat surface.
        vertices, faces = _refine_near(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), center,
                                       radius, radius / 6.0)
        inside = np.linalg.norm(vertices - center, axis=1) < radius
        faces = faces[~inside[faces].all(axis=1)]
        below = (tool.vertices - center) @ normal < 0
        lining = tool.faces[below[tool.faces].all(axis=1)][:, ::-1]  # flipped: the lining faces into the pit
        result = trimesh.Trimesh(np.concatenate([vertices, tool.vertices]),
                                 np.concatenate([faces, lining + len(vertices)]), process=False)
    changed = _convex_signed_distance(tool, result.triangles_center) <= 1e-3 * radius
    return Defect("missing", result, center, normal, radius, radius, changed, tool)


def _foreign(mesh, center, normal, radius, shape, rng):
    """Attach a small convex object (sphere, box or cylinder) to the surface, partly sunk into it."""
    import trimesh

    # About 1.6 x the defect radius across (8 % of the diagonal by default): a smaller object, seen from one side,
    # covers too few of a scan's points to be told from noise.
    if shape == "sphere":
        tool = trimesh.creation.icosphere(subdivisions=3, radius=0.8 * radius)
        sink = 0.4 * radius
    elif shape == "box":
        tool = trimesh.creation.box(extents=(1.6 * radius, 1.3 * radius, 1.3 * radius))
        sink = 0.35 * radius
    elif shape == "cylinder":
        tool = trimesh.creation.cylinder(radius=0.65 * radius, height=1.8 * radius, sections=32)
        sink = 0.45 * radius
    else:
        raise ValueError(f"unknown foreign object shape {shape!r}; expected one of {FOREIGN_SHAPES}")
    # Local z along the normal, a random turn about it, then the object's centre so its bottom sinks in by `sink`.
    turn = trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 0, 1])
    tool.apply_transform(turn)
    tool.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], normal))
    bottom = -np.min(tool.vertices @ normal)
    tool.apply_translation(center + normal * (bottom - sink))
    height = float(np.max((tool.vertices - center) @ normal))
    result = _boolean(mesh, tool, "union")
    if result is None:
        # The part is not a closed solid: the object simply overlaps it, which a scanner cannot tell apart.
        result = trimesh.Trimesh(np.concatenate([mesh.vertices, tool.vertices]),
                                 np.concatenate([mesh.faces, tool.faces + len(mesh.vertices)]), process=False)
    changed = _convex_signed_distance(tool, result.triangles_center) <= 1e-3 * radius
    return Defect("foreign", result, center, normal, radius, height, changed, tool)


def _boolean(mesh, tool, operation):
    """manifold3d boolean of a watertight mesh with a tool; None when the mesh is not a closed solid or it fails."""
    import trimesh

    if not mesh.is_watertight:
        return None
    try:
        result = getattr(trimesh.boolean, operation)([mesh, tool], engine="manifold")
    except Exception:  # manifold3d reports invalid input in several ways
        return None
    if result is None or len(result.faces) == 0 or not result.is_watertight:
        return None
    return result


def _convex_signed_distance(tool, points):
    """A signed distance of (n, 3) points to a convex mesh, -> (n,) float64: <= 0 inside or on it, > 0 outside.

    Inside it is the largest signed distance to the face planes (exact); outside it is a lower bound of the Euclidean
    distance, which is all the inside / on-the-surface test of labelling needs.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(tool.face_normals, dtype=np.float64)
    offsets = np.sum(normals * tool.triangles_center, axis=1)
    # Points beyond the tool's bounding sphere are outside: their distance to it is a lower bound and enough.
    middle = tool.vertices.mean(axis=0)
    reach = np.linalg.norm(tool.vertices - middle, axis=1).max()
    distance = np.linalg.norm(points - middle, axis=1) - reach
    near = np.flatnonzero(distance <= 0)
    distance[near] = np.max(points[near] @ normals.T - offsets, axis=1)
    return distance
