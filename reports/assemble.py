"""A report's parts that come from sweeps and a store: one section per
experiment, and the sentences said above the tables (the reproduction's facts,
the methods compared, the methods added with ``--solver``)."""

from __future__ import annotations

import os
import platform

import pandas as pd

from mpe3d.harness.experiment.sweep import FULL, load_sweep
from mpe3d.reports.claims import runs_per_group
from mpe3d.reports.load import finished, runs
from mpe3d.reports.paper import Section

__all__ = ["METHODS_TEXT", "added_methods", "experiment_section", "other_finished_runs",
           "reproduction_facts", "sweep_section"]

METHODS_TEXT = (
    "Methods: 'baseline (MDS)' and '3DMPE (paper)' are the paper's baseline and its SGD, "
    "implemented faithfully; 'ours (refine)' is mpe3d's exact solver, not the paper's. "
    "CD and EMD are 100 × mean distances after a rigid alignment, the scale of the authors' "
    "code; ROA is the RMS distance between corresponding points. The bundled shapes are "
    "CC0 stand-ins for ShapeNet's categories (`mpe3d shapes`).")


def sweep_section(sweep, tracker) -> Section:
    """The runs of ``sweep`` (at its scale and overrides) that ``tracker`` holds."""
    frame = runs(tracker, sweep.name, hashes=[c.hash() for c in sweep.runs]) \
        if tracker.experiment_id(sweep.name, create=False) else _empty_runs()
    return Section(sweep.name, frame, sweep.description, f"{sweep.path.name} --scale {sweep.scale}",
                   planned=len(sweep.runs), varying=sweep.varying, client=tracker.client,
                   full_runs_per_group=_full_runs_per_group(sweep))


def experiment_section(tracker, name: str, sweep=None) -> Section:
    """Every latest run of experiment ``name``; ``sweep``, a paper sweep of that
    name, gives its description and its varying keys."""
    return Section(name, runs(tracker, name), sweep.description if sweep else "",
                   varying=sweep.varying if sweep else (), client=tracker.client)


def other_finished_runs(sweep, tracker) -> int:
    """How many finished runs ``sweep``'s experiment holds that are not among
    the sweep's configs (other overrides or another scale)."""
    if not tracker.experiment_id(sweep.name, create=False):
        return 0
    frame = finished(runs(tracker, sweep.name))
    if frame.empty:
        return 0
    return int((~frame["config_hash"].isin({c.hash() for c in sweep.runs})).sum())


def _full_runs_per_group(sweep) -> int | None:
    """Runs per compared setting when ``sweep`` runs at its full scale (None: it does)."""
    if sweep.scale == FULL:
        return None
    full = load_sweep(sweep.path, FULL, max_runs=10**7, overrides=sweep.overrides)
    return runs_per_group(pd.DataFrame([c.flat() for c in full.runs]), full.varying)


def _empty_runs():
    return pd.DataFrame(columns=["status", "config_hash", "error", "solver.name", "method"])


def reproduction_facts(sweeps, plans, tracker, *, scale: str, run_wall_s: float, commit: str | None,
                       added: list[str]) -> list[str]:
    """The sentences above a reproduction's tables: what ran, where, on what code."""
    ran = sum(sum(p.counts.values()) for p in plans)
    reused = sum(p.skipped for p in plans)
    facts = [f"Scale {scale}; {sum(len(s.runs) for s in sweeps)} runs in "
             f"{len(sweeps)} experiments: {ran} run now, {reused} reused from {tracker.uri}; "
             f"wall time for the runs {run_wall_s:.1f} s on {os.cpu_count()} cores "
             f"({platform.node()}, mpe3d {tracker.code}{f', git {commit}' if commit else ''}).",
             METHODS_TEXT]
    return facts + added_methods(sweeps, added)


def added_methods(sweeps, names) -> list[str]:
    """A sentence per method added with ``--solver``: whose it is, where it ran."""
    from mpe3d.solvers import get_solver

    lines = []
    for name in names or []:
        spec = get_solver(name)
        used = [s.name for s in sweeps if name in s.added]
        left = [s.name for s in sweeps if name not in s.added]
        lines.append(f"Added method '{name}' ({spec.origin or 'mpe3d'}; {' and '.join(spec.settings)} "
                     f"projections): on the solver axis of {len(used)} experiments"
                     + (f"; not in {', '.join(left)}, which compare no solvers" if left else "") + ".")
    return lines
