"""The packages' data flow, checked on the source: datasets -> autodecoder.field -> autodecoder.latent ->
autodecoder.scanning -> inspection, no import pointing back and no import circle (imports inside functions
included), and light modules that do not import torch or other heavy libraries they do not need.

The benchmark harness too (``benchmarks/``): it imports the library and its own core modules, a suite (a module of
``benchmarks/suites/``, or a package there with its modules) never imports another suite, no module imports a
script, only ``benchmarks.inspect_api`` enters the inspection package (beyond its training and threshold modules),
no circle, no ``sys.path`` edits; the library never imports the benchmarks.

And size: no module of the packages or the harness over ``MAX_MODULE_LINES`` lines, no class over
``MAX_CLASS_LINES`` (a module with one job, a class kept to its contract: ../shared/STYLE.md's lessons)."""
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


def _circles(graph):
    """Every import circle of ``graph`` ({module: modules it imports}), as 'a -> b -> a' lines."""
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
    return circles


def test_no_import_circle_between_modules():
    modules = _modules()
    graph = {name: {t for t in _imports(name, path) if t in modules and t != name and not name.startswith(t + ".")}
             for name, path in modules.items()}
    circles = _circles(graph)
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


# ------------------------------------------------------------------------------------------------------ benchmarks
BENCHMARK_CORE = ("benchmarks", "benchmarks.record", "benchmarks.cache", "benchmarks.metrics", "benchmarks.baselines",
                  "benchmarks.inspect_api", "benchmarks.table", "benchmarks.surface_metrics", "benchmarks.suites",
                  "benchmarks.options")
LIBRARY = ("datasets", "autodecoder", "inspection", "train_latent")
# the inspection modules a benchmark module other than benchmarks.inspect_api may import: {module: who may}
INSPECTION_OUTSIDE_API = {"inspection.threshold": None, "inspection.training": ("benchmarks.cache",)}


