"""The console entry points of pyproject.toml: each names a `main(argv=None)` that exists and whose `--help` exits 0
in-process, and each is the same command as its `python -m` form."""
import tomllib
from importlib.metadata import EntryPoint, PackageNotFoundError, distribution
from pathlib import Path

import pytest

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
EXPECTED = {  # entry point -> the module its `python -m` / `python <script>` form runs
    "nsspr-data": "datasets.__main__",
    "nsspr-train": "train_latent",
    "nsspr-inspect": "inspection.__main__",
    "nsspr-field": "autodecoder.__main__",
}


def _scripts():
    with open(PYPROJECT, "rb") as f:
        return tomllib.load(f)["project"]["scripts"]


def test_every_command_line_has_an_entry_point():
    scripts = _scripts()
    assert set(scripts) == set(EXPECTED)
    for name, module in EXPECTED.items():
        assert scripts[name] == f"{module}:main", name


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_entry_point_resolves_and_help_exits_0(name, capsys):
    main = EntryPoint(name, _scripts()[name], "console_scripts").load()  # what the installed script imports
    try:  # a console script exits with main's return value; argparse's --help may also raise SystemExit itself
        status = main(["--help"])
    except SystemExit as exc:
        status = exc.code
    assert status in (0, None)
    assert "usage:" in capsys.readouterr().out


def test_installed_entry_points_match_pyproject():
    """After `pip install -e .` the installed metadata carries the same scripts (skipped when the installed metadata
    predates them: reinstall to refresh it)."""
    try:
        installed = {ep.name: ep.value for ep in distribution("nsspr-inspect").entry_points
                     if ep.group == "console_scripts"}
    except PackageNotFoundError:
        pytest.skip("nsspr-inspect is not installed (pip install -e .)")
    if not installed:
        pytest.skip("the installed nsspr-inspect metadata predates the console entry points: pip install -e . again")
    assert installed == _scripts()
