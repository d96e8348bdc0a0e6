"""``mpe3d report`` (tables, figures and claim checks of tracked runs) and
``mpe3d reproduce-paper`` (every experiment of the paper, run and reported)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from mpe3d.cli.options import (
    TRACKING_HELP,
    add_plugins,
    add_run_options,
    add_sweep_limits,
    note_journal,
    run_sweeps,
    say,
    with_solvers,
)
from mpe3d.errors import MpeError
from mpe3d.harness.shutdown import EXIT_CODE

SCALES = ("quick", "full", "tiny")


def add_parsers(sub) -> dict:
    """The two parsers; ``reproduce-paper``'s reads options and overrides intermixed."""
    reproduce = sub.add_parser(
        "reproduce-paper", help="run every experiment of the paper (resuming) and render its "
        "tables, figures and claim checks",
        description="Run the paper's sweeps (sweeps/paper/*.yaml) at one scale, skipping runs already "
        "tracked, then write index.md and index.html with every table and figure, and a verdict on "
        "each of the paper's claims. Exit code 1 if a run failed.")
    reproduce.add_argument("--scale", choices=SCALES, default="quick",
                           help="quick (minutes, the default), full (the paper's sizes and repeats) "
                           "or tiny (a smoke test)")
    reproduce.add_argument("--out", default="paper-report", metavar="DIR",
                           help="report folder (default: paper-report)")
    reproduce.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                           help="overrides for every experiment, as for sweep (e.g. repeats=1)")
    add_run_options(reproduce)
    add_plugins(reproduce, solver_axis=True)
    reproduce.set_defaults(func=cmd_reproduce)
    report = sub.add_parser("report", help="render tables and figures of tracked runs",
                            description="Render the tables, figures and claim checks of one "
                            "experiment, or of one sweep file's runs at one scale.")
    which = report.add_mutually_exclusive_group(required=True)
    which.add_argument("--experiment", metavar="NAME", help="every latest run of this experiment")
    which.add_argument("--sweep", metavar="FILE.yaml", help="the runs of this sweep file (at --scale)")
    report.add_argument("--scale", default="full", metavar="NAME", help="with --sweep (default: full)")
    report.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                        help="with --sweep: the overrides the sweep ran with")
    report.add_argument("--out", required=True, metavar="DIR", help="report folder")
    report.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    add_plugins(report, solver_axis=True)
    add_sweep_limits(report)
    report.set_defaults(func=cmd_report)
    return {"reproduce-paper": reproduce}


def _paper_sweeps(scale: str = "full", overrides=()) -> list:
    from mpe3d.harness.experiment.sweep import load_sweep
    from mpe3d.sweeps import paper_sweeps

    return [load_sweep(path, scale, overrides=list(overrides)) for path in paper_sweeps()]


def _write_report(out: Path, sections, title, facts):
    from mpe3d.reports import paper

    try:
        report = paper.write(out, sections, title, facts)
    except OSError as exc:
        raise MpeError(f"cannot write the report to {out}: {exc.strerror or exc}") from None
    tables = sum(1 for p in report.files if p.suffix == ".md")
    figures = sum(1 for p in report.files if p.suffix == ".png")
    print(f"wrote {report.out / 'index.html'} and index.md ({tables} tables, {figures} figures, "
          f"each also as .tex/.pdf)", flush=True)
    return report


def _nothing_to_report(args, tracker, sweep) -> None:
    from mpe3d.reports.assemble import other_finished_runs

    if not args.sweep:
        what = f"experiment {args.experiment}"
        hint = "run it first: mpe3d sweep FILE"
    else:
        what = f"sweep {args.sweep} at scale {args.scale}" + \
            (f" with {' '.join(args.overrides)}" if args.overrides else "")
        others = other_finished_runs(sweep, tracker)
        hint = "run it first: mpe3d sweep FILE" if not others else (
            f"experiment {sweep.name} holds {others} finished run(s) of other configs: give the "
            f"--scale and KEY=VALUE overrides the sweep ran with")
    print(f"mpe3d: no finished runs of {what} in {tracker.uri}: nothing to report ({hint})",
          file=sys.stderr)


def cmd_report(args) -> int:
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports.assemble import experiment_section, sweep_section
    from mpe3d.reports.load import finished

    sweep = None
    if args.sweep:  # the file first: its errors are the user's to fix, whatever the store
        from mpe3d.harness.experiment.sweep import load_sweep

        sweep = with_solvers([load_sweep(args.sweep, args.scale, args.max_runs, args.max_yaml_mb,
                                         args.overrides)], args.solver)[0]
    tracker = Tracker(args.tracking_uri, create=False)
    note_journal(tracker)
    if sweep is not None:
        section = sweep_section(sweep, tracker)
    else:
        paper = {s.name: s for s in _paper_sweeps()}
        section = experiment_section(tracker, args.experiment, paper.get(args.experiment))
    if finished(section.frame).empty:
        _nothing_to_report(args, tracker, sweep)
        return 1
    report = _write_report(Path(args.out), [section], f"mpe3d report: {section.name}",
                           [f"Runs from {tracker.uri}."])
    if report.empty:
        print(f"mpe3d: {len(report.empty)} table(s) had no rows: {', '.join(report.empty)}", file=sys.stderr)
        return 1
    return 0


def cmd_reproduce(args) -> int:
    from mpe3d.harness.tracking.identity import git_commit
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports.assemble import reproduction_facts, sweep_section

    start = time.time()
    commit = git_commit()
    sweeps = with_solvers(_paper_sweeps(args.scale, args.overrides), args.solver)
    with args.shutdown.deferred():
        tracker = Tracker(args.tracking_uri)
        if args.shutdown.stopping:
            return EXIT_CODE
        say(f"reproduce-paper --scale {args.scale}: {len(sweeps)} experiments, "
            f"{sum(len(s.runs) for s in sweeps)} runs, tracked in {tracker.uri}", args.quiet)
        plans, code = run_sweeps(sweeps, args, tracker, summaries=False)  # the report below serves
    if code == EXIT_CODE:
        return code
    facts = reproduction_facts(sweeps, plans, tracker, scale=args.scale, run_wall_s=time.time() - start,
                               commit=commit, added=args.solver)
    sections = [sweep_section(sweep, tracker) for sweep in sweeps]
    report = _write_report(Path(args.out), sections, "3DMPE, reproduced with mpe3d", facts)
    if not args.no_artifacts:  # each parent run shows its experiment's part of the report
        for plan in plans:
            if plan.parent_id:
                tracker.log_parent_artifacts(plan.parent_id, report.out,
                                             report.by_section.get(plan.sweep.name, []))
    say(f"reproduce-paper: {time.time() - start:.1f} s in all", args.quiet)
    return code
