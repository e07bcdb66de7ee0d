"""Next-best-view on a toy sphere whose variance is higher on the +x side: the optimiser must go there."""
import json

import numpy as np
import pytest
import torch

from autodecoder.scanning.views import camera_rays, camera_score, next_best_views
from autodecoder.field.protocol import Field
from tests.scanning.toy_fields import Sphere


def test_camera_rays_are_unit_and_inside_the_field_of_view():
    p = torch.tensor([[0.0, 0.0, 3.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    o, r = camera_rays(p, d, fov_deg=40.0, n_side=4)
    assert o.shape == r.shape == (1, 16, 3)
    assert torch.allclose(r.norm(dim=2), torch.ones(1, 16))
    cos = (r * d[:, None]).sum(2)
    assert (cos >= np.cos(np.radians(20.0)) * np.cos(np.radians(20.0)) - 1e-6).all()


def test_score_is_higher_facing_the_high_variance_side():
    field = Sphere(torch.float32)
    p = torch.tensor([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0]])
    s = camera_score(field, p, -p, np.zeros(3), 1.2 * np.sqrt(3), n_side=2, n_samples=16, qmc_samples=64)
    assert s[0] > 3 * s[1]


def test_optimiser_moves_cameras_toward_higher_variance():
    field = Sphere(torch.float32)
    views = next_best_views(field, n_views=3, starts=6, steps=25, n_side=2, n_samples=12, qmc_samples=32, lr=0.1,
                            seed=1)
    assert 1 <= len(views) <= 3
    best = views[0]
    u = (best.position) / np.linalg.norm(best.position)
    assert u[0] > 0.6, f"best camera direction from the centre {u}"
    assert np.dot(best.direction, -u) > 0.8  # looking at the part
    r = np.linalg.norm(best.position) / (1.2 * np.sqrt(3))
    assert 1.5 - 1e-4 <= r <= 2.5 + 1e-4
    assert [v.score for v in views] == sorted([v.score for v in views], reverse=True)
    json.dumps([v.as_dict() for v in views])


def test_scored_candidates_choose_starts_on_the_high_variance_side():
    """Without any ascent step, starts chosen as the best of 48 scored candidates face the +x (high-variance) side
    for every seed; plain random starts (candidates=starts) do not."""
    field = Sphere(torch.float32)
    kw = dict(n_views=1, starts=2, steps=0, n_side=2, n_samples=12, qmc_samples=32)

    def best_x(seed, candidates):
        best = next_best_views(field, seed=seed, candidates=candidates, **kw)[0]
        return best.position[0] / np.linalg.norm(best.position)

    assert min(best_x(seed, 48) for seed in range(6)) > 0.6
    assert min(best_x(seed, 2) for seed in range(6)) < 0.6
    with pytest.raises(ValueError, match="candidates must be >= starts"):
        next_best_views(field, candidates=1, **kw)


def test_gradient_ascent_improves_on_its_starting_cameras():
    field = Sphere(torch.float32)
    kw = dict(n_views=4, starts=4, candidates=4, n_side=2, n_samples=12, qmc_samples=32, lr=0.1, seed=3,
              min_separation_deg=0.0)  # random starts: the ascent alone
    before = next_best_views(field, steps=0, **kw)
    after = next_best_views(field, steps=20, **kw)
    assert np.mean([v.score for v in after]) > 1.2 * np.mean([v.score for v in before])


def test_cone_projection_keeps_the_axis_near_the_centre():
    from autodecoder.scanning.views import _project_to_cone

    q = torch.tensor([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    a = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.01, 0.0]])
    d = _project_to_cone(a, -q, 0.2)
    off = (-q - ((-q) * d).sum(1, keepdim=True) * d).norm(dim=1)
    assert (off <= 0.2 + 1e-5).all()
    assert torch.allclose(d[1], a[1] / a[1].norm())  # already inside: unchanged


class SeenSphere(Sphere):
    """The toy sphere with a uniform standard deviation, measured on its +x half only (``training_points``)."""

    def __init__(self, dtype=torch.float32):
        super().__init__(dtype)
        v = np.random.default_rng(0).normal(size=(2000, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        self.training_points = torch.tensor(v[v[:, 0] > 0], dtype=dtype)

    def _sd(self, x):
        return torch.full_like(x[:, 0], 0.05)


def test_novelty_scores_the_measured_side_below_the_new_side():
    field = SeenSphere()
    p = torch.tensor([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0]])
    kw = dict(center=np.zeros(3), radius=1.2 * np.sqrt(3), n_side=2, n_samples=16, qmc_samples=64)
    plain = camera_score(field, p, -p, **kw)
    assert torch.allclose(plain[0], plain[1], rtol=1e-3)  # uniform variance: no preference without the data
    s = camera_score(field, p, -p, observed=field.training_points, observed_scale=0.2, **kw)
    # not zero: the expected hit lies up to one ray step (here ~0.28) behind the surface, away from the points
    assert s[0] < 0.3 * s[1]
    assert s[1] > 0.9 * plain[1]  # a ray into unmeasured surface keeps its variance


def test_next_best_view_looks_at_the_unmeasured_side_by_default():
    field = SeenSphere()
    kw = dict(n_views=1, starts=6, steps=20, n_side=2, n_samples=12, qmc_samples=32, lr=0.1, seed=1)
    best = next_best_views(field, observed_scale=0.2, **kw)[0]
    u = best.position / np.linalg.norm(best.position)
    assert u[0] < -0.5, f"best camera direction from the centre {u}"
    with pytest.raises(ValueError, match="observed_scale"):  # a toy field has no lengthscale to default it from
        next_best_views(field, **kw)
    with pytest.raises(ValueError, match="NaN or infinite"):
        next_best_views(field, observed=np.full((5, 3), np.nan), observed_scale=0.2, **kw)
    # observed=None: the variance alone (uniform here), so nothing to prefer; it still runs
    assert len(next_best_views(field, observed=None, **kw)) == 1


def test_distribution_summary_is_the_hit_weighted_variance_along_the_rays():
    """hit_summary='distribution' against a hand computation from the rays' first-hit bins and the field's own
    variance (torch_variance, not the covariance diagonal the score reads), with and without novelty."""
    from autodecoder.scanning.rays import cast_rays
    from autodecoder.scanning.views import _novelty

    field = SeenSphere(torch.float64)
    p = torch.tensor([[3.0, 0.5, 0.0], [-2.0, 2.0, 1.0]], dtype=torch.float64)
    center, radius = np.zeros(3), 1.5
    kw = dict(n_side=2, n_samples=16, qmc_samples=64)
    origins, rays = camera_rays(p, -p, 30.0, 2)
    dist = p.norm(dim=1)
    t_near = (dist - radius).clamp_min(0)[:, None].expand(2, 4).reshape(-1)
    t_far = (dist + radius)[:, None].expand(2, 4).reshape(-1)
    cast = cast_rays(field, origins.reshape(-1, 3), rays.reshape(-1, 3), t_near, t_far, n_samples=16,
                     qmc_samples=64)
    x = origins.reshape(-1, 1, 3) + cast.t[..., None] * rays.reshape(-1, 1, 3)
    var = field.torch_variance(x.reshape(-1, 3)).reshape(8, 16)
    expected = (cast.p_bins * var).sum(1).reshape(2, 4).mean(1)
    got = camera_score(field, p, -p, center, radius, hit_summary="distribution", **kw)
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-12)
    novelty = _novelty(x.reshape(-1, 3), field.training_points, 0.2).reshape(8, 16)
    expected = (cast.p_bins * var * novelty).sum(1).reshape(2, 4).mean(1)
    got = camera_score(field, p, -p, center, radius, hit_summary="distribution", observed=field.training_points,
                       observed_scale=0.2, **kw)
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="hit_summary must be one of"):
        camera_score(field, p, -p, center, radius, hit_summary="mode", **kw)


