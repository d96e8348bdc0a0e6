"""``mpe3d sweep`` (run YAML sweeps, tracked and resumable) and ``mpe3d runs``
(an experiment's runs as a table)."""

from __future__ import annotations

import sys
from pathlib import Path

from mpe3d.cli.options import (
    TRACKING_HELP,
    add_plugins,
    add_run_options,
    add_sweep_limits,
    check_parallel,
    note_journal,
    run_sweeps,
    with_solvers,
)
from mpe3d.errors import MpeError
from mpe3d.harness.shutdown import EXIT_CODE


def add_parsers(sub) -> dict:
    """The two parsers; ``sweep``'s reads options and overrides intermixed."""
    sweep = sub.add_parser("sweep", help="run YAML sweeps, tracked in MLflow, resuming what is done",
                           description="Expand each sweep file into a grid of runs, skip the runs "
                           "already FINISHED in its MLflow experiment, and run the rest in parallel. "
                           "Exit code 1 if a run failed, 2 on bad input.")
    sweep.add_argument("files", nargs="+", metavar="FILE.yaml [KEY=VALUE ...]",
                       help="sweep files, then overrides for all of them: KEY=VALUE sets a base "
                       "key, grid.KEY=[a,b] replaces a grid axis, repeats=N")
    sweep.add_argument("--scale", default="full", metavar="NAME",
                       help="one of the files' scales, e.g. quick (default: full, the file as written)")
    add_run_options(sweep)
    sweep.add_argument("--dry-run", action="store_true", help="list the expanded runs and stop")
    add_plugins(sweep, solver_axis=True)
    add_sweep_limits(sweep)
    sweep.set_defaults(func=cmd_sweep)
    from mpe3d.reports.runs_table import FORMATS

    runs = sub.add_parser("runs", help="print the runs of an experiment as a table")
    runs.add_argument("experiment", metavar="EXPERIMENT", help="the experiment: a sweep's name")
    runs.add_argument("--format", choices=FORMATS, default="text",
                      help="text: aligned columns (default); md: a Markdown table; csv or json "
                      "(records, every digit): for a file or pandas")
    runs.add_argument("--all-columns", action="store_true",
                      help="every param, metric and tag (default: the keys that vary, status, "
                      "cd_x100, emd_x100, roa, runtime_s and code)")
    runs.add_argument("--history", action="store_true",
                      help="every run ever made, not only the latest of each config")
    runs.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    runs.set_defaults(func=cmd_runs)
    return {"sweep": sweep}


def _split_overrides(tokens: list[str]) -> tuple[list[str], list[str]]:
    """``FILE... KEY=VALUE...``: a token with ``=`` that is not an existing file is an override."""
    files = [t for t in tokens if "=" not in t or Path(t).exists()]
    overrides = [t for t in tokens if t not in files]
    if not files:
        raise MpeError(f"no sweep file given, only overrides: {' '.join(overrides)}")
    return files, overrides


def _dry_run(sweeps) -> int:
    import pandas as pd

    for sweep in sweeps:
        dropped = f", {sweep.collapsed} duplicate grid points dropped" if sweep.collapsed else ""
        print(f"{sweep.name} ({sweep.path}): {len(sweep.runs)} runs{dropped}")
        flats = [(c.hash(), c.flat()) for c in sweep.runs]
        table = pd.DataFrame([{"hash": h, **{k: flat.get(k) for k in sweep.varying}}
                              for h, flat in flats])
        print(table.to_string(index=False))
    print(f"{sum(len(s.runs) for s in sweeps)} runs in all")
    return 0


def cmd_sweep(args) -> int:
    from mpe3d.harness.experiment.sweep import load_sweep

    files, overrides = _split_overrides(args.files)
    sweeps = with_solvers([load_sweep(path, args.scale, args.max_runs, args.max_yaml_mb, overrides)
                           for path in files], args.solver)  # all valid before any run
    check_parallel(args)
    if args.dry_run:
        return _dry_run(sweeps)
    from mpe3d.harness.tracking.store import Tracker

    with args.shutdown.deferred():  # a store is never left half-made, a result never half-logged
        tracker = Tracker(args.tracking_uri)
        if args.shutdown.stopping:
            return EXIT_CODE
        return run_sweeps(sweeps, args, tracker)[1]


def cmd_runs(args) -> int:
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports.runs_table import format_runs, runs_table

    tracker = Tracker(args.tracking_uri, create=False)
    note_journal(tracker)
    frame = tracker.runs_frame(args.experiment, history=args.history)
    if frame.empty:
        print(f"mpe3d: experiment '{args.experiment}' has no runs yet", file=sys.stderr)
        return 0
    codes = {code.split("+")[0] for code in frame["code"]}  # a plug-in's part is not a version of ours
    if len(codes) > 1:
        print(f"mpe3d: note: these runs were computed by {len(codes)} versions of the code "
              f"(column code); this code is {tracker.code}", file=sys.stderr)
    print(format_runs(runs_table(frame, args.all_columns), args.format), end="")
    return 0
