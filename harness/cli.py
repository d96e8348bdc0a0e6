"""The ``mpe3d`` command line."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path

from mpe3d.errors import MpeError

# Only light modules at the top: `mpe3d --help` must not pay for numpy,
# scikit-learn or MLflow. Each command imports what it runs.
from mpe3d.harness.experiment.config import BACKENDS, config_from_file, describe_keys, make_config, parse_override
from mpe3d.harness.shutdown import EXIT_CODE, Shutdown

RESUME_LINE = "mpe3d: interrupted; every run logged so far is kept: run the same command to resume"


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line and exit code 2."""

    def error(self, message: str):  # noqa: D401 - argparse's signature
        raise MpeError(message)


def _print_summary(summary: dict) -> None:
    from mpe3d.harness.experiment.execute import pipeline

    print("\n".join(pipeline(summary["config"]["pipeline"]).describe(summary)))


def cmd_run(args) -> int:
    from mpe3d.harness.experiment.execute import run, write_outputs

    overrides = dict(parse_override(item) for item in args.overrides)
    config = config_from_file(args.config, overrides, args.max_yaml_mb) if args.config \
        else make_config(overrides)
    result = run(config)
    summary = result.summary()
    for message in summary["warnings"]:
        print(f"mpe3d: warning: {message}", file=sys.stderr)
    if args.out:
        try:
            written = write_outputs(result, Path(args.out))
        except OSError as exc:
            raise MpeError(f"cannot write outputs to {args.out}: {exc.strerror or exc}") from None
        summary["outputs"] = [str(p) for p in written]
    if args.json:
        print(json.dumps(summary))
    else:
        _print_summary(summary)
        for path in summary.get("outputs", []):
            print(f"wrote {path}")
    return 0


def cmd_shapes(args) -> int:
    from mpe3d.harness.scene.shapes import PROCEDURAL, bundled_manifest

    for name, entry in bundled_manifest().items():
        print(f"{name:<9} stands in for {entry['paper_category']:<9} "
              f"{entry['source_name']} by {entry['creator']} ({entry['faces']} faces, {entry['license']})")
    for name in PROCEDURAL:
        print(f"{name:<9} procedural")
    from mpe3d import plugins
    from mpe3d.harness.scene.shapes import DATASETS

    plugins.load_entry_points()
    for dataset in sorted(DATASETS.values(), key=lambda d: d.name):
        items = ", ".join(f"{dataset.name}:{item}" for item in dataset.items) or f"{dataset.name}:<item>"
        print(f"{dataset.name:<9} {dataset.summary or 'a dataset'}: {items}  (from {dataset.origin})")
    for line in plugins.failures():
        print(f"not loaded: {line}")
    return 0


def cmd_solvers(args) -> int:
    from mpe3d import plugins, solvers

    plugins.load_entry_points()
    specs = sorted(solvers.SOLVERS.values(), key=lambda s: s.name)
    groups = [("the paper's solvers", [s for s in specs if s.origin is None and s.paper]),
              ("our solvers", [s for s in specs if s.origin is None and not s.paper])]
    for origin in dict.fromkeys(s.origin for s in specs if s.origin is not None):
        groups.append((f"from {origin}", [s for s in specs if s.origin == origin]))
    for title, members in groups:
        print(f"{title}:")
        for spec in members:
            notes = [*(["exact"] if spec.exact else []),
                     *([f"{' and '.join(spec.settings)} only"] if len(spec.settings) < 2 else [])]
            print(f"  {spec.name:<9} {spec.summary}" + (f" [{', '.join(notes)}]" if notes else ""))
            for option, default in spec.options().items():
                print(f"    solver.{option}={default}  ({spec.constraints[option]})")
            if spec.uses_init:
                print("    init=smart|random  (the starting point)")
    for line in plugins.failures():
        print(f"not loaded: {line}")
    return 0


def cmd_check_solver(args) -> int:
    from mpe3d.harness.experiment.contract import run_checks

    checks = run_checks(args.name, args.seed)
    for check in checks:
        print(check.line())
    failed = sum(not c.passed for c in checks)
    print(f"{args.name}: {len(checks) - failed} of {len(checks)} checks pass"
          + ("" if not failed else f"; {failed} to fix"))
    return 1 if failed else 0


def _say(text: str = "", quiet: bool = False) -> None:
    if not quiet:
        print(text, flush=True)


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