class TwoSheets(Field):
    """Toy field in z only, seen from +z: a sheet at z = 1 that the ray hits with probability ~1/2 (mean 0 there,
    small sd) and a sure surface at z = -1; the empty space between them (z ~ 0) has a large variance.

    mean = (z - 1)^2 (z + 1),  sd = 0.05 + 0.3 exp(-z^2 / (2 0.3^2)),  correlation exp(-dz^2 / (2 0.1^2)).
    """

    def torch_mean(self, x):
        z = x[:, 2]
        return (z - 1) ** 2 * (z + 1)

    def _sd(self, x):
        return 0.05 + 0.3 * torch.exp(-x[:, 2] ** 2 / (2 * 0.3**2))

    def torch_variance(self, x):
        return self._sd(x) ** 2

    def torch_covariance(self, a, b):
        return self._sd(a) * self._sd(b) * torch.exp(-(a[:, 2] - b[:, 2]) ** 2 / (2 * 0.1**2))


def test_distribution_summary_scores_the_surfaces_a_ray_can_meet_not_the_space_between():
    """Where a ray may hit either of two surfaces, the expected hit point lies between them, in empty space whose
    (large) variance belongs to no surface: the paper's summary reports it, the distribution does not."""
    from autodecoder.scanning.rays import cast_rays

    field = TwoSheets()
    p = torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    kw = dict(center=np.zeros(3), radius=2.0, n_side=2, fov_deg=5.0, n_samples=41, qmc_samples=256)
    cast = cast_rays(field, p, -p, 1.0, 5.0, n_samples=41, qmc_samples=256)
    assert 0.2 < float(cast.p_bins[0, cast.t[0] < 2.5].sum()) < 0.8  # the first sheet is hit about half the time
    assert abs(float(cast.expected_point[0, 2])) < 0.6  # ... so the expected hit lies between the sheets
    at_point = camera_score(field, p, -p, hit_summary="expected-point", **kw)
    over_hits = camera_score(field, p, -p, hit_summary="distribution", **kw)
    surface_var = float(field.torch_variance(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0])
    assert float(at_point[0]) > 5 * float(over_hits[0])  # measured: 13x
    assert float(over_hits[0]) < 4 * surface_var


