"""The server's state: SQLAlchemy Core tables in an embedded SQLite file (the default) or in
PostgreSQL (``--db postgresql://...``), and the job queue's atomic claim with an expiring lease.

Tables: ``users`` (name, token id, argon2 hash of the token's secret, revoked), ``sessions``
(page sign-ins: sha256 of the cookie, CSRF token, expiry), ``submissions`` (owner, method and its
description and links, protocol, stored file, status, result JSON and the scorer and dataset
versions it was computed with), ``held_back`` (per protocol: the test images of the final private
leaderboard, how they were chosen, when revealed) and ``jobs`` (one per submission: state
queued | running | done | failed | cancelled, the current claim, its lease, attempts, stage).
``meta`` records the schema version (for a tdof20 older than alembic's table, which refuses a
newer one); alembic's ``alembic_version`` the revision.

Migrations (alembic, :mod:`tdof20.server.migrations`): every start (server, worker, ``serve user``)
upgrades the database in place to this tdof20's schema, inside one transaction that holds SQLite's
writer lock or a PostgreSQL advisory lock, so processes that start together upgrade it once and a
failed upgrade leaves the old schema whole. A database of the first server (tables and ``meta``
but no ``alembic_version``) is schema 1 = revision 0001. A database newer than this tdof20 is refused.

Claiming is atomic: PostgreSQL ``SELECT ... FOR UPDATE SKIP LOCKED``; SQLite takes its single
writer lock for every transaction (``BEGIN IMMEDIATE``). A claim carries a random token and a lease;
a worker extends the lease while it scores, and its result is recorded only while its claim is
still the job's (:func:`finish_job`), so a job whose worker died is claimed again after the lease
and each submission gets exactly one result.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config as AlembicConfig
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from alembic.util import CommandError
from sqlalchemy import (Boolean, Column, Engine, Float, ForeignKey, Index, Integer, MetaData, String, Table, Text,
                        and_, create_engine, event, func, insert, inspect, or_, select, text, update)

from tdof20.errors import TdofError

SCHEMA_VERSION = 3
MIGRATIONS = Path(__file__).with_name("migrations")
PG_LOCK = 2024_0024  # the advisory lock key that serialises upgrades on PostgreSQL
MAX_ATTEMPTS = 3  # a job whose lease expired this many times fails

metadata = MetaData()
meta = Table("meta", metadata, Column("key", String(64), primary_key=True), Column("value", Text, nullable=False))
users = Table(
    "users", metadata,
    Column("id", Integer, primary_key=True),
    Column("name", String(64), unique=True, nullable=False),
    Column("token_id", String(32), unique=True, nullable=False),
    Column("token_hash", String(255), nullable=False),
    Column("revoked", Boolean, nullable=False, default=False),
    Column("created", Float, nullable=False))
sessions = Table(
    "sessions", metadata,
    Column("id", String(64), primary_key=True),  # sha256 of the cookie value
    Column("user_id", Integer, ForeignKey("users.id"), nullable=False),
    Column("csrf", String(64), nullable=False),
    Column("expires", Float, nullable=False))
submissions = Table(
    "submissions", metadata,
    Column("id", Integer, primary_key=True),
    Column("uid", String(32), unique=True, nullable=False),  # the public id (random)
    Column("user_id", Integer, ForeignKey("users.id"), nullable=False, index=True),
    Column("method", String(100), nullable=False),
    Column("split", String(32), nullable=False),
    Column("part", String(8), nullable=False, server_default="test"),  # test | val (per-image detail)
    Column("description", Text, nullable=False, default=""),
    Column("authors", Text, nullable=False, default=""),
    Column("hardware", Text, nullable=False, default=""),
    Column("time_per_image", Text, nullable=False, default=""),
    Column("training_data", Text, nullable=False, default=""),
    Column("paper", Text, nullable=False, default="", server_default=""),  # a link (http/https) or ""
    Column("code", Text, nullable=False, default="", server_default=""),
    Column("public", Boolean, nullable=False, default=False),
    Column("filename", String(255), nullable=False),  # as uploaded: shown, never a path
    Column("stored", String(64), nullable=False),  # the file's name in the store
    Column("size", Integer, nullable=False),
    Column("sha256", String(64), nullable=False),
    Column("n_rows", Integer, nullable=False),
    Column("status", String(16), nullable=False),  # queued | scoring | done | failed | withdrawn
    Column("created", Float, nullable=False, index=True),
    Column("scored", Float),
    Column("scored_count", Integer, nullable=False, default=0),
    Column("error", Text),  # shown to the owner (no label in it)
    Column("result", Text),  # the summary JSON, warnings, object and scene names
    Column("scorer_version", String(64)),  # what the result was computed with (None: before versions)
    Column("dataset_version", String(64)))
held_back = Table(
    "held_back", metadata,  # per protocol: the test images of the final (private) leaderboard
    Column("split", String(32), primary_key=True),
    Column("by", String(8), nullable=False),  # image | scene
    Column("fraction", Float, nullable=False),
    Column("seed", String(64), nullable=False),  # secret: which images are held back is not shown
    Column("images", Text, nullable=False),  # JSON [[scene_id, im_id], ...]
    Column("n_images", Integer, nullable=False),
    Column("digest", String(64), nullable=False),  # sha256 of the image list (part of the dataset version)
    Column("created", Float, nullable=False),
    Column("revealed", Float))  # when the operator revealed the final leaderboard (None: not yet)
jobs = Table(
    "jobs", metadata,
    Column("id", Integer, primary_key=True),
    Column("submission_id", Integer, ForeignKey("submissions.id"), unique=True, nullable=False),
    Column("state", String(16), nullable=False, index=True),
    Column("claim", String(32)),
    Column("worker", String(128)),
    Column("lease_until", Float),
    Column("attempts", Integer, nullable=False, default=0),
    Column("stage", String(64), nullable=False, default="queued"),
    Column("started", Float),
    Column("finished", Float),
    Index("ix_jobs_state_id", "state", "id"))


def make_engine(url: str) -> Engine:
    """An engine for ``url`` (sqlite:///PATH or postgresql://...). SQLite: WAL, synchronous=FULL
    (a commit is on disk before it returns), a 30 s busy timeout and BEGIN IMMEDIATE (one writer)."""
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url[len("postgresql://"):]
    if url.startswith("sqlite"):
        _private(url)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _connect(dbapi_conn, _record):
            dbapi_conn.isolation_level = None  # SQLAlchemy's begin event issues BEGIN
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=FULL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        @event.listens_for(engine, "begin")
        def _begin(conn):
            conn.exec_driver_sql("BEGIN IMMEDIATE")

        return engine
    if url.startswith("postgresql+psycopg://"):
        return create_engine(url, pool_pre_ping=True)
    raise TdofError(f"--db must be sqlite:///PATH or postgresql://..., got {url.split(':', 1)[0]}:...")


def _private(url: str) -> None:
    """The SQLite file (token hashes, sessions, scores) readable by its owner only: created 0600,
    an older one's mode narrowed to it (SQLite gives its -wal and -shm files the file's mode)."""
    path = url.split("sqlite:///", 1)[1].split("?", 1)[0] if url.startswith("sqlite:///") else ""
    if not path or path == ":memory:" or not Path(path).parent.is_dir():
        return
    try:
        os.close(os.open(path, os.O_CREAT | os.O_RDWR, 0o600))
        for p in (path, path + "-wal", path + "-shm"):
            if os.path.exists(p) and os.stat(p).st_mode & 0o077:
                os.chmod(p, 0o600)
    except OSError:  # (a read-only place, another owner's file: SQLite says why when it opens it)
        pass


def _alembic() -> AlembicConfig:
    cfg = AlembicConfig()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    return cfg


def init_db(engine: Engine) -> None:
    """Bring the database to this tdof20's schema: create it where empty, upgrade it in place
    where older (one transaction; see the module docstring); refuse one that is newer."""
    cfg = _alembic()
    head = ScriptDirectory.from_config(cfg).get_current_head()
    with engine.begin() as c:
        if c.dialect.name == "postgresql":
            c.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": PG_LOCK})
        tables = set(inspect(c).get_table_names())
        version = None
        if "meta" in tables:
            row = c.execute(select(meta.c.value).where(meta.c.key == "schema_version")).first()
            version = None if row is None else int(row.value)
        if version is not None and version > SCHEMA_VERSION:
            raise TdofError(f"the database has schema version {version}, newer than this tdof20's "
                            f"{SCHEMA_VERSION}: upgrade tdof20")
        current = MigrationContext.configure(c).get_current_revision()
        if current == head:
            return
        cfg.attributes["connection"] = c
        try:
            if current is None and version == 1:
                command.stamp(cfg, "0001")  # the first server's schema (made before migrations)
            elif current is None and tables - {"alembic_version"}:
                raise TdofError(f"the database holds tables ({', '.join(sorted(tables)[:5])}) but no schema "
                                "version: not a tdof20 server database")
            command.upgrade(cfg, "head")
        except CommandError as e:  # a revision this tdof20 does not know: a newer one
            raise TdofError(f"the database's schema ({current}) is unknown to this tdof20 (newest {head}): "
                            f"upgrade tdof20 ({e})") from None


@dataclass
class Claim:
    """A claimed job: its ids and the claim token that must still be the job's to record a result."""

    job_id: int
    submission_id: int
    claim: str


