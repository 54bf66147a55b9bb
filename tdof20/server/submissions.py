"""Submissions: accept one (limits, strict checks, durable store, queue), read them back as their
owner or the public may see them, withdraw, and the leaderboard. The pages and the API both
call these; what they return holds no test label (docs/server.md)."""

from __future__ import annotations

import json
import secrets
import time
from dataclasses import dataclass, field
from typing import BinaryIO

from sqlalchemy import Engine, and_, delete, insert, select, update
from sqlalchemy.exc import OperationalError

from tdof20.errors import TdofError
from tdof20.server.check import check_file
from tdof20.server.config import MAX_UPLOADS, RESERVE_S
from tdof20.server.db import jobs, submissions, users
from tdof20.server.disclosure import disclose, server_key
from tdof20.server.facts import DatasetFacts
from tdof20.server.store import FULL, FULL_ERRNOS, Refused, Store, Stored

TEXT_FIELDS = {"method": 100, "description": 4000, "authors": 1000, "hardware": 500, "time_per_image": 100,
               "training_data": 1000}
LEADERBOARD_METRICS = ("add_s", "proj2d", "adds", "add", "auc_adds", "auc_add_s", "ar", "ar_mssd", "ar_mspd",
                       "ar_vsd")


@dataclass
class Fields:
    """What a researcher says about a submission (BOP asks for authors, hardware, time, training data)."""

    method: str
    split: str
    part: str = "test"  # or "val": the protocol's validation part (per-image errors shown)
    description: str = ""
    authors: str = ""
    hardware: str = ""
    time_per_image: str = ""
    training_data: str = ""
    public: bool = False
    extra: dict = field(default_factory=dict)

    def checked(self) -> "Fields":
        for name, limit in TEXT_FIELDS.items():
            v = getattr(self, name)
            if not isinstance(v, str) or len(v) > limit:
                raise Refused(400, f"{name} must be text of at most {limit} characters")
            if "\x00" in v:
                raise Refused(400, f"{name} holds a NUL character")
        if not self.method.strip():
            raise Refused(400, "method must not be empty")
        return self


def _message(e: TdofError) -> str:
    """A reader's error without the store's path (the message is 'PATH: line N: ...')."""
    text = str(e)
    if e.path is not None and text.startswith(f"{e.path}: "):
        text = text[len(str(e.path)) + 2:]
    return text


@dataclass
class Slot:
    """A submission's place in its owner's daily limit, reserved before the file is read: a row of
    status ``receiving`` (no job yet, so no page or list shows it) that :func:`accept` fills and
    queues, or :func:`release` deletes."""

    id: int
    uid: str
    taken: bool = False


def _window(c, user_id: int, now: float) -> tuple[list[float], int]:
    """(creation times of the submissions that count against the limit, uploads in progress).
    Counted: queued, scoring or scored ones, uploads in progress, and ones withdrawn once scoring
    began; not counted: failed ones (a failure is the server's) and ones withdrawn before scoring."""
    rows = c.execute(select(submissions.c.created, submissions.c.status, jobs.c.state)
                     .select_from(submissions.outerjoin(jobs, jobs.c.submission_id == submissions.c.id))
                     .where(and_(submissions.c.user_id == user_id, submissions.c.created > now - 86400))).all()
    counted, uploading = [], 0
    for r in rows:
        if r.status == "receiving":
            if r.created > now - RESERVE_S:  # (older: a server killed mid-upload; swept at start)
                counted.append(r.created)
                uploading += 1
        elif r.status in ("queued", "scoring", "done") or (r.status == "withdrawn" and r.state not in
                                                            (None, "cancelled")):
            counted.append(r.created)
    return sorted(counted), uploading


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t))


def quota(engine: Engine, user: dict, daily_limit: int) -> dict:
    """The user's daily limit now: {"limit", "used", "left", "resets_at" (when the oldest counted
    submission leaves the 24-hour window and a slot comes back; None when none is used),
    "resets_at_unix", "uploading"}."""
    now = time.time()
    with engine.begin() as c:
        counted, uploading = _window(c, user["id"], now)
    reset = counted[0] + 86400 if counted else None
    return {"limit": daily_limit, "used": len(counted), "left": max(0, daily_limit - len(counted)),
            "resets_at": None if reset is None else _utc(reset), "resets_at_unix": reset, "uploading": uploading}


