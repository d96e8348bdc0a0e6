"""Tables, figures and claim checks of the paper, rendered from tracked runs.

Data flows one way: MLflow runs -> :func:`mpe3d.reports.load.runs` (a DataFrame) ->
table, figure and claim functions (``DataFrame -> file``) -> a report folder
with ``index.md`` and ``index.html``. :mod:`mpe3d.reports.paper` lists which
experiment makes which table and figure; :mod:`mpe3d.reports.assemble` makes
a report's sections from sweeps, :mod:`mpe3d.reports.runs_table` the table
that ``mpe3d runs`` prints.

May import: :mod:`mpe3d.harness.experiment`, :mod:`mpe3d.harness.scene`,
:mod:`mpe3d.harness.tracking` and :mod:`mpe3d.solvers`. Never the command line.
"""

__all__ = ["assemble", "claims", "document", "figures", "load", "paper", "photos", "runs_table", "summary", "tables",
           "tracks", "viewer"]