def claim_job(engine: Engine, worker: str, lease_s: float) -> Claim | None:
    """Claim the oldest queued job, or a running one whose lease expired; None when there is none.
    A job whose lease expired :data:`MAX_ATTEMPTS` times fails instead of being claimed again."""
    while True:
        with engine.begin() as c:
            now = time.time()
            q = (select(jobs.c.id, jobs.c.submission_id, jobs.c.attempts, jobs.c.state)
                 .where(or_(jobs.c.state == "queued", and_(jobs.c.state == "running", jobs.c.lease_until < now)))
                 .order_by(jobs.c.id).limit(1))
            if c.dialect.name == "postgresql":
                q = q.with_for_update(skip_locked=True)
            row = c.execute(q).first()
            if row is None:
                return None
            if row.state == "running" and row.attempts >= MAX_ATTEMPTS:
                c.execute(update(jobs).where(jobs.c.id == row.id).values(state="failed", finished=now, claim=None))
                c.execute(update(submissions).where(submissions.c.id == row.submission_id).values(
                    status="failed", error=f"scoring did not finish in {MAX_ATTEMPTS} tries"))
                continue
            token = secrets.token_hex(16)
            c.execute(update(jobs).where(jobs.c.id == row.id).values(
                state="running", claim=token, worker=worker[:128], lease_until=now + lease_s,
                attempts=row.attempts + 1, stage="claimed", started=now))
            c.execute(update(submissions).where(and_(submissions.c.id == row.submission_id,
                                                     submissions.c.status != "done")).values(status="scoring"))
            return Claim(row.id, row.submission_id, token)


