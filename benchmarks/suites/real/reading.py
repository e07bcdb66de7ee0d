"""The Stanford range data: a scanalyze ``.conf`` and its range-grid PLY views, read and aligned into one frame.

The range grid's conventions, worked out from the data (:func:`check_views` prints them when the tree is built):
``bun.conf`` line ``bmesh FILE tx ty tz qx qy qz qw`` maps a view's points by p_world = R(q)^-1 p + t with q
scalar-last (the other readings leave the views apart; this one puts 89-99 % of each view within 0.5 mm of another
view), and the scanner looks down -z of each view's own coordinates: 99.6-100 % of the range grid's outward normals
have n_z > 0. The Cyberware 3030 sweeps linearly (orthographic along x), so the sensor origin stored is a point
``SENSOR_DISTANCE`` (1 m) along the view's +z axis from the view's centre, mapped to the world like the points.
"""
from pathlib import Path

import numpy as np

from benchmarks import cache

BUNNY = cache.REAL_SCANS / "bunny"
SENSOR_DISTANCE = 1.0  # metres along a view's +z from its centre: the Cyberware 3030's sweep is nearly orthographic


def read_range_ply(path):
    """Points (N, 3) in the view's own metres and the range grid (rows, cols) of point indices (-1: no return)."""
    with open(path) as f:
        header = []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: no end_header")
            header.append(line.strip())
            if line.strip() == "end_header":
                break
        info = {h.split()[1]: h.split()[2] for h in header if h.startswith("obj_info")}
        n_vertex = int(next(h for h in header if h.startswith("element vertex")).split()[2])
        n_grid = int(next(h for h in header if h.startswith("element range_grid")).split()[2])
        lines = f.read().split("\n")
    points = np.array([r.split()[:3] for r in lines[:n_vertex]], dtype=np.float64)
    grid = np.full(n_grid, -1, dtype=np.int64)
    for i, r in enumerate(lines[n_vertex:n_vertex + n_grid]):
        if r and r[0] != "0":
            grid[i] = int(r.split()[1])
    return points, grid.reshape(int(info["num_rows"]), int(info["num_cols"]))


def read_conf(path):
    """``[(file name, R (3, 3), t (3,))]`` of a scanalyze ``.conf``: p_world = R @ p_view + t (see the module doc)."""
    from scipy.spatial.transform import Rotation

    views = []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts or parts[0] != "bmesh":
            continue
        if len(parts) != 9:
            raise ValueError(f"{path}: expected 'bmesh FILE tx ty tz qx qy qz qw', got {line!r}")
        t = np.array(parts[2:5], dtype=np.float64)
        rot = Rotation.from_quat(np.array(parts[5:9], dtype=np.float64)).inv()
        views.append((parts[1], rot.as_matrix(), t))
    if not views:
        raise ValueError(f"{path}: no 'bmesh' lines")
    return views


def grid_normals(points, grid):
    """Per-point normals from the range grid's own neighbours (cross product of the row and column steps), signed so
    that +z (toward the scanner) is positive; NaN where a point has no right and lower neighbour."""
    n = np.full(points.shape, np.nan)
    ok = (grid[:-1, :-1] >= 0) & (grid[1:, :-1] >= 0) & (grid[:-1, 1:] >= 0)
    r, c = np.nonzero(ok)
    a = points[grid[r, c]]
    cross = np.cross(points[grid[r, c + 1]] - a, points[grid[r + 1, c]] - a)
    cross /= np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-15)
    cross *= np.sign(np.median(cross[:, 2]))
    n[grid[r, c]] = cross
    return n


def load_views(root=BUNNY):
    """Every view aligned into the world frame: list of dicts name, points (N, 3), sensor (3,), grid_normals, R, t."""
    views = []
    for name, rot, t in read_conf(root / "bun.conf"):
        local, grid = read_range_ply(root / name)
        sensor_local = local.mean(0) + np.array([0.0, 0.0, SENSOR_DISTANCE])
        views.append(dict(name=Path(name).stem, points=local @ rot.T + t, sensor=rot @ sensor_local + t,
                          grid_normals=grid_normals(local, grid) @ rot.T, R=rot, t=t, local_centre=local.mean(0)))
    return views


def check_views(views):
    """Print the two checks of the conventions: overlap of each aligned view with the others, and the fraction of
    its range-grid normals facing its sensor origin. Returns {view: (overlap, facing)}."""
    from scipy.spatial import cKDTree

    out = {}
    for v in views:
        others = np.concatenate([w["points"] for w in views if w is not v])
        d = cKDTree(others).query(v["points"][::10])[0]
        n = v["grid_normals"]
        ok = np.all(np.isfinite(n), axis=1)
        facing = np.mean(np.einsum("ij,ij->i", n[ok], v["sensor"] - v["points"][ok]) > 0)
        out[v["name"]] = (float(np.mean(d < 5e-4)), float(facing))
        print(f"  {v['name']:<9} {len(v['points']):6d} points; within 0.5 mm of another view {out[v['name']][0]:.2f}; "
              f"grid normals facing the sensor origin {facing:.4f}")
    return out
