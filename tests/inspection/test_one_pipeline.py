"""The README's Python example and the command lines are one pipeline: on the same small synthetic collection and
model they store the same calibration and give every test scan the same score and verdict."""
import csv
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from datasets import Frame, Scan, ScanCollection

README = Path(__file__).resolve().parents[2] / "README.md"
FRAME = Frame(np.zeros(3), 1.0)


def _half_sphere(name, split, label, seed, dent=0.0, n=200):
    """A noisy half-sphere seen from +z (a partial scan), optionally with a dent at the pole."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 0.3 - dent * np.exp(-np.sum((v - [0, 0, 1]) ** 2, axis=1) / 0.05)
    p = v * r[:, None] + rng.normal(0, 0.002, (n, 3))
    return Scan(name=name, points=p.astype(np.float32), normals=v.astype(np.float32), split=split, label=label,
                defect="dent" if dent else "", sensor_origin=np.array([0.0, 0.0, 1.5], np.float32))


def _readme_inspection_example():
    """The README's inspection code block (the one that calls ``Inspector(model).fit``)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    found = [b for b in blocks if "Inspector(model).fit(" in b]
    assert len(found) == 1, "the README should hold exactly one inspection example"
    return found[0]


def _assert_same(a, b, where="calibration"):
    """Nested dicts / lists / tensors equal, exactly; the assertion names the first key that differs."""
    import torch

    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, dict):
        assert sorted(a) == sorted(b), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            _assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: lengths {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), f"{where}: tensors differ"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.fixture(scope="module")
def trained(tmp_path_factory, one_torch_thread):
    from inspection.training import train_model

    tmp = tmp_path_factory.mktemp("pipeline")
    scans = [_half_sphere(f"train/good/{i:03d}", "train", "good", seed=i) for i in range(8)]
    scans += [_half_sphere(f"test/good/{i:03d}", "test", "good", seed=20 + i) for i in range(2)]
    scans += [_half_sphere(f"test/dent/{i:03d}", "test", "defective", seed=30 + i, dent=0.1) for i in range(2)]
    ScanCollection.create(tmp / "tree.h5", scans, frame=FRAME)
    train_model(tmp / "tree.h5", tmp / "model.pt", calibration_fraction=0.4, epochs=20, width=32, depth=2,
                features=16, latent_dim=4, mean_samples=256, screen_samples=128, pair_clusters=8, batch=4, lr=3e-3,
                code_lr=3e-3)
    return tmp


def test_the_readme_example_and_the_command_lines_agree(trained, tmp_path, monkeypatch, capsys):
    from inspection import read_calibration
    from inspection.__main__ import main

    api, cli = tmp_path / "api", tmp_path / "cli"
    for folder in (api, cli):
        folder.mkdir()
        for name in ("tree.h5", "model.pt"):
            shutil.copy(trained / name, folder / name)
    # the README's example, as written, in a folder holding its tree.h5 and model.pt
    monkeypatch.chdir(api)
    namespace = {}
    exec(compile(_readme_inspection_example(), str(README), "exec"), namespace)
    insp, again, test = namespace["insp"], namespace["again"], namespace["test"]
    printed = capsys.readouterr().out
    assert "joint True" in printed  # 'auto': the training scans give the reference, the scans have sensor origins
    # the command lines on a copy of the same data
    monkeypatch.chdir(cli)
    assert main(["calibrate", "--model", "model.pt", "--data", "tree.h5", "--quiet"]) == 0
    assert main(["score", "--model", "model.pt", "--data", "tree.h5", "--out", "results", "--quiet"]) == 0
    capsys.readouterr()

    by_api, by_cli = read_calibration(api / "model.pt"), read_calibration(cli / "model.pt")
    _assert_same(by_cli.as_dict(), by_api.as_dict())  # settings, scores, names, roles, reference, rays: all of it
    # few training scans: by default each scored by its leave-one-out fold model
    assert by_api.roles.count("held-back") >= 3 and by_api.roles.count("fold") >= 4
    with open(cli / "results" / "scores.csv", newline="") as f:
        rows = {r["name"]: r for r in csv.DictReader(f)}
    assert sorted(rows) == sorted(s.name for s in test)
    scores = insp.anomaly_scores(test)
    np.testing.assert_allclose([float(rows[s.name]["score"]) for s in test], scores, rtol=1e-6)
    np.testing.assert_array_equal(again.anomaly_scores(test), scores)  # the stored calibration scores the same
    assert [rows[s.name]["verdict"] for s in test] == insp.verdicts_from_scores(scores).tolist()
    flagged = insp.predict(test) == -1
    assert all((rows[s.name]["verdict"] == "defective") <= flag for s, flag in zip(test, flagged))
    # scores.csv keeps 9 significant digits of a score and 6 of a p-value
    np.testing.assert_allclose([float(rows[s.name]["p_value"]) for s in test], insp.p_values(test), rtol=1e-5)
