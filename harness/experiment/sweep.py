"""Sweeps: a YAML file that expands into a grid of run configurations.

A sweep file has these top-level keys (see ``sweeps/README.md``)::

    name: views-vs-accuracy        # the MLflow experiment (default: the file's stem)
    description: free text         # the experiment's description in the MLflow UI
    base: {points: 512, solver: {name: sgd, max_iter: 300}}   # keys of `mpe3d run`
    grid: {views: [2, 3, 4], projections: [fixed, variable]}  # Cartesian product
    zip: {visibility.k: [1, 2, 3], views: [2, 3, 4]}          # vary together
    repeats: 3                     # seeds 0..2, or `seeds: [...]`
    scale:                         # named smaller versions; the file as written is "full"
      quick: {grid: {views: [2, 4]}, repeats: 1}

``zip`` may also be a list of such mappings (each group varies on its own,
and the groups are crossed with each other and with ``grid``). A list item
that is a mapping sets several keys at once, e.g.
``solver: [{name: baseline}, {name: sgd, max_iter: 200}]``.

The whole file is validated before anything runs: every error names
``file:line``. Each run's :meth:`RunConfig.hash` is its cache key.
"""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from mpe3d.errors import MpeError, suggest
from mpe3d.harness.experiment.axes import every_photo_set, varying_keys
from mpe3d.harness.experiment.config import (
    ALIASES,
    KEYS,
    RENDERED,
    RENDERING_KEYS,
    RunConfig,
    coerce_value,
    flatten,
    load_yaml,
    make_config,
    parse_override,
)
from mpe3d.harness.experiment.limits import check_run_count, check_run_memory
from mpe3d.harness.scene.shapes import check_shape

TOP_LEVEL = ("name", "description", "plugins", "base", "grid", "zip", "repeats", "seeds", "scale")
SCALABLE = ("base", "grid", "zip", "repeats", "seeds")  # what a scale may override
FULL = "full"  # the scale of a file as written


@dataclass(frozen=True)
class Sweep:
    """A validated, expanded sweep file."""

    name: str
    description: str
    path: Path
    sha256: str  # of the file's bytes: which exact file made a set of runs
    runs: tuple[RunConfig, ...]
    varying: tuple[str, ...]  # the keys whose value differs between runs
    collapsed: int  # grid points that duplicated an earlier one and were dropped
    scale: str = FULL
    scales: tuple[str, ...] = (FULL,)  # every scale the file offers
    overrides: tuple[str, ...] = ()  # KEY=VALUE given on the command line
    plugins: tuple[Path, ...] = ()  # the plug-in files it loads (its ``plugins`` key)
    added: tuple[str, ...] = ()  # solvers put on its solver axis by add_solvers

    def label(self, config: RunConfig) -> str:
        """``views=4 projections=fixed seed=0``: what sets this run apart."""
        flat = config.flat()  # a solver's run names none of the other solvers' options
        if flat["pipeline"] == "photos" and flat["photos.set"] != RENDERED:  # a folder's photos are not rendered
            flat = {k: v for k, v in flat.items() if k not in RENDERING_KEYS}
        return " ".join(f"{key}={flat[key]}" for key in self.varying if key in flat) or config.hash()


# One value an axis can take: resolved key -> (value, where it was written).
Setting = dict[str, tuple[Any, str]]


class _Source:
    """Turns a dotted YAML path into ``file:line`` for messages."""

    def __init__(self, path: Path, lines: Mapping[str, int]):
        self.path, self.lines = path, lines

    def where(self, dotted: str | None) -> str:
        while dotted:  # the path itself, else its nearest written parent
            if dotted in self.lines:
                line = self.lines[dotted]  # an int, or where an override was given
                return line if isinstance(line, str) else f"{self.path}:{line}"
            dotted = dotted[:max(dotted.rfind("."), dotted.rfind("["), 0)]
        return str(self.path)

    def error(self, message: str, dotted: str | None, hint: str = "") -> MpeError:
        return MpeError(f"{message} at {self.where(dotted)}", hint=hint)


def _resolve(key: str) -> str:
    return ALIASES.get(key, key)


def _check_key(key: str, dotted: str, src: _Source) -> str:
    """The resolved name of a run key written at ``dotted``, or a located error."""
    resolved = _resolve(key)
    if resolved not in KEYS and not resolved.startswith("solver."):
        raise src.error(f"unknown key '{key}'", dotted, suggest(key, list(KEYS) + list(ALIASES)))
    return resolved


def _setting(prefix: str, value: Any, dotted: str, src: _Source) -> Setting:
    """A list item as resolved keys; a mapping item sets several keys at once."""
    raw = flatten({prefix: value}) if isinstance(value, Mapping) else {prefix: value}
    out: Setting = {}
    for key, item in raw.items():
        at = dotted + key[len(prefix):]
        resolved = _check_key(key, at, src)
        if resolved in KEYS:  # types and choices now, with the item's own line
            try:
                item = coerce_value(resolved, item, KEYS[resolved])
            except MpeError as exc:
                raise exc.located(src.where(at)) from None
        out[resolved] = (item, at)
    return out


