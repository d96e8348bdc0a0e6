"""The identity of the code that computes a run's numbers.

A tracked run is only as good as the code that made it, so every run records
``code_identity()``: the package version and a fingerprint of the modules that
can change a run's numbers, and of the bundled meshes. Resume reuses a run
only when its identity matches the running code's.

Which modules count is read from the package tree, never from a list: every
module of ``mpe3d.solvers`` (subpackages included), and every ``mpe3d``
module that the run entry point (:data:`RUN_ENTRY`) imports, directly or
through others, at the top or inside a function, with the packages that hold
them. A module added, moved or split on a run's path is covered without
editing anything; the command line, tracking, sweeps and reports are not on
that path and are not part of it.

The fingerprint is taken over each module's syntax tree with docstrings
dropped, so comments, docstrings and formatting do not change it.

A run of a plug-in's solver or dataset (:mod:`mpe3d.plugins`) carries the
plug-in's identity too (:func:`run_code`): its name, its distribution's
version and the same kind of fingerprint over its own source. Editing a
plug-in changes the identity of its runs and of no other.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import os
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

from mpe3d.harness.files import cache_folder

PACKAGE = "mpe3d"
RUN_ENTRY = "mpe3d.harness.experiment.execute"  # where a worker starts a run: every pipeline is below it
SOLVERS_PACKAGE = "mpe3d.solvers"
_IGNORED_FIELDS = {"ctx", "type_comment", "kind"}


def _canonical(node) -> str:
    """A syntax tree as text, stable across Python versions: empty and ``None``
    fields (which newer Pythons add) are left out, positions are never in."""
    if isinstance(node, list):
        return "[" + ",".join(_canonical(item) for item in node) + "]"
    if not isinstance(node, ast.AST):
        return repr(node)
    fields = []
    for name in node._fields:
        value = getattr(node, name, None)
        if name in _IGNORED_FIELDS or value is None or value == []:
            continue
        fields.append(f"{name}={_canonical(value)}")
    return f"{type(node).__name__}({','.join(fields)})"


def _without_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree


def source_fingerprint(source: str) -> str:
    """SHA-256 of one module's code, blind to comments, docstrings and layout."""
    tree = _without_docstrings(ast.parse(source))
    return hashlib.sha256(_canonical(tree).encode()).hexdigest()


def module_file(name: str) -> Path | None:
    """Where module ``name`` of this package lives (its ``__init__.py`` for a package).

    Read off the package's folders, not by ``find_spec``: that imports every
    parent package, and the fingerprint would load the solvers and POT into a
    fresh process before its first run needs them (a second of each start).
    A layout not on disk (an editable install's finder) falls back to it.
    """
    parts = name.split(".")
    folder = _package_folder()
    if parts[0] != PACKAGE or folder is None:
        return _spec_file(name)
    for i, part in enumerate(parts[1:], start=2):
        if (folder / part / "__init__.py").is_file():
            folder = folder / part
        elif (folder / f"{part}.py").is_file():
            return folder / f"{part}.py" if i == len(parts) else None  # else a name in a module
        elif i == 2:  # a top-level folder not beside mpe3d/__init__.py: another layout
            return _spec_file(name)
        else:
            return None  # a name a package's __init__ defines
    return folder / "__init__.py"


@lru_cache(maxsize=1)
def _package_folder() -> Path | None:
    spec = importlib.util.find_spec(PACKAGE)
    return Path(spec.origin).parent if spec and spec.origin else None


