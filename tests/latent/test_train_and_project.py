"""Latent training over scan collections and test-time projection (autodecoder.latent, train_latent)."""
import math

import numpy as np
import pytest
import torch

from autodecoder.latent.model import LATENT_FORMAT, load_model, read_checkpoint
from autodecoder.latent.history import log_paths
from autodecoder.latent.train import train_latent

from .spheres import RADII, sphere_scan, sphere_scans, zero_crossing_radius

# tiny nets and batches: the whole file runs in well under a minute on 2 cores
TINY = dict(latent_dim=2, width=32, depth=2, features=16, mean_samples=256, screen_samples=128, pair_clusters=8,
            lr=3e-3, code_lr=1e-2, batch=2)


# one torch thread for the whole module (conftest.py): these tiny problems only pay for intra-op threads
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def trained(tmp_path_factory, one_torch_thread):
    out = tmp_path_factory.mktemp("latent") / "model.pt"
    model = train_latent(sphere_scans(), out, epochs=100, seed=0, quiet=True, **TINY)
    return model, out


def test_training_lowers_the_loss_and_writes_log_and_plot(trained):
    model, out = trained
    history = model.info["history"]
    assert len(history) == 100 and model.epoch == 100
    first, last = np.mean([h["loss"] for h in history[:5]]), np.mean([h["loss"] for h in history[-5:]])
    assert last < 0.5 * first
    csv, png = log_paths(out)
    assert csv.name == "model.log.csv" and png.name == "model.loss.png"
    assert len(csv.read_text().strip().splitlines()) == 101  # header + one row per epoch
    assert png.stat().st_size > 1000
    assert model.codes.shape == (4, 2) and model.noise > 0


def test_training_codes_order_the_radii(trained):
    model, _ = trained
    radii = [zero_crossing_radius(model.training_field(n)) for n in model.train_names]
    assert np.all(np.diff(radii) > 0), radii  # the codes tell the spheres apart


def test_projection_recovers_an_unseen_radius(trained):
    model, _ = trained
    scan = sphere_scan("test/new", 0.25, seed=11)
    fit = model.project(scan.points, scan.normals, seed=0)
    assert fit.code.shape == (2,) and np.isfinite(fit.loss)
    radius = zero_crossing_radius(fit.field)
    assert abs(radius - 0.25) < 0.1 * 0.25, radius
    # the field answers every statistical query, in the collection frame
    var = fit.field.variance(scan.points[:10])
    assert np.all(var >= 0) and np.all(np.isfinite(fit.field.nll(scan.points[:10])))
    p = fit.field.prob_inside(np.array([[0.0, 0.0, 0.0], [0.45, 0.45, 0.45]]))
    assert p[0] > 0.5 > p[1]


def test_projection_without_normals_and_batched_projection(trained):
    model, _ = trained
    scans = [sphere_scan(f"t{r}", r, seed=20 + i) for i, r in enumerate((0.18, 0.32))]
    alone = [model.project(s.points, s.normals, seed=5, steps=40) for s in scans]
    together = model.project_many(scans, seed=5, steps=40, batch=2)
    # the same subsets are not drawn (one generator per batch), but both reach the same radius
    for a, b in zip(alone, together):
        assert abs(zero_crossing_radius(a.field) - zero_crossing_radius(b.field)) < 0.02
    bare = model.project(scans[1].points, None, seed=0)
    assert abs(zero_crossing_radius(bare.field) - 0.32) < 0.1 * 0.32


def test_projection_can_leave_a_training_code_out_of_its_starts(trained):
    """Cross-fitted calibration projects a training scan without its own code among the candidate starts."""
    from autodecoder.latent.projection import _candidates

    model, _ = trained
    _, index = _candidates(model, 64)
    assert list(index) == [-1, 0, 1, 2, 3]  # the mean code and every training code
    _, index = _candidates(model, 64, exclude=(2,))
    assert list(index) == [-1, 0, 1, 3]
    scan = sphere_scan("train/002", RADII[2], seed=2)
    fit = model.project(scan.points, scan.normals, seed=0, starts=4, exclude=(2,))
    assert fit.start != 2 and abs(zero_crossing_radius(fit.field) - RADII[2]) < 0.1 * RADII[2]