def heartbeat(engine: Engine, claim: Claim, lease_s: float, stage: str | None = None) -> bool:
    """Extend the lease (and set the stage); False when the claim is no longer the job's."""
    values: dict[str, Any] = {"lease_until": time.time() + lease_s}
    if stage is not None:
        values["stage"] = stage
    with engine.begin() as c:
        r = c.execute(update(jobs).where(and_(jobs.c.id == claim.job_id, jobs.c.claim == claim.claim,
                                              jobs.c.state == "running")).values(**values))
        return r.rowcount == 1


def finish_job(engine: Engine, claim: Claim, result: dict | None, error: str | None,
               versions: dict | None = None) -> bool:
    """Record the result (or the error) if the claim is still the job's, in one transaction, with
    the scorer and dataset ``versions`` it was computed with; returns whether it was recorded
    (False: the lease was lost and another worker has the job)."""
    now = time.time()
    with engine.begin() as c:
        r = c.execute(update(jobs).where(and_(jobs.c.id == claim.job_id, jobs.c.claim == claim.claim,
                                              jobs.c.state == "running"))
                      .values(state="done" if error is None else "failed", finished=now, stage="finished"))
        if r.rowcount != 1:
            return False
        c.execute(update(submissions).where(and_(submissions.c.id == claim.submission_id,
                                                 submissions.c.status != "withdrawn")).values(
            status="done" if error is None else "failed", scored=now, error=error,
            result=None if result is None else json.dumps(result),
            scorer_version=(versions or {}).get("scorer"), dataset_version=(versions or {}).get("dataset"),
            scored_count=submissions.c.scored_count + 1))
        return True


