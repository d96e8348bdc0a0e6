"""Tables, figures and claim checks of the paper, rendered from tracked runs.

Data flows one way: MLflow runs -> :func:`mpe3d.reports.load.runs` (a DataFrame) ->
table, figure and claim functions (``DataFrame -> file``) -> a report folder
with ``index.md`` and ``index.html``. :mod:`mpe3d.reports.paper` lists which
experiment makes which table and figure.
"""
