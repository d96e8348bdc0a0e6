"""The argparse tree of every command, and the ``mpe3d`` entry point."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys

from mpe3d.cli import catalog, reconstruct, report, run, sweep, ui
from mpe3d.cli.options import RESUME_LINE, Parser
from mpe3d.errors import MpeError
from mpe3d.harness.shutdown import EXIT_CODE, Shutdown

# Only light modules at the top: `mpe3d --help` must not pay for numpy,
# scikit-learn or MLflow. Each command imports what it runs.


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mpe3d", description="3D multi-perspective embedding: "
                    "rebuild a 3D point cloud from partial 2D views.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    run.add_parser(sub)
    intermixed = sweep.add_parsers(sub)
    intermixed |= report.add_parsers(sub)
    reconstruct.add_parser(sub)
    ui.add_parser(sub)
    catalog.add_parsers(sub)
    parser.intermixed = intermixed
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
