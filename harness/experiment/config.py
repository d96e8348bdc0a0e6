"""Run configuration: every key of ``mpe3d run``, its default, and validation.

A :class:`RunConfig` is built from dotted ``KEY=VALUE`` overrides and/or a YAML
file, validated at that boundary, and can be turned back into a flat or a
nested dict and hashed canonically (the hash is the cache key of later sweeps).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from mpe3d.errors import MpeError, coerce, suggest
from mpe3d.options import (
    CAMERAS,
    COLMAP_SOLVERS,
    INITS,
    OBJECTIVES,
    OUTLIER_THRESHOLD,
    OUTLIER_THRESHOLDS,
    PROJECTIONS,
    REPROJECTION_LOSSES,
    REPROJECTION_SOLVERS,
    STARTS,
    STRESS_LOSSES,
    Choice,
    Interval,
)

SCHEMA_VERSION = 2  # bump when a key's meaning changes: every cached run is redone

VISIBILITY_MODES = ("all", "exact", "count", "raytrace", "zbuffer")
VIEW_LAYOUTS = ("band", "sphere")
NOISE_TYPES = ("none", "distance", "correspondence")
NOISE_VIEWS = ("one", "all")
NOISE_ROWS = ("per_view", "shared")
OBSERVE = ("distances", "coordinates")
ALIGNS = ("rigid", "ransac4")
PIPELINE_NAMES = ("points", "colmap", "tracks", "photos")  # execute.pipeline(name) runs them
# The files of a tracks run: hashed by their content, never by their path (config.hash)
TRACK_FILES = ("tracks.path", "tracks.truth", "tracks.cameras")
MATCHINGS = ("auto", "exhaustive", "sequential")
RENDERED = "rendered"  # photos.set: the shape photographed along a spiral, exact reference poses
EVERY_SET = "all"  # photos.set: a sweep makes one run per data set under photos.root
# What a rendered photo set is made of: a run of a folder's data set ignores them
RENDERING_KEYS = ("shape", "images.count", "images.size")
BACKENDS = ("loky", "dask")  # where a sweep's runs are computed (the runner's choice)


@dataclass(frozen=True)
class Key:
    """One documented configuration key and its rule: a :class:`Choice` of
    names (a tuple of names is one) or an :class:`Interval` of numbers."""

    default: Any
    kind: type
    doc: str
    rule: Choice | Interval | tuple | None = None
    optional: bool = False  # ``None`` is a valid value
    # Keys added after a cache already existed are hashed only away from their
    # default, so adding a key never invalidates the runs tracked before it.
    hashed_at_default: bool = True
    unit: str = ""  # said after the rule in an error ("pixels")

    def __post_init__(self):
        if isinstance(self.rule, tuple):
            object.__setattr__(self, "rule", Choice(self.rule))

    @property
    def choices(self) -> tuple[str, ...]:
        """The names a choice key takes (empty for any other key)."""
        return self.rule.names if isinstance(self.rule, Choice) else ()


KEYS: dict[str, Key] = {
    "pipeline": Key("points", str, "points: the paper's input, a sampled cloud seen through K projections; colmap: photos of the mesh from images.count cameras, reconstructed by COLMAP (pycolmap), its points scored and its feature tracks fed to mpe3d (views, visibility, noise, projections, observe, init, align and solver do not apply); tracks: a real keypoint data set (tracks.path), perturbed as the tracks.* keys say and solved as `mpe3d reconstruct` solves it (only seed, solver.name and the tracks.* keys apply)", PIPELINE_NAMES, hashed_at_default=False),
    "tracks.path": Key(None, str, "pipeline tracks: the keypoint data set, any input `mpe3d reconstruct` reads (CSV, NPZ, JSON, COLMAP model, Bundler .out, BAL), relative to tracks.root; runs are identified by its content, not its path", optional=True, hashed_at_default=False),
    "tracks.root": Key(None, str, "pipeline tracks: the folder that tracks.path, tracks.truth and tracks.cameras are relative to (null: the current folder); not part of a run's identity", optional=True, hashed_at_default=False),
    "tracks.truth": Key(None, str, "pipeline tracks: reference 3D points (CSV id,x,y,z with the tracks' ids), for the 3D error after a similarity", optional=True, hashed_at_default=False),
    "tracks.cameras": Key(None, str, "pipeline tracks: reference cameras, K 3x4 pinhole matrices (.npy) in the views' order, for the camera-centre error", optional=True, hashed_at_default=False),
    "tracks.views": Key(None, int, "pipeline tracks: keep the first this many views (null: all)", optional=True, hashed_at_default=False, rule=Interval(int, 2, None), unit="(or null: all views)"),
    "tracks.noise_px": Key(0.0, float, "pipeline tracks: Gaussian noise of this standard deviation in pixels added to every observation", hashed_at_default=False, rule=Interval(float, 0, None), unit="pixels"),
    "tracks.wrong_fraction": Key(0.0, float, "pipeline tracks: this share of the observations each replaced by another track's observation in the same view (wrong matches)", hashed_at_default=False, rule=Interval(float, 0, 1, "left")),
    "tracks.drop_fraction": Key(0.0, float, "pipeline tracks: this share of the observations removed (missing observations)", hashed_at_default=False, rule=Interval(float, 0, 1, "left")),
    "tracks.objective": Key("reprojection", str, "pipeline tracks: bundle adjustment of the reprojection error, or the 3DMPE stress of the pixel distances solved by solver.name (any stress solver, a plug-in's too)", OBJECTIVES, hashed_at_default=False),
    "tracks.camera": Key("auto", str, "pipeline tracks, objective reprojection: the camera model (auto: scaled or perspective, whichever explains the keypoints better; radial: the Bundler/BAL pinhole with k1, k2)", CAMERAS, hashed_at_default=False),
    "tracks.loss": Key("l2", str, "pipeline tracks: the robust loss of the reprojection error (scale 1 px), or refine's loss of the stress (l2, huber, soft_l1)", REPROJECTION_LOSSES, hashed_at_default=False),
    "tracks.outlier_threshold": Key(OUTLIER_THRESHOLD, float, "pipeline tracks, objective reprojection: observations beyond this many robust sigmas are taken for wrong matches and dropped (.inf keeps all)", hashed_at_default=False, rule=OUTLIER_THRESHOLDS, unit="(.inf keeps every observation)"),
    "tracks.solver": Key("bundle", str, "pipeline tracks, objective reprojection: who minimises the reprojection error, bundle (mpe3d's bundle adjustment), colmap (COLMAP's geometric verification and incremental mapper, pycolmap) or colmap_global (the same verification and COLMAP's global mapper, GLOMAP's) on the same perturbed tracks (COLMAP's: camera auto, radial or perspective; loss l2; start own)", REPROJECTION_SOLVERS, hashed_at_default=False),
    "tracks.start": Key("own", str, "pipeline tracks: where bundle adjustment starts: mpe3d's own start, or the cameras and points of a Bundler or BAL file", STARTS, hashed_at_default=False),
    "photos.root": Key(None, str, "pipeline photos: the folder whose subfolders holding images/ are photo data sets (each one's reference poses, if any: sparse/0, sparse or a Bundler .out beside images/); not part of a run's identity", optional=True, hashed_at_default=False),
    "photos.set": Key(RENDERED, str, "pipeline photos: the data set: rendered (shape photographed along a spiral of images.count photos of images.size pixels, turned and textured by seed, exact reference poses), a subfolder of photos.root, or all (a sweep makes one run per subfolder; runs are identified by the photos' and reference's content)", hashed_at_default=False),
    "photos.solver": Key("bundle", str, "pipeline photos: the structure-from-motion method given the data set's tracks (features and matches computed once and shared): bundle (mpe3d's bundle adjustment), colmap (COLMAP's incremental mapper), colmap_global (COLMAP's global mapper) or an SfM plug-in's name", hashed_at_default=False),
    "photos.cache": Key(None, str, "pipeline photos: the folder features and matches are cached in, by the photos' content and the extraction's options and code (null: $XDG_CACHE_HOME/mpe3d/features); not part of a run's identity", optional=True, hashed_at_default=False),
    "images.count": Key(250, int, "pipelines colmap and photos (rendered): photos rendered along the camera spiral", hashed_at_default=False, rule=Interval(int, 2, None)),
    "images.size": Key(400, int, "pipelines colmap and photos (rendered): width and height of each photo in pixels", hashed_at_default=False, rule=Interval(int, 64, 4096), unit="pixels"),
    "images.matching": Key("auto", str, "pipelines colmap and photos: COLMAP's matching: exhaustive, sequential along the camera path, or auto (exhaustive up to 50 photos)", MATCHINGS, hashed_at_default=False),
    "shape": Key("chair", str, "bundled name, mesh path, shapenet:<synset>/<id>, pix3d:<category>/<model>, or torus|box|sphere|cone"),
    "points": Key(512, int, "number N of points sampled area-uniformly on the surface", rule=Interval(int, 4, None)),
    "views": Key(4, int, "number K of views", rule=Interval(int, 2, None)),
    "angle_range": Key(360.0, float, "angle band theta_r in degrees from which the view angles are drawn", rule=Interval(float, 0, 360, "right"), unit="degrees"),
    "view_layout": Key("band", str, "band: angles drawn from theta_r split into K bins (the paper); sphere: K nearly equidistant directions (Fibonacci lattice, randomly turned)", VIEW_LAYOUTS, hashed_at_default=False),
    "visibility.mode": Key("exact", str, "which points each view sees: all; exact (k views each); count (random per view); raytrace (rays towards the camera against the mesh); zbuffer (the authors' z-buffer on the points)", VISIBILITY_MODES),
    "visibility.k": Key(3, int, "mode exact: every point is visible in exactly k views (1 <= k <= views)"),
    "visibility.count": Key(None, int, "mode count: every view keeps this many random points; null means round(0.75 * points)", optional=True),
    "visibility.n_rays": Key(None, int, "mode zbuffer: rays a side of each view's grid (a ray keeps the nearest point within 2 grid spacings); null means points // 3, the authors' default (their README uses 400)", optional=True, hashed_at_default=False, rule=Interval(int, 2, None)),
    "visibility.min_views": Key(0, int, "keep only the points visible in at least this many views (0 keeps all), as in the paper's raytrace-count figure", hashed_at_default=False),
    "noise.type": Key("none", str, "distance: Gaussian noise on distance rows; correspondence: wrong correspondences", NOISE_TYPES),
    "noise.fraction": Key(0.0, float, "q, the fraction of rows (distance) or points (correspondence) corrupted", rule=Interval(float, 0, 1)),
    "noise.rows": Key("per_view", str, "distance: the noisy rows drawn independently in each view, round(q n_k) of them, or one set of round(q N) points for all views (the authors' code)", NOISE_ROWS, hashed_at_default=False),
    "noise.views": Key("one", str, "correspondence: each wrong match is made in one random view of its point (the paper and the authors' code) or in all that see it (a consistent, undetectable wrong cloud)", NOISE_VIEWS, hashed_at_default=False),
    "noise.amplitude": Key(0.05, float, "p: noise variance p*d (distance) or displacement radius p*d (correspondence), d = cloud diameter", rule=Interval(float, 0, None)),
    "projections": Key("fixed", str, "fixed: the solver is given P^k; variable: it estimates them", PROJECTIONS),
    "observe": Key("distances", str, "what each view hands the solver: its distance matrix (the paper) or its points' 2D coordinates", OBSERVE),
    "init": Key("smart", str, "smart: start from the baseline (MDS); random: uniform in the unit cube", INITS),
    "align": Key("rigid", str, "alignment before CD/EMD: rigid (O(3) + translation) or ransac4 (paper Eq. 6-7)", ALIGNS),
    "seed": Key(0, int, "root seed; scene, noise, solver and metrics draw from separate streams of it", rule=Interval(int, 0, None)),
    "solver.name": Key("sgd", str, "solver name (see `mpe3d solvers`)"),
}

# ``solver`` alone is short for ``solver.name``.
ALIASES = {"solver": "solver.name"}


@dataclass(frozen=True)
class RunConfig:
    """The resolved configuration of one run.

    ``values`` maps every key of :data:`KEYS` to its value; ``solver_options``
    holds the ``solver.<option>`` keys, validated against the solver's
    signature.
    """

    values: Mapping[str, Any]
    solver_options: Mapping[str, Any] = field(default_factory=dict)

    def __getitem__(self, key: str) -> Any:
        if key.startswith("solver.") and key != "solver.name":
            return self.solver_options[key[len("solver."):]]
        return self.values[key]

    @property
    def solver(self) -> str:
        return self.values["solver.name"]

    def flat(self) -> dict[str, Any]:
        """All keys, dotted, solver options included."""
        out = dict(self.values)
        out.update({f"solver.{k}": v for k, v in sorted(self.solver_options.items())})
        return out

    def nested(self) -> dict[str, Any]:
        """The same keys as nested dicts, as a YAML config file would hold them."""
        out: dict[str, Any] = {}
        for key, value in self.flat().items():
            head, _, tail = key.partition(".")
            if tail:
                out.setdefault(head, {})[tail] = value
            else:
                out[head] = value
        return out

    def hash(self) -> str:
        """Canonical SHA-256 of the resolved values and the schema version."""
        flat = {key: value for key, value in self.flat().items()
                if key not in KEYS or KEYS[key].hashed_at_default or value != KEYS[key].default}
        if self.values["pipeline"] == "tracks":  # the data, not where it lies
            from mpe3d.harness.userdata.formats import content_digest

            flat.pop("tracks.root", None)
            for key in TRACK_FILES:
                if key in flat:
                    flat[key] = content_digest(track_file(self.values, key))
        if self.values["pipeline"] == "photos":  # the photos and their reference, not where they lie
            flat.pop("photos.root", None)
            flat.pop("photos.cache", None)
            folder = photo_set_folder(self.values)
            if folder is not None:
                from mpe3d.harness.userdata.photo_sets import dataset_digest

                flat["photos.set"] = dataset_digest(folder)
        payload = json.dumps({"schema": SCHEMA_VERSION, "config": flat},
                             sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(payload.encode()).hexdigest()[:16]

    def replace(self, **overrides: Any) -> "RunConfig":
        """A copy with dotted overrides applied (``replace(**{"visibility.k": 2})``).

        Switching solver drops the old solver's options: they need not exist
        on the new one.
        """
        overrides = {ALIASES.get(k, k): v for k, v in overrides.items()}
        base = self.flat()
        if overrides.get("solver.name", self.solver) != self.solver:
            base = dict(self.values)
        return make_config(overrides, base=base)


def flatten(mapping: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts to dotted keys; ``{"solver": "sgd"}`` stays a leaf."""
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def parse_override(text: str) -> tuple[str, Any]:
    """``"visibility.k=2"`` -> ``("visibility.k", 2)``; values are read as YAML scalars."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise MpeError(f"expected KEY=VALUE, got '{text}'")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.strip(), value


_MAX_NODES = 1_000_000  # YAML aliases can make a small file a huge tree ("billion laughs")
# PyYAML's C parser where it was built with libyaml: several times faster.
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _key_lines(node, path: Path, prefix: str = "", out: dict[str, int] | None = None,
               budget: list[int] | None = None) -> dict[str, int]:
    """Dotted path -> the 1-based line where it stands in a composed YAML node.

    Mapping keys give ``a.b``; list items give ``a.b[2]`` (so an error can
    point at the one bad value of a list written over several lines). A key
    written twice in one mapping, or once nested and once dotted, is an error
    naming both lines: YAML would silently keep the last.
    """
    out = {} if out is None else out
    budget = [_MAX_NODES] if budget is None else budget
    budget[0] -= 1
    if budget[0] < 0:
        raise MpeError(f"{path}: the YAML expands to over {_MAX_NODES:,} values (aliases?)")
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            dotted = f"{prefix}{key_node.value}"
            line = key_node.start_mark.line + 1
            if dotted in out and key_node.value != "<<":
                raise MpeError(f"duplicate key '{dotted}' at {path}:{line} "
                               f"(first at line {out[dotted]})", key=dotted)
            out[dotted] = line
            _key_lines(value_node, path, dotted + ".", out, budget)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            item_path = f"{prefix[:-1]}[{i}]"
            out[item_path] = item.start_mark.line + 1
            _key_lines(item, path, item_path + ".", out, budget)
    return out


def load_yaml(path: str | Path, what: str = "config file",
              max_mb: float | None = None) -> tuple[Any, dict[str, int]]:
    """Parse one YAML document: its data, and the line of every key and list item."""
    from mpe3d.harness.experiment.limits import check_yaml_size

    path = Path(path)
    try:
        check_yaml_size(path, what, max_mb)
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise MpeError(f"{what} {path} is not a UTF-8 text file") from None
    except OSError as exc:
        raise MpeError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        loader = _LOADER(text)  # one parse gives both the values and their lines
        try:
            node = loader.get_single_node()
            lines = _key_lines(node, path)
            data = loader.construct_document(node) if node is not None else None
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(exc, "problem", None) or "malformed YAML"
        raise MpeError(f"malformed YAML at {where}: {problem}") from None
    except RecursionError:
        raise MpeError(f"{what} {path}: nested too deeply") from None
    return data, lines


def read_yaml(path: str | Path, max_mb: float | None = None) -> tuple[dict[str, Any], dict[str, int]]:
    """A YAML run config (nested or dotted keys) as a flat dict, and each key's line."""
    data, lines = load_yaml(path, max_mb=max_mb)
    if data is None:
        return {}, {}
    if not isinstance(data, Mapping):
        raise MpeError(f"{path}: a run config must be a mapping of keys to values")
    return flatten(data), lines


