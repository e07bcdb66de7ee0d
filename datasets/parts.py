"""Parts to scan: the built-in mechanical part generated in code, and loading a CAD mesh from a file."""
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off")


def builtin_part():
    """A flanged bracket in millimetres, watertight and deterministic.

    A base plate (80 x 50 x 8) with four bolt holes, an upright web at one end, two triangular ribs bracing it, and a
    boss with a bore through the web; built from trimesh primitives with manifold3d booleans.

    Returns
    -------
    trimesh.Trimesh
        About 2k faces, bounding box roughly [-40, 40] x [-25, 25] x [0, 53].
    """
    import trimesh
    from trimesh.creation import box, cylinder

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
             for x in (17.0, 31.0) for y in (-16.0, 16.0)]
    bore = x_cylinder(6.0, 40.0, (-24.0, 0.0, 38.0))
    part = trimesh.boolean.difference([solid, *holes, bore], engine="manifold")
    part.merge_vertices()
    if not part.is_watertight:
        raise RuntimeError("builtin_part: the boolean result is not watertight (manifold3d changed behaviour?)")
    return part


def load_part(path):
    """Load a part's triangle mesh from an OBJ / STL / PLY / OFF file, or the built-in part.

    Parameters
    ----------
    path : str or Path
        A mesh file, or the string ``"builtin"`` for `builtin_part`.

    Returns
    -------
    trimesh.Trimesh

    Raises
    ------
    ValueError
        Naming the file, when it does not exist, has an unknown extension, cannot be read, or holds no triangles
        (an empty file, a point cloud).
    """
    if isinstance(path, str) and path == "builtin":
        return builtin_part()
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file {str(path)!r} not found")
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
