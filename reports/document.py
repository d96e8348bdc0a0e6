"""A report folder: tables (Markdown + LaTeX), figures (PNG + PDF), and an index.

Each table and figure is written as files the moment it is added; the index
(``index.md``, ``index.html``) lists them in order, each under the sweep that
made it.
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd


def _markdown(frame: pd.DataFrame) -> str:
    blank = frame.astype(object).where(frame.notna(), None)  # NaN too shows as "–"
    return blank.to_markdown(index=False, floatfmt=".3g", missingval="–")


def _latex(frame: pd.DataFrame, caption: str, label: str) -> str:
    """A booktabs table, shaped like the paper's."""
    numeric = frame.select_dtypes("number").columns
    style = frame.style.hide(axis="index").format("{:.3g}", subset=list(numeric), na_rep="--")
    return style.to_latex(hrules=True, caption=caption, label=f"tab:{label}",
                          column_format="l" * (len(frame.columns) - len(numeric)) + "r" * len(numeric),
                          position_float="centering")


@dataclass
class Report:
    """Writes files into ``out`` and remembers what to show in the index."""

    out: Path
    title: str
    blocks: list[tuple[str, object]] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    note: str = ""  # appended to every caption while set (e.g. "mixes runs of two code versions")
    empty: list[str] = field(default_factory=list)  # tables that had no rows
    pdf: bool = True  # each figure also as PDF (for papers; a quick look needs only the PNG)
    current: str = ""  # the section (experiment) being rendered
    by_section: dict[str, list[Path]] = field(default_factory=dict)  # its tables and figures

    def __post_init__(self):
        self.out = Path(self.out)
        for sub in ("tables", "figures"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)

    def heading(self, text: str, level: int = 2) -> None:
        self.blocks.append(("heading", (level, text)))

    def text(self, text: str) -> None:
        self.blocks.append(("text", text))

    def table(self, frame: pd.DataFrame, name: str, caption: str, show: bool = True) -> None:
        """``tables/NAME.md`` and ``tables/NAME.tex``, and the table in the index.

        A table without rows is never written: the index says so instead, and
        ``empty`` lists it, so that the caller can fail.
        """
        caption = f"{caption} {self.note}".strip()
        if frame.empty:
            self.empty.append(name)
            self.text(f"Table {name}: no rows (no finished runs fit it).")
            return
        md = self.out / "tables" / f"{name}.md"
        tex = self.out / "tables" / f"{name}.tex"
        md.write_text(f"{caption}\n\n{_markdown(frame)}\n")
        tex.write_text(_latex(frame, caption, name))
        self._wrote([md, tex])
        self.blocks.append(("table", (frame, name, caption, show)))

    def folded_table(self, frame: pd.DataFrame, name: str, caption: str, lines: pd.DataFrame,
                     details: list[list[tuple[str, str]]]) -> None:
        """``frame`` written as :meth:`table` writes it, shown as one line per row
        (``lines``) with each row's ``details`` (label, text) folded beneath it
        in ``index.html``: a wall of prose in narrow cells reads as a list."""
        self.table(frame, name, caption, show=False)
        if not frame.empty:
            self.blocks[-1] = ("folded", (lines, name, self.blocks[-1][1][2], details))

    def figure(self, fig, name: str, caption: str) -> None:
        """``figures/NAME.png`` and ``figures/NAME.pdf``, and the PNG in the index."""
        import matplotlib.pyplot as plt

        png = self.out / "figures" / f"{name}.png"
        pdf = self.out / "figures" / f"{name}.pdf"
        # the tight box measured once for both files: "tight" draws the whole
        # figure once more per file just to measure it
        box = fig.get_tightbbox(fig.canvas.get_renderer()).padded(plt.rcParams["savefig.pad_inches"])
        fig.savefig(png, dpi=120, bbox_inches=box)
        if self.pdf:
            fig.savefig(pdf, bbox_inches=box)
        labels = _legend_labels(fig)
        plt.close(fig)
        self._wrote([png, pdf] if self.pdf else [png])
        self.blocks.append(("figure", (name, caption, labels)))

    def _wrote(self, paths: list[Path]) -> None:
        self.files += paths
        self.by_section.setdefault(self.current, []).extend(paths)

    def viewer(self, clouds: dict, name: str, caption: str) -> None:
        """A cloud to turn with the mouse, in ``index.html`` (``viewer.js`` draws it)."""
        self.blocks.append(("viewer", (clouds, name, caption)))

    def write_index(self) -> tuple[Path, Path]:
        md, page = self.out / "index.md", self.out / "index.html"
        md.write_text(self._markdown())
        page.write_text(self._html())
        if any(kind == "viewer" for kind, _ in self.blocks):
            from mpe3d.reports.viewer import write_script

            self.files.append(write_script(self.out))
        return md, page

    def _markdown(self) -> str:
        parts = [f"# {self.title}"]
        for kind, value in self.blocks:
            if kind == "heading":
                level, text = value
                parts.append(f"{'#' * level} {text}")
            elif kind == "text":
                parts.append(value)
            elif kind == "table":
                frame, name, caption, show = value
                links = f"[md](tables/{name}.md) · [tex](tables/{name}.tex)"
                parts.append(f"**{caption}** ({links})" + (f"\n\n{_markdown(frame)}" if show else ""))
            elif kind == "folded":
                lines, name, caption, _ = value
                parts.append(f"**{caption}** (every test and number: [md](tables/{name}.md) · "
                             f"[tex](tables/{name}.tex))\n\n{_markdown(lines)}")
            elif kind == "viewer":
                parts.append(f"*{value[2].split(' Drag')[0]}* (turn it with the mouse in index.html)")
            else:
                name, caption, labels = value
                pdf = f" · [pdf](figures/{name}.pdf)" if self.pdf else ""
                key = f" Key: {'; '.join(labels)}." if labels else ""
                parts.append(f"![{caption}](figures/{name}.png)\n\n*{caption}*{key} "
                             f"([png](figures/{name}.png){pdf})")
        return "\n\n".join(parts) + "\n"

    def _html(self) -> str:
        body = [f"<h1>{html.escape(self.title)}</h1>"]
        for kind, value in self.blocks:
            if kind == "heading":
                level, text = value
                body.append(f"<h{level}>{html.escape(text)}</h{level}>")
            elif kind == "text":
                body.append(f"<p>{html.escape(value)}</p>")
            elif kind == "table":
                frame, name, caption, show = value
                links = (f'<a href="tables/{name}.md">md</a> · <a href="tables/{name}.tex">tex</a>')
                table = frame.to_html(index=False, na_rep="–", float_format=lambda v: f"{v:.3g}",
                                      border=0) if show else ""
                body.append(f"<figure class='table'><figcaption>{html.escape(caption)} ({links})"
                            f"</figcaption>{table}</figure>")
            elif kind == "folded":
                body.append(_folded_html(*value))
            elif kind == "viewer":
                clouds, name, caption = value
                ident = "cloud-" + "".join(c if c.isalnum() else "-" for c in name)
                payload = json.dumps(clouds, separators=(",", ":")).replace("</", "<\\/")
                body.append(f"<figure class='viewer'><canvas class='mpe3d-cloud' data-cloud='{ident}' "
                            f"width='420' height='340'></canvas><figcaption>{html.escape(caption)}"
                            f"</figcaption><script type='application/json' id='{ident}'>{payload}"
                            "</script></figure>")
            else:
                name, caption, labels = value
                pdf = f" (<a href='figures/{name}.pdf'>pdf</a>)" if self.pdf else ""
                alt = f"{name}: {'; '.join(labels)}" if labels else name
                body.append(f"<figure><img src='figures/{name}.png' alt='{html.escape(alt, quote=True)}'>"
                            f"<figcaption>{html.escape(caption)}{pdf}</figcaption></figure>")
        script = "<script src='viewer.js'></script>" if any(k == "viewer" for k, _ in self.blocks) else ""
        return (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
                f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head>"
                f"<body>{''.join(body)}{script}</body></html>\n")