def config_from_file(path: str | Path, overrides: Mapping[str, Any] | None = None,
                     max_mb: float | None = None) -> RunConfig:
    """A run config from a YAML file, with ``overrides`` on top.

    The file is validated on its own first, so an error in it names
    ``file:line``.
    """
    values, lines = read_yaml(path, max_mb)
    try:
        make_config(values)
    except MpeError as exc:
        spelled = {name: alias for alias, name in ALIASES.items()}  # "solver.name" may be "solver:"
        line = lines.get(exc.key) or lines.get(spelled.get(exc.key))
        where = f"{path}:{line}" if line else str(path)
        raise exc.located(where) from None
    return make_config({**values, **(overrides or {})})


def coerce_value(key: str, value: Any, spec: Key) -> Any:
    if value is None and spec.optional:
        return None
    value = coerce(key, value, spec.kind)
    if isinstance(spec.rule, Choice):
        spec.rule.check(key, value)
    return value


def _check_ranges(v: dict[str, Any]) -> None:
    def bad(key: str, rule: str) -> MpeError:
        return MpeError(f"{key}: {rule}, got {v[key]}", key=key)

    for key, spec in KEYS.items():  # each key's own rule, then the rules between keys
        if isinstance(spec.rule, Interval) and v[key] is not None:
            spec.rule.check(key, v[key], spec.unit)
    if not 1 <= v["visibility.k"] <= v["views"]:
        raise bad("visibility.k", f"must be between 1 and views={v['views']}")
    if not 0 <= v["visibility.min_views"] <= v["views"]:
        raise bad("visibility.min_views", f"must be between 0 and views={v['views']}")
    count = v["visibility.count"]
    if count is not None and not 2 <= count <= v["points"]:
        raise bad("visibility.count", f"must be between 2 and points={v['points']}")
    if v["pipeline"] == "tracks":
        _check_tracks(v, bad)
    if v["pipeline"] == "photos":
        _check_photos(v)
    if v["observe"] == "coordinates" and v["noise.type"] == "distance":
        raise MpeError("noise.type: distance noise perturbs distance matrices; with "
                       "observe=coordinates use correspondence noise", key="noise.type")


