"""Forward-carried jets of the SIREN and the D operators of the covariance nets, against plain autograd.

Every reference here is an independent computation: torch.autograd first / nested (double) backward on the
value-only ``forward`` / ``covariance``. Float64 (``net.double()``) so that agreement is tested to 1e-5 relative
with a wide margin (float64 agreement is ~1e-12); one float32 smoke test guards the default dtype.
"""
import pytest
import torch

from autodecoder.field.siren import FeatureCovarianceNet, MeanNet, PairCovarianceNet
from autodecoder.field.siren import Siren

RTOL = 1e-5


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def assert_rel_close(actual, expected, rtol=RTOL):
    """|actual - expected| <= rtol * max|expected| elementwise (relative to the tensor's scale), shapes equal."""
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    scale = expected.abs().max().clamp_min(1e-300)
    err = (actual - expected).abs().max()
    assert err <= rtol * scale, f"max abs error {err:.3e} > {rtol:g} * {scale:.3e}"


def make_z(latent, batch, zshape, dtype=torch.float64, seed=3):
    if latent == 0:
        return None
    g = torch.Generator().manual_seed(seed)
    shape = (latent,) if zshape == "vec" else (batch, latent)
    return torch.randn(shape, generator=g, dtype=dtype) * 0.3


def rand_x(batch, dim, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, dim, generator=g, dtype=dtype) * 2 - 1


def autograd_jacobian(f, x):
    """d f(x)[b, o] / d x[b, k] -> (B, in, out), rows independent."""
    x = x.detach().requires_grad_(True)
    y = f(x)
    cols = [torch.autograd.grad(y[:, o].sum(), x, retain_graph=True)[0] for o in range(y.shape[1])]
    return y.detach(), torch.stack(cols, -1)


def autograd_mixed(f, x, create_graph=False):
    """Pair net f(x = [a, b]) (B, 6) -> (B, out): value, grad_a, grad_b (B, 3, out), mixed (B, 3, 3, out) by nested grads."""
    x = x.detach().requires_grad_(True) if not x.requires_grad else x
    y = f(x)
    ga, gb, mixed = [], [], []
    for o in range(y.shape[1]):
        g = torch.autograd.grad(y[:, o].sum(), x, create_graph=True)[0]  # (B, 6)
        ga.append(g[:, :3])
        gb.append(g[:, 3:])
        rows = [torch.autograd.grad(g[:, k].sum(), x, create_graph=create_graph, retain_graph=True)[0][:, 3:]
                for k in range(3)]
        mixed.append(torch.stack(rows, 1))  # (B, 3, 3)
    return y, torch.stack(ga, -1), torch.stack(gb, -1), torch.stack(mixed, -1)


def autograd_d_operator(cov, a, b, z=None, create_graph=False):
    """d2 cov(a, b) / d a_k d b_l by two nested autograd passes -> (B, 3, 3)."""
    a = a.detach().requires_grad_(True)
    b = b.detach().requires_grad_(True)
    c = cov(a, b, z)
    ga = torch.autograd.grad(c.sum(), a, create_graph=True)[0]  # (B, 3)
    rows = [torch.autograd.grad(ga[:, k].sum(), b, create_graph=create_graph, retain_graph=True)[0] for k in range(3)]
    return torch.stack(rows, 1)


# ------------------------------------------------------------------------------------------------------ Siren jets

@pytest.mark.parametrize("in_dim", [3, 6])
@pytest.mark.parametrize("depth,latent,zshape", [(1, 0, None), (1, 5, "batch"), (2, 5, "vec"), (4, 0, None),
                                                 (4, 5, "batch"), (4, 5, "vec")])
def test_forward_jet1_matches_autograd(in_dim, depth, latent, zshape):
    torch.manual_seed(depth * 10 + in_dim)
    net = Siren(in_dim, 4, width=24, depth=depth, latent_dim=latent).double()
    x = rand_x(17, in_dim)
    z = make_z(latent, 17, zshape)
    value, jac = net.forward_jet1(x, z)
    ref_value, ref_jac = autograd_jacobian(lambda u: net(u, z), x)
    assert value.shape == (17, 4) and jac.shape == (17, in_dim, 4)
    assert_rel_close(value, ref_value, 1e-12)
    assert_rel_close(jac, ref_jac)