def _check_parallel(args) -> str:
    """The backend the flags ask for, after checking they fit together."""
    backend = args.backend or ("dask" if args.scheduler else "loky")
    if args.scheduler and backend != "dask":
        raise MpeError("--scheduler needs --backend dask")
    if args.jobs == 0 or args.jobs < -1:
        raise MpeError(f"--jobs: expected a positive count or -1 (all cores), got {args.jobs}")
    return backend


def run_sweeps(sweeps, args, tracker, summaries: bool = True) -> tuple[list, int]:
    """:func:`runner.run_sweeps` with the command line's flags, printing as it goes."""
    from mpe3d.harness.runner import run_sweeps as run

    summarise = None
    if summaries and not args.no_artifacts:  # the report's drawing is paid for only here
        from mpe3d.reports.summary import log_sweep_summary as summarise
    reporter = None
    if not args.quiet:
        from mpe3d.harness.progress import RichReporter
        reporter = RichReporter()
    plans, code = run(sweeps, tracker, jobs=args.jobs, backend=_check_parallel(args),
                      scheduler=args.scheduler, artifacts=not args.no_artifacts,
                      rerun_failed=args.rerun_failed, force=args.force, reuse_stale=args.reuse_stale,
                      reporter=reporter, say=lambda text: _say(text, args.quiet),
                      summarise=summarise,
                      warn=lambda text: print(f"mpe3d: {text}", file=sys.stderr, flush=True),
                      stop=args.shutdown)
    return plans, code


def _split_overrides(tokens: list[str]) -> tuple[list[str], list[str]]:
    """``FILE... KEY=VALUE...``: a token with ``=`` that is not an existing file is an override."""
    files = [t for t in tokens if "=" not in t or Path(t).exists()]
    overrides = [t for t in tokens if t not in files]
    if not files:
        raise MpeError(f"no sweep file given, only overrides: {' '.join(overrides)}")
    return files, overrides


def cmd_sweep(args) -> int:
    from mpe3d.harness.experiment.sweep import load_sweep

    files, overrides = _split_overrides(args.files)
    sweeps = _with_solvers([load_sweep(path, args.scale, args.max_runs, args.max_yaml_mb, overrides)
                            for path in files], args.solver)  # all valid before any run
    _check_parallel(args)
    if args.dry_run:
        return _dry_run(sweeps)
    from mpe3d.harness.tracking.store import Tracker

    with args.shutdown.deferred():  # a store is never left half-made, a result never half-logged
        tracker = Tracker(args.tracking_uri)
        if args.shutdown.stopping:
            return EXIT_CODE
        return run_sweeps(sweeps, args, tracker)[1]


RUNS_METRICS = ("cd_x100", "emd_x100", "roa", "runtime_s")  # the paper's, and the time
ERROR_WIDTH = 60  # a Markdown table's error column is cut here; csv and json keep it whole


def runs_table(frame, all_columns: bool):
    """What `mpe3d runs` shows: by default the config keys that vary within the
    experiment (a solver option only if it varies within one solver), status,
    the main metrics and the code; with ``all_columns`` every param, metric and tag."""
    from mpe3d.harness.experiment.config import KEYS
    from mpe3d.reports.load import varying_columns

    params = [c for c in frame.columns if c in KEYS or c.startswith("solver.")]
    tags = ["config_hash", "code", "run_id", "start_time", "error"]
    if all_columns:
        shown = params
        metrics = sorted(set(frame.columns) - set(params) - {"status", *tags})
    else:
        shown = list(varying_columns(frame[params]))
        metrics = [c for c in RUNS_METRICS if c in frame.columns]
    table = frame.sort_values([*shown, "start_time"])
    if all_columns:
        return table[["status", *shown, *metrics, *tags]]
    failed = (table["status"] != "FINISHED").any()
    return table[["status", *shown, *metrics, "code", *(["error"] if failed else [])]].rename(
        columns={"solver.name": "solver"})


def print_runs(table, form: str) -> None:
    """``text``: aligned columns for a terminal; ``md``: a Markdown table;
    ``csv`` and ``json`` (one record per run): every digit, for a file or pandas."""
    if form == "csv":
        print(table.to_csv(index=False), end="")
        return
    if form == "json":
        print(table.to_json(orient="records", date_format="iso", double_precision=15))
        return
    if form == "md":
        print(_cut_errors(table, ERROR_WIDTH).to_markdown(index=False, floatfmt=".4g", missingval=""))
        return

    import shutil

    width = shutil.get_terminal_size((120, 24)).columns - 1
    errors = table.pop("error") if "error" in table else None
    print(_fit(table, width))
    if errors is not None:  # under the table, one line each, as wide as the terminal
        keys = [c for c in table.columns if c not in ("status", *RUNS_METRICS, "code")]
        for (_, row), error in zip(table.iterrows(), errors):
            if error:
                label = " ".join(str(row[k]) for k in keys)  # as in the table's columns
                print(_cut(f"{row['status']} {label}: {error}", width))


