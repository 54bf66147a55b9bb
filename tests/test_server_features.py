"""What researchers ask of a challenge server (issue 32 part 6): failed sign-ins and refused tokens
limited per client address, the 'test labels derivable from public images' note from publish's
rule, queue position and ETA, phases with a held-back private part only the operator reveals,
method descriptions, per-condition cells under the disclosure rule, an exported leaderboard, and
scores versioned and re-computed when the dataset or the scorer changes."""

from __future__ import annotations

from tests.test_server_support import Server, dataset, page_csrf, results_csv, server  # noqa: F401


def test_failed_sign_ins_and_tokens_are_limited_per_client(dataset, tmp_path):
    s = Server(dataset[0], tmp_path / "data", max_failures=3, failure_window_s=600.0)
    bad = {"Authorization": "Bearer tdof20_0123456789abcdef_" + "x" * 43}
    for _ in range(3):
        assert s.client.get("/api/quota", headers=bad).status_code == 401
    r = s.client.get("/api/quota", headers=bad)
    assert r.status_code == 429 and 0 < int(r.headers["retry-after"]) <= 600
    assert r.json()["detail"].startswith("too many refused tokens from your address: try again in")
    # the limit comes before the token is checked: a good token from that address waits too
    assert s.client.get("/api/quota", headers=s.headers("alice")).status_code == 429
    page = s.client.get("/signin")
    csrf = page_csrf(page.text)
    for _ in range(3):
        r = s.client.post("/signin", data={"name": "alice", "token": "nope", "csrf": csrf})
        assert r.status_code == 401
    r = s.client.post("/signin", data={"name": "alice", "token": s.tokens["alice"], "csrf": csrf})
    assert r.status_code == 429 and "too many failed sign-ins" in r.text and int(r.headers["retry-after"]) > 0


def test_the_derivable_note_comes_from_publish_rule(server):
    simple = server.client.get("/", params={"split": "simple"}).text
    assert 'id="derivable"' in simple and "share a static scene with labelled public images" in simple
    assert "single/handle_cup_440" in simple  # the scene publish named
    assert 'id="derivable"' not in server.client.get("/", params={"split": "hard"}).text
