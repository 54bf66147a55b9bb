"""Progress reporting for long jobs (rich): a bar with count, rate and ETA; silent when asked."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)
from rich.text import Text

console = Console(stderr=True)


class RateColumn(ProgressColumn):
    """Items per second of a task."""

    def __init__(self, unit: str = "it") -> None:
        super().__init__()
        self.unit = unit

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("    -" if speed is None else f"{speed:5.1f} {self.unit}/s", style="cyan")


class _Quiet:
    def add_task(self, *a, **k) -> int:
        return 0

    def update(self, *a, **k) -> None:
        pass

    def advance(self, *a, **k) -> None:
        pass


@contextmanager
def progress(enabled: bool = True, unit: str = "fr") -> Iterator[Progress | _Quiet]:
    """A rich Progress (count, rate, elapsed, ETA); a silent stand-in when ``enabled`` is False."""
    if not enabled:
        yield _Quiet()
        return
    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), RateColumn(unit),
            TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    with Progress(*cols, console=console) as p:
        try:
            yield p
        except Exception:  # a failed job's bar is cleared: its one-line error stands alone (an
            p.live.transient = True  # interrupted one keeps it: where it stopped)
            raise