def _fit(table, width: int) -> str:
    """The table as aligned text; when it is wider than ``width``, nested keys
    are headed by their last part (``noise.amplitude`` as ``amplitude``)
    wherever that part names one column only."""
    def text(frame) -> str:
        return frame.to_string(index=False, na_rep="", float_format=lambda v: f"{v:.3g}")
    out = text(table)
    if max(map(len, out.splitlines())) <= width:
        return out
    last = [c.rsplit(".", 1)[-1] for c in table.columns]
    short = {c: part for c, part in zip(table.columns, last) if last.count(part) == 1}
    return text(table.rename(columns=short))


def _cut_errors(table, width: int):
    if "error" not in table:
        return table
    return table.assign(error=[_cut(str(e), width) for e in table["error"].fillna("")])


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[:width - 1] + "…"


def _note_journal(tracker) -> None:
    """Say so when computed results still wait in the journal for this store."""
    from mpe3d.harness.tracking.journal import Journal

    journal = Journal()
    waiting = journal.pending(tracker.uri)
    if waiting:
        print(f"mpe3d: note: {waiting} computed result(s) in {journal.folder} are not in "
              f"{tracker.uri} yet; the next `mpe3d sweep` here replays them", file=sys.stderr)


def cmd_runs(args) -> int:
    from mpe3d.harness.tracking.store import Tracker

    tracker = Tracker(args.tracking_uri, create=False)
    _note_journal(tracker)
    frame = tracker.runs_frame(args.experiment, history=args.history)
    if frame.empty:
        print(f"mpe3d: experiment '{args.experiment}' has no runs yet", file=sys.stderr)
        return 0
    codes = {code.split("+")[0] for code in frame["code"]}  # a plug-in's part is not a version of ours
    if len(codes) > 1:
        print(f"mpe3d: note: these runs were computed by {len(codes)} versions of the code "
              f"(column code); this code is {tracker.code}", file=sys.stderr)
    print_runs(runs_table(frame, args.all_columns), args.format)
    return 0


def _sweep_section(sweep, tracker):
    from mpe3d.reports.load import runs
    from mpe3d.reports.paper import Section

    frame = runs(tracker, sweep.name, hashes=[c.hash() for c in sweep.runs]) \
        if tracker.experiment_id(sweep.name, create=False) else _empty_runs()
    return Section(sweep.name, frame, sweep.description, f"{sweep.path.name} --scale {sweep.scale}",
                   planned=len(sweep.runs), varying=sweep.varying, client=tracker.client,
                   full_runs_per_group=_full_runs_per_group(sweep))


def _full_runs_per_group(sweep) -> int | None:
    """Runs per compared setting when ``sweep`` runs at its full scale (None: it does)."""
    import pandas as pd

    from mpe3d.harness.experiment.sweep import FULL, load_sweep
    from mpe3d.reports.claims import runs_per_group

    if sweep.scale == FULL:
        return None
    full = load_sweep(sweep.path, FULL, max_runs=10**7, overrides=sweep.overrides)
    return runs_per_group(pd.DataFrame([c.flat() for c in full.runs]), full.varying)


def _empty_runs():
    import pandas as pd

    return pd.DataFrame(columns=["status", "config_hash", "error", "solver.name", "method"])


def _wrote(report) -> None:
    tables = sum(1 for p in report.files if p.suffix == ".md")
    figures = sum(1 for p in report.files if p.suffix == ".png")
    print(f"wrote {report.out / 'index.html'} and index.md ({tables} tables, {figures} figures, "
          f"each also as .tex/.pdf)", flush=True)


