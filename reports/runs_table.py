"""The runs table that ``mpe3d runs`` prints: which columns, and how they are
laid out for a terminal, Markdown, CSV or JSON. Light to import (the command
line reads :data:`FORMATS` while it builds its parser)."""

from __future__ import annotations

import shutil

from mpe3d.harness.experiment.config import KEYS

RUNS_METRICS = ("cd_x100", "emd_x100", "roa", "runtime_s")  # the paper's, and the time
ERROR_WIDTH = 60  # a Markdown table's error column is cut here; csv and json keep it whole
FORMATS = ("text", "md", "csv", "json")

__all__ = ["ERROR_WIDTH", "FORMATS", "RUNS_METRICS", "format_runs", "runs_table"]


def runs_table(frame, all_columns: bool):
    """By default the config keys that vary within the experiment (a solver
    option only if it varies within one solver), status, the main metrics and
    the code; with ``all_columns`` every param, metric and tag."""
    from mpe3d.reports.load import varying_columns  # pandas: not for `mpe3d runs --help`

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


def format_runs(table, form: str) -> str:
    """``text``: aligned columns for a terminal; ``md``: a Markdown table;
    ``csv`` and ``json`` (one record per run): every digit, for a file or pandas."""
    if form == "csv":
        return table.to_csv(index=False)
    if form == "json":
        return table.to_json(orient="records", date_format="iso", double_precision=15) + "\n"
    if form == "md":
        return _cut_errors(table, ERROR_WIDTH).to_markdown(index=False, floatfmt=".4g", missingval="") + "\n"
    width = shutil.get_terminal_size((120, 24)).columns - 1
    table = table.copy()
    errors = table.pop("error") if "error" in table else None
    lines = [_fit(table, width)]
    if errors is not None:  # under the table, one line each, as wide as the terminal
        keys = [c for c in table.columns if c not in ("status", *RUNS_METRICS, "code")]
        for (_, row), error in zip(table.iterrows(), errors):
            if error:
                label = " ".join(str(row[k]) for k in keys)  # as in the table's columns
                lines.append(_cut(f"{row['status']} {label}: {error}", width))
    return "\n".join(lines) + "\n"


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
