"""autodecoder.scanning.own_surface: where the surface a scan saw lies around its points, and which rays pass
through it (the rule of autodecoder.scanning.free_space that leaves out rays a sensor at the sidecar's origin could
not have travelled), against closed forms on a flat sheet with a round hole."""
import numpy as np
from scipy.spatial import cKDTree

from autodecoder.scanning.own_surface import median_spacing, passes_through, surface_sides

SPACING = 0.01
HOLE = (np.array([0.0, 0.0]), 0.1)


def _sheet():
    """A square sheet z = 0 over [-0.3, 0.3]^2 on a grid, jittered, without a round hole of radius 0.1 about 0."""
    g = np.arange(-0.3, 0.3 + 1e-9, SPACING)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy + np.random.default_rng(0).uniform(-0.2, 0.2, xy.shape) * SPACING
    xy = xy[np.hypot(*(xy - HOLE[0]).T) >= HOLE[1]]
    return np.c_[xy, np.zeros(len(xy))]


def test_surface_sides_point_where_the_surface_stops():
    """Inside the sheet the neighbours surround a point (no side); on the hole's rim the surface stops toward the
    hole's centre, on the outer edge away from the sheet's centre (closed form: the radial directions), and the
    normal is the sheet's."""
    pts = _sheet()
    tree = cKDTree(pts)
    sides, normals = surface_sides(tree)
    r = np.hypot(pts[:, 0], pts[:, 1])
    inside = (r > HOLE[1] + 3 * SPACING) & (np.abs(pts[:, :2]).max(1) < 0.3 - 3 * SPACING)
    assert (np.linalg.norm(sides[inside], axis=1) == 0).mean() > 0.99
    rim = r < HOLE[1] + 0.5 * SPACING
    towards_hole = -pts[rim, :2] / r[rim, None]
    assert rim.sum() > 20 and (np.einsum("ij,ij->i", sides[rim, :2], towards_hole) > 0.8).mean() > 0.9
    edge = pts[:, 0] > 0.3 - 0.3 * SPACING
    assert (sides[edge, 0] > 0.8).mean() > 0.9
    np.testing.assert_allclose(np.abs(normals[:, 2]), 1.0, atol=1e-6)
    some = np.flatnonzero(rim)[:5]
    np.testing.assert_allclose(surface_sides(tree, some)[0], sides[some])


def test_a_ray_through_the_sheet_passes_through_it_but_one_through_its_hole_or_past_its_edge_does_not():
    """Vertical rays from above (z from 1 to -1): through the sheet's interior, and through it just beside the hole's
    rim or the outer edge on the sheet's side: through. Through the hole's middle, through the hole a third of a
    spacing inside its rim (within the radius of rim points, on the hole's side), or past the outer edge outside: not.
    Without the sides, any ray that comes within the radius counts."""
    pts = _sheet()
    tree = cKDTree(pts)
    radius = 2 * median_spacing(tree)
    xy = np.array([[0.2, 0.05], [HOLE[1] + 0.5 * SPACING, 0.0], [0.0, -0.3 + 0.5 * SPACING],  # through
                   [0.0, 0.0], [HOLE[1] - 0.3 * SPACING, 0.0], [0.0, -0.3 - 0.5 * SPACING]])  # not
    origin = np.array([0.0, 0.0, 1.0])
    starts = np.c_[xy, np.full(len(xy), 1.0)]
    down = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    out = [passes_through(tree, s, d[None], [0.0], [2.0], radius)[0] for s, d in zip(starts, down)]
    assert out == [True, True, True, False, False, False]
    plain = [passes_through(tree, s, d[None], [0.0], [2.0], radius, sides=False)[0] for s, d in zip(starts, down)]
    assert plain == [True, True, True, False, True, True]
    # one call for many rays gives the same as one at a time; rays that end before the sheet pass nothing
    both = passes_through(tree, origin, (np.c_[xy, np.zeros(len(xy))] - origin) /
                          np.linalg.norm(np.c_[xy, np.zeros(len(xy))] - origin, axis=1, keepdims=True),
                          np.zeros(len(xy)), np.full(len(xy), 2.0), radius)
    assert both[0] and not both[3]
    assert not passes_through(tree, starts[0], down[:1], [0.0], [0.5], radius)[0]


def test_free_space_still_offers_the_names_it_was_split_into():
    """free_space was split into own_surface and surface_band: what was imported from it still is, the same objects."""
    from autodecoder.scanning import free_space, own_surface, surface_band

    for module in (own_surface, surface_band):
        for name in (n for n in dir(module) if not n.startswith("_") and n.isidentifier()):
            value = getattr(module, name)
            if getattr(value, "__module__", None) == module.__name__ or name.isupper():
                assert getattr(free_space, name) is value, name
    assert set(free_space.__all__) <= set(dir(free_space))
