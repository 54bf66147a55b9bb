"""The server's protections, each test failing on a server without it: private submissions,
401s, escaping, CSRF, upload file names, size limits, SQL metacharacters."""

from __future__ import annotations

import http.client
import json

from sqlalchemy import func, select

from tdof20.server import auth
from tdof20.server.db import submissions, users
from tdof20.server.worker import run_worker
from tests.test_server_support import (LiveServer, dataset, page_csrf, results_csv,  # noqa: F401
                                       server)

SCRIPT = "<script>alert(1)</script>"


def test_private_submissions_are_their_owners_only(server, dataset):
    _, gt = dataset
    uid = server.submit("alice", results_csv(gt, "hard"), method="secret").json()["uid"]
    run_worker(server.cfg, once=True)
    assert server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).status_code == 200
    for r in (server.client.get(f"/api/submissions/{uid}", headers=server.headers("bob")),
              server.client.post(f"/api/submissions/{uid}/withdraw", headers=server.headers("bob")),
              server.client.get(f"/s/{uid}"), server.client.get(f"/s/{uid}/plots/accuracy_add_s.png")):
        assert r.status_code == 404 and "secret" not in r.text
    bob = server.sign_in("bob")
    page = bob.get("/mine")
    r = bob.post(f"/s/{uid}/withdraw", data={"csrf": page_csrf(page.text)})
    assert r.status_code == 404
    assert "secret" not in bob.get(f"/s/{uid}").text and "secret" not in server.client.get("/").text
    assert server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()["status"] == "done"
    assert [s["uid"] for s in server.client.get("/api/submissions", headers=server.headers("bob")).json()] == []


def test_missing_wrong_or_revoked_token_is_401_in_one_line(server):
    auth.revoke_user(server.engine, "bob")
    for headers in ({}, {"Authorization": "Bearer nonsense"}, {"Authorization": server.tokens["alice"]},
                    {"Authorization": "Bearer " + server.tokens["alice"][:-2] + "xx"}, server.headers("bob")):
        r = server.client.get("/api/submissions", headers=headers)
        assert r.status_code == 401 and "\n" not in r.text.strip() and set(r.json()) == {"detail"}
    assert server.client.get("/api/submissions", headers=server.headers("alice")).status_code == 200


def test_names_and_descriptions_are_escaped(server, dataset):
    _, gt = dataset
    fields = dict(method=SCRIPT, description=SCRIPT, authors=SCRIPT, hardware=SCRIPT, time_per_image=SCRIPT,
                  training_data=SCRIPT, public=True)
    uid = server.submit("alice", results_csv(gt, "hard"), filename=SCRIPT + ".csv", **fields).json()["uid"]
    run_worker(server.cfg, once=True)
    alice = server.sign_in("alice")
    for html in (server.client.get("/").text, server.client.get(f"/s/{uid}").text, alice.get("/mine").text,
                 alice.get(f"/s/{uid}").text):
        assert "<script>" not in html and "&lt;script&gt;alert(1)&lt;/script&gt;" in html


def test_forms_need_the_csrf_token(server, dataset):
    _, gt = dataset
    alice = server.sign_in("alice")
    form = {"method": "m", "split": "hard"}
    files = {"file": ("r.csv", results_csv(gt, "hard"), "text/csv")}
    for extra in ({}, {"csrf": "wrong"}):
        assert alice.post("/submit", data={**form, **extra}, files=files).status_code == 403
    uid = server.submit("alice", results_csv(gt, "hard")).json()["uid"]
    assert alice.post(f"/s/{uid}/withdraw", data={}).status_code == 403
    assert alice.post("/signout", data={"csrf": "x"}).status_code == 403
    assert alice.get(f"/s/{uid}").text.count("withdrawn") == 0
    # the sign-in form without its cookie's token
    r = server.client.post("/signin", data={"name": "alice", "token": server.tokens["alice"], "csrf": "forged"})
    assert r.status_code == 403
    ok = alice.post("/submit", data={**form, "csrf": page_csrf(alice.get("/submit").text)}, files=files,
                    follow_redirects=False)
    assert ok.status_code == 303


def test_an_uploaded_file_name_writes_nowhere_outside_the_store(server, dataset, tmp_path):
    _, gt = dataset
    for name in ("../../escape.csv", "..\\..\\escape2.csv", "/etc/passwd", "a/../../../escape3.csv"):
        assert server.submit("alice", results_csv(gt, "hard"), filename=name).status_code == 201
    stored = sorted(p.name for p in (server.cfg.data / "submissions").iterdir())
    assert len(stored) == 4 and all(len(n) == 20 and n.endswith(".csv") for n in stored)
    everything = {p.name for p in tmp_path.rglob("*")} | {p.name for p in tmp_path.parent.iterdir()}
    assert not {"escape.csv", "escape2.csv", "escape3.csv"} & everything


