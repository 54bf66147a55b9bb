"""The server on PostgreSQL: a real server from Debian's packages (initdb + pg_ctl in a temp
folder, a Unix socket only; skipped where PostgreSQL is not installed), the whole flow, and the
SKIP LOCKED claim under concurrent workers."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import select

from tdof20.server.db import claim_job, submissions
from tdof20.server.worker import run_worker
from tests.test_server_support import Server, dataset, free_port, results_csv  # noqa: F401

BINS = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))


def _as_postgres(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


@pytest.fixture(scope="module")
def pg_url():
    if not BINS:
        pytest.skip("PostgreSQL is not installed (Debian: apt-get install postgresql)")
    bin_dir = Path(BINS[-1]).parent
    base = Path(tempfile.mkdtemp(prefix="tdof20-pg-"))
    if os.geteuid() == 0:
        shutil.chown(base, "postgres")
    port = free_port()
    run = lambda *c: subprocess.run(_as_postgres(list(c)), check=True, capture_output=True, timeout=120)  # noqa: E731
    try:
        run(str(bin_dir / "initdb"), "-D", str(base / "db"), "-A", "trust", "-U", "bench")
        run(str(bin_dir / "pg_ctl"), "-D", str(base / "db"), "-w", "-l", str(base / "log"), "-o",
            f"-p {port} -k {base} -c listen_addresses=''", "start")
        try:
            run(str(bin_dir / "createdb"), "-h", str(base), "-p", str(port), "-U", "bench", "bench")
            yield f"postgresql://bench@/bench?host={base}&port={port}"
        finally:
            run(str(bin_dir / "pg_ctl"), "-D", str(base / "db"), "-m", "immediate", "stop")
    finally:
        shutil.rmtree(base, ignore_errors=True)


def test_submit_and_score_on_postgresql(dataset, tmp_path, pg_url):
    _, gt = dataset
    s = Server(dataset[0], tmp_path / "data", db=pg_url)
    evil = "x'); DROP TABLE jobs; --"
    uids = [s.submit("alice", results_csv(gt, "hard"), method=evil, public=True).json()["uid"] for _ in range(4)]
    assert s.submit("bob", b"nope\n").status_code == 400
    # four workers claim at once: SKIP LOCKED hands each a different job
    claims, barrier = [], threading.Barrier(4)

    def claim():
        barrier.wait(10)
        claims.append(claim_job(s.engine, threading.current_thread().name, lease_s=0.5))

    threads = [threading.Thread(target=claim) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len({c.job_id for c in claims if c}) == 4
    time.sleep(0.6)  # the leases expire; a worker takes the jobs again and scores each once
    assert run_worker(s.cfg, once=True) == 4
    with s.engine.begin() as c:
        rows = c.execute(select(submissions.c.uid, submissions.c.status, submissions.c.scored_count,
                                submissions.c.method)).all()
    assert sorted(r.uid for r in rows) == sorted(uids)
    assert all(r.status == "done" and r.scored_count == 1 and r.method == evil for r in rows)
    board = s.client.get("/api/leaderboard", params={"split": "hard"}).json()
    assert len(board) == 4 and board[0]["score"] is None and board[0]["score_withheld"]  # 9 targets: withheld
