"""Parts to scan: the built-in parts generated in code (a solid bracket, thin-walled and open parts) and CAD meshes."""
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off")


def builtin_part(hole_shift=0.0):
    """A flanged bracket in millimetres, watertight and deterministic.

    A base plate (80 x 50 x 8) with four bolt holes, an upright web at one end, two triangular ribs bracing it, and a
    boss with a bore through the web; built from trimesh primitives with manifold3d booleans.

    Parameters
    ----------
    hole_shift : float
        The bolt holes (radius 4, centres at y = +-16) moved this many mm towards the plate's mid-line y = 0
        (negative: towards its edges): a product family whose holes lie in different places. Within -4.5 .. 11.5
        the holes stay clear of the plate's edges and of each other.

    Returns
    -------
    trimesh.Trimesh
        About 2k faces, bounding box roughly [-40, 40] x [-25, 25] x [0, 53].
    """
    import trimesh
    from trimesh.creation import box, cylinder

    hole_shift = float(hole_shift)
    if not -4.5 <= hole_shift <= 11.5:
        raise ValueError(f"builtin_part: hole_shift must lie in [-4.5, 11.5] mm (the holes inside the plate, apart), "
                         f"got {hole_shift}")

    def moved(mesh, offset):
        mesh.apply_translation(offset)
        return mesh

    def x_cylinder(radius, length, center, sections=64):
        mesh = cylinder(radius=radius, height=length, sections=sections)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        return moved(mesh, center)

    plate = moved(box(extents=(80.0, 50.0, 8.0)), (0.0, 0.0, 4.0))
    web = moved(box(extents=(10.0, 50.0, 45.0)), (-30.0, 0.0, 8.0 + 22.5))
    ribs = []
    for y in (-17.0, 17.0):
        # A triangular prism in the x-z plane, 6 mm thick, from the web's face down to the plate.
        corners = np.array([[-25.5, 0, 7.5], [-25.5, 0, 40.0], [5.0, 0, 7.5]])
        prism = np.concatenate([corners + (0, y - 3.0, 0), corners + (0, y + 3.0, 0)])
        ribs.append(trimesh.convex.convex_hull(prism))
    boss = x_cylinder(12.0, 22.0, (-24.0, 0.0, 38.0))
    solid = trimesh.boolean.union([plate, web, boss, *ribs], engine="manifold")
    holes = [moved(cylinder(radius=4.0, height=12.0, sections=32), (x, y, 4.0))
             for x in (17.0, 31.0) for y in (-16.0 + hole_shift, 16.0 - hole_shift)]
    bore = x_cylinder(6.0, 40.0, (-24.0, 0.0, 38.0))
    part = trimesh.boolean.difference([solid, *holes, bore], engine="manifold")
    part.merge_vertices()
    if not part.is_watertight:
        raise RuntimeError("builtin_part: the boolean result is not watertight (manifold3d changed behaviour?)")
    return part


def sheet_enclosure(size=(100.0, 70.0, 50.0), wall=1.5, hole_shift=0.0):
    """A sheet-metal enclosure cover in millimetres: a thin-walled box open at the bottom, with openings in its walls.

    The top has a rectangular vent (40 x 16) and a round hole (diameter 14); the two long side walls each have a
    rectangular cut-out (30 x 12), one short wall a round hole (diameter 18). Scans see the outside of the sheet, and
    its inside through the openings and the open bottom: the case a hole through the sheet looks like.

    Parameters
    ----------
    size : (3,) floats
        Outer extents (x, y, z) in mm.
    wall : float
        Sheet thickness in mm (walls and top alike).
    hole_shift : float
        The top's round hole (centre (28, -18)) moved this many mm along x (negative: towards the vent): a family
        whose hole lies in different places. Within -20 .. 12 it stays clear of the vent and the top's edges.

    Returns
    -------
    trimesh.Trimesh
        Watertight and deterministic; bounding box [-size/2, size/2] in x, y and [0, size z] in z.
    """
    import trimesh
    from trimesh.creation import box, cylinder

    sx, sy, sz = (float(s) for s in size)
    hole_shift = float(hole_shift)
    if not -20.0 <= hole_shift <= 12.0:
        raise ValueError(f"sheet_enclosure: hole_shift must lie in [-20, 12] mm (clear of the vent and the edges), "
                         f"got {hole_shift}")
    outer = box(extents=(sx, sy, sz), transform=_translation((0.0, 0.0, sz / 2)))
    # the cavity overshoots the bottom so the cover is open there
    inner = box(extents=(sx - 2 * wall, sy - 2 * wall, sz), transform=_translation((0.0, 0.0, sz / 2 - wall)))
    depth = 4.0 * wall  # cutting tools pass through the sheet with room to spare
    tools = [
        box(extents=(40.0, 16.0, depth), transform=_translation((-15.0, 10.0, sz - wall / 2))),
        cylinder(radius=7.0, height=depth, sections=48,
                 transform=_translation((28.0 + hole_shift, -18.0, sz - wall / 2))),
        box(extents=(30.0, depth, 12.0), transform=_translation((-12.0, sy / 2 - wall / 2, sz / 2))),
        box(extents=(30.0, depth, 12.0), transform=_translation((18.0, -sy / 2 + wall / 2, sz / 2 + 6.0))),
        cylinder(radius=9.0, height=depth, sections=48,
                 transform=_translation((sx / 2 - wall / 2, 0.0, sz / 2)) @ _rotation_to_x()),
    ]
    part = trimesh.boolean.difference([outer, inner, *tools], engine="manifold")
    return _checked(part, "sheet_enclosure")


