"""The identity of the code that computes a run's numbers.

A tracked run is only as good as the code that made it, so every run records
``code_identity()``: the package version and a fingerprint of the modules that
can change a run's numbers (scene, views, visibility, noise, observation,
metrics, every solver) and of the bundled meshes. Resume reuses a run only
when its identity matches the running code's.

The fingerprint is taken over each module's syntax tree with docstrings
dropped, so comments, docstrings and formatting do not change it; the command
line, tracking, sweeps and reports are not part of it at all.
"""

from __future__ import annotations

import ast
import hashlib
import subprocess
from functools import lru_cache
from pathlib import Path

# The harness modules on the path from a config to its metrics; every module
# of ``solvers`` counts too, so a new solver is covered without a list to edit.
NUMERIC_MODULES = ("colmap", "execute", "metrics", "noise", "observe", "photos", "pipeline_colmap",
                   "shapes", "views", "visibility")
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


def _numeric_files() -> list[tuple[str, Path]]:
    harness = Path(__file__).resolve().parent
    solvers = harness.parent / "solvers"
    files = [(f"harness/{name}.py", harness / f"{name}.py") for name in NUMERIC_MODULES]
    files += [(f"solvers/{p.name}", p) for p in sorted(solvers.glob("*.py"))]
    files += [(f"meshes/{p.name}", p) for p in sorted((harness / "assets" / "meshes").glob("*.ply"))]
    return files


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """The fingerprint of everything that can change a run's numbers (hex, 12 digits)."""
    digest = hashlib.sha256()
    for name, path in _numeric_files():
        part = source_fingerprint(path.read_text()) if path.suffix == ".py" \
            else hashlib.sha256(path.read_bytes()).hexdigest()
        digest.update(f"{name}:{part}\n".encode())
    return digest.hexdigest()[:12]


@lru_cache(maxsize=1)
def code_identity() -> str:
    """``<version>/<fingerprint>``: what a run's ``mpe3d.code`` tag holds."""
    from .. import __version__

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
