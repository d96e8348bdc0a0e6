"""The house rules: layers, no cycles, public names across modules, one style.

The layer rule itself is written once, as import-linter contracts in
``pyproject.toml`` (docs/architecture.md explains it); these tests run it and
check what it cannot say.
"""
import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mpe3d.harness.tracking.identity import imported_modules
from tests.helpers import PACKAGE_DIRS, REPO, pyproject

OUR_CODE = [REPO / d for d in ("src", "harness", "solvers", "reports", "sweeps", "tests",
                               "scripts", "benchmarks", "examples")]


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """The package as it installs (one ``mpe3d`` folder), made of links to the
    checkout: static analysis reads it from disk, and an editable install
    keeps ``mpe3d``'s subpackages in other folders."""
    root = tmp_path_factory.mktemp("tree")
    package = root / "mpe3d"
    package.mkdir()
    for path in PACKAGE_DIRS["mpe3d"].iterdir():
        if path.suffix == ".py" or (path / "__init__.py").is_file():
            (package / path.name).symlink_to(path, target_is_directory=path.is_dir())
    for name, folder in PACKAGE_DIRS.items():
        if name != "mpe3d":
            (package / name.split(".")[1]).symlink_to(folder, target_is_directory=True)
    return root


def _modules() -> dict[str, Path]:
    """Every module of the package, by dotted name."""
    out = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in folder.rglob("*.py"):
            if "__pycache__" in path.parts:
                continue
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((package, *parts))
            out[name.removesuffix(".__init__")] = path
    return out


def _lint_imports(tree: Path, config: Path) -> subprocess.CompletedProcess:
    lint = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run([lint, "--config", str(config), "--no-cache"], cwd=tree, env=env,
                          capture_output=True, text=True, timeout=300)


def test_the_import_contracts_hold(tree):
    result = _lint_imports(tree, REPO / "pyproject.toml")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "broken" not in result.stdout.lower().split("contracts:")[-1].replace("0 broken", "")


def test_an_upward_import_breaks_the_contracts(tree, tmp_path):
    """The contracts can fail: a scene that imports the runner is refused."""
    copy = tmp_path / "mpe3d"
    shutil.copytree(tree / "mpe3d", copy, symlinks=False, ignore=shutil.ignore_patterns("__pycache__"))
    shapes = copy / "harness" / "scene" / "shapes.py"
    shapes.write_text(shapes.read_text() + "\nfrom mpe3d.harness import runner  # noqa\n")
    result = _lint_imports(tmp_path, REPO / "pyproject.toml")
    assert result.returncode != 0
    assert "mpe3d.harness.scene.shapes -> mpe3d.harness.runner" in result.stdout


def test_no_import_cycle_among_the_modules():
    """Module by module, function-level imports included (Tarjan's strongly
    connected components): a package importing its own modules is no cycle."""
    modules = _modules()
    edges = {name: sorted(m for m in imported_modules(name, path) & set(modules) if m != name
                          and not name.startswith(m + "."))
             for name, path in modules.items()}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for name in modules:
        if name not in index:
            visit(name)
    assert not cycles, cycles


def _private_uses(path: Path, own: str | None) -> list[str]:
    """``from mpe3d.x import _name`` and ``module._name`` where the module is
    another ``mpe3d`` module than ``own``."""
    tree = ast.parse(path.read_text())
    modules, found = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mpe3d") \
                and node.module != own:
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"{path.name}:{node.lineno} imports {node.module}.{alias.name}")
                modules[alias.asname or alias.name] = f"{node.module}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("mpe3d") and alias.name != own:
                    modules[alias.asname or alias.name.split(".")[0]] = alias.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                and node.value.id in modules and node.attr.startswith("_") \
                and not node.attr.startswith("__"):
            found.append(f"{path.name}:{node.lineno} uses {modules[node.value.id]}.{node.attr}")
    return found