@pytest.fixture(scope="module")
def open_sheet_fields():
    """Fields of a flat square patch seen from +z (an open sheet, like one scan of a flat face): the paper's loss,
    and with the boundary term."""
    from autodecoder import fit_cloud

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (1200, 2)), np.zeros(1200)]
    normals = np.tile([0.0, 0.0, 1.0], (1200, 1))
    kw = dict(seed=0, quiet=True, width=32, depth=2, features=16, steps=250, mean_batch=512, screen_batch=256,
              pair_clusters=16)
    return {w: fit_cloud(points, normals, representation="siren", outside_weight=w, **kw) for w in (0.0, 100.0)}


def test_far_field_check_tells_an_open_sheet_from_a_closed_one(open_sheet_fields):
    from autodecoder.scanning.views import HALF_SOLID_FRACTION, far_field_inside_fraction

    assert far_field_inside_fraction(open_sheet_fields[0.0]) > 2 * HALF_SOLID_FRACTION
    assert far_field_inside_fraction(open_sheet_fields[100.0]) == 0.0


def test_next_best_views_warns_about_a_half_solid_far_field(open_sheet_fields, recwarn):
    kw = dict(n_views=1, starts=2, steps=1, n_side=2, n_samples=8, qmc_samples=16)
    with pytest.warns(UserWarning, match="outside_weight=100"):
        next_best_views(open_sheet_fields[0.0], **kw)
    recwarn.clear()
    next_best_views(open_sheet_fields[100.0], **kw)
    assert not [w for w in recwarn if "outside_weight" in str(w.message)]
