"""The B-spline grid networks (autodecoder/field/grid_networks.py) and their single-cloud fit (autodecoder/field/grid_fit.py).

References are independent computations: autograd (first and nested) of the value-only forward passes, central
finite differences, closed forms of the cubic B-spline, and a sphere whose surface is known. Float64 where
derivatives are compared.
"""
import numpy as np
import pytest
import torch

from autodecoder.field.grid_networks import (BSplineGrid, GridCovarianceNet, GridMeanNet, build_grid_networks,
                                    cubic_bspline_weights, level_cells)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LO, HI = [-0.5, -0.4, -0.6], [0.5, 0.7, 0.4]


def assert_rel_close(actual, expected, rtol=1e-9):
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    scale = expected.abs().max().clamp_min(1e-300)
    err = (actual - expected).abs().max()
    assert err <= rtol * scale, f"max abs error {err:.3e} > {rtol:g} * {scale:.3e}"


def randomised(net, seed=0, std=0.3):
    """The net in float64 with every parameter random (grids start at 0 for a summed mean)."""
    g = torch.Generator().manual_seed(seed)
    net = net.double()
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * std)
    return net


def inside_points(n, seed=1):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(LO, dtype=torch.float64), torch.tensor(HI, dtype=torch.float64)
    return lo + torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo)


MEANS = {
    "summed": lambda: GridMeanNet(LO, HI, finest=12, levels=3),
    "decoded": lambda: GridMeanNet(LO, HI, finest=8, levels=2, channels=3, hidden=8, depth=2),
    "latent": lambda: GridMeanNet(LO, HI, finest=8, levels=2, channels=2, hidden=8, latent_dim=4),
    # the latent model's mean: decoded levels plus a shared level added to the decoder's output
    "latent_shared": lambda: GridMeanNet(LO, HI, finest=8, levels=2, channels=2, hidden=8, latent_dim=4,
                                         shared_cells=5),
    # the same, centred: the decoder's output at the code 0 subtracted
    "latent_centred": lambda: GridMeanNet(LO, HI, finest=8, levels=2, channels=2, hidden=8, latent_dim=4,
                                          shared_cells=5, centred=True),
}


def code_for(net, batch=None):
    latent = 0 if net.decoder is None else net.decoder.latent_dim
    if latent == 0:
        return None
    return torch.linspace(-1, 1, latent, dtype=torch.float64) if batch is None else \
        torch.randn(batch, latent, generator=torch.Generator().manual_seed(5), dtype=torch.float64)


def test_cubic_bspline_weights_partition_unity_and_derivative():
    t = torch.linspace(0, 1, 101, dtype=torch.float64)
    w, dw = cubic_bspline_weights(t)
    assert_rel_close(w.sum(-1), torch.ones_like(t))
    assert dw.sum(-1).abs().max() < 1e-12
    assert (w >= 0).all()
    eps = 1e-6
    fd = (cubic_bspline_weights(t + eps)[0] - cubic_bspline_weights(t - eps)[0]) / (2 * eps)
    assert_rel_close(dw, fd, rtol=1e-8)


@pytest.mark.parametrize("kind", sorted(MEANS))
def test_mean_gradient_matches_autograd_and_finite_differences(kind):
    net = randomised(MEANS[kind]())
    x = inside_points(40)
    z = code_for(net)
    value, grad = net.value_and_gradient(x, z)
    xr = x.clone().requires_grad_(True)
    plain = net(xr, z)
    assert_rel_close(value, plain.detach())
    assert_rel_close(grad, torch.autograd.grad(plain.sum(), xr)[0])
    eps = 1e-6
    fd = torch.stack([(net(x + eps * e, z) - net(x - eps * e, z)) / (2 * eps)
                      for e in torch.eye(3, dtype=torch.float64)], 1).detach()
    assert_rel_close(grad.detach(), fd, rtol=1e-6)