def release_job(engine: Engine, claim: Claim) -> bool:
    """Give a claimed job back to the queue, not counted as a try (its worker met a full disk or a
    database error: the server's trouble, not the submission's); False when the claim was no
    longer the job's (its lease had expired: that try counts, as any expired lease does)."""
    with engine.begin() as c:
        r = c.execute(update(jobs).where(and_(jobs.c.id == claim.job_id, jobs.c.claim == claim.claim,
                                              jobs.c.state == "running")).values(
            state="queued", claim=None, worker=None, lease_until=None, stage="queued",
            attempts=jobs.c.attempts - 1))
        if r.rowcount != 1:
            return False
        c.execute(update(submissions).where(and_(submissions.c.id == claim.submission_id,
                                                 submissions.c.status == "scoring")).values(status="queued"))
        return True


def requeue(engine: Engine, uid: str | None = None, failed: bool = False) -> list[str]:
    """Queue again the failed submission ``uid`` (or, ``failed``, every failed one) with its tries
    reset: the operator's way back for submissions that failed through the server's trouble.
    Returns their uids; a uid that is not a failed submission is a TdofError in one line."""
    with engine.begin() as c:
        q = (select(submissions.c.id, submissions.c.uid, submissions.c.status)
             .select_from(submissions.join(jobs, jobs.c.submission_id == submissions.c.id)))
        rows = c.execute(q.where(submissions.c.uid == uid) if uid is not None
                         else q.where(submissions.c.status == "failed")).all()
        if uid is not None and not rows:
            raise TdofError(f"no submission {uid[:40]}")
        if uid is not None and rows[0].status != "failed":
            raise TdofError(f"submission {uid} is {rows[0].status}, not failed: only a failed one is queued again "
                            "(each submission is scored once)")
        ids = [r.id for r in rows]
        if ids:
            c.execute(update(jobs).where(jobs.c.submission_id.in_(ids)).values(
                state="queued", claim=None, worker=None, lease_until=None, attempts=0, stage="queued", finished=None))
            c.execute(update(submissions).where(submissions.c.id.in_(ids)).values(status="queued", error=None,
                                                                                  result=None, scored=None))
        return [r.uid for r in rows]


def held_back_part(engine: Engine, split: str) -> dict | None:
    """The held-back part of ``split``'s test images: {"split", "by", "fraction", "images" ([[scene,
    im], ...]), "n_images", "digest", "created", "revealed"} (the seed stays in the table); None
    when the protocol has none."""
    with engine.begin() as c:
        r = c.execute(select(held_back).where(held_back.c.split == split)).first()
    if r is None:
        return None
    d = {k: r._mapping[k] for k in ("split", "by", "fraction", "n_images", "digest", "created", "revealed")}
    d["images"] = json.loads(r.images)
    return d


def hold_back(engine: Engine, split: str, frames: list[tuple[int, int]], fraction: float, by: str = "image",
              seed: str | None = None) -> dict:
    """Choose and record the held-back part of ``split``'s test images ``frames``: deterministic
    from a secret ``seed`` (made here when not given, kept in the table) — ``by`` image: within each
    scene, the ``round(fraction * n)`` images first in the order of sha256(seed, split, scene, im),
    so every scene is in both parts; ``by`` scene: the scenes first in the order of sha256(seed,
    split, scene), ``round(fraction * scenes)`` of them. Refused (one line) when the protocol has one."""
    import hashlib

    if not 0.0 < fraction < 1.0:
        raise TdofError(f"--fraction must be between 0 and 1 (exclusive), got {fraction:g}")
    if by not in ("image", "scene"):
        raise TdofError(f"--by must be image or scene, got {by[:20]!r}")
    seed = seed or secrets.token_hex(16)

    def rank(*parts) -> str:
        return hashlib.sha256(":".join(map(str, (seed, split) + parts)).encode()).hexdigest()

    per_scene: dict[int, list[int]] = {}
    for s, im in sorted(set((int(s), int(i)) for s, i in frames)):
        per_scene.setdefault(s, []).append(im)
    chosen: list[list[int]] = []
    if by == "image":
        for s, ims in per_scene.items():
            k = int(round(fraction * len(ims)))
            chosen += [[s, im] for im in sorted(sorted(ims, key=lambda im: rank(s, im))[:k])]
    else:
        k = int(round(fraction * len(per_scene)))
        for s in sorted(sorted(per_scene, key=lambda s: rank(s))[:k]):
            chosen += [[s, im] for im in per_scene[s]]
    if not chosen or len(chosen) == len(frames):
        raise TdofError(f"--fraction {fraction:g} by {by} holds back {len(chosen)} of {len(frames)} test images: "
                        "both parts must hold some")
    images = json.dumps(chosen, separators=(",", ":"))
    digest = hashlib.sha256(images.encode()).hexdigest()
    with engine.begin() as c:
        if c.execute(select(held_back.c.split).where(held_back.c.split == split)).first() is not None:
            raise TdofError(f"{split} has a held-back part already (chosen once: changing it would let the public "
                            "scores of two parts be subtracted)")
        c.execute(insert(held_back).values(split=split, by=by, fraction=float(fraction), seed=seed, images=images,
                                           n_images=len(chosen), digest=digest, created=time.time()))
    return held_back_part(engine, split)


