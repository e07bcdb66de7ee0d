"""Tests of the thin-walled parts (datasets.parts) and of defects and scans on them: sheets, holes through them."""
import numpy as np
import pytest
import trimesh

from datasets.defects import make_defect
from datasets.parts import BUILTIN_PARTS, load_part, open_cup, sheet_enclosure
from datasets.scanner import VirtualScanner
from autodecoder.field.protocol import Field

WALL = 1.5  # both parts' default sheet thickness, mm


@pytest.fixture(scope="module")
def enclosure():
    return sheet_enclosure()


@pytest.fixture(scope="module")
def cup():
    return open_cup()


def _hits(mesh, origin, direction):
    """Sorted distances along a ray from ``origin`` to every crossing of the mesh's surface."""
    direction = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    where, _, _ = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_location(
        [origin], [direction], multiple_hits=True)
    return np.sort((np.reshape(where, (-1, 3)) - origin) @ direction)


def test_enclosure_is_a_deterministic_watertight_sheet_box(enclosure):
    assert enclosure.is_watertight and enclosure.is_winding_consistent and enclosure.body_count == 1
    np.testing.assert_allclose(enclosure.bounds, [[-50, -35, 0], [50, 35, 50]], atol=1e-9)
    # open at the bottom (a disc thickened: genus 0) with five openings through the sheet: genus 5
    assert enclosure.euler_number == 2 - 2 * 5
    # the sheet's volume in closed form: the shell minus the openings (the round ones are 48-gons, a hair smaller)
    shell = 100 * 70 * 50 - 97 * 67 * 48.5
    openings = WALL * (40 * 16 + 2 * 30 * 12 + np.pi * (7 ** 2 + 9 ** 2))
    assert enclosure.volume == pytest.approx(shell - openings, rel=2e-3)
    again = sheet_enclosure()
    np.testing.assert_array_equal(again.vertices, enclosure.vertices)
    np.testing.assert_array_equal(again.faces, enclosure.faces)


@pytest.mark.parametrize("origin, direction", [((10.0, -20.0, 80.0), (0, 0, -1)),  # the top
                                               ((-80.0, 10.0, 30.0), (1, 0, 0)),  # a short wall, both sides
                                               ((0.0, -60.0, 20.0), (0, 1, 0))])  # the long walls
def test_enclosure_walls_are_one_sheet_thick(enclosure, origin, direction):
    t = _hits(enclosure, np.array(origin), direction)
    assert len(t) % 2 == 0 and len(t) >= 2
    np.testing.assert_allclose(t[1::2] - t[0::2], WALL, atol=1e-9)


def test_enclosure_openings_go_through_the_sheet(enclosure):
    assert len(_hits(enclosure, np.array([-15.0, 10.0, 80.0]), (0, 0, -1))) == 0  # the top vent, then the open bottom
    assert len(_hits(enclosure, np.array([28.0, -18.0, 80.0]), (0, 0, -1))) == 0  # the round hole on top
    # through the round hole of the +x wall the ray meets only the -x wall
    t = _hits(enclosure, np.array([80.0, 0.0, 25.0]), (-1, 0, 0))
    np.testing.assert_allclose(t, [80 + 50 - WALL, 80 + 50], atol=1e-9)


def test_cup_is_a_watertight_curved_sheet_of_uniform_thickness(cup):
    assert cup.is_watertight and cup.body_count == 1 and cup.euler_number == 2
    np.testing.assert_allclose(cup.bounds[:, 2], [0, 70], atol=1e-9)
    assert np.abs(cup.bounds[:, :2]).max() <= 40 + 1e-9
    # radially through the cylindrical wall (capsule vertices lie on the +x axis, where the facets touch the circle)
    for z in (45.0, 60.0):
        t = _hits(cup, np.array([0.0, 0.0, z]), (1, 0, 0))
        np.testing.assert_allclose(t, [40 - WALL, 40], atol=1e-6)
    # the bottom pole: the sheet is WALL thick along the axis; from above the ray enters through the open top
    np.testing.assert_allclose(_hits(cup, np.array([0.0, 0.0, 100.0]), (0, 0, -1)), [100 - WALL, 100], atol=1e-6)
    # the volume of a hemispherical shell plus a cylindrical one, up to the facets
    r = 40 - WALL
    exact = 2 / 3 * np.pi * (40 ** 3 - r ** 3) + np.pi * (40 ** 2 - r ** 2) * 30
    assert cup.volume == pytest.approx(exact, rel=0.01)


def test_load_part_names_the_builtin_parts(tmp_path):
    assert set(BUILTIN_PARTS) == {"builtin", "enclosure", "cup"}
    assert load_part("cup").volume == pytest.approx(open_cup().volume)
    with pytest.raises(ValueError) as error:
        load_part("bowl")
    assert "'bowl'" in str(error.value) and "enclosure" in str(error.value) and "cup" in str(error.value)