def _folded_html(lines: pd.DataFrame, name: str, caption: str, details) -> str:
    """One ``<details>`` per row: its line as the summary, its details beneath."""
    links = f'<a href="tables/{name}.md">md</a> · <a href="tables/{name}.tex">tex</a>'
    head = "".join(f"<span>{html.escape(str(c))}</span>" for c in lines.columns)
    rows = []
    for (_, line), more in zip(lines.iterrows(), details):
        cells = "".join(f"<span>{html.escape(str(v))}</span>" for v in line)
        folded = "".join(f"<dt>{html.escape(label)}</dt><dd>{html.escape(text)}</dd>" for label, text in more)
        rows.append(f"<details><summary>{cells}</summary><dl>{folded}</dl></details>")
    return (f"<figure class='folded'><figcaption>{html.escape(caption)} ({links}); "
            f"click a line for its test and numbers</figcaption><div class='folded-head'>{head}</div>"
            f"{''.join(rows)}</figure>")


_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;line-height:1.4}"
        "table{border-collapse:collapse;font-size:0.85em;margin:0.5em 0}"
        "th,td{padding:2px 8px;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}"
        "img{max-width:100%}figure{margin:1em 0}figcaption{font-size:0.9em;color:#333}"
        "figure.viewer{display:inline-block;width:430px;vertical-align:top;margin:0.5em 1em 0.5em 0}"
        "canvas.mpe3d-cloud{border:1px solid #ddd;cursor:grab;touch-action:none}"
        ".folded summary,.folded-head{display:grid;grid-template-columns:minmax(0,3fr) 7em 7em minmax(0,2fr);"
        "gap:0 1em;padding:3px 0;border-bottom:1px solid #ddd;font-size:0.9em}"
        ".folded summary{cursor:pointer;list-style:none}.folded summary::-webkit-details-marker{display:none}"
        ".folded-head{font-weight:bold}.folded dl{margin:0.3em 0 0.8em 1.5em;font-size:0.85em}"
        ".folded dt{font-weight:bold;margin-top:0.3em}.folded dd{margin:0 0 0 1em}")


def _legend_labels(fig) -> list[str]:
    """What a figure's legends name (its lines and marks), each once: said
    beside the figure, for a reader who cannot see the colours."""
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes)]
    texts = [t.get_text() for legend in legends if legend is not None for t in legend.get_texts()]
    return list(dict.fromkeys(t for t in texts if t))