def test_sql_metacharacters_are_harmless(server, dataset):
    _, gt = dataset
    evil = ["'; DROP TABLE users; --", "\" OR 1=1 --", "x' OR '1'='1", "%_\\'", "Robert'); DELETE FROM jobs;--"]
    for i, text in enumerate(evil):
        r = server.submit("alice", results_csv(gt, "hard"), method=text, description=text, authors=text,
                          hardware=text, time_per_image=text, training_data=text, public=True)
        assert r.status_code == 201, r.text
        assert r.json()["method"] == text.strip() and r.json()["authors"] == text
    assert server.submit("bob", results_csv(gt, "hard"), split=evil[0]).status_code == 400  # (alice: at her limit)
    for text in evil:
        assert server.client.get(f"/api/submissions/{text}", headers=server.headers("alice")).status_code in (404, 405)
        assert server.client.get("/api/leaderboard", params={"split": text, "metric": "add_s"}).status_code == 200
        assert server.client.get("/api/leaderboard", params={"split": "hard", "metric": text}).status_code == 400
        assert server.client.post("/signin", data={"name": text, "token": text}).status_code == 403
    with server.engine.begin() as c:
        assert c.execute(select(func.count()).select_from(users)).scalar_one() == 2
        assert c.execute(select(func.count()).select_from(submissions)).scalar_one() == len(evil)
    assert run_worker(server.cfg, once=True) == len(evil)


def test_a_long_line_is_refused_by_the_line_limit(server, dataset):
    _, gt = dataset
    data = results_csv(gt, "hard")
    long = data.replace(b",0.02\n", b"," + b"0" * 10_000 + b"0.02\n", 1)
    r = server.submit("alice", long)
    assert r.status_code == 413 and "line is longer than the limit of 4096 bytes" in r.json()["detail"]
    assert not list((server.cfg.data / "tmp").iterdir())


def _post_streaming(url_port: int, token: str, total: int, chunk: bytes, length: int | None) -> tuple[int, str, int]:
    """POST a multipart body of ``total`` bytes of ``chunk`` (chunked when ``length`` is None);
    returns (status, body, bytes sent before the server answered or closed)."""
    conn = http.client.HTTPConnection("127.0.0.1", url_port, timeout=30)
    conn.putrequest("POST", "/api/submissions")
    conn.putheader("Authorization", f"Bearer {token}")
    conn.putheader("Content-Type", "multipart/form-data; boundary=XyZ")
    if length is None:
        conn.putheader("Transfer-Encoding", "chunked")
    else:
        conn.putheader("Content-Length", str(length))
    conn.endheaders()
    sent = 0
    head = b'--XyZ\r\nContent-Disposition: form-data; name="file"; filename="r.csv"\r\n\r\n'
    try:
        for piece in [head] + [chunk] * (total // len(chunk)):  # bounded: total / chunk pieces
            conn.send(b"%x\r\n%s\r\n" % (len(piece), piece) if length is None else piece)
            sent += len(piece)
        if length is None:
            conn.send(b"0\r\n\r\n")
    except (BrokenPipeError, ConnectionResetError):
        pass
    try:
        r = conn.getresponse()
        return r.status, r.read().decode(), sent
    finally:
        conn.close()


def test_huge_uploads_are_refused_by_size_without_exhausting_memory(dataset, tmp_path):
    root, _ = dataset
    with LiveServer(root, tmp_path / "data", "--max-upload", str(8 << 20)) as live:
        token = live.tokens["alice"]
        rss0 = live.rss_mb()
        # a 2 GB upload announced by its Content-Length: refused before a byte of it is read
        status, body, sent = _post_streaming(live.port, token, 2 << 30, b"x" * (1 << 20), 2 << 30)
        assert status == 413 and json.loads(body)["detail"].startswith("the request is larger than the limit")
        assert sent < 2 << 30
        # the same streamed without a length (chunked): refused once past the limit
        status, body, sent = _post_streaming(live.port, token, 2 << 30, b"x" * (1 << 20), None)
        assert status == 413 and sent < 64 << 20
        # a CSV of one 100 MB line
        status, body, sent = _post_streaming(live.port, token, 100 << 20, b"1" * (1 << 20), None)
        assert status == 413 and sent < 64 << 20
        assert live.rss_mb() - rss0 < 100
        assert not list((live.data / "tmp").iterdir()) and not list((live.data / "submissions").iterdir())