def _axis_lists(section: Any, name: str, src: _Source) -> dict[str, tuple[list, str]]:
    """``{key: [values]}`` of a grid or zip group, nested or dotted, checked to be lists."""
    if not isinstance(section, Mapping):
        raise src.error(f"{name}: expected a mapping of keys to lists of values", name)
    out: dict[str, tuple[list, str]] = {}

    def walk(node: Mapping, prefix: str) -> None:
        for key, value in node.items():
            key = f"{prefix}{key}"
            dotted = f"{name}.{key}"
            if isinstance(value, Mapping):  # nested keys, as in base
                walk(value, key + ".")
                continue
            if not isinstance(value, list):
                raise src.error(f"{dotted}: expected a list of values, got {value!r} "
                                "(put a single value under base)", dotted)
            if not value:
                raise src.error(f"{dotted}: empty list", dotted)
            out[key] = (value, dotted)

    walk(section, "")
    if not out:
        raise src.error(f"{name}: no keys to vary", name)
    return out


def _grid_axes(section: Any, src: _Source) -> list[list[Setting]]:
    if section is None:
        return []
    return [[_setting(key, v, f"{dotted}[{i}]", src) for i, v in enumerate(values)]
            for key, (values, dotted) in _axis_lists(section, "grid", src).items()]


def _zip_group(section: Any, name: str, src: _Source) -> list[Setting]:
    lists = _axis_lists(section, name, src)
    lengths = {key: len(values) for key, (values, _) in lists.items()}
    if len(set(lengths.values())) > 1:
        shown = ", ".join(f"{key} has {n}" for key, n in lengths.items())
        raise src.error(f"{name}: lists differ in length ({shown})", name)
    settings = [{} for _ in range(next(iter(lengths.values())))]
    for key, (values, dotted) in lists.items():
        for i, value in enumerate(values):
            settings[i].update(_setting(key, value, f"{dotted}[{i}]", src))
    return settings


def _zip_axes(section: Any, src: _Source) -> list[list[Setting]]:
    if section is None:
        return []
    if isinstance(section, list):
        if not section:
            raise src.error("zip: empty list", "zip")
        return [_zip_group(group, f"zip[{i}]", src) for i, group in enumerate(section)]
    return [_zip_group(section, "zip", src)]