@pytest.mark.parametrize("depth,latent,zshape,out_dim", [
    (1, 0, None, 1), (1, 7, "batch", 2), (2, 7, "vec", 1), (3, 0, None, 2), (3, 7, "batch", 1), (5, 7, "vec", 1),
    (5, 0, None, 1),
])
def test_forward_mixed_jet_matches_nested_autograd(depth, latent, zshape, out_dim):
    torch.manual_seed(100 + depth)
    net = Siren(6, out_dim, width=20, depth=depth, latent_dim=latent).double()
    x = rand_x(13, 6, seed=depth)
    z = make_z(latent, 13, zshape)
    value, ga, gb, mixed = net.forward_mixed_jet(x, z)
    ref = autograd_mixed(lambda u: net(u, z), x)
    assert mixed.shape == (13, 3, 3, out_dim)
    assert_rel_close(value, ref[0].detach(), 1e-12)
    assert_rel_close(ga, ref[1].detach())
    assert_rel_close(gb, ref[2].detach())
    assert_rel_close(mixed, ref[3].detach())


def test_forward_mixed_jet_with_torch_functional_hessian():
    """Independent of the nested-grad helper: the (a, b) block of torch.autograd.functional.hessian per sample."""
    torch.manual_seed(7)
    net = Siren(6, 1, width=16, depth=3).double()
    x = rand_x(4, 6, seed=11)
    _, _, _, mixed = net.forward_mixed_jet(x)
    for i in range(len(x)):
        hess = torch.autograd.functional.hessian(lambda u: net(u[None])[0, 0], x[i])
        assert_rel_close(mixed[i, :, :, 0], hess[:3, 3:])


def test_forward_mixed_jet_float32_smoke():
    torch.manual_seed(8)
    net = Siren(6, 1, width=32, depth=3)
    x = rand_x(32, 6, dtype=torch.float32)
    _, _, _, mixed = net.forward_mixed_jet(x)
    ref = net.double().forward_mixed_jet(x.double())[3]
    assert_rel_close(mixed.double(), ref, 1e-4)


def test_mixed_jet_rejects_non_pair_network():
    with pytest.raises(ValueError):
        Siren(3, 1, 8, 2).forward_mixed_jet(torch.zeros(2, 3))


# ---------------------------------------------------------------------------------------------------------- MeanNet

@pytest.mark.parametrize("latent,zshape", [(0, None), (6, "vec"), (6, "batch")])
def test_mean_value_and_gradient(latent, zshape):
    torch.manual_seed(1)
    net = MeanNet(width=32, depth=3, latent_dim=latent).double()
    x = rand_x(21, 3)
    z = make_z(latent, 21, zshape)
    value, grad = net.value_and_gradient(x, z)
    xr = x.clone().requires_grad_(True)
    ref_value = net(xr, z)
    ref_grad = torch.autograd.grad(ref_value.sum(), xr)[0]
    assert value.shape == (21,) and grad.shape == (21, 3)
    assert_rel_close(value, ref_value.detach(), 1e-12)
    assert_rel_close(grad, ref_grad)


# ------------------------------------------------------------------------------------------- covariance nets: D c

COV_NETS = {
    "pair": lambda latent, depth: PairCovarianceNet(width=24, depth=depth, latent_dim=latent),
    "feature": lambda latent, depth: FeatureCovarianceNet(width=24, depth=depth, features=16, latent_dim=latent),
}


@pytest.mark.parametrize("kind", ["pair", "feature"])
@pytest.mark.parametrize("depth,latent,zshape", [(1, 0, None), (1, 5, "batch"), (3, 5, "vec"), (3, 5, "batch"),
                                                 (3, 0, None)])
def test_d_operator_matches_double_backward(kind, depth, latent, zshape):
    torch.manual_seed(5 + depth)
    net = COV_NETS[kind](latent, depth).double()
    a, b = rand_x(15, 3, seed=1) * 0.5, rand_x(15, 3, seed=2) * 0.5
    z = make_z(latent, 15, zshape)
    d = net.d_operator(a, b, z)
    ref = autograd_d_operator(net.covariance, a, b, z).detach()
    assert d.shape == (15, 3, 3)
    assert_rel_close(d, ref)
    # D c(a, b) = D c(b, a)^T follows from the symmetry of c
    assert_rel_close(net.d_operator(b, a, z).transpose(1, 2), d, 1e-12)