@pytest.mark.parametrize("kind", ["latent", "latent_shared"])
def test_per_row_codes_are_accepted(kind):
    net = randomised(MEANS[kind]())
    x = inside_points(6)
    z = code_for(net, batch=6)
    value, grad = net.value_and_gradient(x, z)
    for i in range(6):
        v, g = net.value_and_gradient(x[i:i + 1], z[i])
        assert_rel_close(value[i:i + 1], v)
        assert_rel_close(grad[i:i + 1], g)


@pytest.mark.parametrize("kind", ["latent", "latent_shared"])
def test_cached_features_give_the_same_mean_and_gradient(kind):
    # projection interpolates the grids once per scan (features_at) and then runs only the decoder, on rows of the
    # cache picked by index and with a code per row
    net = randomised(MEANS[kind]())
    x = inside_points(12)
    z = code_for(net, batch=5)
    pick = torch.tensor([3, 0, 11, 3, 7])
    cache = net.features_at(x)
    value, grad = net.value_and_gradient_from({k: v[pick] for k, v in cache.items()}, z)
    ref_value, ref_grad = net.value_and_gradient(x[pick], z)
    assert_rel_close(value.detach(), ref_value.detach())
    assert_rel_close(grad.detach(), ref_grad.detach())
    # the cache carries no graph back to the grids; the code still gets its gradient
    assert all(not v.requires_grad for v in cache.values())
    zr = z.clone().requires_grad_(True)
    value, grad = net.value_and_gradient_from({k: v[pick] for k, v in cache.items()}, zr)
    dz = torch.autograd.grad((value + grad.sum(1)).sum(), zr)[0]
    zr2 = z.clone().requires_grad_(True)
    value2, grad2 = net.value_and_gradient(x[pick], zr2)
    assert_rel_close(dz, torch.autograd.grad((value2 + grad2.sum(1)).sum(), zr2)[0])
    with pytest.raises(ValueError, match="decoded"):
        randomised(MEANS["summed"]()).features_at(x)


def test_shared_level_needs_a_decoder():
    with pytest.raises(ValueError, match="shared_cells"):
        GridMeanNet(LO, HI, finest=8, shared_cells=4)
    with pytest.raises(ValueError, match="shared_cells"):
        GridMeanNet(LO, HI, finest=8, channels=2, hidden=8, shared_cells=-1)


