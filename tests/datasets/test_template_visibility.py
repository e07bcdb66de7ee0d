"""Which template points a sensor returns (datasets.templates): against closed-form visibility of two spheres, one
shadowing the other, a geometry a ray caster on the true surface would see exactly."""
import numpy as np
import pytest

from datasets.templates import TemplateSurface, poisson_depth, render_views, visible_points

CENTERS = np.array([[0.0, 0.0, 0.0], [2.6, 0.0, 0.0]])
RADIUS = 1.0
NOISE = 0.01


def two_spheres(n_each=5000, seed=0):
    """Noisy points on two unit spheres 0.6 apart, their true outward normals, and which sphere each lies on."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(2 * n_each, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    which = np.repeat([0, 1], n_each)
    points = CENTERS[which] + d * (RADIUS + rng.normal(0, NOISE, (2 * n_each, 1)))
    return points, d, which


def truly_visible(points, which, origin):
    """Closed form: a point of sphere k is seen from ``origin`` when it faces it (on the clean sphere through it)
    and the segment to it misses the other sphere."""
    facing = np.einsum("ij,ij->i", points - CENTERS[which], origin - points) > 0
    other = CENTERS[1 - which]
    d = points - origin
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    b = np.einsum("ij,ij->i", u, origin - other)
    c = np.sum((origin - other) ** 2, axis=1) - RADIUS**2
    disc = b**2 - c
    t_in = -b - np.sqrt(np.maximum(disc, 0))
    blocked = (disc > 0) & (t_in > 0) & (t_in < length)
    return facing & ~blocked


@pytest.mark.parametrize("origin", [[8.0, 0.3, 0.2], [-7.0, 1.0, -0.5], [1.3, 7.5, 0.0], [6.0, 4.0, 3.0]])
def test_returned_points_match_closed_form_visibility_where_one_sphere_shadows_the_other(origin):
    points, normals, which = two_spheres()
    surface = TemplateSurface(points, normals)
    origin = np.asarray(origin)
    truth = truly_visible(points, which, origin)
    picked = np.zeros(len(points), dtype=bool)
    picked[visible_points(points, normals, origin, surface)] = True
    # a few points on the shadow's edge and at grazing incidence may go either way; hidden-point removal, the rule
    # before, kept all of its points right but only 82-91 % of the visible ones from these four sensors
    precision = (picked & truth).sum() / picked.sum()
    recall = (picked & truth).sum() / truth.sum()
    assert precision > 0.97 and recall > 0.95, (precision, recall)
    if abs(origin[1]) < 2 and abs(origin[2]) < 2:  # on the spheres' axis: one shadows the other
        assert truth.sum() < 0.45 * len(points)


def test_the_template_noise_is_read_from_the_points():
    points, normals, _ = two_spheres()
    assert TemplateSurface(points, normals).sigma == pytest.approx(NOISE, rel=0.3)


def test_the_same_template_gives_the_same_surface_every_time():
    # open3d's threaded Poisson solve sums in a varying order; its surface moved a view by a point from run to run
    points, normals, _ = two_spheres(n_each=2000)
    origin = np.array([8.0, 0.3, 0.2])
    first = TemplateSurface(points, normals)
    hits = first.first_hits(origin, points)[0]
    for _ in range(3):
        again = TemplateSurface(points, normals)
        assert again.sigma == first.sigma
        np.testing.assert_array_equal(again.first_hits(origin, points)[0], hits)


def test_poisson_depth_follows_the_point_count():
    assert poisson_depth(10_000) == 8
    assert poisson_depth(100) == 4 + 2  # floored at 6
    assert poisson_depth(10**9) == 10
    assert [poisson_depth(4**k) for k in range(5, 9)] == [6, 7, 8, 9]


def test_bad_templates_get_one_clear_error():
    with pytest.raises(ValueError, match="N >= 10"):
        TemplateSurface(np.zeros((5, 3)), np.ones((5, 3)))
    points, normals, _ = two_spheres(200)
    with pytest.raises(ValueError, match="N >= 10"):
        TemplateSurface(points, normals[:10])
    with pytest.raises(ValueError, match="template .flat.: .*one line or point"):
        render_views("flat", np.zeros((50, 3)), np.tile([0.0, 0.0, 1.0], (50, 1)), 2, 1)
    with pytest.raises(ValueError, match="non-finite"):
        TemplateSurface(np.where(np.arange(len(points))[:, None] == 3, np.nan, points), normals)
