"""The daily limit holds under concurrency: 30 uploads sent at once by one user through a real
``tdof20 serve`` on loopback (uvicorn, its threads and event loop) with ``--daily-limit 5`` get
exactly 5 accepted, on SQLite and on PostgreSQL (a real server from Debian's packages: the
user's row locked FOR UPDATE). Failed submissions and ones withdrawn before scoring give their
slot back; the limit's state is in the API and on the pages; a user's uploads in progress at once
are bounded, and a refused or cut upload gives its slot back."""

from __future__ import annotations

import http.client
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from sqlalchemy import select, update

from tdof20.errors import TdofError
from tdof20.server import auth
from tdof20.server.client import submit
from tdof20.server.db import init_db, jobs, make_engine, submissions
from tests.test_server_postgres import pg_url  # noqa: F401
from tests.test_server_support import LiveServer, Server, dataset, page_csrf, results_csv  # noqa: F401

N, LIMIT = 30, 5


def _race(live, csv) -> list:
    """N uploads of alice's, released together by a barrier; each returns its status or its refusal."""
    barrier = threading.Barrier(N)

    def one(i):
        barrier.wait(30)
        try:
            return submit(csv, live.url, live.tokens["alice"], f"m{i}", "hard")["status"]
        except TdofError as e:
            return str(e).split(": ", 1)[1]

    with ThreadPoolExecutor(max_workers=N) as pool:  # bounded: N uploads, N threads
        return list(pool.map(one, range(N)))


def _check_race(outcomes, engine) -> None:
    accepted = [o for o in outcomes if o == "queued"]
    refused = [o for o in outcomes if o != "queued"]
    assert len(accepted) == LIMIT, outcomes
    assert all(o.startswith("the server refused the submission (429): limit reached: 5 submissions per user per 24 "
                            "hours; the next one can be sent after ") and "\n" not in o for o in refused), refused
    with engine.begin() as c:
        rows = c.execute(select(submissions.c.status)).all()
    assert sorted(r.status for r in rows) == ["queued"] * LIMIT  # no reservation left behind


@pytest.mark.parametrize("db", ["sqlite", "postgresql"])
def test_30_concurrent_uploads_get_exactly_the_limit(dataset, tmp_path, db, request):
    root, gt = dataset
    csv = tmp_path / "r.csv"
    csv.write_bytes(results_csv(gt, "hard"))
    data = tmp_path / "data"
    args = ["--daily-limit", str(LIMIT), "--max-uploads", str(N)]
    tokens = None
    if db == "postgresql":
        url = request.getfixturevalue("pg_url")
        engine = make_engine(url)
        init_db(engine)
        with engine.begin() as c:  # (the module's database is shared: start this test from no submission)
            c.execute(jobs.delete())
            c.execute(submissions.delete())
        tokens = {n: auth.add_user(engine, f"{n}-{time.time_ns()}") for n in ("alice", "bob")}
        args += ["--db", url]
    with LiveServer(root, data, *args, tokens=tokens) as live:
        engine = make_engine(url) if db == "postgresql" else make_engine(f"sqlite:///{data / 'server.db'}")
        try:
            _check_race(_race(live, csv), engine)
            q = __import__("json").loads(_get(live, "/api/quota", live.tokens["alice"]))
            assert q["limit"] == LIMIT and q["used"] == LIMIT and q["left"] == 0 and q["uploading"] == 0
            assert q["resets_at"].endswith(" UTC") and q["resets_at_unix"] > time.time() + 86000
            # another user's limit is their own
            assert submit(csv, live.url, live.tokens["bob"], "b", "hard")["quota"]["left"] == LIMIT - 1
        finally:
            engine.dispose()


def _get(live, path: str, token: str) -> str:
    conn = http.client.HTTPConnection("127.0.0.1", live.port, timeout=30)
    try:
        conn.request("GET", path, headers={"Authorization": f"Bearer {token}"})
        r = conn.getresponse()
        assert r.status == 200
        return r.read().decode()
    finally:
        conn.close()