def test_finetuning_leaves_the_loaded_model_untouched(trained):
    model, _ = trained
    before = {k: v.clone() for k, v in model.mean_net.state_dict().items()}
    scan = sphere_scan("t", 0.25, seed=3)
    fit = model.project(scan.points, scan.normals, steps=20, finetune_steps=5)
    assert fit.field.mean_net is not model.mean_net
    for k, v in model.mean_net.state_dict().items():
        assert torch.equal(v, before[k])


def test_checkpoint_round_trip_gives_identical_outputs(trained):
    model, out = trained
    loaded = load_model(out)
    assert loaded.train_names == model.train_names and loaded.noise == model.noise
    assert torch.equal(loaded.codes, model.codes)
    x = np.random.default_rng(0).uniform(-0.5, 0.5, (100, 3))
    for name in model.train_names[:2]:
        a, b = model.training_field(name), loaded.training_field(name)
        assert np.array_equal(a.mean(x), b.mean(x)) and np.array_equal(a.variance(x), b.variance(x))
    state = torch.load(out, weights_only=True)  # plain tensors and Python values only
    assert state["format"] == LATENT_FORMAT and state["frame"] == {"center": [0.0, 0.0, 0.0], "scale": 1.0}


def test_resume_gives_the_same_weights_as_an_uninterrupted_run(tmp_path):
    scans = sphere_scans(radii=(0.2, 0.3, 0.25))
    kw = dict(epochs=4, seed=3, quiet=True, checkpoint_every=1, **{**TINY, "batch": 2})
    full = train_latent(scans, tmp_path / "full.pt", **kw)
    train_latent(scans, tmp_path / "part.pt", stop_after=2, **kw)
    part = read_checkpoint(tmp_path / "part.pt")
    assert part["epoch"] == 2
    resumed = train_latent(scans, tmp_path / "part.pt", resume=part, **kw)
    a, b = read_checkpoint(tmp_path / "full.pt"), read_checkpoint(tmp_path / "part.pt")
    assert b["epoch"] == 4
    for key in ("mean_state", "cov_state"):
        for name, value in a[key].items():
            assert torch.equal(value, b[key][name]), (key, name)
    assert torch.equal(a["codes"], b["codes"]) and torch.equal(full.codes, resumed.codes)
    assert a["noise"] == b["noise"]


def test_resume_against_other_data_is_rejected(trained, tmp_path):
    _, out = trained
    state = read_checkpoint(out)
    with pytest.raises(ValueError, match="another collection"):
        train_latent(sphere_scans(), None, resume=state, fingerprint="0" * 64, quiet=True)
    with pytest.raises(ValueError, match="training scans differ"):
        train_latent(sphere_scans()[:3], None, resume=state, quiet=True)