def cmd_report(args) -> int:
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports import paper
    from mpe3d.reports.load import finished, runs

    if args.sweep:  # the file first: its errors are the user's to fix, whatever the store
        from mpe3d.harness.experiment.sweep import load_sweep

        sweep = _with_solvers([load_sweep(args.sweep, args.scale, args.max_runs, args.max_yaml_mb,
                                          args.overrides)], args.solver)[0]
    tracker = Tracker(args.tracking_uri, create=False)
    _note_journal(tracker)
    if args.sweep:
        section = _sweep_section(sweep, tracker)
    else:
        known = {s.name: s for s in map(_load_paper_sweep, _paper_sweep_files())}
        sweep = known.get(args.experiment)
        section = paper.Section(args.experiment, runs(tracker, args.experiment),
                                sweep.description if sweep else "", varying=sweep.varying if sweep else (),
                                client=tracker.client)
    if finished(section.frame).empty:
        what = f"sweep {args.sweep} at scale {args.scale}" if args.sweep else f"experiment {args.experiment}"
        print(f"mpe3d: no finished runs of {what} in {tracker.uri}: nothing to report "
              f"(run it first: mpe3d sweep FILE)", file=sys.stderr)
        return 1
    report = _write_report(Path(args.out), [section], f"mpe3d report: {section.name}",
                           [f"Runs from {tracker.uri}."])
    _wrote(report)
    if report.empty:
        print(f"mpe3d: {len(report.empty)} table(s) had no rows: {', '.join(report.empty)}", file=sys.stderr)
        return 1
    return 0


def _with_solvers(sweeps, names):
    """``--solver NAME``: each sweep with NAME on its solver axis, where it has one."""
    if not names:
        return sweeps
    from mpe3d.harness.experiment.sweep import add_solvers
    from mpe3d.solvers import get_solver

    for name in names:  # an unknown name fails before anything runs
        get_solver(name)
    return [add_solvers(sweep, names) for sweep in sweeps]


def _added_methods(sweeps, names) -> list[str]:
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


def _paper_sweep_files():
    from mpe3d.sweeps import paper_sweeps

    return paper_sweeps()


def _load_paper_sweep(path, scale="full", overrides=()):
    from mpe3d.harness.experiment.sweep import load_sweep

    return load_sweep(path, scale, overrides=list(overrides))


def _write_report(out: Path, sections, title, facts):
    from mpe3d.reports import paper

    try:
        return paper.write(out, sections, title, facts)
    except OSError as exc:
        raise MpeError(f"cannot write the report to {out}: {exc.strerror or exc}") from None


def cmd_reproduce(args) -> int:
    import platform

    from mpe3d.harness.tracking.identity import git_commit
    from mpe3d.harness.tracking.store import Tracker

    start = time.time()
    commit = git_commit()
    sweeps = _with_solvers([_load_paper_sweep(path, args.scale, args.overrides)
                            for path in _paper_sweep_files()], args.solver)
    with args.shutdown.deferred():
        tracker = Tracker(args.tracking_uri)
        if args.shutdown.stopping:
            return EXIT_CODE
        _say(f"reproduce-paper --scale {args.scale}: {len(sweeps)} experiments, "
             f"{sum(len(s.runs) for s in sweeps)} runs, tracked in {tracker.uri}", args.quiet)
        plans, code = run_sweeps(sweeps, args, tracker, summaries=False)  # the report below serves
    if code == EXIT_CODE:
        return code
    ran = sum(sum(p.counts.values()) for p in plans)
    reused = sum(p.skipped for p in plans)
    run_wall = time.time() - start
    sections = [_sweep_section(sweep, tracker) for sweep in sweeps]
    facts = [f"Scale {args.scale}; {sum(len(s.runs) for s in sweeps)} runs in "
             f"{len(sweeps)} experiments: {ran} run now, {reused} reused from {tracker.uri}; "
             f"wall time for the runs {run_wall:.1f} s on {os.cpu_count()} cores "
             f"({platform.node()}, mpe3d {tracker.code}{f', git {commit}' if commit else ''}).",
             "Methods: 'baseline (MDS)' and '3DMPE (paper)' are the paper's baseline and its SGD, "
             "implemented faithfully; 'ours (refine)' is mpe3d's exact solver, not the paper's. "
             "CD and EMD are 100 × mean distances after a rigid alignment, the scale of the authors' "
             "code; ROA is the RMS distance between corresponding points. The bundled shapes are "
             "CC0 stand-ins for ShapeNet's categories (`mpe3d shapes`)."]
    facts += _added_methods(sweeps, args.solver)
    report = _write_report(Path(args.out), sections, "3DMPE, reproduced with mpe3d", facts)
    _wrote(report)
    if not args.no_artifacts:  # each parent run shows its experiment's part of the report
        for plan in plans:
            if plan.parent_id:
                tracker.log_parent_artifacts(plan.parent_id, report.out,
                                             report.by_section.get(plan.sweep.name, []))
    _say(f"reproduce-paper: {time.time() - start:.1f} s in all", args.quiet)
    return code


