"""Nothing lost, and every refusal one line: a worker meeting a full disk (a real tmpfs filled to
its last byte) gives its job back — not counted as a try — and waits, and once room is freed
every submission is scored exactly once; ``tdof20 serve requeue UID|--failed`` queues failed
submissions again; a form's missing field is one line in the API (FastAPI's list of errors is
not what a client gets) and in ``tdof20 submit``; every response says it may not be framed and
carries the CSP; ``server.db`` is its owner's only."""

from __future__ import annotations

import http.client
import http.server
import json
import os
import stat
import subprocess
import threading
import time

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from tdof20.errors import TdofError
from tdof20.server.cli import app
from tdof20.server.client import submit
from tdof20.server.db import MAX_ATTEMPTS, claim_job, jobs, submissions
from tdof20.server.worker import run_worker
from tests.test_server_support import CLI, LiveServer, Server, dataset, free_port, results_csv, server  # noqa: F401


def _rows(engine):
    with engine.begin() as c:
        return c.execute(select(submissions.c.uid, submissions.c.status, submissions.c.scored_count, jobs.c.state,
                                jobs.c.attempts)
                         .select_from(submissions.join(jobs, jobs.c.submission_id == submissions.c.id))).all()


def _fill(path) -> None:
    """Write ``path`` until its file system has not one byte left."""
    with open(path, "wb", buffering=0) as f:
        for size in (1 << 16, 1 << 12, 1 << 8, 1):  # bounded: each size until ENOSPC
            for _ in range(1 << 16):
                try:
                    f.write(b"\0" * size)
                except OSError:
                    break


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (a real file system that fills); skipped where none can be mounted."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip()[:80]})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.parametrize("full", ["store", "store and database"])
def test_a_full_disk_loses_no_submission(dataset, tmp_path, small_disk, full):
    """Three queued submissions, the disk under the store (and, second, under the SQLite database
    too) filled to its last byte, a worker started: it meets ENOSPC (writing what the figures
    are drawn from, or claiming), gives the job back and waits, never failing one; room freed,
    it scores each exactly once."""
    root, gt = dataset
    data = small_disk / "data"
    db = f"sqlite:///{tmp_path / 'server.db'}" if full == "store" else None
    s = Server(root, data, db=db)
    uids = [s.submit(n, results_csv(gt, "hard")).json()["uid"] for n in ("alice", "bob", "alice")]
    filler = small_disk / "filler"
    _fill(filler)
    cmd = CLI + ["serve", "worker", "--dataset", str(root), "--data", str(data), "--poll", "0.2", "--max-wait", "0.5",
                 "--once"] + (["--db", db] if db else [])
    worker = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(8)  # several tries of the worker against the full disk
        assert worker.poll() is None, worker.communicate()
        rows = _rows(s.engine)
        assert all(r.status in ("queued", "scoring") and r.scored_count == 0 and r.attempts <= 1 for r in rows), rows
        filler.unlink()
        out, err = worker.communicate(timeout=180)
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait(10)
    assert worker.returncode == 0, err[-2000:]
    assert out.strip() == "scored 3 submission(s)"
    waits = [ln for ln in err.splitlines() if "waiting" in ln]
    assert waits and all(ln.startswith("worker: ") for ln in waits), err[-2000:]
    assert "Traceback" not in err and ("No space left on device" in err or "disk is full" in err), err[-2000:]
    rows = _rows(s.engine)
    assert sorted(r.uid for r in rows) == sorted(uids)
    assert all(r.status == "done" and r.scored_count == 1 and r.state == "done" and r.attempts == 1 for r in rows), rows


def test_requeue_failed_submissions(dataset, tmp_path):
    root, gt = dataset
    s = Server(root, tmp_path / "data")
    a, b = (s.submit(n, results_csv(gt, "hard")).json()["uid"] for n in ("alice", "bob"))
    for _ in range(MAX_ATTEMPTS):  # workers that die: their leases expire, each a try
        assert claim_job(s.engine, "dies", lease_s=-1) is not None
    assert claim_job(s.engine, "dies", lease_s=-1) is not None  # (b's first try; a fails)
    by = {r.uid: r for r in _rows(s.engine)}
    assert by[a].status == "failed" and by[b].status == "scoring"
    run = CliRunner().invoke
    data = ["--data", str(s.cfg.data)]
    r = run(app, ["serve", "requeue", b, *data])
    assert r.exit_code != 0 and str(r.exception) == f"submission {b} is scoring, not failed: only a failed one is " \
                                                     "queued again (each submission is scored once)"
    r = run(app, ["serve", "requeue", *data])
    assert r.exit_code != 0 and "give one submission's UID or --failed" in str(r.exception)
    r = run(app, ["serve", "requeue", "--failed", *data])
    assert r.exit_code == 0 and r.output.strip() == f"queued again 1 submission(s): {a}"
    assert run(app, ["serve", "requeue", "--failed", *data]).output.strip() == "queued again 0 submission(s)"
    time.sleep(0.05)
    assert run_worker(s.cfg, once=True) == 2  # a again, and b (its lease expired)
    rows = _rows(s.engine)
    assert all(r.status == "done" and r.scored_count == 1 for r in rows), rows
    r = run(app, ["serve", "requeue", a, *data])
    assert r.exit_code != 0 and "is done, not failed" in str(r.exception)


