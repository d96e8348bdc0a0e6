"""Plug-ins: solvers, datasets and SfM methods that live outside mpe3d.

Two ways in, as benchopt users asked for (its issue 654):

- an installed distribution declares an entry point in the group
  ``mpe3d.solvers``, ``mpe3d.datasets`` or ``mpe3d.sfm`` whose value is a
  module; importing that module registers what it holds with
  :func:`mpe3d.register_solver`, :func:`mpe3d.register_dataset` or
  :func:`mpe3d.register_sfm`. Entry points are read the first time a
  name is not found, so mpe3d pays nothing for them until then;
- a plain Python file, named on the command line (``--plugin FILE``) or in a
  sweep file (``plugins: [FILE]``), loaded with :func:`load_file`.

Every registration is attributed to the plug-in it came from (an
:class:`Origin`): that is what the run's code identity fingerprints, what
``mpe3d solvers`` lists, and what an error names. A plug-in loads all or
nothing: one that fails to import, or registers a name that is taken,
leaves no registration behind and is reported in one line naming it and its
file. An installed plug-in that fails never breaks mpe3d for the other
solvers: it becomes a :class:`PluginWarning`, and asking for one of its names
says why it is missing.

This module sits below the solvers and the harness (it imports only
:mod:`mpe3d.errors`): the registries call :func:`claim` when something
registers, and tell it how to withdraw a name with :func:`add_registry`.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import sys
import traceback
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, MutableMapping

from mpe3d.errors import MpeError

# Kinds whose names share one namespace: a stress solver and an SfM method are both asked for by --solver NAME
ONE_NAMESPACE = {"solver": ("sfm",), "sfm": ("solver",)}
GROUPS = {"solver": "mpe3d.solvers", "dataset": "mpe3d.datasets", "sfm": "mpe3d.sfm"}  # kind -> entry-point group


class PluginError(MpeError):
    """A plug-in that cannot be used: it names the plug-in and its file."""


class PluginWarning(UserWarning):
    """An installed plug-in that failed to load; the others work."""


@dataclass(frozen=True)
class Origin:
    """Where registered names come from: one plug-in.

    ``path`` is the plug-in's file, or the folder of an installed plug-in's
    top-level package (every ``.py`` under it is its code); ``distribution``
    and ``version`` name the installed distribution, if any.
    """

    name: str
    path: Path | None
    how: str  # "entry point", "file" or "module" (registered by code mpe3d did not load)
    distribution: str | None = None
    version: str | None = None

    def sources(self) -> list[Path]:
        """The Python files whose code is this plug-in's."""
        if self.path is None:
            return []
        if self.path.is_dir():
            return sorted(p for p in self.path.rglob("*.py") if "__pycache__" not in p.parts)
        return [self.path]

    def __str__(self) -> str:
        where = f"{self.distribution} {self.version}, " if self.distribution else ""
        return f"plug-in {self.name} ({where}{self.how} {self.path or 'without a file'})"


_REGISTRIES: dict[str, MutableMapping] = {}  # kind -> the registry mapping names to specs
_OWNERS: dict[tuple[str, str], Origin] = {}  # (kind, name) -> its plug-in; absent: ours
_LOADED: dict[Path, str] = {}  # plug-in file -> the hash of the text that was loaded
_FAILED: dict[str, str] = {}  # entry-point plug-ins that failed -> the line that says why
_state = {"loading": None, "added": [], "entry_points": False}


def add_registry(kind: str, registry: MutableMapping) -> None:
    """Tell the loader where names of ``kind`` live, so that a plug-in that
    fails halfway can be withdrawn."""
    _REGISTRIES[kind] = registry


def claim(kind: str, name: str, func, reserved: tuple[str, ...] = ()) -> Origin | None:
    """Called by a registry as ``name`` registers: its plug-in (``None``: ours).

    Raises :class:`PluginError` when a plug-in takes a name that another
    plug-in or mpe3d already has, or one of ``reserved`` (names mpe3d's own
    methods of that kind answer to without being in the registry).
    """
    found = _origin_of(func)
    if found is None:  # ours, even when a plug-in's import is what imported it
        return None
    origin = _state["loading"] or found
    if name in reserved:
        raise PluginError(f"{origin}: {kind} '{name}' is one of mpe3d's own ({', '.join(reserved)}); "
                          "rename yours")
    for other in ONE_NAMESPACE.get(kind, ()):  # `--solver NAME` names either kind: one name, one method
        if name in _REGISTRIES.get(other, {}):
            holder = _OWNERS.get((other, name))
            raise PluginError(f"{origin}: {kind} '{name}' is already a {other} of "
                              f"{holder or 'mpe3d itself'}; rename yours")
    taken = name in _REGISTRIES.get(kind, {})
    holder = _OWNERS.get((kind, name))
    if taken and (holder is None or holder.path != origin.path):
        owner = str(holder) if holder else "mpe3d itself"
        raise PluginError(f"{origin}: {kind} '{name}' is already registered by {owner}; "
                          "rename yours")
    _OWNERS[(kind, name)] = origin
    _state["added"].append((kind, name))
    return origin


def owner(kind: str, name: str) -> Origin | None:
    """The plug-in that registered ``name`` (``None`` for mpe3d's own)."""
    return _OWNERS.get((kind, name))


def failure_note(kind: str) -> str:
    """Why installed plug-ins of ``kind`` are missing, for an 'unknown name' error."""
    group = GROUPS[kind]
    lines = [why for key, why in _FAILED.items() if key.startswith(group + ":")]
    return f" ({'; '.join(lines)})" if lines else ""


