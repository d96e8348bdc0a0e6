"""What several commands share: the one-line parser, the options of the
commands that run sweeps, plug-ins, YAML limits, and the sweep runner's call."""

from __future__ import annotations

import argparse
import sys

from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import BACKENDS

TRACKING_HELP = "MLflow store (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)"
RESUME_LINE = "mpe3d: interrupted; every run logged so far is kept: run the same command to resume"


class Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line and exit code 2."""

    def error(self, message: str):  # noqa: D401 - argparse's signature
        raise MpeError(message)


def say(text: str = "", quiet: bool = False) -> None:
    if not quiet:
        print(text, flush=True)


def add_run_options(parser) -> None:
    """The options of every command that runs sweeps."""
    parser.add_argument("--jobs", type=int, default=-1, metavar="N",
                        help="parallel runs (default -1: one per core; dask: local workers)")
    parser.add_argument("--backend", choices=BACKENDS, default=None,
                        help="loky (one machine, default) or dask (a cluster)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster)")
    parser.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    parser.add_argument("--rerun-failed", action="store_true", help="retry runs that FAILED before")
    parser.add_argument("--force", action="store_true", help="rerun every run, even FINISHED ones")
    parser.add_argument("--reuse-stale", action="store_true",
                        help="reuse FINISHED runs computed by other code (by default a run counts "
                        "as done only when the code that computed it is this code)")
    parser.add_argument("--no-artifacts", action="store_true",
                        help="do not store reconstruction.ply and ground_truth.ply")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no summary")


def add_plugins(parser, solver_axis: bool = False) -> None:
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                        help="load a plug-in file (solvers, datasets) first; repeatable")
    if solver_axis:
        parser.add_argument("--solver", action="append", default=[], metavar="NAME",
                            help="add solver NAME to the solver axis of every sweep that compares "
                            "solvers, in the settings it declares; repeatable")


def add_yaml_limit(parser) -> None:
    from mpe3d.harness.experiment.limits import MAX_YAML_MB

    parser.add_argument("--max-yaml-mb", type=float, default=MAX_YAML_MB, metavar="MB",
                        help=f"refuse YAML files larger than this (default {MAX_YAML_MB:g} MiB)")


def add_sweep_limits(parser) -> None:
    from mpe3d.harness.experiment.limits import MAX_RUNS

    parser.add_argument("--max-runs", type=int, default=MAX_RUNS, metavar="N",
                        help=f"refuse a sweep that expands to more runs (default {MAX_RUNS:,})")
    add_yaml_limit(parser)


def check_parallel(args) -> str:
    """The backend the flags ask for, after checking they fit together."""
    backend = args.backend or ("dask" if args.scheduler else "loky")
    if args.scheduler and backend != "dask":
        raise MpeError("--scheduler needs --backend dask")
    if args.jobs == 0 or args.jobs < -1:
        raise MpeError(f"--jobs: expected a positive count or -1 (all cores), got {args.jobs}")
    return backend


def run_sweeps(sweeps, args, tracker, summaries: bool = True) -> tuple[list, int]:
    """:func:`mpe3d.harness.runner.run_sweeps` with the command line's flags, printing as it goes."""
    from mpe3d.harness.runner import run_sweeps as run

    summarise = None
    if summaries and not args.no_artifacts:  # the report's drawing is paid for only here
        from mpe3d.reports.summary import log_sweep_summary as summarise
    reporter = None
    if not args.quiet:
        from mpe3d.harness.progress import RichReporter
        reporter = RichReporter()
    return run(sweeps, tracker, jobs=args.jobs, backend=check_parallel(args),
               scheduler=args.scheduler, artifacts=not args.no_artifacts,
               rerun_failed=args.rerun_failed, force=args.force, reuse_stale=args.reuse_stale,
               reporter=reporter, say=lambda text: say(text, args.quiet),
               summarise=summarise,
               warn=lambda text: print(f"mpe3d: {text}", file=sys.stderr, flush=True),
               stop=args.shutdown)


def with_solvers(sweeps, names):
    """``--solver NAME``: each sweep with NAME on its solver axis, where it has one."""
    if not names:
        return sweeps
    from mpe3d.harness.experiment.axes import add_solvers
    from mpe3d.solvers import SOLVERS, get_solver
    from mpe3d.solvers.sfm.methods import SFM_METHODS, get_sfm

    for name in names:  # an unknown name fails before anything runs
        if name not in SOLVERS and name in SFM_METHODS:
            get_sfm(name)
        else:
            get_solver(name)
    return [add_solvers(sweep, names) for sweep in sweeps]


def note_journal(tracker) -> None:
    """Say so when computed results still wait in the journal for this store."""
    from mpe3d.harness.tracking.journal import Journal

    journal = Journal()
    waiting = journal.pending(tracker.uri)
    if waiting:
        print(f"mpe3d: note: {waiting} computed result(s) in {journal.folder} are not in "
              f"{tracker.uri} yet; the next `mpe3d sweep` here replays them", file=sys.stderr)
