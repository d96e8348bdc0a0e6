"""The ``mpe3d`` command line, on top of the harness and the reports.

One module per command or command family, each with its parser
(``add_parser``) and its ``cmd_*`` function: :mod:`.run` (one run),
:mod:`.sweep` (``sweep``, ``runs``), :mod:`.report` (``report``,
``reproduce-paper``), :mod:`.reconstruct`, :mod:`.ui`, :mod:`.catalog`
(``solvers``, ``shapes``, ``check-solver``). :mod:`.options` holds the options
several commands share, :mod:`.main` the argparse tree and the entry point.

May import: :mod:`mpe3d.reports`, :mod:`mpe3d.harness`, :mod:`mpe3d.solvers`,
:mod:`mpe3d.sweeps`, :mod:`mpe3d.plugins`, :mod:`mpe3d.options` and
:mod:`mpe3d.errors`. Nothing imports it.
"""

from mpe3d.cli.main import build_parser, console, main

__all__ = ["build_parser", "console", "main"]