@pytest.mark.parametrize("name, center, normal", [("enclosure", (0, -20, 50), (0, 0, 1)),
                                                  ("cup", (0, -40, 55), (0, -1, 0))])
def test_missing_punches_a_hole_through_the_sheet(name, center, normal):
    part = load_part(name)
    defect = make_defect(part, "missing", center, normal, radius=0.05, seed=0)
    assert defect.mesh.is_watertight
    assert defect.mesh.euler_number == part.euler_number - 2  # one more handle: a hole through the sheet
    origin = np.asarray(center, dtype=np.float64) + 20 * np.asarray(normal)
    assert len(_hits(part, origin, -np.asarray(normal))) >= 2
    t = _hits(defect.mesh, origin, -np.asarray(normal))
    assert len(t) == 0 or t[0] > 20 + WALL  # nothing of the sheet is left where the ball went through it


@pytest.mark.parametrize("kind", ["dent", "bump"])
def test_dent_and_bump_move_the_whole_sheet(enclosure, kind):
    center, normal = np.array([0.0, -20.0, 50.0]), np.array([0.0, 0.0, 1.0])
    defect = make_defect(enclosure, kind, center, normal, radius=0.05, height=0.03, seed=0)
    assert defect.mesh.is_watertight and defect.mesh.volume == pytest.approx(enclosure.volume, rel=1e-4)
    t = _hits(defect.mesh, center + 20 * normal, -normal)
    # the sheet moved by the full height at the centre (up to the refined facets: edges of radius / 6)
    assert t[0] == pytest.approx(20 - defect.height, abs=0.05)
    assert t[1] - t[0] == pytest.approx(WALL, abs=0.02)  # and kept its thickness (both sides moved)


def test_points_seen_through_a_hole_are_labelled_missing(enclosure):
    center, normal = np.array([0.0, -20.0, 50.0]), np.array([0.0, 0.0, 1.0])
    defect = make_defect(enclosure, "missing", center, normal, radius=0.05, seed=0)
    # obliquely through the hole in the top: the sensor sees the inside of the -y wall (the bottom is open)
    sensor = np.array([0.0, 150.0, 120.0])
    scan = VirtualScanner(defect.mesh).scan(sensor, look_at=center, fov_deg=12.0, n_points=3000, seed=0)
    seen = defect.seen_through(enclosure, sensor, scan.clean_points)
    # independent check: a point lies below the top sheet and its ray crossed the top inside the hole's disc
    below = scan.clean_points[:, 2] < 50 - WALL - 1e-6
    s = (50 - sensor[2]) / (scan.clean_points[:, 2] - sensor[2])
    crossing = sensor + s[:, None] * (scan.clean_points - sensor)
    through_disc = np.linalg.norm(crossing[:, :2] - center[:2], axis=1) < np.sqrt(defect.radius ** 2 - WALL ** 2) - 0.3
    assert seen[below & through_disc].all() and (below & through_disc).sum() > 30
    outside_disc = np.linalg.norm(crossing[:, :2] - center[:2], axis=1) > defect.radius + 0.3
    assert not seen[outside_disc].any()
    assert not make_defect(enclosure, "dent", center, normal, seed=0).seen_through(enclosure, sensor,
                                                                                    scan.clean_points).any()