def track_file(values: Mapping[str, Any], key: str) -> Path | None:
    """Where the file of ``key`` (one of :data:`TRACK_FILES`) is: under tracks.root when relative."""
    if values[key] is None:
        return None
    path = Path(values[key]).expanduser()
    root = values["tracks.root"]
    return path if root is None or path.is_absolute() else Path(root).expanduser() / path


def _check_tracks(v: dict[str, Any], bad) -> None:
    if v["tracks.path"] is None:
        raise MpeError("tracks.path: pipeline=tracks needs a keypoint data set (tracks.path=FILE)",
                       key="tracks.path")
    for key in TRACK_FILES:
        path = track_file(v, key)
        if path is not None and not path.exists():
            hint = " (relative paths are under tracks.root=FOLDER, else the current folder)" \
                if v["tracks.root"] is None and not path.is_absolute() else ""
            raise MpeError(f"{key}: {path}: no such file or folder{hint}", key=key)
    if v["tracks.solver"] in COLMAP_SOLVERS and v["tracks.objective"] == "reprojection":
        from mpe3d.solvers.sfm.colmap_mapper import refused

        for option in ("camera", "loss", "start", "outlier_threshold"):
            reason = refused(option, v[f"tracks.{option}"])
            if reason is not None:
                raise bad(f"tracks.{option}", f"tracks.solver={v['tracks.solver']}: {reason}")
    if v["tracks.objective"] == "stress":  # solver.name: any registered solver (make_config checks it)
        if v["tracks.loss"] not in STRESS_LOSSES:
            raise bad("tracks.loss", f"the stress takes {' or '.join(STRESS_LOSSES)}")
        if v["tracks.loss"] != "l2" and v["solver.name"] != "refine":
            raise bad("tracks.loss", "a robust loss of the stress needs solver.name=refine")