def _origin_of(func) -> Origin | None:
    """A registration from code mpe3d did not load (a script, a notebook, a
    package imported by hand): its plug-in is the file the function is in."""
    module = inspect.getmodule(func)
    name = getattr(module, "__name__", "__main__")
    if name == "mpe3d" or name.startswith("mpe3d."):
        return None
    file = getattr(module, "__file__", None)
    return Origin(name=name, path=Path(file).resolve() if file else None, how="module")


@contextmanager
def _loading(origin: Origin) -> Iterator[None]:
    """Attribute registrations to ``origin``; if loading fails, withdraw them."""
    outer, added = _state["loading"], _state["added"]
    _state["loading"], _state["added"] = origin, []
    try:
        yield
        if not _state["added"]:
            raise PluginError(f"{origin}: registers no solver, no dataset and no SfM method (decorate "
                              "a function with mpe3d.register_solver, mpe3d.register_dataset or "
                              "mpe3d.register_sfm)")
    except BaseException:
        for kind, name in _state["added"]:
            _REGISTRIES.get(kind, {}).pop(name, None)
            _OWNERS.pop((kind, name), None)
        raise
    finally:
        _state["loading"], _state["added"] = outer, added


def _failure(origin: Origin, exc: BaseException) -> PluginError:
    """One line: the plug-in, its file and line, and what went wrong there."""
    if isinstance(exc, PluginError):
        return exc
    files = {str(p) for p in origin.sources()}
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename in files]
    where = f" at {Path(frames[-1].filename).name} line {frames[-1].lineno}" if frames else ""
    text = str(exc).splitlines()[0] if str(exc) else ""
    return PluginError(f"{origin} failed to load{where}: {type(exc).__name__}"
                       + (f": {text}" if text else ""))


def load_file(path: str | Path) -> Origin:
    """Load the plug-in file ``path`` (again if its text changed since) and
    return its origin. Raises :class:`PluginError` in one line."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise PluginError(f"plug-in {path}: no such file")
    if path.suffix != ".py":
        raise PluginError(f"plug-in {path}: expected a Python file (.py)")
    path = path.resolve()
    origin = Origin(name=path.stem, path=path, how="file")
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise PluginError(f"plug-in {path}: cannot read it: {exc.strerror or exc}") from None
    digest = hashlib.sha256(text).hexdigest()
    if _LOADED.get(path) == digest:
        return origin
    module_name = f"mpe3d_plugin_{path.stem}_{hashlib.sha256(str(path).encode()).hexdigest()[:8]}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses and pickling look their module up here
    try:
        with _loading(origin):
            spec.loader.exec_module(module)
    except BaseException as exc:  # noqa: BLE001 - SystemExit and all: a plug-in never ends mpe3d
        sys.modules.pop(module_name, None)
        if isinstance(exc, KeyboardInterrupt):
            raise
        raise _failure(origin, exc) from None
    _LOADED[path] = digest
    return origin


def load_files(paths) -> list[Origin]:
    """:func:`load_file` for each path, in order."""
    return [load_file(p) for p in paths]


def loaded_files() -> list[Path]:
    """The plug-in files loaded in this process: a worker loads the same."""
    return list(_LOADED)


def _package_folder(module: str) -> Path | None:
    """The folder of ``module``'s top-level package (or its file, for a lone module)."""
    try:
        spec = importlib.util.find_spec(module.split(".")[0])
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin:
        return None
    top = Path(spec.origin).resolve()
    return top.parent if top.name == "__init__.py" else top


def load_entry_points() -> None:
    """Import every installed plug-in, once per process. One that fails is a
    :class:`PluginWarning`; the others and mpe3d's own names still work."""
    if _state["entry_points"]:
        return
    _state["entry_points"] = True
    for group in GROUPS.values():
        for point in importlib.metadata.entry_points(group=group):
            dist = getattr(point, "dist", None)
            origin = Origin(name=point.name, path=_package_folder(point.module), how="entry point",
                            distribution=getattr(dist, "name", None),
                            version=getattr(dist, "version", None))
            try:
                with _loading(origin):
                    point.load()
            except BaseException as exc:  # noqa: BLE001 - see load_file
                if isinstance(exc, KeyboardInterrupt):
                    raise
                line = str(_failure(origin, exc))
                _FAILED[f"{group}:{point.name}"] = line
                warnings.warn(line, PluginWarning, stacklevel=2)


def loaded() -> list[Origin]:
    """The plug-ins whose names are registered now, each once (entry points
    not yet read are not among them)."""
    return list(dict.fromkeys(_OWNERS.values()))


def unload(origin: Origin) -> None:
    """Withdraw every name ``origin`` registered, as if it had never loaded
    (a notebook that rewrites its plug-in, a test that cleans up)."""
    for kind, name in [key for key, owner in _OWNERS.items() if owner == origin]:
        _REGISTRIES.get(kind, {}).pop(name, None)
        del _OWNERS[(kind, name)]
    if origin.path is not None:
        _LOADED.pop(origin.path, None)


def installed() -> dict[str, list[Origin]]:
    """kind -> the plug-ins that registered names of that kind, each once."""
    load_entry_points()
    out: dict[str, list[Origin]] = {}
    for (kind, _), origin in _OWNERS.items():
        if origin not in out.setdefault(kind, []):
            out[kind].append(origin)
    return out


def failures() -> list[str]:
    """The installed plug-ins that failed to load, a line each."""
    load_entry_points()
    return list(_FAILED.values())
