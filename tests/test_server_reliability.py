"""The queue under failure: a worker killed with SIGKILL mid-score leaves its job to the next
worker after the lease, and every acknowledged submission is scored exactly once; the
``submit`` command against a real server on loopback."""

from __future__ import annotations

import os
import signal
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


def test_kill_9_a_worker_mid_score_and_every_submission_is_scored_once(dataset, tmp_path):
    root, gt = dataset
    data = tmp_path / "data"
    with LiveServer(root, data) as live:
        csv = tmp_path / "r.csv"
        csv.write_bytes(results_csv(gt, "hard"))
        uids = [submit(csv, live.url, live.tokens["alice"], f"m{i}", "hard")["uid"] for i in range(2)]
        r = CliRunner().invoke(app, ["submit", str(csv), "--server", live.url, "--token", live.tokens["alice"],
                                     "--method", "m2", "--split", "hard"])
        assert r.exit_code == 0 and r.output.startswith("submitted ") and ": queued (" in r.output
        uids.append(r.output.split()[1].rstrip(":"))
        bad = tmp_path / "bad.csv"
        bad.write_text("scene_id,im_id,obj_id,score,R,t\n")
        with pytest.raises(TdofError, match=r"refused the submission \(400\): line 1: malformed header"):
            submit(bad, live.url, live.tokens["alice"], "m", "hard")
        with pytest.raises(TdofError, match=r"\(401\): invalid or revoked token"):
            submit(csv, live.url, "tdof20_0123456789abcdef_" + "x" * 30, "m", "hard")
        engine = make_engine(ServerConfig(dataset=root, data=data).db_url)
        worker = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--lease", "2",
                        "--poll", "0.2"]
        first = subprocess.Popen(worker + ["--pause", "60"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            assert _wait(lambda: any(r.state == "running" for r in _rows(engine)), 60)
            os.kill(first.pid, signal.SIGKILL)
            first.wait(10)
        finally:
            if first.poll() is None:
                first.kill()
                first.wait(10)
        assert [r.status for r in _rows(engine)].count("scoring") == 1
        second = subprocess.run(worker + ["--once"], capture_output=True, text=True, timeout=240)
        assert second.returncode == 0, second.stderr[-2000:]
        rows = _rows(engine)
        assert [r.uid for r in rows] == uids
        assert all(r.status == "done" and r.state == "done" and r.scored_count == 1 for r in rows), rows
        assert sorted(r.attempts for r in rows) == [1, 1, 2]  # the killed one was claimed twice
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


def test_a_full_disk_during_an_upload_is_a_clear_refusal(dataset, tmp_path, monkeypatch):
    import errno

    from tdof20.server import store as store_module
    from tests.test_server_support import Server

    root, gt = dataset
    s = Server(root, tmp_path / "data")
    real_open = open

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, b):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(store_module, "open", lambda p, mode: Full(real_open(p, mode)), raising=False)
    r = s.submit("alice", results_csv(gt, "hard"))
    assert r.status_code == 507 and r.json() == {"detail": "the server's disk is full: the submission was not "
                                                           "stored; try later"}
    monkeypatch.undo()
    assert _rows(s.engine) == [] and not list((s.cfg.data / "tmp").iterdir())
    assert s.submit("alice", results_csv(gt, "hard")).status_code == 201  # and it works again


def test_50_concurrent_submissions_are_all_acknowledged_and_scored(dataset, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    root, gt = dataset
    data = tmp_path / "data"
    csv = tmp_path / "r.csv"
    csv.write_bytes(results_csv(gt, "hard"))
    with LiveServer(root, data, "--daily-limit", "100") as live:
        with ThreadPoolExecutor(max_workers=50) as pool:  # bounded: 50 submissions, 50 threads
            acks = list(pool.map(lambda i: submit(csv, live.url, live.tokens[("alice", "bob")[i % 2]], f"m{i}",
                                                  "hard"), range(50)))
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