def test_missing_fields_are_one_line(server, dataset):
    _, gt = dataset
    h = server.headers("alice")
    r = server.client.post("/api/submissions", headers=h, data={"split": "hard"},
                           files={"file": ("r.csv", results_csv(gt, "hard"), "text/csv")})
    assert r.status_code == 422 and r.json() == {"detail": "method: field required"}
    r = server.client.post("/api/submissions", headers=h, data={"method": "m", "split": "hard"},
                           files={"results": ("r.csv", results_csv(gt, "hard"), "text/csv")})  # not named "file"
    assert r.status_code == 422 and r.json() == {"detail": "file: field required"}
    r = server.client.post("/api/submissions", headers=h, data={"method": "m", "split": "hard", "public": "maybe"},
                           files={"file": ("r.csv", results_csv(gt, "hard"), "text/csv")})
    assert r.status_code == 422 and r.json() == {"detail": "public: must be true or false"}
    r = server.client.post("/api/submissions", headers={**h, "Content-Type": "application/x-www-form-urlencoded"},
                           content=b"method=m")
    assert r.status_code == 400 and r.json()["detail"].startswith("the body must be multipart/form-data")
    r = server.client.get("/api/leaderboard")  # FastAPI's own validation: one line too
    assert r.status_code == 422 and r.json() == {"detail": "split: field required"}
    # nothing was reserved by the refusals
    assert server.client.get("/api/quota", headers=h).json()["used"] == 0


class _OldServer(http.server.BaseHTTPRequestHandler):
    """A server answering as FastAPI's default handlers do (a 422 with a list) or a proxy's HTML 502."""

    def do_POST(self):  # noqa: N802
        self.rfile.read(int(self.headers.get("content-length", 0)))
        if self.path.startswith("/old"):
            body, ctype, code = json.dumps({"detail": [{"type": "missing", "loc": ["body", "method"],
                                                        "msg": "Field required", "input": None}]}), "json", 422
        else:
            body, ctype, code = "<html><body><h1>502 Bad Gateway</h1></body></html>", "html", 502
        self.send_response(code)
        self.send_header("Content-Type", f"application/{ctype}" if ctype == "json" else "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body.encode())

    def log_message(self, *a):
        pass


def test_submit_prints_one_line_never_a_repr(dataset, tmp_path):
    _, gt = dataset
    csv = tmp_path / "r.csv"
    csv.write_bytes(results_csv(gt, "hard"))
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), _OldServer)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{srv.server_port}"
        with pytest.raises(TdofError) as e:
            submit(csv, url + "/old", "t", "m", "hard")
        assert str(e.value).endswith("the server refused the submission (422): method: Field required")
        with pytest.raises(TdofError) as e:
            submit(csv, url + "/proxy", "t", "m", "hard")
        assert str(e.value).endswith("the server refused the submission (502): Bad Gateway")
    finally:
        srv.shutdown()
        srv.server_close()
    # a real server's refusal through the command: one line
    with LiveServer(dataset[0], tmp_path / "data", "--daily-limit", "1") as live:
        args = ["submit", str(csv), "--server", live.url, "--token", live.tokens["alice"], "--method", "m",
                "--split", "hard"]
        assert CliRunner().invoke(app, args).exit_code == 0
        r = CliRunner().invoke(app, args)
        assert r.exit_code != 0 and "\n" not in str(r.exception)
        assert "refused the submission (429): limit reached: 1 submissions per user per 24 hours" in str(r.exception)


def test_headers_on_every_response_and_a_private_database(dataset, tmp_path):
    with LiveServer(dataset[0], tmp_path / "data", "--max-upload", "1000") as live:
        conn_paths = [("GET", "/", None), ("GET", "/signin", None), ("GET", "/openapi.json", None),
                      ("GET", "/s/nope", None), ("GET", "/api/submissions", None),
                      ("POST", "/api/submissions", b"x" * 200_000)]  # the body limit's own 413
        for method, path, body in conn_paths:
            c = http.client.HTTPConnection("127.0.0.1", live.port, timeout=30)
            try:
                c.request(method, path, body=body, headers={"Content-Type": "multipart/form-data; boundary=x"})
                r = c.getresponse()
                r.read()
                assert r.getheader("X-Frame-Options") == "DENY", (path, r.status)
                csp = r.getheader("Content-Security-Policy")
                assert "frame-ancestors 'none'" in csp and "default-src 'none'" in csp, (path, csp)
                assert r.getheader("X-Content-Type-Options") == "nosniff"
            finally:
                c.close()
    mode = stat.S_IMODE(os.stat(tmp_path / "data" / "server.db").st_mode)
    assert mode == 0o600, oct(mode)