@pytest.mark.parametrize("kind", ["pair", "feature"])
@pytest.mark.parametrize("latent", [0, 4])
def test_covariance_symmetric_and_variance(kind, latent):
    torch.manual_seed(2)
    net = COV_NETS[kind](latent, 3).double()
    a, b = rand_x(25, 3, seed=4), rand_x(25, 3, seed=5)
    z = make_z(latent, 25, "batch")
    assert_rel_close(net.covariance(a, b, z), net.covariance(b, a, z), 1e-13)
    assert_rel_close(net.variance(a, z), net.covariance(a, a, z), 1e-13)


def test_feature_covariance_is_psd():
    torch.manual_seed(9)
    net = FeatureCovarianceNet(width=32, depth=3, features=12).double()
    x = rand_x(60, 3, seed=6)  # 60 points > K = 12: the Gram matrix is rank-deficient, the hard case
    i, j = torch.meshgrid(torch.arange(60), torch.arange(60), indexing="ij")
    gram = net.covariance(x[i.reshape(-1)], x[j.reshape(-1)]).reshape(60, 60)
    assert torch.allclose(gram, gram.T, rtol=0, atol=1e-14)
    assert torch.linalg.eigvalsh(gram).min() >= -1e-8


def test_pair_covariance_positive_and_zero_free_variance():
    """SoftPlus makes c(a, b) > 0 and the variance positive (sanity of the paper's construction)."""
    torch.manual_seed(4)
    net = PairCovarianceNet(width=16, depth=2).double()
    x = rand_x(30, 3)
    assert (net.variance(x) > 0).all()


# ---------------------------------------------------------------------------- parameter gradients: jet == autograd

def _loss_from_d(d, sigma):
    eye = torch.eye(3, dtype=d.dtype)
    return (sigma[:, None, None] * eye - d).square().sum()


@pytest.mark.parametrize("kind", ["pair", "feature"])
@pytest.mark.parametrize("latent", [0, 5])
def test_parameter_gradients_jet_equal_double_backward(kind, latent):
    torch.manual_seed(12)
    net = COV_NETS[kind](latent, 3).double()
    a, b = rand_x(11, 3, seed=7) * 0.3, rand_x(11, 3, seed=8) * 0.3
    sigma = torch.rand(11, dtype=torch.float64)
    z0 = make_z(latent, 11, "vec")

    def grads(use_jet):
        net.zero_grad()
        z = None if z0 is None else z0.clone().requires_grad_(True)
        if use_jet:
            d = net.d_operator(a, b, z)
        else:
            d = autograd_d_operator(net.covariance, a, b, z, create_graph=True)
        _loss_from_d(d, sigma).backward()
        # the last layer's bias does not reach D c: its .grad stays None (both ways); compare it as zeros
        out = {n: torch.zeros_like(p) if p.grad is None else p.grad.clone() for n, p in net.named_parameters()}
        if z is not None:
            out["z"] = z.grad.clone()
        return out

    jet, ref = grads(True), grads(False)
    assert set(jet) == set(ref)
    for name in ref:
        assert_rel_close(jet[name], ref[name])


def test_mean_parameter_gradients_jet_equal_autograd():
    torch.manual_seed(13)
    net = MeanNet(width=24, depth=3, latent_dim=3).double()
    x = rand_x(19, 3)
    z = make_z(3, 19, "batch")
    target = torch.randn(19, 3, dtype=torch.float64)

    net.zero_grad()
    _, g = net.value_and_gradient(x, z)
    (g - target).square().sum().backward()
    jet = {n: torch.zeros_like(p) if p.grad is None else p.grad.clone() for n, p in net.named_parameters()}

    net.zero_grad()
    xr = x.clone().requires_grad_(True)
    g_ref = torch.autograd.grad(net(xr, z).sum(), xr, create_graph=True)[0]
    (g_ref - target).square().sum().backward()
    for n, p in net.named_parameters():
        assert_rel_close(jet[n], torch.zeros_like(p) if p.grad is None else p.grad)