def _spec_file(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def imported_modules(name: str, path: Path) -> set[str]:
    """The ``mpe3d`` modules that module ``name`` imports anywhere in its code
    (a name imported from a package counts when it is a module itself)."""
    found = _parsed(name, path)["imports"]
    return {m for m in found if module_file(m)}


def _imported_names(name: str, path: Path, tree: ast.AST) -> list[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                root = ".".join(parts[:len(parts) - node.level + 1])
                base = f"{root}.{base}" if base else root
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names}
    return sorted(m for m in found if m.split(".")[0] == PACKAGE)


def _parsed(name: str, path: Path) -> dict:
    """Module ``name``'s fingerprint and the package's names it imports, from
    the on-disk cache when its bytes were parsed before (two syntax-tree passes
    over the run's 50 modules are 1.1 s of every fresh process)."""
    data = path.read_bytes()
    key = f"{name}:{hashlib.sha256(data).hexdigest()}"
    cache = _parse_cache()
    if key not in cache.entries:
        source = data.decode()
        tree = ast.parse(source)
        cache.entries[key] = {"imports": _imported_names(name, path, tree),
                              "fingerprint": source_fingerprint(source)}
        cache.changed = True
    return cache.entries[key]


class _ParseCache:
    """Parsed modules by name and SHA-256 of their bytes, in one JSON file per
    version of this module and of Python (either may change what a parse
    gives), under ``$XDG_CACHE_HOME/mpe3d`` (``~/.cache/mpe3d``). Keyed by
    content, an entry can never describe other code than the file's; an
    unreadable cache is ignored, an unwritable one is not written."""

    def __init__(self):
        own = hashlib.sha256(Path(__file__).read_bytes() + sys.version.encode()).hexdigest()[:16]
        self.path = cache_folder() / f"identity-{own}.json"
        self.changed = False
        try:
            self.entries = json.loads(self.path.read_text())
            if not isinstance(self.entries, dict):
                raise ValueError
        except (OSError, ValueError):
            self.entries = {}

    def save(self) -> None:
        if not self.changed:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            part = self.path.with_suffix(f".{os.getpid()}.part")
            part.write_text(json.dumps(self.entries))
            os.replace(part, self.path)  # whole or not at all, whoever writes last
        except OSError:
            pass
        self.changed = False


@lru_cache(maxsize=1)
def _parse_cache() -> _ParseCache:
    return _ParseCache()


def _with_packages(names: set[str]) -> set[str]:
    """Importing ``a.b.c`` runs ``a`` and ``a.b`` first: they count too."""
    return names | {".".join(n.split(".")[:i]) for n in names for i in range(1, n.count(".") + 1)}


def _solver_modules() -> set[str]:
    root = module_file(SOLVERS_PACKAGE).parent
    return {SOLVERS_PACKAGE + "".join("." + part for part in p.relative_to(root).with_suffix("").parts
                              if part != "__init__")
            for p in root.rglob("*.py")}


@lru_cache(maxsize=1)
def fingerprinted_modules() -> frozenset[str]:
    """Every module whose code is in :func:`code_fingerprint`: the solvers, and
    the closure of :data:`RUN_ENTRY`'s imports inside the package."""
    todo, seen = [RUN_ENTRY, *_solver_modules()], set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        todo.extend(imported_modules(name, module_file(name)) - seen)
    return frozenset(_with_packages(seen))


def _numeric_files() -> list[tuple[str, Path]]:
    files = [(name, module_file(name)) for name in sorted(fingerprinted_modules())]
    meshes = module_file("mpe3d.harness.scene").parent / "assets" / "meshes"
    files += [(f"meshes/{p.name}", p) for p in sorted(meshes.glob("*.ply"))]
    return files


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """The fingerprint of everything that can change a run's numbers (hex, 12 digits)."""
    digest = hashlib.sha256()
    for name, path in _numeric_files():
        part = _parsed(name, path)["fingerprint"] if path.suffix == ".py" \
            else hashlib.sha256(path.read_bytes()).hexdigest()
        digest.update(f"{name}:{part}\n".encode())
    _parse_cache().save()
    return digest.hexdigest()[:12]


@lru_cache(maxsize=1)
def code_identity() -> str:
    """``<version>/<fingerprint>``: what a run's ``mpe3d.code`` tag holds."""
    from mpe3d import __version__

    return f"{__version__}/{code_fingerprint()}"


@lru_cache(maxsize=1)
def git_commit() -> str | None:
    """The git commit of the checkout this code runs from (``+dirty`` if modified).

    ``None`` for an installed copy: a virtual environment inside a checkout is
    not that checkout's code, so the module must be a file git tracks.
    """
    here = Path(__file__).resolve()

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(here.parent), *args], capture_output=True,
                              text=True, timeout=10)

    try:
        if git("ls-files", "--error-unmatch", "__init__.py").returncode != 0:
            return None
        commit = git("rev-parse", "HEAD")
        if commit.returncode != 0:
            return None
        dirty = git("status", "--porcelain", "--untracked-files=no").stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit.stdout.strip() + ("+dirty" if dirty else "")


def _plugin_fingerprint(origin) -> str:
    digest = hashlib.sha256()
    root = origin.path if origin.path and origin.path.is_dir() else None
    for path in origin.sources():
        name = path.relative_to(root) if root else path.name
        try:
            part = source_fingerprint(path.read_text())
        except (OSError, SyntaxError, ValueError):  # unreadable now: its bytes, or nothing
            part = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "missing"
        digest.update(f"{name}:{part}\n".encode())
    return digest.hexdigest()[:12]


_FINGERPRINTS: dict = {}


def plugin_identity(origin) -> str:
    """``<plug-in>-<version>/<fingerprint>``: a plug-in's part of a run's code
    identity, by the same canonical-tree method as ours, over its file or every
    module of its package (``file`` stands for the version of a lone file)."""
    stamps = tuple((str(p), p.stat().st_mtime_ns) for p in origin.sources() if p.is_file())
    key = (origin, stamps)
    if key not in _FINGERPRINTS:
        _FINGERPRINTS[key] = _plugin_fingerprint(origin)
    return f"{origin.name}-{origin.version or 'file'}/{_FINGERPRINTS[key]}"


def run_code(solver: str, shape: str, sfm: str | None = None) -> str:
    """The code identity of a run of ``solver`` on ``shape``: ours, and that of
    each plug-in it uses (its solver; its dataset for ``shape=NAME:item``; its
    structure-from-motion method ``sfm``), joined by ``+``. Editing a plug-in
    changes its runs' identity and no other's."""
    from mpe3d import plugins

    plugins.load_entry_points()
    used = [plugins.owner("solver", solver), plugins.owner("dataset", shape.partition(":")[0])]
    if sfm is not None:
        used.append(plugins.owner("sfm", sfm))
    return "+".join([code_identity(), *(plugin_identity(o) for o in used if o)])


def is_current(code: str, current: str) -> bool:
    """Whether a run's ``code`` is ``current`` code, a plug-in's part aside."""
    return code == current or code.startswith(current + "+")