def cmd_reconstruct(args) -> int:
    from mpe3d.harness.userdata.formats import OUTPUT_FORMATS, check_ids_fit, check_output, write_result
    from mpe3d.harness.userdata.reconstruct import prepare, solve_problem

    if args.seed < 0:
        raise MpeError(f"--seed: expected an integer >= 0, got {args.seed}")
    from mpe3d.harness.userdata import bundler

    model = _model_out(args.out)  # every output path before any work, not after it
    out = model / "points3D.ply" if model else \
        check_output(args.out, formats=OUTPUT_FORMATS + bundler.BUNDLE_OUTPUTS)
    solution = out.suffix.lower() in bundler.BUNDLE_OUTPUTS
    report = check_output(args.report, "--report", (".json",)) if args.report else None
    if report is not None and report.resolve() == out.resolve():
        raise MpeError(f"--report {report}: the same file as --out")
    problem = prepare(args.input, projections=args.projections, solver=args.solver,
                      loss=args.loss, random_state=args.seed, objective=args.objective,
                      camera=args.camera, missing=args.missing,
                      outlier_threshold=args.outlier_threshold,
                      principal_point=args.principal_point, start=args.start)
    check_ids_fit(out, problem.ids)
    if solution:
        bundler.check_solution_out(out, problem)
    result = solve_problem(problem)
    extra = {"input": str(args.input), "output": str(model or out)}
    if model:
        from mpe3d.harness.userdata.colmap_model import write_model_folder

        result.warnings.extend(write_model_folder(model, problem, result))
    writer = bundler.solution_writer(out, problem, result) if solution else None
    write_result(out, result, report, extra, writer)
    print(_reconstruct_summary(result.report))
    for message in result.warnings:
        print(f"mpe3d: warning: {message}", file=sys.stderr)
    print(f"wrote {model or out}" + (f" and {report}" if report else ""))
    return 0


def _model_out(text: str) -> Path | None:
    """The folder of a COLMAP model when ``--out`` names one (no file suffix),
    checked as :func:`check_output` checks a file."""
    from mpe3d.harness.userdata.colmap_model import check_model_out

    path = Path(text)
    if text.endswith(("/", os.sep)) or not path.suffix:
        return check_model_out(path)
    return None


def _reconstruct_summary(summary: dict) -> str:
    where = f"{summary['points']} points from {summary['views']} views ({summary['setting']} "
    if summary["objective"] == "stress":
        worst = max(summary["rms_residual_per_view"])
        return (where + f"projections, {summary['solver']}): stress {summary['stress']:.3g}, "
                f"worst view RMS residual {worst:.3g}, {summary['unplaced']['count']} unplaced, "
                f"{summary['runtime_s']:.2f} s")
    worst = max(v for v in summary["rms_px_per_view"] if v is not None)
    return (where + f"cameras, {summary['camera']} camera, bundle adjustment): reprojection RMS "
            f"{summary['reprojection_rms_px']:.3g} px (worst view {worst:.3g} px), "
            f"{summary['dropped']['count']} wrong matches dropped, "
            f"{summary['unplaced']['count']} unplaced, {summary['runtime_s']:.2f} s")


def _pair(text: str):
    """``X,Y`` as two numbers, for --missing and --principal-point."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y (two numbers), got {text!r}") from None
    return x, y


def cmd_ui(args) -> int:
    import socket
    import subprocess

    from mpe3d.harness.tracking.store import artifact_root, resolve_uri

    uri = resolve_uri(args.tracking_uri)
    if uri.startswith(("http://", "https://")):
        raise MpeError(f"{uri} is a tracking server: open it in a browser, it serves its own UI")
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", args.port)) == 0:
            raise MpeError(f"--port: 127.0.0.1:{args.port} is in use; choose another port")
    command = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri,
               "--host", "127.0.0.1", "--port", str(args.port), "--workers", "1"]  # one user
    root = artifact_root(uri)
    if root:
        command += ["--artifacts-destination", root]
    print(f"MLflow UI at http://127.0.0.1:{args.port}, serving the store {uri}"
          + (f" (artifacts {root})" if root else "") + "; Ctrl-C stops it", flush=True)
    # Its own process group: the server forks workers, and a signal to us must reach them all.
    args.shutdown.line = "mpe3d: interrupted; the MLflow UI is stopped"
    server = subprocess.Popen(command, start_new_session=True)
    try:
        return server.wait()
    except KeyboardInterrupt:
        _stop_group(server)
        return EXIT_CODE


def _stop_group(process, grace_s: float = 2.0) -> None:
    """SIGTERM to ``process``'s whole group, then SIGKILL to whatever outlives ``grace_s``."""
    import subprocess

    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(grace_s)
        except subprocess.TimeoutExpired:
            continue
        # the leader is gone; its workers may linger a moment
        deadline = time.time() + grace_s
        while time.time() < deadline:
            try:
                os.killpg(process.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.1)