def scored_before(engine: Engine, split: str) -> int:
    """How many of ``split``'s test submissions have a result recorded (scored or withdrawn after)."""
    with engine.begin() as c:
        return c.execute(select(func.count()).select_from(submissions).where(and_(
            submissions.c.split == split, submissions.c.part == "test",
            submissions.c.result.is_not(None)))).scalar_one()


def versions_behind(engine: Engine, current: dict[str, dict]) -> int:
    """How many scored submissions are on other versions than ``current`` ({split: {"scorer", "dataset"}})."""
    with engine.begin() as c:
        rows = c.execute(select(submissions.c.split, submissions.c.scorer_version, submissions.c.dataset_version)
                         .where(submissions.c.status == "done")).all()
    return sum(1 for r in rows if _behind(r, current))


def _behind(r, current: dict[str, dict]) -> bool:
    cur = current.get(r.split)
    return cur is None or (r.scorer_version, r.dataset_version) != (cur["scorer"], cur["dataset"])


def reveal(engine: Engine, split: str) -> dict:
    """Reveal ``split``'s final leaderboard (its held-back part's scores); refused without a part."""
    with engine.begin() as c:
        r = c.execute(update(held_back).where(held_back.c.split == split).values(
            revealed=func.coalesce(held_back.c.revealed, time.time())))
        if r.rowcount != 1:
            raise TdofError(f"{split} has no held-back part (tdof20 serve hold-back --split {split})")
    return held_back_part(engine, split)


def rescore(engine: Engine, current: dict[str, dict], everything: bool = False) -> list[str]:
    """Queue again every scored submission whose result is not on ``current`` ({split: {"scorer",
    "dataset"}}: the versions a result computed now would be on), or ``everything``; it keeps its
    shown result (status done) until the new one is recorded. Returns their uids."""
    with engine.begin() as c:
        rows = c.execute(select(submissions.c.id, submissions.c.uid, submissions.c.split, submissions.c.scorer_version,
                                submissions.c.dataset_version).where(submissions.c.status == "done")).all()
        old = [r for r in rows if everything or _behind(r, current)]
        ids = [r.id for r in old]
        if ids:
            c.execute(update(jobs).where(and_(jobs.c.submission_id.in_(ids), jobs.c.state == "done")).values(
                state="queued", claim=None, worker=None, lease_until=None, attempts=0, stage="rescoring",
                finished=None))
        return [r.uid for r in old]


def is_resource_error(e: BaseException) -> bool:
    """Whether ``e`` is the server's trouble, not the submission's: a write that found no room
    (ENOSPC, EDQUOT, EFBIG) or a database error (no room, locked, gone), at any depth of its causes."""
    from sqlalchemy.exc import DBAPIError, OperationalError

    seen = 0
    while e is not None and seen < 20:  # bounded: a cause chain
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO):
            return True
        if isinstance(e, (OperationalError, DBAPIError)):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


__all__ = ["Claim", "MAX_ATTEMPTS", "MIGRATIONS", "SCHEMA_VERSION", "claim_job", "finish_job", "heartbeat",
           "held_back_part", "hold_back", "init_db", "is_resource_error", "release_job", "requeue", "rescore", "reveal",
           "scored_before", "versions_behind",
           "held_back", "jobs",
           "make_engine", "meta", "metadata", "sessions", "submissions", "users"]
