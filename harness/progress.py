"""A progress bar for sweeps (rich, on stderr): done, failed, skipped, ETA."""

from __future__ import annotations

import sys

from mpe3d.harness.runner import Reporter


class RichReporter(Reporter):
    """Shows ``runs ━━━━━━ 12/40  ✓ 11  ✗ 1  ↷ 8 skipped  0:00:31 < 0:01:12``."""

    def __init__(self, stream=None):
        from rich.console import Console

        self.console = Console(file=stream or sys.stderr)
        self.progress = None
        self.counts = {"FINISHED": 0, "FAILED": 0}
        self.skipped = 0

    def _fields(self) -> str:
        text = (f"[green]✓ {self.counts['FINISHED']}[/]  [red]✗ {self.counts['FAILED']}[/]  "
                f"↷ {self.skipped} skipped")
        if self.counts.get("ELSEWHERE"):  # computed by a concurrent sweep
            text += f"  ⇄ {self.counts['ELSEWHERE']} by another sweep"
        return text

    def start(self, total: int, skipped: int) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.skipped = skipped
        self.progress = Progress(TextColumn("runs"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[counts]}"), TimeElapsedColumn(),
                                 TextColumn("<"), TimeRemainingColumn(),
                                 console=self.console, transient=False)
        self.task = self.progress.add_task("runs", total=total, counts=self._fields())
        self.progress.start()

    def advance(self, status: str) -> None:
        self.counts[status] = self.counts.get(status, 0) + 1
        self.progress.update(self.task, advance=1, counts=self._fields())

    def stop(self) -> None:
        if self.progress is not None:
            self.progress.stop()
