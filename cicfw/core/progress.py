"""The project's progress bar: one rich layout for collecting samples and driving episodes."""
from __future__ import annotations

from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class ProgressBar:
    """A rich bar of ``total`` units: ``label``, bar, done/total, ``unit``, elapsed and time left; nothing
    at all when disabled. ``unit`` may name ``fields`` given at the start and to ``advance``
    (``"episodes, success {task.fields[rate]}"``)."""

    def __init__(self, enabled: bool, total: int, label: str, unit: str, **fields: Any) -> None:
        self._bar = None
        if enabled:
            self._bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn(unit), TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn())
            self._task = self._bar.add_task(label, total=total, **fields)
            self._bar.start()

    def advance(self, n: int = 1, **fields: Any) -> None:
        """``n`` more units done (and the unit's fields, if any, updated)."""
        if self._bar is not None:
            self._bar.update(self._task, advance=n, **fields)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
