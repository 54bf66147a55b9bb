"""The file store: DATA/submissions/<uid>.csv and DATA/results/<uid>/ (what the figures are drawn
from, and the figures once drawn: :mod:`tdof20.server.figures`). An upload is
copied in bounded chunks to a temp file in DATA/tmp/ (its size and longest line checked as it
comes), fsynced, and renamed to its final name — a name the server makes, never the uploaded
one — so nothing is written outside the store and a half-written file is never taken as stored.
A temp file is named after its host and process; a server starting removes the temp files of
this host's processes that are gone (an upload cut by a crash or a kill -9), never a live one's."""

from __future__ import annotations

import errno
import hashlib
import os
import secrets
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

CHUNK = 1 << 20
SLICE = 64 * 1024  # bytes checked and written at once (the line check splits them: a bounded copy)
FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # no room: the disk, a quota, a file size limit
FULL = "the server's disk is full: the submission was not stored; try later"


class Refused(Exception):
    """An upload refused: an HTTP status and one line."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass
class Stored:
    """A file copied into the store's tmp/ (not yet accepted)."""

    path: Path
    size: int
    sha256: str


class Store:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        for sub in ("submissions", "results", "tmp"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.host = socket.gethostname().replace(".", "_")[:64]

    def remove_stale_uploads(self) -> int:
        """Remove this host's temp files whose process is gone; returns how many."""
        n = 0
        for f in (self.root / "tmp").glob(f"{self.host}.*.*.part"):
            pid = f.name[len(self.host) + 1:].split(".", 1)[0]
            if pid.isdigit() and not _alive(int(pid)):
                f.unlink(missing_ok=True)
                n += 1
        return n

    def submission_path(self, stored: str) -> Path:
        return self.root / "submissions" / stored

    def results_dir(self, uid: str) -> Path:
        return self.root / "results" / uid

    def receive(self, src: BinaryIO, max_bytes: int, max_line: int) -> Stored:
        """Copy ``src`` into tmp/ in chunks: refused (413) beyond ``max_bytes`` or a line longer than
        ``max_line``, (507) when the disk is full; the temp file goes on any refusal."""
        w = self.writer(max_bytes, max_line)
        try:
            while chunk := src.read(CHUNK):
                w.write(chunk)
            return w.finish()
        except BaseException:
            w.abort()
            raise

    def writer(self, max_bytes: int, max_line: int) -> "Upload":
        """An upload written into tmp/ as it arrives (:class:`Upload`): memory O(1) in its size."""
        return Upload(self.root / "tmp" / f"{self.host}.{os.getpid()}.{secrets.token_hex(16)}.part", max_bytes,
                      max_line)

    def keep(self, stored: Stored, name: str) -> None:
        """Move an accepted file to submissions/<name> and make the rename durable."""
        os.replace(stored.path, self.submission_path(name))
        fd = os.open(self.root / "submissions", os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class Upload:
    """A file written chunk by chunk to ``path`` (exclusive create): its size and longest line are
    checked as it comes (413), a full disk is the one-line 507; :meth:`finish` syncs it,
    :meth:`abort` (on any refusal) removes it."""

    def __init__(self, path: Path, max_bytes: int, max_line: int):
        self.path, self.max_bytes, self.max_line = path, max_bytes, max_line
        self.size = self.line = 0
        self.h = hashlib.sha256()
        try:
            self.f = open(path, "xb")
        except OSError as e:
            raise _full(e) from None

    def write(self, data: bytes) -> None:
        for i in range(0, len(data), SLICE):  # (a server may hand over megabytes at once)
            self._write(data[i:i + SLICE])

    def _write(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.size > self.max_bytes:
            raise Refused(413, f"the file is larger than the limit of {self.max_bytes} bytes")
        parts = chunk.split(b"\n")
        longest = self.line + len(parts[0])  # the line the previous chunk left open
        if len(parts) > 1:
            longest = max([longest] + [len(p) for p in parts[1:-1]])
            self.line = len(parts[-1])
        else:
            self.line = longest
        if max(longest, self.line) > self.max_line:
            raise Refused(413, f"a line is longer than the limit of {self.max_line} bytes")
        self.h.update(chunk)
        try:
            self.f.write(chunk)
        except OSError as e:
            raise _full(e) from None

    def finish(self) -> Stored:
        try:
            self.f.flush()
            os.fsync(self.f.fileno())
            self.f.close()
        except OSError as e:
            raise _full(e) from None
        return Stored(self.path, self.size, self.h.hexdigest())

    def abort(self) -> None:
        try:
            self.f.close()
        except OSError:
            pass
        self.path.unlink(missing_ok=True)


def _full(e: OSError) -> BaseException:
    """A write's OSError: the one-line 507 when it found no room, else itself."""
    return Refused(507, FULL) if e.errno in FULL_ERRNOS else e


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


__all__ = ["FULL", "FULL_ERRNOS", "Refused", "Store", "Stored", "Upload"]