def _seed_axis(data: Mapping, src: _Source) -> list[Setting]:
    if "repeats" in data and "seeds" in data:
        raise src.error("give either repeats or seeds, not both", "seeds")
    if "repeats" in data:
        n = data["repeats"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise src.error(f"repeats: expected a positive integer, got {n!r}", "repeats")
        return [{"seed": (s, "repeats")} for s in range(n)]
    if "seeds" in data:
        seeds = data["seeds"]
        if not isinstance(seeds, list) or not seeds:
            raise src.error(f"seeds: expected a non-empty list of integers, got {seeds!r}", "seeds")
        for i, s in enumerate(seeds):
            if isinstance(s, bool) or not isinstance(s, int) or s < 0:
                raise src.error(f"seeds: expected integers >= 0, got {s!r}", f"seeds[{i}]")
        if len(set(seeds)) != len(seeds):
            raise src.error("seeds: a seed is listed twice", "seeds")
        return [{"seed": (s, f"seeds[{i}]")} for i, s in enumerate(seeds)]
    return []


def _base(data: Mapping, src: _Source) -> Setting:
    section = data.get("base")
    if section is None:
        return {}
    if not isinstance(section, Mapping):
        raise src.error("base: expected a mapping of run keys", "base")
    out: Setting = {}
    for key, value in flatten(section).items():
        resolved = _check_key(key, f"base.{key}", src)
        out[resolved] = (value, f"base.{key}")
    return out


def _apply_overrides(data: Mapping, lines: Mapping[str, Any], overrides: Sequence[str],
                     src: _Source) -> tuple[dict, dict]:
    """``KEY=VALUE`` sets a base key and ``grid.KEY=[a, b]`` replaces (or adds) a
    grid axis, as if written in the file; errors name the override itself.

    A key that varies in the file cannot be set in base: the override must
    replace its axis (``grid.KEY=``), so that no setting is silently dropped.
    """
    data, lines = dict(data), dict(lines)
    for text in overrides:
        key, value = parse_override(text)
        where = f"the command line ({text})"
        if key in ("repeats", "seeds", "name"):
            if key != "name":  # one replaces the other, as in a scale
                data.pop("seeds" if key == "repeats" else "repeats", None)
            data[key], lines[key] = value, where
            continue
        section = "grid" if key.startswith("grid.") else "base"
        key = key[len(section) + 1:] if key.startswith(f"{section}.") else key
        resolved = _check_key(key, where, _Source(src.path, {where: where}))
        if section == "grid" and not isinstance(value, list):
            raise MpeError(f"grid.{key}: expected a list like [a, b], got {value!r} at {where}")
        axes = {name: _axis_lists(data[name], name, src) for name in ("grid", "zip")
                if isinstance(data.get(name), Mapping)}
        varied = [f"{name}.{k}" for name, lists in axes.items() for k in lists if _resolve(k) == resolved]
        if section == "base" and varied:
            raise MpeError(f"{key} varies in the sweep ({src.where(varied[0])}): replace its axis "
                           f"with grid.{key}=[...] at {where}")
        if section == "grid" and any(v.startswith("zip.") for v in varied):
            raise MpeError(f"{key} varies in a zip group ({src.where(varied[0])}); "
                           f"it cannot become a grid axis at {where}")
        current = flatten(data[section]) if isinstance(data.get(section), Mapping) else {}
        kept = {k: v for k, v in current.items() if _resolve(k) != resolved}
        base = flatten(data["base"]) if isinstance(data.get("base"), Mapping) else {}
        if section == "grid" and any(_resolve(k) == resolved for k in base):
            data["base"] = {k: v for k, v in base.items() if _resolve(k) != resolved}
        data[section] = {**kept, key: value}
        lines[f"{section}.{key}"] = where
    return data, lines


def _check_axes_disjoint(base: Setting, axes: list[list[Setting]], seeded: bool,
                         src: _Source) -> None:
    owner: dict[str, int] = {}
    for index, axis in enumerate(axes):
        for key, (_, where) in {k: v for setting in axis for k, v in setting.items()}.items():
            if owner.setdefault(key, index) != index:
                raise src.error(f"key '{key}' varies in two places (grid and zip, or two zip "
                                "groups); vary it in one", where)
    if seeded:
        written = [*base.items(), *((k, v) for axis in axes for s in axis for k, v in s.items())]
        for key, (_, where) in written:
            if key == "seed":
                raise src.error("seed is set by repeats/seeds; do not set it here too", where)


def _check_shapes(base: Setting, axes: list[list[Setting]], src: _Source) -> None:
    values = [base["shape"]] if "shape" in base else []
    values += [s["shape"] for axis in axes for s in axis if "shape" in s]
    for value, where in values:
        try:
            check_shape(value)
        except MpeError as exc:
            raise exc.located(src.where(where)) from None


def _grid_count(data: Mapping, src: _Source) -> int:
    """How many runs the grid expands to, from the lists' lengths alone."""
    count = 1
    if data.get("grid") is not None:
        count *= math.prod(len(v) for v, _ in _axis_lists(data["grid"], "grid", src).values())
    zips = data.get("zip")
    for i, group in enumerate(zips if isinstance(zips, list) else [zips] if zips else []):
        count *= max(len(v) for v, _ in _axis_lists(group, f"zip[{i}]", src).values())
    repeats = data.get("repeats")
    if isinstance(repeats, int) and not isinstance(repeats, bool) and repeats > 0:
        count *= repeats
    elif isinstance(data.get("seeds"), list):
        count *= max(1, len(data["seeds"]))
    return count


def _expand(base: Setting, axes: list[list[Setting]], src: _Source) -> list[RunConfig]:
    base_values = {key: value for key, (value, _) in base.items()}
    runs = []
    for combination in itertools.product(*axes):
        setting: Setting = dict(base)
        for part in combination:
            setting.update(part)
        overrides = {key: value for key, (value, _) in setting.items()}
        try:
            runs.append(make_config(overrides, base=base_values))
            check_run_memory(runs[-1])
        except MpeError as exc:
            varied = ", ".join(f"{k}={overrides[k]}" for p in combination for k in p)
            context = f" (in the run with {varied})" if varied else ""
            where = src.where(setting.get(exc.key, (None, None))[1])
            raise MpeError(f"{exc.message} at {where}{context}", key=exc.key, hint=exc.hint) from None
    return runs


def _scales(data: Mapping, src: _Source) -> dict[str, Mapping]:
    """The file's named scales, each a mapping of the sections it overrides."""
    section = data.get("scale") or {}
    if not isinstance(section, Mapping):
        raise src.error("scale: expected a mapping of scale names to overrides", "scale")
    for name, override in section.items():
        at = f"scale.{name}"
        if name == FULL:
            raise src.error(f"{at}: '{FULL}' is the file as written; it takes no overrides", at)
        if not isinstance(override, Mapping):
            raise src.error(f"{at}: expected a mapping of {', '.join(SCALABLE)}", at)
        for key in override:
            if key not in SCALABLE:
                raise src.error(f"{at}: a scale overrides only {', '.join(SCALABLE)}, not '{key}'",
                                f"{at}.{key}", suggest(str(key), SCALABLE))
    return dict(section)


def _merge(section: Any, override: Any) -> Any:
    """A scale's base or grid on top of the file's: dotted keys replace one by one."""
    if not isinstance(section, Mapping) or not isinstance(override, Mapping):
        return override
    return {**flatten(section), **flatten(override)}


def _apply_scale(data: Mapping, lines: dict[str, int], scale: str, scales: Mapping,
                 src: _Source) -> tuple[dict, dict[str, int]]:
    """``data`` with scale ``scale`` applied, and the lines of the values it wrote."""
    if scale == FULL:
        return dict(data), lines
    if scale not in scales:
        offered = ", ".join([FULL, *scales])
        raise MpeError(f"{src.path} has no scale '{scale}' (it has: {offered})",
                       hint=suggest(scale, [FULL, *scales]))
    data, lines = dict(data), dict(lines)
    prefix = f"scale.{scale}."
    lines.update({k[len(prefix):]: v for k, v in lines.items() if k.startswith(prefix)})
    for key, override in scales[scale].items():
        if key in ("repeats", "seeds"):  # one replaces the other
            data.pop("seeds" if key == "repeats" else "repeats", None)
        data[key] = _merge(data.get(key), override) if key in ("base", "grid") else override
    return data, lines


def load_sweep(path: str | Path, scale: str = FULL, max_runs: int | None = None,
               max_mb: float | None = None, overrides: Sequence[str] = ()) -> Sweep:
    """Read, validate and expand a sweep file at one of its scales.

    ``overrides`` (``KEY=VALUE`` for a base key, ``grid.KEY=[a, b]`` for a
    grid axis, also ``repeats=N``) apply after the scale, as if written in the
    file: they are validated alike and the configs hash the same.

    Every error names ``file:line``; a scale's override is reported at its
    own line. A grid over ``max_runs`` runs (default
    :data:`~mpe3d.harness.experiment.limits.MAX_RUNS`) is refused before it is expanded, a
    file over ``max_mb`` MiB before it is parsed, and a run that cannot fit
    in memory before anything runs.
    """
    path = Path(path)
    data, lines = load_yaml(path, "sweep file", max_mb)
    src = _Source(path, lines)
    if not isinstance(data, Mapping):
        raise MpeError(f"{path}: a sweep must be a mapping with keys {', '.join(TOP_LEVEL)}")
    for key in data:
        if key not in TOP_LEVEL:
            raise src.error(f"unknown key '{key}'", str(key), suggest(str(key), TOP_LEVEL))
    plugin_files = _load_plugins(data.get("plugins"), path, src)  # before any key names a solver
    scales = _scales(data, src)
    data, lines = _apply_scale(data, lines, scale, scales, src)
    if overrides:
        data, lines = _apply_overrides(data, lines, overrides, _Source(path, lines))
    src = _Source(path, lines)
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not name.strip():
        raise src.error(f"name: expected a non-empty string, got {name!r}", "name")
    description = data.get("description") or ""
    if not isinstance(description, str):
        raise src.error("description: expected text", "description")
    base = _base(data, src)
    check_run_count(_grid_count(data, src), str(path), max_runs)
    seeds = _seed_axis(data, src)
    axes = _grid_axes(data.get("grid"), src) + _zip_axes(data.get("zip"), src)
    _check_axes_disjoint(base, axes, bool(seeds), src)
    _check_shapes(base, axes, src)
    runs = every_photo_set(_expand(base, axes + ([seeds] if seeds else []), src), src.where("base.photos.root"))
    unique: dict[str, RunConfig] = {}
    for config in runs:  # the first of identical grid points wins
        unique.setdefault(config.hash(), config)
    unique = list(unique.values())
    return Sweep(name=name.strip(), description=description.strip(), path=path,
                 sha256=hashlib.sha256(path.read_bytes() + "\n".join(overrides).encode()).hexdigest(),
                 runs=tuple(unique),
                 varying=varying_keys(unique), collapsed=len(runs) - len(unique),
                 scale=scale, scales=(FULL, *scales), overrides=tuple(overrides),
                 plugins=plugin_files)


def _load_plugins(value, path: Path, src: "_Source") -> tuple[Path, ...]:
    """The ``plugins`` key: plug-in files, relative to the sweep file, loaded now."""
    from mpe3d.plugins import PluginError, load_file

    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise src.error(f"plugins: expected a list of Python files, got {value!r}", "plugins")
    files = tuple((path.parent / Path(v).expanduser()).resolve() for v in value)
    for file in files:
        try:
            load_file(file)
        except PluginError as exc:
            raise src.error(f"plugins: {exc}", "plugins") from None
    return files