def test_failed_and_withdrawn_before_scoring_do_not_count(dataset, tmp_path):
    root, gt = dataset
    s = Server(root, tmp_path / "data", daily_limit=2)
    a = s.submit("alice", results_csv(gt, "hard")).json()
    assert a["quota"] == {**a["quota"], "limit": 2, "used": 1, "left": 1}
    b = s.submit("alice", results_csv(gt, "hard")).json()
    r = s.submit("alice", results_csv(gt, "hard"))
    assert r.status_code == 429 and r.json()["detail"].startswith("limit reached: 2 submissions per user")
    # withdrawn before a worker took it: the slot comes back
    assert s.client.post(f"/api/submissions/{a['uid']}/withdraw", headers=s.headers("alice")).status_code == 200
    assert s.client.get("/api/quota", headers=s.headers("alice")).json()["left"] == 1
    c = s.submit("alice", results_csv(gt, "hard"))
    assert c.status_code == 201, c.text
    # a submission the server failed: not counted either
    with s.engine.begin() as conn:
        conn.execute(update(submissions).where(submissions.c.uid == b["uid"]).values(status="failed"))
    assert s.client.get("/api/quota", headers=s.headers("alice")).json()["left"] == 1
    # a refused file (here: a bad line) takes no slot
    bad = s.submit("alice", b"scene_id,im_id,obj_id,score,R,t,time\n28,0,1,x,1 0 0 0 1 0 0 0 1,0 0 700,1\n")
    assert bad.status_code == 400 and bad.json()["detail"] == "line 2: score: 'x' is not a number"
    assert s.client.get("/api/quota", headers=s.headers("alice")).json()["left"] == 1
    # withdrawn once scoring began: it counts (a score was computed)
    with s.engine.begin() as conn:
        sid = conn.execute(select(submissions.c.id).where(submissions.c.uid == c.json()["uid"])).scalar_one()
        conn.execute(update(jobs).where(jobs.c.submission_id == sid).values(state="running"))
    s.client.post(f"/api/submissions/{c.json()['uid']}/withdraw", headers=s.headers("alice"))
    assert s.client.get("/api/quota", headers=s.headers("alice")).json()["left"] == 1
    # the pages show it
    page = s.sign_in("alice")
    for path in ("/submit", "/mine"):
        html = page.get(path).text
        assert "1 of 2 submissions left in the last 24 hours" in html and " UTC" in html, html[-800:]


def test_uploads_at_once_are_bounded_and_a_cut_upload_gives_its_slot_back(dataset, tmp_path):
    root, gt = dataset
    csv = tmp_path / "r.csv"
    body = results_csv(gt, "hard")
    csv.write_bytes(body)
    with LiveServer(root, tmp_path / "data", "--daily-limit", "3", "--max-uploads", "1") as live:
        token = live.tokens["alice"]
        # an upload that stalls half-way holds alice's one upload slot
        conn = http.client.HTTPConnection("127.0.0.1", live.port, timeout=30)
        head = b'--XyZ\r\nContent-Disposition: form-data; name="method"\r\n\r\nm\r\n'
        conn.putrequest("POST", "/api/submissions")
        conn.putheader("Authorization", f"Bearer {token}")
        conn.putheader("Content-Type", "multipart/form-data; boundary=XyZ")
        conn.putheader("Content-Length", str(len(head) + 10_000))
        conn.endheaders()
        conn.send(head)
        deadline = time.monotonic() + 30
        while True:  # bounded: 30 s for the server to reserve the stalled upload's slot
            try:
                submit(csv, live.url, token, "second", "hard")
            except TdofError as e:
                if "uploads of yours are in progress (at most 1 at once)" in str(e):
                    break
                raise
            assert time.monotonic() < deadline, "the stalled upload took no slot"
        assert submit(csv, live.url, live.tokens["bob"], "b", "hard")["status"] == "queued"  # bob's own
        conn.close()  # cut: the slot goes back, and counts for nothing
        deadline = time.monotonic() + 30
        while True:  # bounded
            try:
                out = submit(csv, live.url, token, "after", "hard")
                break
            except TdofError as e:
                assert "in progress" in str(e) and time.monotonic() < deadline, e
                time.sleep(0.1)
        assert out["status"] == "queued" and out["quota"]["used"] == 1 and out["quota"]["left"] == 2
