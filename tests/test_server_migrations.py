"""Schema migrations: a database written by the first server (schema version 1, made here by hand
with that server's SQL, not with the new code) is upgraded in place when the server starts — on
SQLite and on PostgreSQL — its rows kept, its queued job scored, its schema then equal to a new
database's; processes starting at once upgrade it once; a newer database is refused."""

from __future__ import annotations

import json

import threading

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from argon2 import PasswordHasher
from fastapi.testclient import TestClient
from sqlalchemy import select, text

from tdof20.errors import TdofError
from tdof20.server import auth
from tdof20.server.app import create_app
from tdof20.server.config import ServerConfig
from tdof20.server.db import init_db, jobs, make_engine, meta, metadata, submissions
from tdof20.server.worker import run_worker
from tests.test_server_postgres import pg_url  # noqa: F401
from tests.test_server_support import dataset, results_csv  # noqa: F401

# the first server's tables, as SQLAlchemy's create_all wrote them ({serial}: SQLite's INTEGER,
# PostgreSQL's SERIAL)
V1_SQL = """
CREATE TABLE meta (key VARCHAR(64) NOT NULL, value TEXT NOT NULL, PRIMARY KEY (key));
CREATE TABLE users (id {serial} NOT NULL, name VARCHAR(64) NOT NULL, token_id VARCHAR(32) NOT NULL,
  token_hash VARCHAR(255) NOT NULL, revoked BOOLEAN NOT NULL, created FLOAT NOT NULL, PRIMARY KEY (id),
  UNIQUE (name), UNIQUE (token_id));
CREATE TABLE sessions (id VARCHAR(64) NOT NULL, user_id INTEGER NOT NULL, csrf VARCHAR(64) NOT NULL,
  expires FLOAT NOT NULL, PRIMARY KEY (id), FOREIGN KEY(user_id) REFERENCES users (id));
CREATE TABLE submissions (id {serial} NOT NULL, uid VARCHAR(32) NOT NULL, user_id INTEGER NOT NULL,
  method VARCHAR(100) NOT NULL, split VARCHAR(32) NOT NULL, description TEXT NOT NULL, authors TEXT NOT NULL,
  hardware TEXT NOT NULL, time_per_image TEXT NOT NULL, training_data TEXT NOT NULL, public BOOLEAN NOT NULL,
  filename VARCHAR(255) NOT NULL, stored VARCHAR(64) NOT NULL, size INTEGER NOT NULL, sha256 VARCHAR(64) NOT NULL,
  n_rows INTEGER NOT NULL, status VARCHAR(16) NOT NULL, created FLOAT NOT NULL, scored FLOAT,
  scored_count INTEGER NOT NULL, error TEXT, result TEXT, PRIMARY KEY (id), UNIQUE (uid),
  FOREIGN KEY(user_id) REFERENCES users (id));
CREATE INDEX ix_submissions_user_id ON submissions (user_id);
CREATE INDEX ix_submissions_created ON submissions (created);
CREATE TABLE jobs (id {serial} NOT NULL, submission_id INTEGER NOT NULL, state VARCHAR(16) NOT NULL,
  claim VARCHAR(32), worker VARCHAR(128), lease_until FLOAT, attempts INTEGER NOT NULL, stage VARCHAR(64) NOT NULL,
  started FLOAT, finished FLOAT, PRIMARY KEY (id), UNIQUE (submission_id),
  FOREIGN KEY(submission_id) REFERENCES submissions (id));
CREATE INDEX ix_jobs_state ON jobs (state);
INSERT INTO meta (key, value) VALUES ('schema_version', '1');
"""
TOKEN_ID, SECRET = "0123456789abcdef", "s" * 43
OLD_RESULT = '{"summary": {"mean": {"n": 3, "add_s": 0.75}}, "plots": []}'


def write_v1(url: str, data, csv: bytes) -> None:
    """A v1 database with user alice, a scored public submission and a queued one (its file stored)."""
    engine = make_engine(url)
    serial = "SERIAL" if engine.dialect.name == "postgresql" else "INTEGER"
    raw = engine.raw_connection()  # the DBAPI's own connection: the SQL as written
    try:
        cur = raw.cursor()
        for stmt in V1_SQL.format(serial=serial).split(";"):
            if stmt.strip():
                cur.execute(stmt)
        raw.commit()
    finally:
        raw.close()
    (data / "submissions").mkdir(parents=True, exist_ok=True)
    (data / "submissions" / "bbbbbbbbbbbbbbbb.csv").write_bytes(csv)
    row = ("INSERT INTO submissions (uid, user_id, method, split, description, authors, hardware, time_per_image, "
           "training_data, public, filename, stored, size, sha256, n_rows, status, created, scored, scored_count, "
           "result) VALUES (:uid, 1, :m, 'hard', 'old', 'A. Lice', '', '', '', :pub, 'r.csv', :stored, :size, "
           "'0', 3, :status, 1.0, :scored, :n, :result)")
    with engine.begin() as c:
        c.execute(text("INSERT INTO users (name, token_id, token_hash, revoked, created) "
                       "VALUES ('alice', :tid, :h, :rev, 1.0)"),
                  {"tid": TOKEN_ID, "h": PasswordHasher().hash(SECRET), "rev": False})
        c.execute(text(row), {"uid": "aaaaaaaaaaaaaaaa", "m": "old-scored", "pub": True,
                              "stored": "aaaaaaaaaaaaaaaa.csv",
                              "size": 1, "status": "done", "scored": 2.0, "n": 1, "result": OLD_RESULT})
        c.execute(text(row), {"uid": "bbbbbbbbbbbbbbbb", "m": "old-queued", "pub": True,
                              "stored": "bbbbbbbbbbbbbbbb.csv", "size": len(csv), "status": "queued", "scored": None,
                              "n": 0, "result": None})
        c.execute(text("INSERT INTO jobs (submission_id, state, attempts, stage) VALUES (1, 'done', 1, 'finished'), "
                       "(2, 'queued', 0, 'queued')"))
    engine.dispose()