def _check_photos(v: dict[str, Any]) -> None:
    from mpe3d.solvers.sfm.methods import BUILT_IN, get_sfm

    if v["photos.solver"] not in BUILT_IN:  # else a plug-in's, registered by now
        try:
            get_sfm(v["photos.solver"])
        except MpeError as exc:
            raise MpeError(f"photos.solver: {exc.message}", key="photos.solver", hint=exc.hint) from None
    if v["photos.set"] == EVERY_SET:  # a sweep expands it (to none without photos.root); a run takes one
        return
    if v["photos.set"] != RENDERED:
        from mpe3d.harness.userdata.photo_sets import set_folder

        set_folder(v["photos.root"], v["photos.set"])
        for key in RENDERING_KEYS:  # a folder's photos are not rendered: these keys do not apply
            v[key] = KEYS[key].default


def photo_set_folder(values: Mapping[str, Any]) -> Path | None:
    """The folder of a photos run's data set (None: a rendered set)."""
    if values["photos.set"] in (RENDERED, EVERY_SET):
        return None
    return Path(values["photos.root"]).expanduser() / values["photos.set"]


def make_config(overrides: Mapping[str, Any] | None = None,
                base: Mapping[str, Any] | None = None) -> RunConfig:
    """Validate dotted overrides on top of ``base`` (itself on top of the defaults)."""
    from mpe3d.solvers import validate_options  # solvers own their option lists

    values = {key: spec.default for key, spec in KEYS.items()}
    options: dict[str, Any] = {}
    merged = dict(base or {})
    merged.update(overrides or {})
    merged = {ALIASES.get(k, k): v for k, v in merged.items()}
    for key, value in merged.items():
        if key in KEYS:
            values[key] = coerce_value(key, value, KEYS[key])
        elif key.startswith("solver."):
            options[key[len("solver."):]] = value
        else:
            raise MpeError(f"unknown key '{key}'", key=key, hint=suggest(key, list(KEYS) + list(ALIASES)))
    _check_ranges(values)
    options = validate_options(values["solver.name"], options)
    return RunConfig(values=values, solver_options=options)


def describe_keys() -> str:
    """A table of every key, its default and its meaning (for ``--help`` and the README)."""
    rows = []
    for key, spec in KEYS.items():
        default = "null" if spec.default is None else spec.default
        choices = f" ({' | '.join(spec.choices)})" if spec.choices else \
            (f" ({spec.rule})" if spec.rule is not None else "")
        rows.append(f"  {key:<18} {str(default):<8} {spec.doc}{choices}")
    return "\n".join(rows)
