"""The raw session's journal, ``journal.jsonl``: one JSON line per captured frame, appended.

The journal is the truth: a frame exists once its line is in the journal. Frames are written
first (atomically), then their journal line is appended and fsync'ed, so an interrupted capture
resumes from the journal and never trusts a half-written image. A journal line torn by a crash
is decided by one rule (:func:`_torn_tail`) that the reader and the appender share. The folder
around it: :mod:`tdof20.formats.session`; see ``docs/formats.md``.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from tdof20.errors import TdofError
from tdof20.formats.checks import Checker, is_int, json_type
from tdof20.formats.io import dumps_json
from tdof20.progress import console

JOURNAL_FILE = "journal.jsonl"
PHASES = ("transparent", "opaque")
FrameKey = tuple[str, int, int]  # (phase, arm, step)


def _frame_check(phase: Any, arm: Any, step: Any) -> None:
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
    if not is_int(arm) or arm < 0:
        raise ValueError(f"arm must be an integer >= 0, got {arm!r}")
    if not is_int(step) or step < 0:
        raise ValueError(f"step must be an integer >= 0, got {step!r}")


def frame_paths(phase: str, arm: int, step: int) -> tuple[str, str]:
    """Relative POSIX paths (rgb, depth) of a frame inside a session folder."""
    _frame_check(phase, arm, step)
    return (f"{phase}/arm{int(arm)}/rgb/{int(step):06d}.png", f"{phase}/arm{int(arm)}/depth/{int(step):06d}.png")


_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_JOURNAL_KNOWN = ("phase", "arm", "step", "angle_deg", "rgb", "depth", "sha256", "t")


@dataclass
class JournalEntry:
    """One captured frame: which it is, where its files are (relative POSIX paths), their sha256
    checksums, and when it was captured (unix time). ``extra`` keeps any further keys."""

    phase: str
    arm: int
    step: int
    angle_deg: float
    rgb: str
    depth: str
    sha256: dict
    t: float
    extra: dict = field(default_factory=dict)
    line: int | None = field(default=None, compare=False, repr=False)  # journal line it came from

    @property
    def key(self) -> FrameKey:
        return (self.phase, self.arm, self.step)

    def to_dict(self) -> dict:
        d = {"phase": self.phase, "arm": int(self.arm), "step": int(self.step),
             "angle_deg": float(self.angle_deg), "rgb": self.rgb, "depth": self.depth,
             "sha256": dict(self.sha256), "t": float(self.t)}
        for k, v in self.extra.items():
            if k not in d:
                d[k] = v
        return d

    @classmethod
    def from_dict(cls, d: Any, path: str | Path | None = None, line: int | None = None) -> "JournalEntry":
        c = Checker(path, prefix=f"line {line}: " if line is not None else "")
        if not isinstance(d, dict):
            c.fail(f"a journal entry must be a JSON object {{...}}, got {json_type(d)}")
        phase = c.string(c.get(d, "phase", ""), "phase")
        if phase not in PHASES:
            c.fail(f"phase must be one of {', '.join(PHASES)}, got {phase!r}")
        arm = c.integer(c.get(d, "arm", ""), "arm", lo=0)
        step = c.integer(c.get(d, "step", ""), "step", lo=0)
        angle = c.number(c.get(d, "angle_deg", ""), "angle_deg")
        files = {}
        for k in ("rgb", "depth"):
            rel = c.string(c.get(d, k, ""), k)
            pp = PurePosixPath(rel)
            if not rel or pp.is_absolute() or ".." in pp.parts or "\\" in rel:
                c.fail(f"{k} must be a relative POSIX path inside the session, got {rel!r}")
            files[k] = rel
        sha = c.obj(c.get(d, "sha256", ""), "sha256")
        for k in ("rgb", "depth"):
            h = c.string(c.get(sha, k, "sha256"), f"sha256.{k}")
            if not _HEX64.match(h):
                c.fail(f"sha256.{k} must be 64 lower-case hex digits, got {h[:80]!r}")
        t = c.number(c.get(d, "t", ""), "t")
        extra = {k: v for k, v in d.items() if k not in _JOURNAL_KNOWN}
        return cls(phase, arm, step, angle, files["rgb"], files["depth"], dict(sha), t, extra, line)


def _journal_file(path: str | Path) -> Path:
    p = Path(path)
    return p if p.suffix == ".jsonl" else p / JOURNAL_FILE


def _parse_line(raw: bytes) -> Any:
    return json.loads(raw.decode("utf-8"))


def _torn_tail(f, size: int) -> int | None:
    """Where the journal's torn last line starts (a byte offset), or None when it has none.

    **The torn-line rule**, the one place it is decided: the last non-blank line of the journal is
    *torn* when it is not valid JSON (a crash or power cut cut the append short), whether or not a
    newline follows it. :func:`read_journal` leaves a torn line out and :func:`append_journal`
    cuts it off (with any blank lines after it) before it appends, so the two always agree. A
    malformed line anywhere else, or a last line that is valid JSON but not a valid entry, is no
    tear: it is an error naming its line. ``f``: a binary file (or BytesIO) open for reading.
    """
    pos, tail = size, b""
    while pos > 0:
        n = min(4096, pos)
        pos -= n
        f.seek(pos)
        tail = f.read(n) + tail
        body = tail.rstrip()
        i = body.rfind(b"\n")
        if body and (i >= 0 or pos == 0):
            try:
                _parse_line(body[i + 1:])
            except ValueError:  # json.JSONDecodeError and UnicodeDecodeError both are
                return pos + i + 1
            return None
    return None


def _count_lines(f, upto: int) -> int:
    f.seek(0)
    return f.read(upto).count(b"\n")


_NOTICED_ENV = "TDOF20_JOURNAL_NOTICES"
_noticed: set[str] = set()


def _notice_torn(path: Path, lineno: int, text: str) -> None:
    """Say once, on stderr, that line ``lineno`` of the journal ``path`` is torn: once per process
    and file line however many readers open the journal, and not again in the worker processes
    this process starts afterwards (they inherit the environment that records it)."""
    key = hashlib.sha256(f"{os.path.realpath(path)}:{lineno}".encode()).hexdigest()[:16]
    seen = set(os.environ.get(_NOTICED_ENV, "").split())
    if key in _noticed or key in seen:
        return
    _noticed.add(key)
    os.environ[_NOTICED_ENV] = " ".join(sorted(seen | {key}))
    console.print(f"warning: {path}: line {lineno} {text}", markup=False, highlight=False, soft_wrap=True)


def append_journal(dir: str | Path, entry: JournalEntry) -> None:
    """Append one entry to ``<dir>/journal.jsonl``, flushed and fsync'ed before returning.

    A torn last line (see :func:`_torn_tail`: not valid JSON, with or without a newline after it)
    is cut off first, so the new line starts on a line of its own; a valid last line missing its
    newline is ended. Complete lines are never changed.
    """
    path = _journal_file(dir)
    line = (dumps_json(entry.to_dict(), indent=None) + "\n").encode()
    created = not path.exists()
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as f:
        size = f.seek(0, os.SEEK_END)
        cut = _torn_tail(f, size)
        if cut is not None:
            _notice_torn(path, _count_lines(f, cut) + 1,
                         "is incomplete (an interrupted write): cut off before appending")
            f.truncate(cut)
        elif size > 0:
            f.seek(size - 1)
            if f.read(1) != b"\n":  # a valid last line whose newline the crash did not write
                f.write(b"\n")
        f.write(line)
        f.flush()
        os.fsync(f.fileno())
    if created:
        _fsync_dir(path.parent)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # pragma: no cover - not supported on every OS
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def read_journal(dir: str | Path) -> list[JournalEntry]:
    """All entries of ``<dir>/journal.jsonl`` in file order ([] if there is no journal).

    A torn last line (see :func:`_torn_tail`) is left out, said once on stderr; a malformed line
    anywhere else is a TdofError naming the file and the line number. Blank lines are skipped.
    """
    path = _journal_file(dir)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    except (IsADirectoryError, PermissionError) as e:
        raise TdofError(f"cannot read ({type(e).__name__})", path) from None
    cut = _torn_tail(io.BytesIO(data), len(data))
    if cut is not None:
        _notice_torn(path, data.count(b"\n", 0, cut) + 1,
                     "is incomplete (an interrupted write): ignored; resuming the capture takes "
                     "its frame again and cuts the line off")
        data = data[:cut]
    out = []
    for i, raw in enumerate(data.split(b"\n")):
        if not raw.strip():
            continue
        try:
            d = _parse_line(raw)
        except ValueError as e:
            msg = e.msg if isinstance(e, json.JSONDecodeError) else "not UTF-8 text"
            raise TdofError(f"line {i + 1} is not valid JSON ({msg})", path) from None
        out.append(JournalEntry.from_dict(d, path, i + 1))
    return out


__all__ = ["JOURNAL_FILE", "PHASES", "FrameKey", "JournalEntry", "append_journal", "read_journal", "frame_paths"]
