"""The server's settings: where the dataset, the database and the file store are, and the limits
(docs/server.md states them to researchers)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

MAX_UPLOAD_BYTES = 64 * 1024 * 1024  # a request body (results of ~200k estimates fit)
MAX_LINE_BYTES = 4096  # a results row is ~300 bytes
DAILY_LIMIT = 5  # submissions per user per 24 hours (failed by the server or withdrawn before scoring: not counted)
MAX_UPLOADS = 2  # uploads of one user in progress at once
RESERVE_S = 3600.0  # an upload's reserved slot lapses this long after it began (a server killed mid-upload)
MAX_FAILURES = 10  # failed sign-ins (and, apart, refused API tokens) per client address within FAILURE_WINDOW_S
FAILURE_WINDOW_S = 900.0
LEASE_S = 60.0  # a worker's claim on a job lasts this long unless renewed


@dataclass
class ServerConfig:
    """``dataset``: the full dataset (with its test labels) the scorer reads; ``data``: the folder of
    the file store (and of the SQLite database when ``db`` is None: DATA/server.db)."""

    dataset: Path
    data: Path
    db: str | None = None
    max_upload_bytes: int = MAX_UPLOAD_BYTES
    max_line_bytes: int = MAX_LINE_BYTES
    daily_limit: int = DAILY_LIMIT
    max_uploads: int = MAX_UPLOADS
    lease_s: float = LEASE_S
    secure_cookies: bool = False  # set behind HTTPS
    max_failures: int = MAX_FAILURES
    failure_window_s: float = FAILURE_WINDOW_S

    @property
    def db_url(self) -> str:
        return self.db or f"sqlite:///{Path(self.data).resolve() / 'server.db'}"


__all__ = ["DAILY_LIMIT", "FAILURE_WINDOW_S", "LEASE_S", "MAX_FAILURES", "MAX_LINE_BYTES", "MAX_UPLOADS", "MAX_UPLOAD_BYTES", "RESERVE_S", "ServerConfig"]
