"""Submissions: accept one (limits, strict checks, durable store, queue), read them back as their
owner or the public may see them, withdraw, and the leaderboard. The pages and the API both
call these; what they return holds no test label (docs/server.md)."""

from __future__ import annotations

import json
import math
import secrets
import sys
import time
from dataclasses import dataclass, field
from typing import BinaryIO

from sqlalchemy import Engine, and_, delete, func, insert, or_, select, update
from sqlalchemy.exc import OperationalError

from tdof20.errors import TdofError
from tdof20.server.check import check_file
from tdof20.server.config import MAX_UPLOADS, RESERVE_S
from tdof20.server.db import held_back, jobs, submissions, users
from tdof20.server.disclosure import disclose, server_key
from tdof20.server.facts import DatasetFacts
from tdof20.server.store import FULL, FULL_ERRNOS, Refused, Store, Stored

TEXT_FIELDS = {"method": 100, "description": 4000, "authors": 1000, "hardware": 500, "time_per_image": 100,
               "training_data": 1000, "paper": 500, "code": 500}
LINK_FIELDS = ("paper", "code")  # shown as links: http(s) only
PHASES = ("val", "test", "final")  # the validation phase, the test phase (public part), the final leaderboard
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
    paper: str = ""  # a link to the paper (http or https)
    code: str = ""  # a link to the code
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
        for name in LINK_FIELDS:
            v = getattr(self, name).strip()
            setattr(self, name, v)
            if v and (not v.lower().startswith(("http://", "https://")) or any(ch.isspace() for ch in v)):
                raise Refused(400, f"{name} must be a link starting with http:// or https:// (or empty)")
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


_UNRELEASED: dict[str, set[int]] = {}  # per database: slots this process could not give back (no room)


def _unreleased(engine: Engine) -> set[int]:
    return _UNRELEASED.setdefault(engine.url.render_as_string(hide_password=True), set())


def _window(c, user_id: int, now: float) -> tuple[list[float], int]:
    """(creation times of the submissions that count against the limit, uploads in progress).
    Counted: queued, scoring or scored ones, uploads in progress, and ones withdrawn once scoring
    began; not counted: failed ones (a failure is the server's), ones withdrawn before scoring, and
    slots refused while the database had no room to give them back (:func:`release`)."""
    rows = c.execute(select(submissions.c.id, submissions.c.created, submissions.c.status, jobs.c.state)
                     .select_from(submissions.outerjoin(jobs, jobs.c.submission_id == submissions.c.id))
                     .where(and_(submissions.c.user_id == user_id, submissions.c.created > now - 86400))).all()
    counted, uploading = [], 0
    for r in rows:
        if r.status == "receiving":
            # (older: a server killed mid-upload, swept at start; unreleased: refused, given back later)
            if r.created > now - RESERVE_S and r.id not in _unreleased(c.engine):
                counted.append(r.created)
                uploading += 1
        elif r.status in ("queued", "scoring", "done") or (r.status == "withdrawn" and r.state not in
                                                            (None, "cancelled")):
            counted.append(r.created)
    return sorted(counted), uploading


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t))


utc = _utc


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
    if _unreleased(engine):  # (slots refused while the database had no room: given back now if it has)
        try:
            with engine.begin() as c:
                done = _drop_unreleased(c)
            _unreleased(engine).difference_update(done)  # (once committed)
        except OperationalError:
            pass
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


def _drop_unreleased(c) -> list[int]:
    ids = sorted(_unreleased(c.engine))
    if ids:
        c.execute(delete(submissions).where(and_(submissions.c.id.in_(ids), submissions.c.status == "receiving")))
    return ids