def test_no_private_name_is_used_across_modules():
    """Outside the tests. A test may use the private names of a module it
    imports as a module (``bundle._race_points``): the module it tests, as
    scikit-learn's tests do."""
    own = {path: name for name, path in _modules().items()}
    uses = []
    for folder in OUR_CODE:
        for path in folder.rglob("*.py"):
            if "__pycache__" not in path.parts:
                found = _private_uses(path, own.get(path))
                if folder.name == "tests":
                    found = [use for use in found if " imports " in use]
                uses += found
    assert not uses, uses


def test_the_harness_shows_its_rooms():
    """At most about 8 modules at the harness's top."""
    top = [p.name for p in (REPO / "harness").glob("*.py") if p.name != "__init__.py"]
    assert len(top) <= 8, top


# The one module that calls COLMAP: every other reaches pycolmap through it.
COLMAP_ADAPTER = "mpe3d.solvers.sfm.colmap"


def _pycolmap_uses(source: str) -> list[int]:
    """The lines of ``source`` that import pycolmap, name it, or reach for the adapter's own handle."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if (isinstance(node, ast.Import) and any(a.name.split(".")[0] == "pycolmap" for a in node.names)
                or isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "pycolmap"
                or isinstance(node, ast.Name) and node.id == "pycolmap"
                or isinstance(node, ast.Attribute) and node.attr in ("_pycolmap", "_colmap")
                or isinstance(node, ast.Constant) and node.value == "pycolmap"):
            lines.append(node.lineno)
    return lines


def test_no_pycolmap_call_outside_the_colmap_adapter():
    uses = {name: found for name, path in _modules().items()
            if name != COLMAP_ADAPTER and (found := _pycolmap_uses(path.read_text()))}
    assert not uses, uses
    assert _pycolmap_uses(Path(_modules()[COLMAP_ADAPTER]).read_text())  # the rule sees a use
    assert _pycolmap_uses("import importlib\nimportlib.import_module('pycolmap')\n") == [2]
    assert _pycolmap_uses("from mpe3d.solvers.sfm import colmap\ncolmap.Camera('X', 1, 1, ())._colmap()\n") == [2]


# A module over MAX_LINES lines is two jobs until a line here says why it is one.
MAX_LINES = 500
ONE_JOB = {
    COLMAP_ADAPTER: "the one module that calls pycolmap (622 lines): its parts (cameras, databases, extraction and "
                    "matching with the photos numbered in name order, mapping by either mapper, models, estimators) "
                    "share its error handling and camera conversions",
}


def test_no_module_is_over_500_lines_without_a_reason():
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES and name not in ONE_JOB}
    assert not long, long


def test_no_constant_is_dead_and_no_module_ends_on_a_heading():
    """A module-level constant that nothing reads (INPUT_FORMATS was one) is a
    rule nobody follows; a section heading with nothing under it is a room
    with no one in it."""
    import re

    read = set()  # every name the code reads: loads, attributes, imports (comments and strings are not reads)
    for folder in OUR_CODE:
        for path in folder.rglob("*.py"):
            if "__pycache__" not in path.parts:
                for node in ast.walk(ast.parse(path.read_text())):
                    if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load):
                        read.add(node.id)
                    elif isinstance(node, ast.Attribute):
                        read.add(node.attr)
                    elif isinstance(node, ast.alias):
                        read.add(node.name.rsplit(".", 1)[-1])
                    elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                            and re.fullmatch(r"_?[A-Z][A-Z0-9_]*", node.value):
                        read.add(node.value)  # monkeypatch.setattr(module, "NAME", ...)
    dead, headings = [], []
    for name, path in _modules().items():
        source = path.read_text()
        for node in ast.parse(source).body:
            targets = node.targets if isinstance(node, ast.Assign) else \
                [node.target] if isinstance(node, ast.AnnAssign) else []
            for target in targets:
                if isinstance(target, ast.Name) and re.fullmatch(r"_?[A-Z][A-Z0-9_]*", target.id) \
                        and target.id not in read:
                    dead.append(f"{name}.{target.id}")
        last = [line for line in source.splitlines() if line.strip()][-1]
        if last.lstrip().startswith("# --"):
            headings.append(name)
    assert not dead, dead
    assert not headings, headings


def _packages() -> dict[str, Path]:
    return {name: path for name, path in _modules().items() if path.name == "__init__.py"}


def test_every_subpackage_declares_its_public_names():
    """``__all__`` in every package; each name is defined there (the root's
    on first use) or is one of its modules."""
    import importlib

    modules = _modules()
    for name in _packages():
        package = importlib.import_module(name)
        assert "__all__" in vars(package), f"{name} has no __all__"
        for public in package.__all__:
            assert f"{name}.{public}" in modules or hasattr(package, public), f"{name}.__all__: {public}"


def _layer_contracts() -> list[tuple[str, list[list[str]]]]:
    """(container, layers as lists of members) of each layers contract."""
    contracts = pyproject()["tool"]["importlinter"]["contracts"]
    out = []
    for contract in contracts:
        if contract["type"] == "layers":
            layers = [[m.strip() for m in layer.split("|")] for layer in contract["layers"]]
            for container in contract.get("containers", [""]):
                out.append((container, layers))
    return out


def _place(name: str, container: str, layers) -> tuple[int, str] | None:
    """(layer index, member) of module ``name`` in one contract, or None."""
    relative = name if not container else name.removeprefix(container + ".") if \
        name.startswith(container + ".") else None
    if relative is None:
        return None
    for index, layer in enumerate(layers):
        for member in layer:
            if relative == member or relative.startswith(member + "."):
                return index, member
    return None


def _may_import(doc: str, package: str) -> set[str]:
    """The modules a package's docstring says it may import."""
    import re

    text = doc.split("May import", 1)[1].split("\n\n", 1)[0]
    named = set()
    for ref in re.findall(r":mod:`~?([.\w]+)`", text):
        named.add(package + ref if ref.startswith(".") else ref)
    return named


