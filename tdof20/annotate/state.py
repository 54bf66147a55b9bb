"""The scene folder's bookkeeping: what ``tdof20 annotate`` keeps in ``SCENE/work/`` besides results.

* fingerprints: :func:`sha_file`, :func:`sha_obj` (of JSON-able data), :func:`dir_hash` (the files
  directly in a folder), :func:`count_files`;
* :class:`StateFile` — ``work/state.json``: per finished stage when it ran, how long, the
  fingerprint of its inputs and the signature of its outputs; a stage being (re)run has no
  ``finished``, so an interruption leaves it unfinished;
* :class:`FolderLock` — ``work/.lock``, one annotate run per scene folder (an ``flock``);
* :func:`session_identity` (which capture a scene folder was annotated from), :func:`clear_scene`
  (``--force`` over another session's annotation), :func:`remove_stale_temp_files` (what a killed
  run left).
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

from tdof20.annotate.config import jsonable
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, write_json
from tdof20.formats.io import stale_temp_files

__all__ = ["STATE_FORMAT", "STATE_VERSION", "WORK", "FolderLock", "StateFile", "clear_scene", "count_files",
           "dir_hash", "remove_stale_temp_files", "session_identity", "sha_file", "sha_obj"]

STATE_FORMAT = "tdof20-annotate-state"
STATE_VERSION = 1
WORK = "work"   # the scene folder's working folder: intermediate results, state, lock, summary


# ---------------------------------------------------------------------------------------------
# fingerprints and the state file
# ---------------------------------------------------------------------------------------------
def sha_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sha_obj(obj: Any) -> str:
    return hashlib.sha256(json.dumps(jsonable(obj), sort_keys=True).encode()).hexdigest()


def dir_hash(d: Path) -> str:
    """Names and contents of the files directly in ``d``."""
    if not d.is_dir():
        return "absent"
    return sha_obj({p.name: sha_file(p) for p in sorted(d.iterdir()) if p.is_file()})


def count_files(d: Path) -> int:
    try:
        return sum(1 for e in os.scandir(d) if e.is_file())
    except FileNotFoundError:
        return 0


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


class StateFile:
    """``work/state.json``: {stage: {started, finished, seconds, fingerprint, outputs}}; a stage
    being (re)run has no ``finished``, so an interruption leaves it unfinished."""

    def __init__(self, work: Path, raw: Path):
        self.path = work / "state.json"
        self.data = {"format": STATE_FORMAT, "version": STATE_VERSION, "raw": str(raw), "stages": {}}
        if self.path.exists():
            d = read_json(self.path)
            if not isinstance(d, dict) or d.get("format") != STATE_FORMAT or not isinstance(d.get("stages"), dict):
                raise TdofError(f"not an annotation state file (format must be '{STATE_FORMAT}')", self.path)
            if int(d.get("version", 0)) > STATE_VERSION:
                raise TdofError(f"written by a newer tdof20 (version {d.get('version')}): upgrade tdof20", self.path)
            self.data = d
            self.data["raw"] = str(raw)

    def entry(self, stage: str) -> dict:
        return self.data["stages"].get(stage, {})

    def finished(self, stage: str) -> bool:
        return bool(self.entry(stage).get("finished"))

    def start(self, stage: str) -> None:
        self.data["stages"][stage] = {"started": _now()}
        self.save()

    def finish(self, stage: str, fingerprint: str, seconds: float, outputs: dict) -> None:
        e = self.data["stages"].setdefault(stage, {"started": _now()})
        e.update(finished=_now(), seconds=round(seconds, 3), fingerprint=fingerprint, outputs=outputs)
        self.save()

    def save(self) -> None:
        write_json(self.path, self.data)


# ---------------------------------------------------------------------------------------------
# the folder: lock, identity, clearing, stale temporary files
# ---------------------------------------------------------------------------------------------
class FolderLock:
    """``work/.lock``: one annotate run per scene folder at a time. An exclusive ``flock`` on the
    file is the lock (atomic, and released by the kernel when the holder dies, however it dies);
    the pid written into it only serves the message a second run prints. The file is never
    deleted: a run that unlinked it could let a third run lock a new file beside a live holder."""

    def __init__(self, work: Path):
        self.path = work / ".lock"
        self.fd: int | None = None

    def __enter__(self) -> "FolderLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
            finally:
                os.close(fd)
            who = f" (pid {pid})" if pid.isdigit() else ""
            raise TdofError(f"another annotate run{who} is writing this folder; wait for it to finish",
                            self.path) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self.fd = fd
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            os.close(self.fd)   # closing releases the flock
            self.fd = None


def session_identity(session: RawSession) -> dict:
    """What makes a raw session this one capture: its scene and the checksums of its first
    journalled frame (a resumed capture, an edited session.json or a moved folder keep it)."""
    entries = sorted(session.entries, key=lambda e: e.t) if session.entries else []
    first = entries[0] if entries else None
    return {"scene_id": session.info.scene_id,
            "first_frame": None if first is None else {"key": list(first.key), **dict(first.sha256)}}


def clear_scene(out: Path) -> None:
    """Remove everything an annotate run wrote into ``out`` (for ``--force`` over another session's
    annotation), keeping ``work/.lock`` (held by this run)."""
    for p in out.iterdir():
        if p.name == WORK and p.is_dir():
            for q in p.iterdir():
                if q.name != ".lock":
                    shutil.rmtree(q) if q.is_dir() and not q.is_symlink() else q.unlink()
        elif p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def remove_stale_temp_files(out: Path) -> int:
    """Delete the temporary files an interrupted run left in ``out`` (atomic writes'
    ``.NAME.<8 chars>.tmp``, :func:`tdof20.formats.io.stale_temp_files`; the fused mesh's
    ``*.tmp.ply``); only called while this run holds the folder's lock."""
    stale = stale_temp_files(out) + sorted(p for p in Path(out).rglob("*.tmp.ply") if p.is_file())
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)