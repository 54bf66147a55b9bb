"""The one exception type a user sees: its message is a single line naming the file or option."""

from __future__ import annotations

from pathlib import Path


class TdofError(Exception):
    """A user-facing error. The CLI prints ``error: <message>`` and exits non-zero, no traceback."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else Path(path)
        text = " ".join(str(message).split())  # always one line
        super().__init__(f"{self.path}: {text}" if self.path is not None else text)
