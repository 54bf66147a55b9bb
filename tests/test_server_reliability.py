"""The server under failure, with real processes: the uvicorn server and a worker killed with
SIGKILL mid-upload and mid-score, then restarted (every acknowledged submission scored exactly
once); a full disk (a real tmpfs that fills) and a file size limit during uploads; 50 concurrent
submissions on loopback; the ``submit`` command against a real server."""

from __future__ import annotations

import http.client
import os
import re
import resource
import shutil
import signal
import socket
import sqlite3
import subprocess
import time

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from tdof20.errors import TdofError
from tdof20.server.cli import app
from tdof20.server.client import submit
from tdof20.server.config import ServerConfig
from tdof20.server.db import jobs, make_engine, submissions
from tests.test_server_support import CLI, LiveServer, dataset, results_csv  # noqa: F401


def _rows(engine):
    with engine.begin() as c:
        return c.execute(select(submissions.c.uid, submissions.c.status, submissions.c.scored_count,
                                jobs.c.state, jobs.c.attempts)
                         .select_from(submissions.join(jobs, jobs.c.submission_id == submissions.c.id))
                         .order_by(submissions.c.id)).all()


def _wait(predicate, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:  # bounded
        if predicate():
            return True
        time.sleep(0.1)
    return False


def _workers(root, data, n: int, *extra: str) -> list[subprocess.Popen]:
    cmd = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--lease", "2", "--poll", "0.2",
                 *extra]
    return [subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for _ in range(n)]


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def test_kill_9_the_server_mid_upload_and_a_worker_mid_score(dataset, tmp_path):
    """kill -9 the uvicorn server while an upload streams in and a worker while it scores; restart
    both: every acknowledged submission is scored exactly once, the cut upload left nothing."""
    root, gt = dataset
    data = tmp_path / "data"
    csv = tmp_path / "r.csv"
    csv.write_bytes(results_csv(gt, "simple"))  # the smallest protocol: the time goes to processes, not scoring
    live = LiveServer(root, data).__enter__()
    engine = make_engine(ServerConfig(dataset=root, data=data).db_url)
    procs = [live.proc]
    try:
        uids = [submit(csv, live.url, live.tokens["alice"], f"m{i}", "simple")["uid"] for i in range(2)]
        r = CliRunner().invoke(app, ["submit", str(csv), "--server", live.url, "--token", live.tokens["alice"],
                                     "--method", "m2", "--split", "simple"])
        assert r.exit_code == 0 and r.output.startswith("submitted ") and ": queued (" in r.output
        uids.append(r.output.split()[1].rstrip(":"))
        bad = tmp_path / "bad.csv"
        bad.write_text("scene_id,im_id,obj_id,score,R,t\n")
        with pytest.raises(TdofError, match=r"refused the submission \(400\): line 1: malformed header"):
            submit(bad, live.url, live.tokens["alice"], "m", "hard")
        with pytest.raises(TdofError, match=r"\(401\): invalid or revoked token"):
            submit(csv, live.url, "tdof20_0123456789abcdef_" + "x" * 30, "m", "hard")
        first = _workers(root, data, 1, "--pause", "60")[0]  # claims a job and holds it, mid-score
        procs.append(first)
        assert _wait(lambda: any(r.state == "running" for r in _rows(engine)), 60)
        # an upload that has sent half its body when the server dies
        conn = http.client.HTTPConnection("127.0.0.1", live.port, timeout=30)
        body = b"--XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"r.csv\"\r\n\r\n" + \
            results_csv(gt, "hard") * 200
        conn.putrequest("POST", "/api/submissions")
        conn.putheader("Authorization", f"Bearer {live.tokens['alice']}")
        conn.putheader("Content-Type", "multipart/form-data; boundary=XyZ")
        conn.putheader("Content-Length", str(len(body) + 100))
        conn.endheaders()
        conn.send(body[:len(body) // 2])
        time.sleep(0.5)
        dead_pid = live.proc.pid
        os.kill(live.proc.pid, signal.SIGKILL)
        os.kill(first.pid, signal.SIGKILL)
        live.proc.wait(10)
        first.wait(10)
        conn.close()
        assert [r.status for r in _rows(engine)].count("scoring") == 1
        # what a server killed inside its copy to the store leaves: a temp file of a dead process
        left = data / "tmp" / f"{socket.gethostname().replace('.', '_')[:64]}.{dead_pid}.{'0' * 32}.part"
        left.write_bytes(b"scene_id,im_id")

        again = LiveServer(root, data, tokens=live.tokens).__enter__()  # restart
        procs.append(again.proc)
        assert not left.exists()  # the dead process's temp file is gone
        workers = _workers(root, data, 2)
        procs += workers
        uids.append(submit(csv, again.url, again.tokens["bob"], "after", "simple")["uid"])
        assert _wait(lambda: all(r.status == "done" for r in _rows(engine)), 240), _rows(engine)
        _stop(workers)
        rows = _rows(engine)
        assert [r.uid for r in rows] == uids  # every acknowledged one, and the cut upload is not there
        assert all(r.status == "done" and r.state == "done" and r.scored_count == 1 for r in rows), rows
        assert sorted(r.attempts for r in rows) == [1, 1, 1, 2]  # the killed worker's job was claimed twice
        assert not list((data / "tmp").iterdir())
        assert len(list((data / "submissions").iterdir())) == 4
    finally:
        _stop(procs)
        engine.dispose()


def test_a_result_is_recorded_only_under_a_live_claim(dataset, tmp_path):
    from tdof20.server.db import claim_job, finish_job
    from tests.test_server_support import Server

    root, gt = dataset
    s = Server(root, tmp_path / "data")
    s.submit("alice", results_csv(gt, "hard"))
    a = claim_job(s.engine, "a", lease_s=0.0)  # a's lease is over at once
    b = claim_job(s.engine, "b", lease_s=60.0)
    assert a and b and (a.job_id, a.claim) != (b.job_id, b.claim) and a.job_id == b.job_id
    assert claim_job(s.engine, "c", lease_s=60.0) is None  # b's lease holds
    assert finish_job(s.engine, a, {"summary": {}}, None) is False
    assert finish_job(s.engine, b, {"summary": {}}, None) is True
    assert finish_job(s.engine, b, {"summary": {}}, None) is False
    assert [(r.status, r.scored_count, r.attempts) for r in _rows(s.engine)] == [("done", 1, 2)]


def _consistent(data, reserved: bool = False) -> list:
    """The database is whole and the store agrees with it: a file for every row, a row for every
    file, a job for every submission, nothing left in tmp/; returns the rows. ``reserved``: slots
    of refused uploads may remain (a database with no room left even to delete them: the server
    counts them no more and deletes them once there is room)."""
    con = sqlite3.connect(data / "server.db")
    try:
        assert con.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        held = con.execute("SELECT count(*) FROM submissions WHERE status = 'receiving'").fetchone()[0]
        assert reserved or held == 0
        stored = [r[0] for r in con.execute("SELECT stored FROM submissions WHERE status != 'receiving'")]
        assert con.execute("SELECT count(*) FROM jobs").fetchone()[0] == len(stored)
    finally:
        con.close()
    assert sorted(stored) == sorted(p.name for p in (data / "submissions").iterdir())
    assert not list((data / "tmp").iterdir())
    return stored


@pytest.fixture
def tiny_disk(tmp_path):
    """A 2 MiB tmpfs (a real file system that fills: ENOSPC); skipped where none can be mounted."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip()[:80]}); "
                    "test_a_file_size_limit_during_an_upload covers EFBIG")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_full_disk_during_an_upload_is_a_clear_refusal(dataset, tiny_disk, tmp_path):
    """The store and the SQLite database on a 2 MiB tmpfs: a 3 MB upload, then uploads as the disk
    fills page by page — each is acknowledged or refused in one line (507), never a 500, and the
    database and the store stay consistent; once there is room again, a submission goes in."""
    root, gt = dataset
    data = tiny_disk / "data"
    big = tmp_path / "big.csv"
    line = results_csv(gt, "hard").splitlines(keepends=True)
    big.write_bytes(line[0] + b"".join(line[1:]) * 1400)  # ~3 MB, every line short
    small = tmp_path / "r.csv"
    small.write_bytes(results_csv(gt, "hard"))
    refusal = r"refused the submission \(507\): the server's disk is full: the submission was not stored; try later$"
    with LiveServer(root, data, "--daily-limit", "1000") as live:
        token = live.tokens["alice"]
        with pytest.raises(TdofError, match=refusal):
            submit(big, live.url, token, "big", "hard")
        assert _consistent(data) == []
        filler = tiny_disk / "filler"
        outcomes = []
        with open(filler, "wb", buffering=0) as f:
            for _ in range(600):  # bounded: fill 4 KiB at a time until even a refusal is all there is
                try:
                    outcomes.append(submit(small, live.url, token, "m", "hard")["status"])
                except TdofError as e:
                    assert re.search(refusal, str(e)), e  # one clear line, not a 500
                    outcomes.append("full")
                if outcomes[-3:] == ["full"] * 3 and shutil.disk_usage(tiny_disk).free < 4096:
                    break
                try:
                    f.write(b"\0" * 4096)
                except OSError:  # the filler cannot grow: the server's writes alone fill the rest
                    pass
        assert "queued" in outcomes and outcomes[-1] == "full"
        accepted = _consistent(data, reserved=True)
        assert len(accepted) == outcomes.count("queued")
        filler.unlink()
        assert submit(small, live.url, token, "after", "hard")["status"] == "queued"
        assert len(_consistent(data)) == len(accepted) + 1  # (a slot left behind is given back by then)


def test_a_file_size_limit_during_an_upload_is_a_clear_refusal(dataset, tmp_path):
    """The server under RLIMIT_FSIZE (a write past it fails with EFBIG, as on a quota): a larger
    upload is refused in one line (507) and nothing is half-stored."""
    root, gt = dataset
    data = tmp_path / "data"
    big = tmp_path / "big.csv"
    line = results_csv(gt, "hard").splitlines(keepends=True)
    big.write_bytes(line[0] + b"".join(line[1:]) * 1400)
    limit = lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))  # noqa: E731
    with LiveServer(root, data, preexec=limit) as live:
        with pytest.raises(TdofError, match=r"\(507\): the server's disk is full"):
            submit(big, live.url, live.tokens["alice"], "big", "hard")
        assert _consistent(data) == []
        csv = tmp_path / "r.csv"
        csv.write_bytes(results_csv(gt, "hard"))
        assert submit(csv, live.url, live.tokens["alice"], "m", "hard")["status"] == "queued"
        assert len(_consistent(data)) == 1


def test_50_concurrent_submissions_are_all_acknowledged_and_scored(dataset, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    root, gt = dataset
    data = tmp_path / "data"
    csv = tmp_path / "r.csv"
    csv.write_bytes(results_csv(gt, "simple"))  # the smallest protocol (2 images): the workers' time is scoring
    with LiveServer(root, data, "--daily-limit", "100", "--max-uploads", "50") as live:
        with ThreadPoolExecutor(max_workers=50) as pool:  # bounded: 50 submissions, 50 threads
            acks = list(pool.map(lambda i: submit(csv, live.url, live.tokens[("alice", "bob")[i % 2]], f"m{i}",
                                                  "simple"), range(50)))
        assert all(a["status"] == "queued" for a in acks) and len({a["uid"] for a in acks}) == 50
        worker = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--once"]
        procs = [subprocess.Popen(worker, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
        outs = [p.communicate(timeout=500) for p in procs]
        assert all(p.returncode == 0 for p in procs), [o[1][-1000:] for o in outs]
        engine = make_engine(ServerConfig(dataset=root, data=data).db_url)
        rows = _rows(engine)
        engine.dispose()
        assert len(rows) == 50 and all(r.status == "done" and r.scored_count == 1 for r in rows)
        assert sum(int(o[0].split()[1]) for o in outs) == 50  # the queue drained, each job scored by one worker