def reserve(engine: Engine, user: dict, daily_limit: int, max_uploads: int = MAX_UPLOADS) -> Slot:
    """Check the daily limit and the uploads in progress and reserve a slot, in one transaction
    (SQLite: its single writer lock, BEGIN IMMEDIATE; PostgreSQL: the user's row locked FOR UPDATE),
    so that concurrent uploads never pass the limit together. 429 in one line when over either."""
    now = time.time()
    try:
        with engine.begin() as c:
            if c.dialect.name == "postgresql":
                c.execute(select(users.c.id).where(users.c.id == user["id"]).with_for_update())
            counted, uploading = _window(c, user["id"], now)
            if len(counted) >= daily_limit:
                raise Refused(429, f"limit reached: {daily_limit} submissions per user per 24 hours; the next one "
                                   f"can be sent after {_utc(counted[0] + 86400)}")
            if uploading >= max_uploads:
                raise Refused(429, f"{uploading} uploads of yours are in progress (at most {max_uploads} at once): "
                                   "send this one when one has finished")
            uid = secrets.token_hex(8)
            sid = c.execute(insert(submissions).values(
                uid=uid, user_id=user["id"], method="", split="", part="test", filename="", stored="", size=0,
                sha256="", n_rows=0, status="receiving", created=now, scored_count=0)).inserted_primary_key[0]
    except OperationalError as e:  # nothing reserved: a full disk under the database, or one too busy
        raise Refused(507, FULL) if _disk_full(e) else Refused(503, "the server's database is busy: try again "
                                                                     "in a minute") from None
    return Slot(sid, uid)


def release(engine: Engine, slot: Slot) -> None:
    """Give back a slot whose upload was refused (or cut); a slot already taken stays."""
    if slot.taken:
        return
    with engine.begin() as c:
        c.execute(delete(submissions).where(and_(submissions.c.id == slot.id, submissions.c.status == "receiving")))


def sweep_reservations(engine: Engine) -> int:
    """Delete the slots of uploads that began over :data:`RESERVE_S` ago and never finished (their
    server was killed mid-upload): they stopped counting then. Returns how many."""
    with engine.begin() as c:
        return c.execute(delete(submissions).where(and_(submissions.c.status == "receiving",
                                                        submissions.c.created < time.time() - RESERVE_S))).rowcount


def accept(engine: Engine, store: Store, facts: DatasetFacts, user: dict, src: BinaryIO | Stored, filename: str,
           fields: Fields, max_bytes: int, max_line: int, daily_limit: int, slot: Slot | None = None,
           max_uploads: int = MAX_UPLOADS) -> dict:
    """Check, store durably and queue one submission; returns its status dict (with ``quota``).
    ``slot``: the place :func:`reserve` gave it before its file was read (the server's way); without
    one it is reserved here. ``src``: the file, already in the store's tmp/ (a :class:`Stored`) or
    a stream to copy there. Refused (with an HTTP status and one line) on a limit, a bad field or
    the first error of the strict checks (streamed: :func:`tdof20.server.check.check_file`);
    nothing is stored or queued then, and the slot is given back."""
    slot = slot if slot is not None else reserve(engine, user, daily_limit, max_uploads)
    try:
        fields.checked()
        if fields.split not in facts.splits:
            raise Refused(400, f"split must be one of {', '.join(facts.splits)}")
        if fields.part not in facts.parts(fields.split):
            raise Refused(400, f"part must be one of {', '.join(facts.parts(fields.split))} for {fields.split} "
                               "(val: the protocol's validation part, where this server has one)")
        got = src if isinstance(src, Stored) else store.receive(src, max_bytes, max_line)
        try:
            try:
                res = check_file(got.path, facts, fields.split)
            except TdofError as e:
                raise Refused(400, _message(e)) from None
            name = f"{slot.uid}.csv"
            store.keep(got, name)
            try:
                with engine.begin() as c:
                    r = c.execute(update(submissions).where(and_(submissions.c.id == slot.id,
                                                                 submissions.c.status == "receiving")).values(
                        method=fields.method.strip(), split=fields.split, part=fields.part,
                        description=fields.description, authors=fields.authors, hardware=fields.hardware,
                        time_per_image=fields.time_per_image, training_data=fields.training_data,
                        public=fields.public, filename=(filename or "results.csv")[-255:], stored=name,
                        size=got.size, sha256=got.sha256, n_rows=res.n_rows, status="queued"))
                    if r.rowcount != 1:  # (swept: the upload took longer than RESERVE_S)
                        raise Refused(408, "the upload took too long and its slot lapsed: send it again")
                    c.execute(insert(jobs).values(submission_id=slot.id, state="queued", attempts=0, stage="queued"))
            except BaseException as e:  # not committed: its file goes too
                store.submission_path(name).unlink(missing_ok=True)
                if _disk_full(e):
                    raise Refused(507, FULL) from None
                raise
            slot.taken = True
        finally:
            got.path.unlink(missing_ok=True)
    finally:
        if not slot.taken:
            try:
                release(engine, slot)
            except Exception:  # (a database without room: the slot lapses after RESERVE_S)
                pass
    out = get(engine, slot.uid, user)
    out["warnings"] = list(res.warnings)
    out["quota"] = quota(engine, user, daily_limit)
    return out


