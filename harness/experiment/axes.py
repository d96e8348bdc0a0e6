"""What a sweep's runs are crossed with beyond its file's own axes.

* :func:`every_photo_set`: ``photos.set=all`` becomes one run per data set
  found under ``photos.root`` when the sweep is expanded (the folder's
  content, not the file, says what the data sets are);
* :func:`add_solvers`: ``--solver NAME`` puts a method on a sweep's solver
  axis, a stress solver beside its points runs' solvers or an SfM plug-in
  beside its photos runs' methods;
* :func:`varying_keys`: what then sets its runs apart.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable, Sequence

from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import EVERY_SET, RENDERED, RunConfig


def every_photo_set(runs: list[RunConfig], where: str) -> list[RunConfig]:
    """Each photos run of ``photos.set=all`` as one run per data set under
    ``photos.root`` (none when it is not given: the sweep's rendered sets alone);
    ``where`` says where photos.root was set, for an error."""
    out = []
    for config in runs:
        if config["pipeline"] != "photos" or config["photos.set"] != EVERY_SET:
            out.append(config)
        elif config["photos.root"] is not None:
            names = _photo_sets(config["photos.root"], where)
            found = {}
            for name in names:
                run = config.replace(**{"photos.set": name})
                same = found.setdefault(run.hash(), name)  # a run is its data's, not its folder's
                if same != name:
                    raise MpeError(f"photos.root: {name} and {same} hold the same photos and reference; "
                                   f"keep one (at {where})", key="photos.root")
                out.append(run)
    return out


def _photo_sets(root: str, where: str) -> list[str]:
    """The data sets under ``root``: one line for none, or for a name a data set cannot have."""
    from pathlib import Path

    from mpe3d.harness.userdata.photo_sets import IMAGES, photo_sets

    try:
        names = photo_sets(root)
    except MpeError as exc:
        raise exc.located(where) from None
    if not names:
        hint = "it is a data set itself: give its parent" if (Path(root).expanduser() / IMAGES).is_dir() \
            else f"each data set is a subfolder holding {IMAGES}/"
        raise MpeError(f"photos.root: {root} holds no data set ({hint}) at {where}", key="photos.root")
    for name in names:
        if name in (RENDERED, EVERY_SET):
            raise MpeError(f"photos.root: {Path(root) / name}: a data set may not be named '{name}' (photos.set "
                           f"says {RENDERED} and {EVERY_SET} for the rendered sets and every data set); rename "
                           f"it at {where}", key="photos.root")
    return names


def add_solvers(sweep, names: Sequence[str]):
    """``sweep`` with solvers ``names`` put on its solver axis.

    A sweep has a solver axis when its ``points`` runs use two solvers or
    more (one compared with another); each such run is then run again with
    each added solver, in the settings (fixed, variable) the solver declares.
    Its ``photos`` runs are its structure-from-motion axis: each is run again
    with each added SfM plug-in (``photos.solver``).
    The sweep's own runs, and so their hashes and tracked results, are
    unchanged. A sweep without a solver axis is returned as it is.
    """
    from mpe3d.solvers import get_solver
    from mpe3d.solvers.sfm.methods import SFM_METHODS

    photos = [c for c in sweep.runs if c["pipeline"] == "photos"]
    points = [c for c in sweep.runs if c["pipeline"] == "points"]
    on_axis = [n for n in names if (n in SFM_METHODS and photos)
               or (n not in SFM_METHODS and len({c.solver for c in points}) >= 2)]
    if not on_axis:
        return sweep
    known = {c.hash() for c in sweep.runs}
    added: dict[str, RunConfig] = {}
    for name in on_axis:
        if name in SFM_METHODS:  # a structure-from-motion plug-in
            others = [c.replace(**{"photos.solver": name}) for c in photos]
        else:
            settings = get_solver(name).settings
            others = [c.replace(**{"solver.name": name}) for c in points if c["projections"] in settings]
        for other in others:
            if other.hash() not in known:
                added.setdefault(other.hash(), other)
    runs = sweep.runs + tuple(added.values())
    return replace(sweep, runs=runs, varying=varying_keys(runs),
                   added=tuple(dict.fromkeys((*sweep.added, *on_axis))))


def varying_keys(configs: Iterable[RunConfig]) -> tuple[str, ...]:
    """The dotted keys whose values differ between ``configs``, in key order.

    A solver option varies only if the runs of one solver differ in it: that
    other solvers lack it, or have another default, is not a difference.
    """
    flats = [c.flat() for c in configs]
    keys = dict.fromkeys(k for flat in flats for k in flat)

    def varies(key: str) -> bool:
        option = key.startswith("solver.") and key != "solver.name"
        seen: dict[object, set[str]] = {}
        for flat in flats:
            if key in flat:
                seen.setdefault(flat["solver.name"] if option else None, set()).add(repr(flat[key]))
        return any(len(values) > 1 for values in seen.values())

    return tuple(k for k in keys if varies(k))
