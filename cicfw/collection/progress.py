"""The collection's progress bar, in samples."""
from __future__ import annotations


class ProgressBar:
    """A rich progress bar in samples (silent when disabled)."""

    def __init__(self, enabled: bool, total: int, label: str) -> None:
        self.p = None
        if enabled:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)

            self.p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                              TextColumn("samples"), TimeElapsedColumn(), TimeRemainingColumn())
            self.p.start()
            self.task = self.p.add_task(label, total=total)

    def advance(self, n: int) -> None:
        if self.p is not None:
            self.p.advance(self.task, n)

    def close(self) -> None:
        if self.p is not None:
            self.p.stop()