def test_foreign_and_other_version_files_are_rejected(trained, tmp_path):
    _, out = trained
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint")
    with pytest.raises(ValueError, match="notes.pt"):
        load_model(text)
    other = tmp_path / "other.pt"
    torch.save({"format": "something-else", "weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="other.pt.*not a latent model checkpoint"):
        load_model(other)
    state = torch.load(out, weights_only=True)
    state["version"] = 99
    newer = tmp_path / "newer.pt"
    torch.save(state, newer)
    with pytest.raises(ValueError, match="newer.pt.*version 99"):
        load_model(newer)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_model(tmp_path / "missing.pt")
    # inspection reads model files through the same format check: one error naming the file
    from inspection.model_io import load_model_handle

    with pytest.raises(ValueError, match="other.pt.*not a model file"):
        load_model_handle(other)
    with pytest.raises(ValueError, match="newer.pt.*version 99"):
        load_model_handle(newer)
    del state["noise"]
    state["version"] = 1
    damaged = tmp_path / "damaged.pt"
    torch.save(state, damaged)
    with pytest.raises(ValueError, match="damaged.pt.*missing noise"):
        load_model_handle(damaged)
    handle = load_model_handle(out)
    model = load_model(out)
    assert handle.kind == "latent" and handle.heldback_names == model.calibration_names
    assert handle.train_names == model.train_names and handle.frame == model.frame


# ---- the command line ------------------------------------------------------------------------------------------
def _collection(path, scans, **kw):
    from datasets.collection import ScanCollection

    ScanCollection.create(path, scans, **kw)
    return path


def test_cli_trains_and_resumes_on_the_same_collection_only(tmp_path, capsys):
    """Training, resuming, and refusing to resume on another collection (the other user mistakes of the command line:
    tests/latent/test_train_cli.py)."""
    from train_latent import main

    scans = sphere_scans(radii=(0.15, 0.2, 0.25, 0.3, 0.35)) + [
        sphere_scan("val/000", 0.22, seed=40, split="validation"), sphere_scan("test/000", 0.3, seed=41, split="test")]
    data = _collection(tmp_path / "spheres.h5", scans)
    out = tmp_path / "run" / "model.pt"
    out.parent.mkdir()
    args = ["--data", str(data), "--out", str(out), "--latent-dim", "2", "--width", "16", "--depth", "1",
            "--epochs", "2", "--batch", "3", "--quiet"]
    assert main(args) == 0
    model = load_model(out)
    assert model.calibration_names == ["val/000"]  # the validation split is the calibration set
    assert len(model.train_names) == 5 and "test/000" not in model.train_names
    assert (tmp_path / "run" / "model.log.csv").is_file() and (tmp_path / "run" / "model.loss.png").is_file()
    from datasets.collection import ScanCollection

    with ScanCollection(data) as c:
        assert model.fingerprint == c.fingerprint()

    assert main(args[:-5] + ["--batch", "3", "--epochs", "3", "--resume", "--quiet"]) == 0
    assert load_model(out).epoch == 3

    other = _collection(tmp_path / "other.h5", sphere_scans(radii=(0.2, 0.3)))
    capsys.readouterr()
    assert main(["--data", str(other), "--out", str(out), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(out) in err and "another collection" in err
    assert load_model(out).epoch == 3  # untouched


def test_cli_trains_on_the_threads_it_is_given(tmp_path, monkeypatch):
    import torch

    import train_latent

    import autodecoder.latent.train as train_module

    seen = []  # the threads torch has when training starts
    monkeypatch.setattr(train_module, "train_collection", lambda *a, **k: seen.append(torch.get_num_threads()))
    before = torch.get_num_threads()
    try:
        base = ["--data", "c.h5", "--out", str(tmp_path / "m.pt")]
        train_latent.run(train_latent.build_parser().parse_args(base))  # default: one thread
        torch.set_num_threads(2)
        train_latent.run(train_latent.build_parser().parse_args(base + ["--threads", "0"]))  # torch's own: untouched
    finally:
        torch.set_num_threads(before)
    assert seen == [1, 2]


def test_cli_holds_back_a_calibration_fraction_without_validation_split(tmp_path):
    from train_latent import main

    data = _collection(tmp_path / "s.h5", sphere_scans(radii=(0.15, 0.2, 0.25, 0.3, 0.35)))
    out = tmp_path / "m.pt"
    assert main(["--data", str(data), "--out", str(out), "--latent-dim", "2", "--width", "16", "--depth", "1",
                 "--epochs", "1", "--quiet", "--calibration-fraction", "0.4"]) == 0
    model = load_model(out)
    assert len(model.calibration_names) == 2 and len(model.train_names) == 3
    assert not set(model.calibration_names) & set(model.train_names)


def test_cli_and_api_hold_back_the_same_scans(tmp_path):
    """train_latent.py and inspection's train_model choose the calibration scans by the one rule: the same seed and
    fraction hold back the same scans of the same collection (a fraction without a validation split, the
    validation split's good scans with one)."""
    from train_latent import main

    from autodecoder.latent.collection_split import split_training_scans
    from datasets.collection import ScanCollection
    from inspection.training import train_model

    # spheres of several radii look like a family of sizes: its decision is not what this test is about
    tiny = ["--latent-dim", "2", "--width", "16", "--depth", "1", "--epochs", "1", "--quiet", "--family", "off"]
    scans = sphere_scans(radii=(0.15, 0.2, 0.25, 0.3, 0.35)) + [sphere_scan("train/005", 0.32, seed=42)]
    for name, extra in (("plain", []), ("val", [sphere_scan("val/000", 0.22, seed=40, split="validation")])):
        data = _collection(tmp_path / f"{name}.h5", scans + extra)
        cli, api = tmp_path / f"{name}_cli.pt", tmp_path / f"{name}_api.pt"
        assert main(["--data", str(data), "--out", str(cli), "--seed", "3", "--calibration-fraction", "0.5",
                     *tiny]) == 0
        train_model(data, api, calibration_fraction=0.5, seed=3, epochs=1, latent_dim=2, width=16, depth=1,
                    family=False)
        a, b = load_model(cli), load_model(api)
        assert a.calibration_names == b.calibration_names and a.train_names == b.train_names
        with ScanCollection(data) as c:
            train, held = split_training_scans(c, calibration_fraction=0.5, seed=3)
            assert a.train_names == [c.names[i] for i in train] and a.calibration_names == held
        assert len(held) == (1 if extra else 3) and not set(held) & set(a.train_names)


def test_trimmed_mean_matches_numpy_and_trim_is_validated(trained):
    from autodecoder.latent.projection import _trimmed_mean

    values = torch.rand(3, 50, generator=torch.Generator().manual_seed(0))
    expected = np.sort(values.numpy(), axis=1)[:, :40].mean(1)
    assert np.allclose(_trimmed_mean(values, 0.2).numpy(), expected, rtol=1e-6)
    assert np.allclose(_trimmed_mean(values, 0.0).numpy(), values.numpy().mean(1), rtol=1e-6)
    model, _ = trained
    with pytest.raises(ValueError, match="trim"):
        model.project(sphere_scan("t", 0.25).points, trim=1.0)


def test_trimmed_projection_is_not_pulled_by_a_defect(trained):
    """A quarter of a 0.25-sphere's points moved out to 0.33 (close enough for E f not to saturate there, so that
    they pull a plain least-squares projection): the trimmed projection keeps the radius of the good majority."""
    model, _ = trained
    scan = sphere_scan("test/bumped", 0.25, seed=12)
    points = scan.points.copy()
    moved = np.random.default_rng(1).random(len(points)) < 0.25
    points[moved] *= 0.33 / 0.25
    plain = model.project(points, scan.normals, seed=0)
    trimmed = model.project(points, scan.normals, seed=0, trim=0.3)
    r_plain, r_trim = zero_crossing_radius(plain.field), zero_crossing_radius(trimmed.field)
    assert abs(r_plain - 0.25) > abs(r_trim - 0.25) + 0.01, (r_trim, r_plain)  # measured: 0.258 vs 0.277
    assert abs(r_trim - 0.25) < 0.1 * 0.25, r_trim


def test_target_pools_are_a_function_of_scan_and_epoch_and_reuse_samples():
    from autodecoder.latent.pools import ScanTargetPool
    from autodecoder.field.targets import CloudTargets

    scan = sphere_scan("a", 0.3, n=300)
    targets = CloudTargets(scan.points, scan.normals, 0.05)
    kw = dict(seed=3, mean_samples=64, refresh=2, passes=3, pair_clusters=4, cluster_size=3)
    a, b = ScanTargetPool(targets, 6, **kw), ScanTargetPool(targets, 6, **kw)  # 6: cycles start at epoch 0
    for e in (0, 1, 5, 6, 2):  # b sees only these epochs, a sees them again below: no hidden state
        assert all(np.array_equal(u, v) for u, v in zip(a.mean_batch(e), b.mean_batch(e)))
    epochs = [a.mean_batch(e)[0] for e in range(6)]  # one pool of 128 samples serves 6 epochs
    pool = {tuple(r) for r in np.concatenate(epochs[:2])}
    assert len(pool) == 128 and all({tuple(r) for r in np.concatenate(epochs[k:k + 2])} == pool for k in (2, 4))
    assert not np.array_equal(epochs[0], epochs[2])  # a new shuffle each pass
    assert not np.array_equal(a.mean_batch(6)[0], epochs[0])  # a new pool after `passes` passes
    x0 = a.pair_batch(0)[0]
    assert np.array_equal(a.pair_batch(2)[0], x0) and not np.array_equal(a.pair_batch(3)[0], x0)
    other = ScanTargetPool(targets, 1, **kw)  # another scan draws other samples, on a staggered cycle
    assert not np.array_equal(other.mean_batch(0)[0], a.mean_batch(0)[0])
    first = {tuple(r) for e in range(5) for r in other.mean_batch(e)[0]}
    assert len(first) == 128 and not first & {tuple(r) for r in other.mean_batch(5)[0]}


def test_default_epochs_give_every_code_the_same_number_of_updates():
    from autodecoder.latent.options import DEFAULT_EPOCHS, MAX_DEFAULT_STEPS, MIN_DEFAULT_EPOCHS, default_epochs

    # every code is updated DEFAULT_EPOCHS times, whatever the collection's size and the batch
    for n in (3, 26, 64, 100):
        assert default_epochs(n, 8) == DEFAULT_EPOCHS
    assert default_epochs(26, 4) == default_epochs(100, 8, world=2) == DEFAULT_EPOCHS
    # a collection so large that this would exceed MAX_DEFAULT_STEPS steps: as many epochs as fit, at least the minimum
    assert default_epochs(1000, 8) == MAX_DEFAULT_STEPS // 125 < DEFAULT_EPOCHS  # 125 steps an epoch
    assert default_epochs(1000, 8) * 125 <= MAX_DEFAULT_STEPS < (default_epochs(1000, 8) + 1) * 125
    assert default_epochs(2000, 8, world=2) == default_epochs(1000, 8)  # 1,000 scans a process
    assert default_epochs(100_000, 8) == MIN_DEFAULT_EPOCHS
    # the resolved count is what the checkpoint records
    model = train_latent(sphere_scans()[:2], None, seed=0, quiet=True, stop_after=1, **TINY)
    assert model.config["epochs"] == default_epochs(2, TINY["batch"]) and model.epoch == 1


def test_training_threads_sets_and_restores_torch_threads():
    import torch

    from autodecoder.latent.distributed import TRAINING_THREADS, training_threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with training_threads():
            assert torch.get_num_threads() == TRAINING_THREADS
        assert torch.get_num_threads() == 2
        with training_threads(0):  # torch's own setting, untouched
            assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError), training_threads(1):
            assert torch.get_num_threads() == 1
            raise RuntimeError("restored on the way out too")
        assert torch.get_num_threads() == 2
        with pytest.raises(ValueError, match="threads"), training_threads(-1):
            pass
    finally:
        torch.set_num_threads(before)


def test_the_reported_loss_of_a_large_scan_comes_from_a_subsample_and_the_code_does_not_change(trained):
    """With one code left (any steps with several starts end with the best one), the final loss only reports it:
    ``loss_points`` of the points give the same code and a loss within 10 % of the loss on every point; with several
    codes left (no steps) the loss picks among them on every point."""
    model, _ = trained
    scan = sphere_scan("test/large", 0.25, seed=12)
    n = len(scan.points)
    options = dict(seed=0, steps=30, starts=2, explore=10)
    full = model.project(scan.points, scan.normals, loss_points=None, **options)
    sub = model.project(scan.points, scan.normals, loss_points=n // 4, **options)
    assert torch.equal(full.code, sub.code) and full.start == sub.start
    assert sub.loss != full.loss and abs(sub.loss - full.loss) <= 0.1 * full.loss
    # a scan no larger than loss_points, or several codes left: the loss on every point
    assert model.project(scan.points, scan.normals, loss_points=n, **options).loss == full.loss
    several = dict(options, steps=0)
    assert model.project(scan.points, scan.normals, loss_points=n // 4, **several).loss == \
        model.project(scan.points, scan.normals, loss_points=None, **several).loss
    with pytest.raises(ValueError, match="loss_points"):
        model.project(scan.points, scan.normals, loss_points=0)


@pytest.mark.parametrize("oriented,trim", [(True, 0.0), (False, 0.0), (True, 0.25), (False, 0.25)])
def test_the_manual_code_gradient_is_autograds(trained, oriented, trim):
    """The projection's SIREN path (no autograd) gives autograd's loss and code gradient, in float64, for oriented
    and sign-free normals, with and without trimming; and a whole projection follows the same codes."""
    import copy

    from autodecoder.latent import projection as proj

    model, _ = trained
    net = copy.deepcopy(model.mean_net).double()
    rng = np.random.default_rng(3)
    x = torch.from_numpy(rng.normal(scale=0.3, size=(3, 40, 3)))
    normals = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(3, 40, 3))), dim=-1)
    flags = torch.tensor([oriented, True, oriented])
    z = torch.from_numpy(rng.normal(scale=0.1, size=(3, model.latent_dim))).requires_grad_(True)
    expected = proj._data_loss(net, x, normals, flags, z, 100.0, trim)
    expected.sum().backward()
    loss, grad = proj._data_loss_and_code_grad(net, x, normals, flags, z.detach(), 100.0, trim)
    np.testing.assert_allclose(loss.numpy(), expected.detach().numpy(), rtol=1e-12)
    np.testing.assert_allclose(grad.numpy(), z.grad.numpy(), rtol=1e-9, atol=1e-12 * float(z.grad.abs().max()))

    scan = sphere_scan("t", 0.27, seed=4)
    normals_in = None if not oriented else scan.normals
    fast = model.project(scan.points, normals_in, seed=0, trim=trim)
    proj_manual = proj._manual_path
    try:
        proj._manual_path = lambda *a: False
        slow = model.project(scan.points, normals_in, seed=0, trim=trim)
    finally:
        proj._manual_path = proj_manual
    np.testing.assert_allclose(fast.code.numpy(), slow.code.numpy(), atol=1e-4)
    assert fast.start == slow.start and abs(fast.loss - slow.loss) <= 1e-4 * abs(slow.loss)


def test_the_projections_adam_is_torchs_step_for_step():
    """The projection's Adam on the codes gives torch.optim.Adam's codes to the bit: through a decaying learning
    rate, and after keeping one start per scan with its moments (as the projection does at the end of exploring)."""
    from autodecoder.latent.projection import _CodeAdam

    rng = torch.Generator().manual_seed(0)
    z0 = torch.randn(2, 3, 5, generator=rng)
    grads = [torch.randn(2, 3, 5, generator=rng) for _ in range(40)]
    ours, theirs = torch.nn.Parameter(z0.clone()), torch.nn.Parameter(z0.clone())
    adam, opt = _CodeAdam(ours), torch.optim.Adam([theirs], lr=0.05)
    rows, keep = torch.arange(2), torch.tensor([2, 0])
    for step, grad in enumerate(grads):
        lr = 0.05 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / 40)))
        adam.step(grad if step < 15 else grad[:, :1], lr)
        for group in opt.param_groups:
            group["lr"] = lr
        theirs.grad = grad if step < 15 else grad[:, :1]
        opt.step()
        if step == 14:  # one start per scan kept, with its moments
            ours = torch.nn.Parameter(ours.detach()[rows, keep][:, None].clone())
            adam = adam.kept(ours, rows, keep)
            state = opt.state[theirs]
            theirs = torch.nn.Parameter(theirs.detach()[rows, keep][:, None].clone())
            opt = torch.optim.Adam([theirs], lr=lr)
            opt.state[theirs] = {"step": state["step"], "exp_avg": state["exp_avg"][rows, keep][:, None].clone(),
                                 "exp_avg_sq": state["exp_avg_sq"][rows, keep][:, None].clone()}
        assert torch.equal(ours, theirs), step