def release(engine: Engine, slot: Slot) -> None:
    """Give back a slot whose upload was refused (or cut); a slot already taken stays. Where the
    database has no room even for that (a full disk), the slot is remembered: this process counts
    it no more, and the next :func:`reserve` that finds room deletes it (else a refusal the server
    caused would hold one of the user's slots for :data:`RESERVE_S`)."""
    if slot.taken:
        return
    _unreleased(engine).add(slot.id)
    with engine.begin() as c:
        done = _drop_unreleased(c)
    _unreleased(engine).difference_update(done)


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
            try:
                store.keep(got, name)  # (inside: a rename whose sync found no room leaves no file behind)
                with engine.begin() as c:
                    r = c.execute(update(submissions).where(and_(submissions.c.id == slot.id,
                                                                 submissions.c.status == "receiving")).values(
                        method=fields.method.strip(), split=fields.split, part=fields.part,
                        description=fields.description, authors=fields.authors, hardware=fields.hardware,
                        time_per_image=fields.time_per_image, training_data=fields.training_data,
                        paper=fields.paper, code=fields.code, public=fields.public,
                        filename=(filename or "results.csv")[-255:], stored=name,
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
    try:  # (committed: the answer is that it is queued even if the database cannot be read now)
        out = get(engine, slot.uid, user)
        out["quota"] = quota(engine, user, daily_limit)
    except Exception as e:  # noqa: BLE001
        print(f"server: submission {slot.uid} queued; its status could not be read: {type(e).__name__}: {e}",
              file=sys.stderr)
        out = {"uid": slot.uid, "status": "queued", "method": fields.method.strip(), "split": fields.split,
               "part": fields.part}
    out["warnings"] = list(res.warnings)
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


def held_parts(engine: Engine) -> dict[str, dict]:
    """{split: {"revealed", "n_images", "by", "fraction", "digest"}} of the protocols with a held-back part."""
    with engine.begin() as c:
        rows = c.execute(select(held_back.c.split, held_back.c.revealed, held_back.c.n_images, held_back.c.by,
                                held_back.c.fraction, held_back.c.digest)).all()
    return {r.split: {"revealed": r.revealed, "n_images": r.n_images, "by": r.by, "fraction": r.fraction,
                      "digest": r.digest} for r in rows}


def queue_info(c, job_id: int, state: str, started: float | None, now: float | None = None) -> dict:
    """Where a job stands: {"position" (1: next to be claimed; 0: being scored), "ahead" (queued jobs
    before it), "workers" (scoring now or within the last 10 minutes, at least 1), "typical_s" (the
    median scoring time of the last 20 scored jobs; None before any), "eta_s" (seconds until its
    result, None when unknown), "based_on" (how many scorings the median is of)}. With ``w`` workers
    a queued job is done after ceil((ahead + 1) / w) typical scorings; one being scored after the
    typical time less what it has had."""
    now = time.time() if now is None else now
    ahead = c.execute(select(func.count()).select_from(jobs).where(and_(jobs.c.state == "queued",
                                                                         jobs.c.id < job_id))).scalar_one() \
        if state == "queued" else 0
    recent = c.execute(select(jobs.c.started, jobs.c.finished).where(and_(
        jobs.c.state == "done", jobs.c.started.is_not(None), jobs.c.finished.is_not(None)))
        .order_by(jobs.c.finished.desc()).limit(20)).all()
    durations = sorted(max(0.0, r.finished - r.started) for r in recent)
    typical = None
    if durations:
        m = len(durations) // 2
        typical = durations[m] if len(durations) % 2 else (durations[m - 1] + durations[m]) / 2
    busy = c.execute(select(jobs.c.worker).where(or_(and_(jobs.c.state == "running", jobs.c.lease_until > now),
                                                     jobs.c.finished > now - 600)).distinct()).all()
    workers = max(1, len({r.worker for r in busy if r.worker}))
    eta = None
    if typical is not None:
        if state == "queued":
            eta = typical * math.ceil((ahead + 1) / workers)
        elif started is not None:
            eta = max(0.0, typical - (now - started))
    return {"position": ahead + 1 if state == "queued" else 0, "ahead": ahead, "workers": workers,
            "typical_s": None if typical is None else round(typical, 1), "eta_s": None if eta is None else round(eta),
            "based_on": len(durations)}


def _row_dict(r, owner: bool, key: bytes, held: dict | None = None, current: dict | None = None) -> dict:
    d = {k: r._mapping[k] for k in ("uid", "method", "split", "part", "description", "authors", "hardware",
                                    "time_per_image", "training_data", "paper", "code", "public", "status",
                                    "created", "scored")}
    d["user"] = r.user
    if owner:
        d.update(filename=r.filename, n_rows=r.n_rows, size=r.size, sha256=r.sha256, error=r.error,
                 stage=r.stage, attempts=r.attempts)
    stored = json.loads(r.result) if r.result and r.status == "done" else None
    # the one point where a result leaves the server: what the disclosure rule lets it show
    d["result"] = disclose(stored, r.part, key, r.uid, (held or {}).get(r.split) if r.part == "test" else None)
    cur = (current or {}).get(r.split)
    d["version"] = None if stored is None else {
        "scorer": r.scorer_version, "dataset": r.dataset_version,
        "current": None if cur is None else (r.scorer_version, r.dataset_version) == (cur["scorer"], cur["dataset"])}
    d["rescoring"] = r.status == "done" and r.job_state in ("queued", "running")
    return d


def _query():
    return (select(submissions, users.c.name.label("user"), jobs.c.stage, jobs.c.attempts,
                   jobs.c.state.label("job_state"), jobs.c.id.label("job_id"), jobs.c.started.label("job_started"))
            .select_from(submissions.join(users, users.c.id == submissions.c.user_id)
                         .join(jobs, jobs.c.submission_id == submissions.c.id)))


def _with_queue(c, r, d: dict) -> dict:
    if r.job_state in ("queued", "running"):
        d["queue"] = queue_info(c, r.job_id, r.job_state, r.job_started)
    return d


def get(engine: Engine, uid: str, viewer: dict | None, current: dict | None = None) -> dict:
    """One submission as ``viewer`` may see it: its owner always, others only a public one not
    withdrawn. 404 otherwise (whether it exists is not said). One queued or being scored has
    ``queue`` (:func:`queue_info`); ``current`` ({split: versions}) says whether its score is on them."""
    held, key = held_parts(engine), server_key(engine)  # (before the transaction: SQLite has one writer)
    with engine.begin() as c:
        r = c.execute(_query().where(submissions.c.uid == str(uid)[:32])).first()
        owner = r is not None and viewer is not None and r.user_id == viewer["id"]
        if r is None or not (owner or (r.public and r.status != "withdrawn")):
            raise Refused(404, "no such submission")
        return _with_queue(c, r, _row_dict(r, owner, key, held, current))


def mine(engine: Engine, user: dict, current: dict | None = None) -> list[dict]:
    key = server_key(engine)
    held = held_parts(engine)
    with engine.begin() as c:
        rows = c.execute(_query().where(submissions.c.user_id == user["id"]).order_by(submissions.c.id.desc()))
        return [_with_queue(c, r, _row_dict(r, True, key, held, current)) for r in rows]


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


def leaderboard(engine: Engine, split: str, metric: str = "add_s", phase: str = "test",
                current: dict | None = None) -> list[dict]:
    """The public, scored submissions of one phase of a protocol, best first by the mean over objects
    of ``metric`` as the disclosure rule shows it. ``phase``: test (the test part; where the protocol
    has a held-back part, its public part), val (the validation part: public labels, full
    precision) or final (the held-back part: 403 until the operator reveals it). Equal shown scores
    keep the order they were submitted in, so a rank tells nothing finer than a score."""
    if metric not in LEADERBOARD_METRICS:
        raise Refused(400, f"metric must be one of {', '.join(LEADERBOARD_METRICS)}")
    if phase not in PHASES:
        raise Refused(400, f"phase must be one of {', '.join(PHASES)}")
    held = held_parts(engine)
    if phase == "final" and not (held.get(split) or {}).get("revealed"):
        raise Refused(403, (f"the final leaderboard of {split} is shown once the server's operators reveal its "
                            "held-back part") if split in held else f"{split} has no held-back part: no final "
                                                                    "leaderboard")
    key = server_key(engine)
    with engine.begin() as c:
        rows = c.execute(_query().where(and_(submissions.c.split == split,
                                             submissions.c.part == ("val" if phase == "val" else "test"),
                                             submissions.c.public.is_(True),
                                             submissions.c.status == "done")))
        out = [_row_dict(r, False, key, held, current) for r in rows]
    for d in out:
        res = d["result"] or {}
        sm = (res.get("private") or {}).get("summary", {}) if phase == "final" else res.get("summary", {})
        mean = sm.get("mean") or {}
        d["score"] = mean.get(metric)
        d["score_step"] = mean.get("step")
        d["score_withheld"] = mean.get("withheld") or sm.get("withheld")
    out.sort(key=lambda d: (d["score"] is None, -(d["score"] or 0.0), d["created"]))
    for i, d in enumerate(out):
        d["rank"] = i + 1
    return out


CSV_COLUMNS = ("rank", "method", "score", "score_step", "score_withheld", "authors", "paper", "code", "hardware",
               "time_per_image", "training_data", "description", "user", "uid", "submitted_utc", "scorer_version",
               "dataset_version")


def _csv_cell(v) -> str:
    """A cell a spreadsheet will not run: text starting with = + - @ (or a tab, a CR) gets a quote."""
    text = "" if v is None else str(v)
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def leaderboard_csv(rows: list[dict], metric: str, phase: str) -> str:
    """The leaderboard as CSV: one row per submission, ``score`` in % as shown (its step beside it)."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"score ({metric}, %, {phase})" if c == "score" else c for c in CSV_COLUMNS])
    for d in rows:
        v = d.get("version") or {}
        vals = {**d, "score": None if d["score"] is None else round(100 * d["score"], 6),
                "score_step": None if d["score_step"] is None else round(100 * d["score_step"], 6),
                "submitted_utc": _utc(d["created"]), "scorer_version": v.get("scorer"),
                "dataset_version": v.get("dataset")}
        w.writerow([_csv_cell(vals.get(c)) for c in CSV_COLUMNS])
    return buf.getvalue()


__all__ = ["CSV_COLUMNS", "Fields", "LEADERBOARD_METRICS", "PHASES", "Slot", "accept", "get", "held_parts",
           "leaderboard", "leaderboard_csv", "mine", "queue_info", "quota", "release", "reserve", "sweep_reservations",
           "withdraw"]