def _disk_full(e: BaseException) -> bool:
    """Whether a failed commit ran out of room (SQLite: SQLITE_FULL; PostgreSQL: SQLSTATE 53100)."""
    if isinstance(e, OSError):
        return e.errno in FULL_ERRNOS
    if isinstance(e, OperationalError):
        orig = e.orig
        return ("database or disk is full" in str(orig) or getattr(orig, "sqlstate", None) == "53100"
                or getattr(orig, "sqlite_errorname", None) == "SQLITE_FULL")
    return False


def _row_dict(r, owner: bool, key: bytes) -> dict:
    d = {k: r._mapping[k] for k in ("uid", "method", "split", "part", "description", "authors", "hardware",
                                    "time_per_image", "training_data", "public", "status", "created", "scored")}
    d["user"] = r.user
    if owner:
        d.update(filename=r.filename, n_rows=r.n_rows, size=r.size, sha256=r.sha256, error=r.error,
                 stage=r.stage, attempts=r.attempts)
    stored = json.loads(r.result) if r.result and r.status == "done" else None
    # the one point where a result leaves the server: what the disclosure rule lets it show
    d["result"] = disclose(stored, r.part, key, r.uid)
    return d


def _query():
    return (select(submissions, users.c.name.label("user"), jobs.c.stage, jobs.c.attempts)
            .select_from(submissions.join(users, users.c.id == submissions.c.user_id)
                         .join(jobs, jobs.c.submission_id == submissions.c.id)))


def get(engine: Engine, uid: str, viewer: dict | None) -> dict:
    """One submission as ``viewer`` may see it: its owner always, others only a public one not
    withdrawn. 404 otherwise (whether it exists is not said)."""
    with engine.begin() as c:
        r = c.execute(_query().where(submissions.c.uid == str(uid)[:32])).first()
    owner = r is not None and viewer is not None and r.user_id == viewer["id"]
    if r is None or not (owner or (r.public and r.status != "withdrawn")):
        raise Refused(404, "no such submission")
    return _row_dict(r, owner, server_key(engine))


def mine(engine: Engine, user: dict) -> list[dict]:
    key = server_key(engine)
    with engine.begin() as c:
        rows = c.execute(_query().where(submissions.c.user_id == user["id"]).order_by(submissions.c.id.desc()))
        return [_row_dict(r, True, key) for r in rows]


def withdraw(engine: Engine, uid: str, user: dict) -> dict:
    """The owner withdraws a submission: off the leaderboard, its job cancelled if not yet scored."""
    with engine.begin() as c:
        r = c.execute(select(submissions.c.id, submissions.c.user_id).where(submissions.c.uid == str(uid)[:32])).first()
        if r is None or r.user_id != user["id"]:
            raise Refused(404, "no such submission")
        c.execute(update(submissions).where(submissions.c.id == r.id).values(status="withdrawn"))
        c.execute(update(jobs).where(and_(jobs.c.submission_id == r.id, jobs.c.state == "queued"))
                  .values(state="cancelled"))
    return get(engine, uid, user)


def leaderboard(engine: Engine, split: str, metric: str = "add_s") -> list[dict]:
    """The public, scored submissions on a protocol's test part, best first by the mean over objects
    of ``metric`` as the disclosure rule shows it (validation submissions are not ranked): equal
    shown scores keep the order they were submitted in, so a rank tells nothing finer than a score."""
    if metric not in LEADERBOARD_METRICS:
        raise Refused(400, f"metric must be one of {', '.join(LEADERBOARD_METRICS)}")
    key = server_key(engine)
    with engine.begin() as c:
        rows = c.execute(_query().where(and_(submissions.c.split == split, submissions.c.part == "test",
                                             submissions.c.public.is_(True),
                                             submissions.c.status == "done")))
        out = [_row_dict(r, False, key) for r in rows]
    for d in out:
        mean = (d["result"] or {}).get("summary", {}).get("mean") or {}
        d["score"] = mean.get(metric)
        d["score_step"] = mean.get("step")
        d["score_withheld"] = mean.get("withheld")
    out.sort(key=lambda d: (d["score"] is None, -(d["score"] or 0.0), d["created"]))
    return out


__all__ = ["Fields", "LEADERBOARD_METRICS", "Slot", "accept", "quota", "release", "reserve", "sweep_reservations",
           "get", "leaderboard", "mine", "withdraw"]