def _add_run_options(parser) -> None:
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


def _add_plugins(parser, solver_axis: bool = False) -> None:
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                        help="load a plug-in file (solvers, datasets) first; repeatable")
    if solver_axis:
        parser.add_argument("--solver", action="append", default=[], metavar="NAME",
                            help="add solver NAME to the solver axis of every sweep that compares "
                            "solvers, in the settings it declares; repeatable")


def _add_yaml_limit(parser) -> None:
    from mpe3d.harness.experiment.limits import MAX_YAML_MB

    parser.add_argument("--max-yaml-mb", type=float, default=MAX_YAML_MB, metavar="MB",
                        help=f"refuse YAML files larger than this (default {MAX_YAML_MB:g} MiB)")


def _add_sweep_limits(parser) -> None:
    from mpe3d.harness.experiment.limits import MAX_RUNS

    parser.add_argument("--max-runs", type=int, default=MAX_RUNS, metavar="N",
                        help=f"refuse a sweep that expands to more runs (default {MAX_RUNS:,})")
    _add_yaml_limit(parser)


TRACKING_HELP = "MLflow store (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mpe3d", description="3D multi-perspective embedding: "
                     "rebuild a 3D point cloud from partial 2D views.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    run = sub.add_parser("run", help="run one configuration",
                         formatter_class=argparse.RawDescriptionHelpFormatter,
                         epilog="keys (KEY=VALUE; solver=NAME is short for solver.name=NAME,\n"
                                "solver options are solver.<option>=VALUE):\n" + describe_keys())
    run.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                     help="run keys (listed below), e.g. shape=lamp points=1024 solver=refine")
    run.add_argument("--config", metavar="FILE.yaml", help="YAML file of keys (overrides win)")
    run.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    run.add_argument("--out", metavar="DIR", help="write ground_truth.ply, reconstruction.ply and a PNG")
    _add_plugins(run)
    _add_yaml_limit(run)
    run.set_defaults(func=cmd_run)
    sweep = sub.add_parser("sweep", help="run YAML sweeps, tracked in MLflow, resuming what is done",
                           description="Expand each sweep file into a grid of runs, skip the runs "
                           "already FINISHED in its MLflow experiment, and run the rest in parallel. "
                           "Exit code 1 if a run failed, 2 on bad input.")
    sweep.add_argument("files", nargs="+", metavar="FILE.yaml [KEY=VALUE ...]",
                       help="sweep files, then overrides for all of them: KEY=VALUE sets a base "
                       "key, grid.KEY=[a,b] replaces a grid axis, repeats=N")
    sweep.add_argument("--scale", default="full", metavar="NAME",
                       help="one of the files' scales, e.g. quick (default: full, the file as written)")
    _add_run_options(sweep)
    sweep.add_argument("--dry-run", action="store_true", help="list the expanded runs and stop")
    _add_plugins(sweep, solver_axis=True)
    _add_sweep_limits(sweep)
    sweep.set_defaults(func=cmd_sweep)
    reproduce = sub.add_parser(
        "reproduce-paper", help="run every experiment of the paper (resuming) and render its "
        "tables, figures and claim checks",
        description="Run the paper's sweeps (sweeps/paper/*.yaml) at one scale, skipping runs already "
        "tracked, then write index.md and index.html with every table and figure, and a verdict on "
        "each of the paper's claims. Exit code 1 if a run failed.")
    reproduce.add_argument("--scale", choices=("quick", "full", "tiny"), default="quick",
                           help="quick (minutes, the default), full (the paper's sizes and repeats) "
                           "or tiny (a smoke test)")
    reproduce.add_argument("--out", default="paper-report", metavar="DIR",
                           help="report folder (default: paper-report)")
    reproduce.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                           help="overrides for every experiment, as for sweep (e.g. repeats=1)")
    _add_run_options(reproduce)
    _add_plugins(reproduce, solver_axis=True)
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
    _add_plugins(report, solver_axis=True)
    _add_sweep_limits(report)
    report.set_defaults(func=cmd_report)
    runs = sub.add_parser("runs", help="print the runs of an experiment as a table")
    runs.add_argument("experiment", metavar="EXPERIMENT", help="the experiment: a sweep's name")
    runs.add_argument("--format", choices=("text", "md", "csv", "json"), default="text",
                      help="text: aligned columns (default); md: a Markdown table; csv or json "
                      "(records, every digit): for a file or pandas")
    runs.add_argument("--all-columns", action="store_true",
                      help="every param, metric and tag (default: the keys that vary, status, "
                      "cd_x100, emd_x100, roa, runtime_s and code)")
    runs.add_argument("--history", action="store_true",
                      help="every run ever made, not only the latest of each config")
    runs.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    runs.set_defaults(func=cmd_runs)
    rec = sub.add_parser("reconstruct", help="rebuild a 3D cloud from your own keypoints or "
                         "distance matrices", description="Read matched 2D keypoints (CSV view,point,x,y; "
                         "NPZ; JSON; or a folder of .npz per view) or per-view distance matrices, check "
                         "them, and write the 3D cloud with each point's id.")
    rec.add_argument("input", metavar="INPUT", help="a .csv, .npz or .json file, a folder of .npz, "
                     "a COLMAP model folder, a Bundler .out or BAL problem file, or a VGG "
                     "nview-corners table (its .corners files beside it)")
    rec.add_argument("--out", required=True, metavar="CLOUD",
                     help="output: .ply, .csv or .npy (the cloud, with ids); a folder (a COLMAP "
                     "model); or .out or .bal (Bundler or BAL: pinhole cameras f, k1, k2, the "
                     "points and the kept keypoints, centred on the principal point)")
    rec.add_argument("--projections", metavar="FILE",
                     help="known cameras (.npy or .json, K matrices: 2x3 or 3x3 orthographic, "
                     "or 3x4 pinhole): the fixed setting")
    rec.add_argument("--objective", choices=("reprojection", "stress"),
                     help="reprojection (bundle adjustment; the default for keypoints) or "
                     "stress (paper Eq. 1; the default and only choice for distance matrices)")
    rec.add_argument("--camera", default="auto",
                     choices=("auto", "orthographic", "scaled", "perspective", "radial"),
                     help="the camera model for reprojection (default auto: the pinhole camera "
                     "when it fits clearly better than weak perspective; radial: the pinhole "
                     "with radial distortion k1, k2, Bundler's and BAL's camera)")
    rec.add_argument("--start", choices=("file", "own"),
                     help="where bundle adjustment starts: the input's cameras and points (a "
                     "Bundler or BAL file; the default when it has them) or mpe3d's own start")
    rec.add_argument("--principal-point", type=_pair, metavar="X,Y",
                     help="the pinhole camera's principal point in pixels, usually the image "
                     "centre (default: the centre of the keypoints)")
    rec.add_argument("--missing", type=_pair, metavar="X,Y",
                     help="drop observations at exactly X,Y (e.g. -1,-1: a tracker's 'not seen')")
    rec.add_argument("--outlier-threshold", type=float, default=20.0, metavar="SIGMAS",
                     help="reprojection: drop observations beyond this many robust sigmas as "
                     "wrong matches (default 20; inf keeps all, and turns refine's rejection "
                     "rounds off for the stress)")
    rec.add_argument("--solver", default="refine", help="stress solver: refine (default), "
                     "factorize or sgd")
    rec.add_argument("--loss", default="l2", choices=("l2", "huber", "soft_l1", "cauchy"),
                     help="l2 (default), or a robust loss: huber, soft_l1 (cauchy: reprojection only)")
    rec.add_argument("--report", metavar="FILE.json", help="write per-view residuals (pixels "
                     "for reprojection), cameras, dropped and unplaced ids and runtime as JSON")
    rec.add_argument("--seed", type=int, default=0, help="random state (default 0)")
    rec.set_defaults(func=cmd_reconstruct)
    ui = sub.add_parser("ui", help="start the MLflow UI on the tracking store, on 127.0.0.1")
    ui.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    ui.add_argument("--port", type=int, default=5000, help="the port on 127.0.0.1 (default 5000)")
    ui.set_defaults(func=cmd_ui)
    shapes = sub.add_parser("shapes", help="list the bundled and procedural shapes, and plug-in datasets")
    _add_plugins(shapes)
    shapes.set_defaults(func=cmd_shapes)
    listing = sub.add_parser("solvers", help="list solvers and their options, plug-ins in their own group")
    _add_plugins(listing)
    listing.set_defaults(func=cmd_solvers)
    check = sub.add_parser("check-solver", help="check a solver against the solver contract",
                           description="Run solver NAME on small scenes and check the contract every "
                           "solver keeps (result shapes, orthonormal projections, one result per seed, "
                           "option rules, observations only, coordinates, exactness if claimed). One "
                           "line per check; exit code 0 if all pass, 1 if one fails.")
    check.add_argument("name", metavar="NAME", help="a registered solver (see mpe3d solvers)")
    check.add_argument("--seed", type=int, default=0, help="the scenes' and the solver's seed (default 0)")
    _add_plugins(check)
    check.set_defaults(func=cmd_check_solver)
    parser.intermixed = {"sweep": sweep, "reproduce-paper": reproduce}
    return parser