# ---------------------------------------------------------------------------------------------- the field of a sheet
def _sheet_cloud(thickness, n=600, seed=0):
    """Oriented points on the square [-1, 1]^2 of the plane z = 0 (normals +z) and, when ``thickness`` is given,
    of the plane z = -thickness (normals -z): a sheet seen from one side, or from both."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, size=(n, 2))
    if thickness is None:
        return np.c_[xy, np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))
    half = n // 2
    points = np.r_[np.c_[xy[:half], np.zeros(half)], np.c_[xy[half:], np.full(n - half, -thickness)]]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (half, 1)), np.tile([0.0, 0.0, -1.0], (n - half, 1))]
    return points, normals


def _fit(points, normals):
    from autodecoder import fit_cloud

    return fit_cloud(points, normals, representation="siren",
                     seed=0, quiet=True, width=64, depth=2, features=32, steps=120,
                     mean_batch=1024, screen_batch=512, pair_clusters=48, covariance_every=8)


def _profile(field, z):
    x = np.c_[np.zeros_like(z), np.zeros_like(z), z]
    return field.mean(x), np.sqrt(field.variance(x))


@pytest.mark.usefixtures("one_torch_thread")
def test_fitted_mean_changes_sign_across_a_sheet_seen_from_one_side_only():
    """Why the ray score can see a hole in a sheet at all, and why it needs `own_depth`: a partial scan sees one
    side of a sheet, and its Poisson field is negative everywhere behind it (the cavity of an open part is solid
    to it). Seen from both sides, a sheet thinner than the kernel has no sign change left: the two faces' normals
    cancel in the posterior mean (to O(t^2 / h^2)), so the field of a closed thin sheet is ~0 across it."""
    one = _fit(*_sheet_cloud(None))
    h = one.config["lengthscale"] / one.frame.scale
    mean, sd = _profile(one, np.array([h, -h, -3 * h]))
    assert mean[0] > sd[0] and mean[1] < -sd[1] and mean[2] < -sd[2]  # negative behind the face, far behind too
    both = _fit(*_sheet_cloud(0.4 * h))
    z = np.linspace(-3 * h, 2 * h, 21)
    mean_both, sd_both = _profile(both, z)
    assert np.abs(mean_both).max() < 0.25 * np.abs(mean).min()
    assert np.abs(mean_both).max() < 0.25 * sd_both.min()  # P(inside) ~ 1/2 everywhere: no material, no free space


# ---------------------------------------------------------------------------------------------- rays through a sheet
class OneSidedSheetField(Field):
    """The field of a flat sheet z = 0 seen from above, as a partial scan's latent field is: E f = clip(z, -a, a)
    (solid everywhere below the sheet), sd constant; box [-1, 1]^3; kernel lengthscale 0.02."""

    def __init__(self, a=0.02, sd=0.004, ell=0.05):
        self.a, self.sd, self.ell = a, sd, ell
        self.lengthscale = 0.02
        self.bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def torch_mean(self, x):
        return x[:, 2].clamp(-self.a, self.a)

    def torch_covariance(self, a, b):
        import torch

        return self.sd ** 2 * torch.exp(-((a - b) ** 2).sum(1) / (2 * self.ell ** 2))

    def torch_variance(self, x):
        import torch

        return torch.full((len(x),), self.sd ** 2, dtype=x.dtype)


SENSOR = np.array([0.0, 0.0, 2.0])


def _sheet_scan(hole, n_side=40):
    """Returns of a pinhole grid from SENSOR over a sheet z = 0 with a round hole of radius ``hole`` about the z
    axis and a floor z = -0.5 below: (points (m, 3), seen through the hole (m,) bool)."""
    u = (np.arange(n_side) + 0.5) / n_side * 0.6 - 0.3
    uu, vv = np.meshgrid(u, u)
    d = np.c_[uu.ravel(), vv.ravel(), -np.ones(uu.size)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    at_sheet = SENSOR + (SENSOR[2] / -d[:, 2])[:, None] * d
    through = np.linalg.norm(at_sheet[:, :2], axis=1) < hole
    t = np.where(through, (SENSOR[2] + 0.5) / -d[:, 2], SENSOR[2] / -d[:, 2])
    return SENSOR + t[:, None] * d, through


@pytest.mark.usefixtures("one_torch_thread")
def test_rays_through_a_hole_in_a_sheet_pass_where_the_field_puts_material():
    from scipy.special import log_ndtr

    from autodecoder.scanning.free_space import blocked_probability

    field = OneSidedSheetField()
    points, through = _sheet_scan(hole=0.15)
    check = blocked_probability(field, SENSOR, points, observed=points)
    # closed form: a ray to the floor crosses the sheet, then samples at E f = -a all the way down (those farther
    # than the clearance from the hole's rim and the floor's points): P(free) <= P(f > 0) at one of them,
    # = Phi(-a / sd); a ray to the sheet itself ends on its own surface and is free
    bound = log_ndtr(-field.a / field.sd)
    assert (check.log_free[through] <= bound + 1e-9).all() and through.sum() > 50
    assert (check.p_blocked[~through] < 0.05).all()
    # where the rays enter the material: the sheet's plane (within a sample step, half the lengthscale)
    entry_z = SENSOR[2] + check.t_enter[through] * ((points[through] - SENSOR)[:, 2]
                                                    / np.linalg.norm(points[through] - SENSOR, axis=1))
    assert np.abs(entry_z).max() < 0.012
    # the old rule (no own_depth): nothing clearly outside follows the sheet, so the whole ray was the floor
    # point's own surface and the hole went unseen
    blind = blocked_probability(field, SENSOR, points[through], observed=points, own_depth=None)
    assert (blind.p_blocked < 0.05).all()
    # the same sheet without a hole: every ray ends on it, none is blocked
    intact, _ = _sheet_scan(hole=0.0)
    assert (blocked_probability(field, SENSOR, intact, observed=intact).p_blocked < 0.05).all()


@pytest.mark.usefixtures("one_torch_thread")
def test_without_good_surfaces_auto_tests_no_deep_material():
    from inspection.ray_evidence import ray_evidence

    field = OneSidedSheetField()
    # a good part has an opening of radius 0.15 at the origin: its rays through the opening enter the field's
    # "solid" at the sheet's plane too, on every good scan
    good, _ = _sheet_scan(hole=0.15)
    options = dict(n_rays=len(good), n_empty=0)
    alone = ray_evidence(field, good, SENSOR, own_depth=0.06, **options)
    assert alone.score > 5.0  # deep material tested without a band of good surfaces: the opening looks like a hole
    # without good scans' surfaces, 'auto' tests no deep material (openings would look like holes)
    assert ray_evidence(field, good, SENSOR, **options).score < 1e-3