def test_solve_shared_makes_the_shared_level_interpolate_the_grid_minimiser():
    from autodecoder.field.grid_fit import solve_shared
    from autodecoder.field.grid_minimiser import grid_minimiser
    from autodecoder.field.sampling import Box
    from autodecoder.field.targets import CloudTargets

    rng = np.random.default_rng(0)
    normals = rng.normal(size=(800, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    box = Box(np.full(3, -0.5), np.full(3, 0.5))
    targets = CloudTargets(0.3 * normals, normals, 0.08, box=box)
    net = GridMeanNet(box.lo, box.hi, finest=4, levels=1, channels=2, hidden=4, latent_dim=2, shared_cells=10)
    info = solve_shared(net, targets)
    nodes, lo, delta, _ = grid_minimiser(targets, 11, tol=1e-6)
    assert info["converged"]
    axis = lo[0] + delta * np.arange(11)
    x = torch.from_numpy(np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)).float()
    with torch.no_grad():
        shared = net.shared(x)[:, 0].double().numpy()
    assert np.abs(shared - nodes.ravel()).max() < 1e-4 * np.abs(nodes).max()
    # the sphere's inside is negative, the box's corners positive
    assert shared[np.argmin(np.linalg.norm(x.numpy(), axis=1))] < 0 < shared[0]
    with pytest.raises(ValueError, match="shared level"):
        solve_shared(GridMeanNet(box.lo, box.hi, finest=4, channels=2, hidden=4, latent_dim=2), targets)


def test_latent_mean_without_code_is_refused():
    net = MEANS["latent"]()
    with pytest.raises(ValueError, match="latent code"):
        net(inside_points(3).float())


@pytest.mark.parametrize("decoded", [False, True, "per-row codes"])
def test_d_operator_matches_nested_autograd(decoded):
    kwargs = {"hidden": 8, "features": 5, "latent_dim": 2} if decoded else {}
    net = randomised(GridCovarianceNet(LO, HI, finest=6, levels=2, channels=3, **kwargs))
    z = torch.tensor([0.3, -0.7], dtype=torch.float64) if decoded else None
    if decoded == "per-row codes":  # latent training: one code per pair, as many codes as scans in the batch
        z = torch.randn(10, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    a, b = inside_points(10, seed=2), inside_points(10, seed=3)
    d_c = net.d_operator(a, b, z)
    ar, br = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    grad_a = torch.autograd.grad(net.covariance(ar, br, z).sum(), ar, create_graph=True)[0]  # (B, 3)
    rows = [torch.autograd.grad(grad_a[:, k].sum(), br, retain_graph=True)[0] for k in range(3)]
    assert_rel_close(d_c, torch.stack(rows, 1))
    # c is the feature map's Gram: symmetric, variance = c(x, x)
    assert_rel_close(net.covariance(a, b, z), net.covariance(b, a, z))
    assert_rel_close(net.variance(a, z), net.covariance(a, a, z))


def test_set_from_nodes_interpolates_the_nodes():
    level = BSplineGrid(6, 2, [0, 0, 0], [1.2, 1.2, 1.2]).double()
    nodes = np.random.default_rng(0).normal(size=(7, 7, 7))
    level.set_from_nodes(nodes, channel=1)
    axis = np.linspace(0, 1.2, 7)
    x = torch.from_numpy(np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3))
    with torch.no_grad():
        values = level(x)
    assert np.abs(values[:, 1].numpy() - nodes.ravel()).max() < 1e-6  # the box is stored in float32
    assert values[:, 0].abs().max() == 0


def test_level_cells_run_from_base_to_finest():
    assert level_cells(128, 4) == [16, 32, 64, 128]
    assert level_cells(50, 1) == [50]
    assert level_cells(96, 3, base=24) == [24, 48, 96]


def test_state_dict_round_trip_rebuilds_the_same_functions():
    config = {"box_lo": LO, "box_hi": HI, "latent_dim": 0, "grid_mean": {"finest": 10, "levels": 2},
              "grid_cov": {"finest": 6, "channels": 4}}
    mean_net, cov_net = build_grid_networks(config)
    randomised(mean_net), randomised(cov_net)
    mean2, cov2 = build_grid_networks(config)
    mean2.double().load_state_dict(mean_net.state_dict())
    cov2.double().load_state_dict(cov_net.state_dict())
    x = inside_points(20)
    with torch.no_grad():
        assert torch.equal(mean_net(x), mean2(x))
        assert torch.equal(cov_net.variance(x), cov2.variance(x))


CENTRE, RADIUS = np.array([1.0, -3.0, 0.5]), 2.0


@pytest.fixture(scope="module")
def sphere_field():
    from autodecoder import fit_cloud

    rng = np.random.default_rng(0)
    normals = rng.normal(size=(3000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    field = fit_cloud(RADIUS * normals + CENTRE, normals, grid_mean={"finest": 48},  # the default representation
                      grid_cov={"finest": 8, "levels": 2, "channels": 4}, cov_steps=20, mean_steps=20)
    assert field.config["representation"] == "grid"
    return field


def test_grid_fit_refuses_siren_settings_and_the_boundary_term():
    from autodecoder import fit_cloud
    from autodecoder.field.fit import FitOptions

    points = np.random.default_rng(1).normal(size=(50, 3))
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    with pytest.raises(ValueError, match="width is a SIREN setting.*representation='siren'"):
        fit_cloud(points, normals, width=64)
    with pytest.raises(ValueError, match="depth, omega0 are SIREN settings"):
        fit_cloud(points, normals, depth=2, omega0=10.0)
    with pytest.raises(ValueError, match="steps: not an option of the grid fit"):
        fit_cloud(points, normals, steps=100)  # a FitOptions field
    with pytest.raises(ValueError, match="FitOptions"):
        fit_cloud(points, normals, options=FitOptions())
    with pytest.raises(ValueError, match="outside_weight.*representation='siren'"):
        fit_cloud(points, normals, outside_weight=100.0)
    with pytest.raises(ValueError, match="representation must be"):
        fit_cloud(points, normals, representation="voxels")


def test_fitted_sphere_mean_surface_is_the_sphere(sphere_field):
    surface = sphere_field.mesh(64)
    distance = np.abs(np.linalg.norm(surface.vertices - CENTRE, axis=1) - RADIUS)
    assert distance.mean() < 0.01 * RADIUS and distance.max() < 0.04 * RADIUS, (distance.mean(), distance.max())
    assert sphere_field.mean(CENTRE[None])[0] < 0 < sphere_field.mean((CENTRE + [0, 0, 1.5 * RADIUS])[None])[0]
    assert np.all(np.isfinite(sphere_field.variance(surface.vertices[:100])))


def test_grid_field_file_round_trip(sphere_field, tmp_path):
    from autodecoder import StochasticField

    sphere_field.save(tmp_path / "grid.pt")
    loaded = StochasticField.load(tmp_path / "grid.pt")
    x = CENTRE + np.random.default_rng(1).uniform(-1.2 * RADIUS, 1.2 * RADIUS, (50, 3))
    assert loaded.config["representation"] == "grid"
    assert np.array_equal(loaded.mean(x), sphere_field.mean(x))
    assert np.array_equal(loaded.variance(x), sphere_field.variance(x))
    assert np.array_equal(loaded.mean_gradient(x), sphere_field.mean_gradient(x))


def test_update_refits_a_grid_field_on_old_and_new_points():
    """update_field on a grid field: refitted on the union with the field's own grid settings. A half sphere
    extended by the other half: the new mean surface is the whole sphere; the old field's was not there."""
    from autodecoder import fit_cloud, update_field

    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    top, bottom = d[d[:, 2] > 0.1], d[d[:, 2] < -0.1]
    grids = dict(grid_mean={"finest": 48}, grid_cov={"finest": 8, "levels": 2, "channels": 4})
    half = fit_cloud(RADIUS * top + CENTRE, top, representation="grid", cov_steps=20, mean_steps=20, **grids)
    whole = update_field(half, RADIUS * bottom + CENTRE, bottom, seed=1)
    assert whole.config["representation"] == "grid" and whole.config["grid_mean"] == {"finest": 48}
    assert len(whole.training_points) == len(top) + len(bottom)
    assert whole.info["updates"][-1]["n_new"] == len(bottom) and whole.info["updates"][-1]["refit"]
    probe = RADIUS * np.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8]]) + CENTRE  # on the new half
    assert np.abs(whole.mean(probe)).max() < 0.05 * RADIUS
    assert np.abs(half.mean(probe)).max() > np.abs(whole.mean(probe)).max()
    with pytest.raises(TypeError, match="GridFitOptions"):
        from autodecoder.field.fit import FitOptions

        update_field(half, RADIUS * bottom + CENTRE, bottom, options=FitOptions())


def test_centred_mean_is_the_shared_level_at_code_zero_and_the_decoder_difference_elsewhere():
    torch.manual_seed(0)
    net = GridMeanNet(LO, HI, finest=8, levels=2, channels=2, hidden=8, latent_dim=4, shared_cells=5,
                      centred=True).double()
    with torch.no_grad():
        net.shared.values.normal_(0.0, 0.1)
    x = inside_points(30)
    s, ds = net.shared.value_and_jacobian(x)
    g0, grad0 = net.value_and_gradient(x, torch.zeros(4, dtype=torch.float64))
    assert torch.allclose(g0, s[:, 0], atol=1e-12) and torch.allclose(grad0, ds[:, :, 0], atol=1e-12)
    z = code_for(net)
    f = net.encoder(x)
    expected = s[:, 0] + net.decoder(f, z)[0][:, 0] - net.decoder(f, torch.zeros_like(z))[0][:, 0]
    assert torch.allclose(net(x, z), expected, atol=1e-12)
    assert not torch.allclose(net(x, z), s[:, 0], atol=1e-6)  # the code does change the field
    with pytest.raises(ValueError, match="centred"):
        GridMeanNet(LO, HI, finest=8, channels=2, hidden=8, centred=True)