def check_upgraded(url: str, root, data) -> None:
    engine = make_engine(url)
    with engine.connect() as c:
        assert MigrationContext.configure(c).get_current_revision() is None  # (v1: no alembic table)
    cfg = ServerConfig(dataset=root, data=data, db=url)
    client = TestClient(create_app(cfg))  # the server starts: the database is upgraded in place
    with engine.connect() as c:
        assert MigrationContext.configure(c).get_current_revision() == "0003"
        assert compare_metadata(MigrationContext.configure(c), metadata) == []  # = a new database's schema
        assert c.execute(select(meta.c.value).where(meta.c.key == "schema_version")).scalar_one() == "3"
        rows = c.execute(select(submissions.c.uid, submissions.c.part, submissions.c.status)
                         .order_by(submissions.c.id)).all()
    assert [tuple(r) for r in rows] == [("aaaaaaaaaaaaaaaa", "test", "done"), ("bbbbbbbbbbbbbbbb", "test", "queued")]
    token = f"tdof20_{TOKEN_ID}_{SECRET}"
    assert auth.authenticate(engine, token)["name"] == "alice"  # the old token still works
    assert run_worker(cfg, once=True) == 1  # the queued job of the old schema is scored once
    board = client.get("/api/leaderboard", params={"split": "hard"}).json()
    # both on the board, scores withheld (3 targets: docs/server.md's disclosure rule), in the order submitted
    assert [(b["method"], b["score"], bool(b["score_withheld"])) for b in board] == \
        [("old-scored", None, True), ("old-queued", None, True)]
    with engine.begin() as c:  # the results themselves, the old one as it was stored and the new one
        stored = dict(c.execute(select(submissions.c.method, submissions.c.result)).all())
    assert json.loads(stored["old-scored"])["summary"]["mean"]["add_s"] == 0.75
    assert json.loads(stored["old-queued"])["summary"]["mean"]["add_s"] == 1.0
    with engine.begin() as c:
        assert {r.state for r in c.execute(select(jobs.c.state))} == {"done"}
        assert [r.scored_count for r in c.execute(select(submissions.c.scored_count))] == [1, 1]
    init_db(engine)  # at head: nothing to do
    engine.dispose()


def test_a_version_1_sqlite_database_is_upgraded_in_place(dataset, tmp_path):
    root, gt = dataset
    data = tmp_path / "data"
    data.mkdir()
    url = f"sqlite:///{data / 'server.db'}"
    write_v1(url, data, results_csv(gt, "hard"))
    check_upgraded(url, root, data)


def test_a_version_1_postgresql_database_is_upgraded_in_place(dataset, tmp_path, pg_url):  # noqa: F811
    root, gt = dataset
    write_v1(pg_url, tmp_path / "data", results_csv(gt, "hard"))
    check_upgraded(pg_url, root, tmp_path / "data")


def test_processes_starting_together_upgrade_once(dataset, tmp_path):
    _, gt = dataset
    data = tmp_path / "data"
    data.mkdir()
    url = f"sqlite:///{data / 'server.db'}"
    write_v1(url, data, results_csv(gt, "hard"))
    errors, barrier = [], threading.Barrier(4)

    def start():
        engine = make_engine(url)
        barrier.wait(10)
        try:
            init_db(engine)
        except Exception as e:  # noqa: BLE001 (collected for the assertion)
            errors.append(e)
        engine.dispose()

    threads = [threading.Thread(target=start) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == []
    engine = make_engine(url)
    with engine.connect() as c:
        assert c.execute(text("SELECT count(*) FROM alembic_version")).scalar_one() == 1
        assert c.execute(text("SELECT version_num FROM alembic_version")).scalar_one() == "0003"
    engine.dispose()


def test_a_newer_or_foreign_database_is_refused(tmp_path):
    url = f"sqlite:///{tmp_path / 'a.db'}"
    engine = make_engine(url)
    init_db(engine)
    with engine.begin() as c:
        c.execute(meta.update().where(meta.c.key == "schema_version").values(value="4"))
    with pytest.raises(TdofError, match="schema version 4, newer than this tdof20's 3: upgrade tdof20"):
        init_db(engine)
    with engine.begin() as c:
        c.execute(meta.update().where(meta.c.key == "schema_version").values(value="3"))
        c.execute(text("UPDATE alembic_version SET version_num = '0099'"))
    with pytest.raises(TdofError, match=r"schema \(0099\) is unknown to this tdof20"):
        init_db(engine)
    engine.dispose()
    other = make_engine(f"sqlite:///{tmp_path / 'b.db'}")
    with other.begin() as c:
        c.execute(text("CREATE TABLE orders (id INTEGER)"))
    with pytest.raises(TdofError, match=r"tables \(orders\) but no schema version: not a tdof20 server database"):
        init_db(other)
    other.dispose()