def _parse(parser, argv: list[str]) -> argparse.Namespace:
    """Overrides anywhere on the commands that run sweeps, as Hydra users type
    them (``mpe3d sweep s.yaml --quiet points=70``): those commands' own
    parsers read their options and positionals intermixed."""
    intermixed = getattr(parser, "intermixed", {})
    if argv and argv[0] in intermixed:
        args = intermixed[argv[0]].parse_intermixed_args(argv[1:])
        args.command = argv[0]
        return args
    return parser.parse_args(argv)


def main(argv: list[str] | None = None, shutdown: Shutdown | None = None) -> int:
    """Run one command; Ctrl-C, SIGINT and SIGTERM all end it through
    :class:`~mpe3d.harness.shutdown.Shutdown`: exit code 130 and one last line.
    Without ``shutdown`` the handlers are installed for the command only."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setLevel(logging.WARNING)  # libraries (dask) send INFO records up to the root
    handler.setFormatter(logging.Formatter("mpe3d: %(message)s"))
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    with (contextlib.nullcontext(shutdown) if shutdown else Shutdown()) as shutdown:
        code = _command(argv, shutdown)
        if code == EXIT_CODE:
            shutdown.tell()
    return code


def _load_plugins(files) -> None:
    """Installed plug-ins (one that fails is a line on stderr, and the rest
    works), then the ``--plugin`` files (one that fails is the error)."""
    import warnings

    from mpe3d import plugins

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", plugins.PluginWarning)
        plugins.load_entry_points()
    for warning in caught:
        if issubclass(warning.category, plugins.PluginWarning):
            print(f"mpe3d: warning: {warning.message}", file=sys.stderr)
    plugins.load_files(files)


def _command(argv: list[str] | None, shutdown: Shutdown) -> int:
    try:
        args = _parse(build_parser(), sys.argv[1:] if argv is None else [str(a) for a in argv])
        args.shutdown = shutdown
        _load_plugins(getattr(args, "plugin", []))
        if args.command in ("sweep", "reproduce-paper"):
            shutdown.line = RESUME_LINE
        return args.func(args)
    except MpeError as exc:
        print(f"mpe3d: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return EXIT_CODE
    except BrokenPipeError:  # `mpe3d runs X | head`: the reader left; that is not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def console() -> int:
    """The ``mpe3d`` command: :func:`main`, and after an interrupt of a
    ``--jobs 1`` sweep an immediate exit.

    Such a sweep stops while its run thread may still be inside a solver's
    compiled code; finalising the interpreter around that thread can abort
    the process ("terminate called without an active exception", exit -6
    instead of 130). Every finished run is logged or journaled by then, so the
    process leaves without finalising. Other commands finalise normally (loky
    releases its semaphores then, so its resource tracker has nothing to warn
    about); the shutdown watchdog bounds even that, and a signal that comes
    while the process finalises ends it at once with 130 and the line.
    """
    import threading

    shutdown = Shutdown().__enter__()  # for the life of the process, finalisation included
    code = main(shutdown=shutdown)
    shutdown.settle(code)
    if code == EXIT_CODE and any(t.name == "mpe3d-run" and t.is_alive()
                                 for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(console())