def _benchmark_modules(root=ROOT):
    """{module name: source path} of every module under ``root/benchmarks``."""
    out = {}
    for path in sorted((root / "benchmarks").rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _edits_sys_path(path):
    """Whether the source refers to ``sys.path`` at all (insert, append, assignment, ...)."""
    tree = ast.parse(path.read_text(), str(path))
    return any(isinstance(n, ast.Attribute) and n.attr == "path" and isinstance(n.value, ast.Name)
               and n.value.id == "sys" for n in ast.walk(tree))


def _scripts(modules):
    """{stem: module name} of the files directly in benchmarks/ (a script run by path imports its neighbours by their
    bare stem); the library's package names excepted."""
    return {name.split(".")[1]: name for name in modules if name.count(".") == 1 and name.split(".")[1] not in LIBRARY}


def _within(module, package):
    return module == package or module.startswith(package + ".")


def _suite_of(module):
    """The suite a module of benchmarks/suites/ belongs to: ``benchmarks.suites.fit.grid`` -> ``benchmarks.suites.fit``
    (a suite that is a package may import its own modules, never another suite's)."""
    return ".".join(module.split(".")[:3])


def _benchmark_violations(modules):
    """What breaks the harness' rules in ``modules`` ({name: path} of benchmarks' modules): a list of lines."""
    scripts = _scripts(modules)
    wrong = []
    for name, path in modules.items():
        if _edits_sys_path(path):
            wrong.append(f"{name} edits sys.path")
        is_suite = name.startswith("benchmarks.suites.")
        for target in sorted(_imports(name, path)):
            top = target.split(".")[0]
            if top in scripts:
                wrong.append(f"{name} imports the script {target}")
            elif _within(target, "benchmarks.suites") and target != "benchmarks.suites" and (
                    is_suite and not _within(target, _suite_of(name))
                    or not is_suite and name != "benchmarks.__main__"):
                wrong.append(f"{name} imports the suite {target}")
            elif _within(target, "benchmarks") and not _within(target, "benchmarks.suites") and not any(
                    target == core or target.startswith(core + ".") for core in BENCHMARK_CORE) \
                    and target != "benchmarks.__main__":
                wrong.append(f"{name} imports {target}, not a core module of the harness")
            elif _within(target, "inspection") and target != "inspection" and name != "benchmarks.inspect_api":
                allowed = [m for m, who in INSPECTION_OUTSIDE_API.items()
                           if _within(target, m) and (who is None or name in who)]
                if not allowed:
                    wrong.append(f"{name} imports {target}: the inspection package goes through "
                                 f"benchmarks.inspect_api")
            elif target == "inspection" and name != "benchmarks.inspect_api":
                wrong.append(f"{name} imports inspection: the inspection package goes through benchmarks.inspect_api")
    return wrong


def test_benchmarks_keep_the_harness_rules():
    wrong = _benchmark_violations(_benchmark_modules())
    assert not wrong, "benchmarks/ against its rules:\n" + "\n".join(wrong)


def test_no_import_circle_in_the_benchmarks():
    modules = _benchmark_modules()
    scripts = _scripts(modules)
    graph = {}
    for name, path in modules.items():
        targets = set()
        for t in _imports(name, path):
            top, _, rest = t.partition(".")
            if top in scripts:  # a script's bare `import verdicts` is benchmarks.verdicts
                t = scripts[top] + ("." + rest if rest else "")
            if t in modules and t != name and not name.startswith(t + "."):
                targets.add(t)
        graph[name] = targets
    circles = _circles(graph)
    assert not circles, "import circles in benchmarks/:\n" + "\n".join(circles)


def test_the_library_never_imports_the_benchmarks():
    wrong = [f"{name} imports {t}" for name, path in _modules().items() for t in _imports(name, path)
             if _within(t, "benchmarks")]
    assert not wrong, "\n".join(wrong)


def test_the_benchmark_checks_see_a_wrong_module(tmp_path):
    """The checks above must be able to fail: a suite importing another suite, a script, the inspection package
    directly, and editing sys.path is found on each count; a module of a suite that is a package may import its own
    suite's modules and no other suite's; and a circle of two modules is found."""
    (tmp_path / "benchmarks" / "suites" / "pack").mkdir(parents=True)
    (tmp_path / "benchmarks" / "suites" / "pack" / "__init__.py").write_text(
        "from benchmarks.suites.pack.mode import run\n")
    (tmp_path / "benchmarks" / "suites" / "pack" / "mode.py").write_text(
        "from benchmarks.suites.pack import common\nfrom benchmarks.suites.probe import f\n")
    bad = tmp_path / "benchmarks" / "suites" / "probe.py"
    bad.write_text("import sys\nsys.path.insert(0, '..')\nfrom benchmarks.suites import inspection\n"
                   "def f():\n    from verdicts import synth\n    from inspection.run import score\n")
    (tmp_path / "benchmarks" / "verdicts.py").write_text("from benchmarks.suites.probe import f\n")
    wrong = "\n".join(_benchmark_violations(_benchmark_modules(tmp_path)))
    for expected in ("benchmarks.suites.probe edits sys.path", "imports the suite benchmarks.suites.inspection",
                     "imports the script verdicts", "imports inspection.run", "benchmarks.verdicts imports the suite",
                     "benchmarks.suites.pack.mode imports the suite benchmarks.suites.probe"):
        assert expected in wrong, wrong
    assert "imports the suite benchmarks.suites.pack" not in wrong, wrong  # its own modules
    assert _circles({"a": {"b"}, "b": {"a"}}) == ["a -> b -> a"]


# ------------------------------------------------------------------------------------------------------------ size
MAX_MODULE_LINES = 600
MAX_CLASS_LINES = 300
SIZED = ("datasets", "autodecoder", "inspection", "benchmarks")


def _oversized(paths, root=ROOT):
    """Lines naming each module of ``paths`` over ``MAX_MODULE_LINES`` lines and each class over ``MAX_CLASS_LINES``
    (from its ``class`` line to its last, decorators left out), with its size."""
    wrong = []
    for path in paths:
        source = path.read_text()
        name = path.relative_to(root).as_posix()
        lines = len(source.splitlines())
        if lines > MAX_MODULE_LINES:
            wrong.append(f"{name}: {lines} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(source, str(path))):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                wrong.append(f"{name}: class {node.name} {node.end_lineno - node.lineno + 1} lines (at most "
                             f"{MAX_CLASS_LINES})")
    return wrong


def test_no_module_or_class_is_too_long():
    """A module over 600 lines holds more than one job, a class over 300 more than its contract: split them (the
    procedure into a module of functions, each job into a module of its own)."""
    wrong = _oversized([p for package in SIZED for p in sorted((ROOT / package).rglob("*.py"))])
    assert not wrong, "too long:\n" + "\n".join(wrong)


def test_the_size_check_sees_a_long_module_and_a_long_class(tmp_path):
    long_class = "class Big:\n" + "    x = 1\n" * MAX_CLASS_LINES
    (tmp_path / "big.py").write_text(long_class + "\n" * (MAX_MODULE_LINES - MAX_CLASS_LINES))
    # exactly at both limits: a class of MAX_CLASS_LINES lines in a module of MAX_MODULE_LINES lines
    (tmp_path / "fine.py").write_text("class Small:\n" + "    x = 1\n" * (MAX_CLASS_LINES - 1)
                                      + "\n" * (MAX_MODULE_LINES - MAX_CLASS_LINES))
    wrong = _oversized(sorted(tmp_path.glob("*.py")), root=tmp_path)
    assert wrong == [f"big.py: {MAX_MODULE_LINES + 1} lines (at most {MAX_MODULE_LINES})",
                     f"big.py: class Big {MAX_CLASS_LINES + 1} lines (at most {MAX_CLASS_LINES})"], wrong
