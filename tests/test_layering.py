"""The packages' data flow, checked on the source: datasets -> autodecoder.field -> autodecoder.latent ->
autodecoder.scanning -> inspection, no import pointing back and no import circle (imports inside functions
included), and light modules that do not import torch or other heavy libraries they do not need."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("datasets", "autodecoder.field", "autodecoder.latent", "autodecoder.scanning", "inspection")
HEAVY = ("torch", "open3d", "matplotlib", "sklearn", "h5py", "trimesh")


def _modules():
    """{module name: source path} of every module of the three packages."""
    out = {}
    for package in ("datasets", "autodecoder", "inspection"):
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(name, path):
    """Every project module ``name`` imports, anywhere in its source (absolute and relative, functions too)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names}  # `from pkg import module`
    return found


def _layer(module):
    matches = [i for i, layer in enumerate(LAYERS) if module == layer or module.startswith(layer + ".")]
    return matches[-1] if matches else None


def test_no_import_points_against_the_data_flow():
    wrong = []
    for name, path in _modules().items():
        own = _layer(name)
        if own is None:  # the packages' own __init__ / __main__ of autodecoder: the entry points, allowed all
            continue
        for target in _imports(name, path):
            other = _layer(target)
            if other is not None and other > own:
                wrong.append(f"{name} imports {target}")
    assert not wrong, "imports against datasets -> field -> latent -> scanning -> inspection:\n" + "\n".join(wrong)


def test_no_import_circle_between_modules():
    modules = _modules()
    graph = {name: {t for t in _imports(name, path) if t in modules and t != name and not name.startswith(t + ".")}
             for name, path in modules.items()}
    circles, state = [], {}

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                circles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not circles, "import circles:\n" + "\n".join(circles)


def test_the_layering_check_sees_a_wrong_import(tmp_path):
    """The checks above must be able to fail: a function-level import from inspection inside datasets is found."""
    bad = tmp_path / "probe.py"
    bad.write_text("def f():\n    from inspection.scores import point_scores\n")
    assert "inspection.scores" in _imports("datasets.probe", bad)
    assert _layer("inspection.scores") > _layer("datasets.probe")


LIGHT = sorted(name for name in _modules() if name.startswith("datasets") and name != "datasets.scan_dataset") + [
    "autodecoder", "autodecoder.__main__", "inspection", "inspection.__main__", "inspection.threshold",
    "inspection.report", "inspection.calibration", "train_latent"]


@pytest.mark.parametrize("module", LIGHT)
def test_light_modules_import_no_heavy_library(module):
    """Reading files, the command lines' --help and the threshold statistics must not wait for torch, open3d or
    matplotlib: those are imported by the functions that use them."""
    code = (f"import importlib, sys; importlib.import_module({module!r}); "
            f"print(','.join(h for h in {HEAVY!r} if h in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"importing {module} imports {out.stdout.strip()}"