def open_cup(radius=40.0, height=70.0, wall=1.5, sections=96):
    """A thin open cup in millimetres: a cylindrical wall on a hemispherical bottom, open at the top.

    A curved sheet ``wall`` thick everywhere, seen from outside and, from above, through its opening.

    Parameters
    ----------
    radius : float
        Outer radius in mm.
    height : float
        Overall height in mm (bottom of the hemisphere to the rim); must exceed ``radius``.
    wall : float
        Sheet thickness in mm.
    sections : int
        Facets around the axis.

    Returns
    -------
    trimesh.Trimesh
        Watertight and deterministic; bounding box about [-radius, radius]^2 x [0, height] (the facets lie inside
        the circle of ``radius``).
    """
    import trimesh
    from trimesh.creation import capsule

    radius, height, wall = float(radius), float(height), float(wall)
    if not height > radius > wall > 0:
        raise ValueError(f"open_cup needs height > radius > wall > 0, got {height}, {radius}, {wall}")
    # a capsule's cylinder runs from -length/2 to +length/2 with hemispheres beyond; this one's bottom pole is at 0
    length = 2.0 * (height - radius)
    count = [sections, sections // 2]
    outer = capsule(height=length, radius=radius, count=count, transform=_translation((0, 0, radius + length / 2)))
    inner = capsule(height=length, radius=radius - wall, count=count,
                    transform=_translation((0, 0, radius + length / 2)))
    cut = trimesh.creation.box(extents=(4 * radius, 4 * radius, 2 * radius),
                               transform=_translation((0, 0, height + radius)))
    part = trimesh.boolean.difference([outer, inner, cut], engine="manifold")
    return _checked(part, "open_cup")


def _translation(offset):
    matrix = np.eye(4)
    matrix[:3, 3] = offset
    return matrix


def _rotation_to_x():
    """(4, 4) rotation taking the z axis (trimesh's cylinder axis) to the x axis."""
    import trimesh

    return trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])


def _checked(part, name):
    part.merge_vertices()
    if not part.is_watertight or part.volume <= 0:
        raise RuntimeError(f"{name}: the boolean result is not a watertight solid (manifold3d changed behaviour?)")
    return part


BUILTIN_PARTS = {"builtin": builtin_part, "enclosure": sheet_enclosure, "cup": open_cup}


def load_part(path):
    """Load a part's triangle mesh from an OBJ / STL / PLY / OFF file, or a built-in part by name.

    Parameters
    ----------
    path : str or Path
        A mesh file, or the name of a built-in part (a key of `BUILTIN_PARTS`): ``"builtin"`` (`builtin_part`, the
        solid bracket), ``"enclosure"`` (`sheet_enclosure`), ``"cup"`` (`open_cup`).

    Returns
    -------
    trimesh.Trimesh

    Raises
    ------
    ValueError
        Naming the file, when it does not exist, has an unknown extension, cannot be read, or holds no triangles
        (an empty file, a point cloud).
    """
    if isinstance(path, str) and path in BUILTIN_PARTS:
        return BUILTIN_PARTS[path]()
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file {str(path)!r} not found (nor is it a built-in part: {sorted(BUILTIN_PARTS)})")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"mesh file {str(path)!r}: unknown extension {suffix!r} (expected one of {MESH_SUFFIXES})")
    if path.stat().st_size == 0:
        raise ValueError(f"mesh file {str(path)!r} is empty")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as error:  # trimesh raises many types for malformed files
        raise ValueError(f"mesh file {str(path)!r} could not be read as a mesh: {error}") from error
    faces = getattr(mesh, "faces", None)
    if not isinstance(mesh, trimesh.Trimesh) or faces is None or len(faces) == 0:
        raise ValueError(f"mesh file {str(path)!r} holds no triangles (a point cloud or an empty mesh?)")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"mesh file {str(path)!r} has non-finite vertex coordinates")
    return mesh