def test_a_single_codes_loss_is_computed_when_first_read(trained):
    """With one code left the projection's loss is computed only when read (inspection never reads it), and is then
    what it always was; with several codes left it picks among them and is there at once."""
    model, _ = trained
    scan = sphere_scan("test/lazy", 0.25, seed=13)
    one = model.project(scan.points, scan.normals, seed=0, steps=20, starts=2, explore=5)
    assert one.loss_value is None and one.loss_of is not None
    again = model.project(scan.points, scan.normals, seed=0, steps=20, starts=2, explore=5)
    assert torch.equal(one.code, again.code) and np.isfinite(one.loss) and one.loss == again.loss
    assert one.loss_value == one.loss and one.loss_of is None
    several = model.project(scan.points, scan.normals, seed=0, steps=0, starts=2)
    assert several.loss_value is not None and several.loss_of is None


def test_the_steps_parallel_pieces_give_the_run_of_one_thread(tmp_path, monkeypatch):
    """The training draws each step's targets in a worker thread while the step before runs, and computes the
    covariance net's terms and gradients in another thread beside the mean net's (autodecoder.latent.loop): the
    same run to the bit as every piece in the calling thread (an executor that runs each piece when submitted),
    and as the one graph of all four terms with one backward pass (no thread beside)."""
    import concurrent.futures

    import autodecoder.latent.loop as loop

    class AtOnce:  # an executor that runs each piece when it is submitted, in the calling thread
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args):
            future = concurrent.futures.Future()
            future.set_result(fn(*args))
            return future

    import datasets.parallel

    monkeypatch.setattr(datasets.parallel, "usable_cores", lambda: 2)  # the threads' path on a machine of any size
    scans = sphere_scans(radii=(0.2, 0.3, 0.25))
    kw = dict(epochs=3, seed=5, quiet=True, **{**TINY, "batch": 1})
    runs = {"threads": train_latent(scans, tmp_path / "threads.pt", **kw)}
    with monkeypatch.context() as patch:
        patch.setattr(concurrent.futures, "ThreadPoolExecutor", AtOnce)
        runs["at_once"] = train_latent(scans, tmp_path / "at_once.pt", **kw)
    one_graph = loop._train_step
    monkeypatch.setattr(loop, "_train_step", lambda state, module, inputs, options, pos, beside=None:
                        one_graph(state, module, inputs, options, pos, None))
    runs["one_graph"] = train_latent(scans, tmp_path / "one_graph.pt", **kw)
    a = read_checkpoint(tmp_path / "threads.pt")
    for other in ("at_once", "one_graph"):
        b = read_checkpoint(tmp_path / f"{other}.pt")
        for key in ("mean_state", "cov_state"):
            for name, value in a[key].items():
                assert torch.equal(value, b[key][name]), (other, key, name)
        assert torch.equal(runs["threads"].codes, runs[other].codes), other
        assert [r["loss"] for r in a["info"]["history"]] == [r["loss"] for r in b["info"]["history"]], other
