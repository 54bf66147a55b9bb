"""Progress reporting for long jobs (rich): a bar with count, rate and ETA; silent when asked."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator, TextIO

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)
from rich.rule import Rule
from rich.text import Text

NO_WRAP_WIDTH = 100_000  # piped or redirected output: one line stays one line


def make_console(stream: TextIO | None = None, *, stderr: bool = False) -> Console:
    """A console for ``stream`` (stdout, or stderr): a terminal's own width; piped or redirected,
    no wrapping at all (rich would wrap at 80 columns: headers cut to "capaci…", figures split from
    their labels), so that a file or a ``grep`` gets whole lines."""
    stream = stream or (sys.stderr if stderr else sys.stdout)
    tty = hasattr(stream, "isatty") and stream.isatty()
    return Console(stderr=stderr, width=None if tty else NO_WRAP_WIDTH, soft_wrap=not tty)


console = make_console(stderr=True)
out_console = make_console()  # stdout: tables and reports


def rule(title: str, align: str = "center", con: Console | None = None) -> None:
    """A titled rule across the terminal; piped (no width to span), as wide as its title, at least 80."""
    con = con or console
    width = None if con.is_terminal else max(80, Text.from_markup(title).cell_len + 6)
    con.print(Rule(title, align=align), width=width)


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