def test_each_package_says_what_it_may_import_and_the_contracts_agree():
    """Every package's docstring has a "May import" paragraph naming modules
    that exist; the package imports nothing else (function-level imports
    included; mpe3d itself, the root, is free to all); and every module it
    names sits below it in every layer contract that places both."""
    modules = _modules()
    contracts = _layer_contracts()
    for package, path in _packages().items():
        if package == "mpe3d":
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        assert "May import" in doc, package
        allowed = _may_import(doc, package)
        assert all(m in modules for m in allowed), (package, sorted(allowed - set(modules)))
        inside = {n for n in modules if n == package or n.startswith(package + ".")}
        used = {m for n in inside for m in imported_modules(n, modules[n])} - inside - {"mpe3d"}
        stray = sorted(m for m in used if not any(m == a or m.startswith(a + ".") for a in allowed))
        assert not stray, f"{package} imports {stray}, which its docstring does not name"
        for module in allowed:
            for container, layers in contracts:
                mine, theirs = _place(package, container, layers), _place(module, container, layers)
                if mine and theirs and mine[1] != theirs[1]:
                    assert theirs[0] > mine[0], f"{package} may import {module}, above it in the contracts"


def test_a_stale_may_import_line_fails(tmp_path):
    """The check can fail: a docstring naming a module that does not exist."""
    assert _may_import("May import: :mod:`.pipelines` and :mod:`mpe3d.errors`.", "mpe3d.harness.experiment") \
        == {"mpe3d.harness.experiment.pipelines", "mpe3d.errors"}
    assert "mpe3d.harness.experiment.pipelines" not in _modules()


def test_the_code_follows_the_style():
    ruff = shutil.which("ruff") or str(Path(sys.executable).parent / "ruff")
    result = subprocess.run([ruff, "check", "--no-cache", "."], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:]
