"""The benchmark server's core: the public release, accounts, submitting (API, pages, the
``submit`` command), strict checks at once, the worker, results and the leaderboard."""

from __future__ import annotations

import json

import numpy as np
from sqlalchemy import func, select
from typer.testing import CliRunner

from tdof20.dataset.results import format_results_csv
from tdof20.formats.io import read_json
from tdof20.server import auth
from tdof20.server.cli import app
from tdof20.server.db import jobs, submissions, users
from tdof20.server.publish import publish
from tdof20.server.worker import run_worker
from tests.test_server_support import HIDDEN, Server, dataset, page_csrf, results_csv, server  # noqa: F401


def _count(engine, table) -> int:
    with engine.begin() as c:
        return c.execute(select(func.count()).select_from(table)).scalar_one()


def test_publish_leaves_no_test_label(dataset, tmp_path):
    root, _ = dataset
    out = tmp_path / "public"
    info = publish(root, out)
    assert info["hidden_test_images"] == 5 and info["train_images_dropped"] == {"hard_train": 2}
    assert not (out / ".cache").exists()
    label_bytes = set()
    for sid, ims in HIDDEN.items():
        src, dst = root / "scenes" / f"{sid:06d}", out / "scenes" / f"{sid:06d}"
        for name in ("scene_gt.json", "scene_gt_info.json"):
            assert not set(map(int, read_json(dst / name))) & ims
            assert set(map(int, read_json(src / name))) & ims  # (the source had them)
        for folder in ("mask", "mask_visib", "depth_restored"):
            for f in (src / folder).iterdir():
                if int(f.name[:6]) in ims:
                    label_bytes.add(f.read_bytes())
                    assert not (dst / folder / f.name).exists()
        for folder in ("rgb", "depth"):  # the images themselves stay
            assert {int(f.name[:6]) for f in (dst / folder).iterdir()} >= ims
        assert read_json(dst / "scene_camera.json") == read_json(src / "scene_camera.json")
    # no file of PUBLIC holds a hidden label's bytes or a hidden pose
    poses = [json.dumps(g["cam_t_m2c"]) for sid, ims in HIDDEN.items()
             for im, gts in read_json(root / "scenes" / f"{sid:06d}" / "scene_gt.json").items() if int(im) in ims
             for g in gts]
    for f in out.rglob("*"):
        if f.is_file():
            b = f.read_bytes()
            assert b not in label_bytes or f.parent.name in ("rgb", "depth"), f
            if f.suffix == ".json":
                text = json.dumps(read_json(f))
                assert not any(p in text for p in poses), f
    assert read_json(out / "splits" / "hard_train.json") == {"8": [0, 1]}
    assert read_json(out / "test_targets_hard.json") == read_json(root / "test_targets_hard.json")
    r = CliRunner().invoke(app, ["publish", str(root), "--out", str(tmp_path / "p2"), "--split", "hard"])
    assert r.exit_code == 0 and "3 test images without labels" in r.output


def test_tokens_are_stored_hashed(server):
    token = server.tokens["alice"]
    with server.engine.begin() as c:
        row = c.execute(select(users).where(users.c.name == "alice")).first()
    assert token not in row.token_hash and row.token_hash.startswith("$argon2")
    assert auth.authenticate(server.engine, token)["name"] == "alice"
    assert auth.authenticate(server.engine, token[:-1] + ("A" if token[-1] != "A" else "B")) is None


def test_submit_score_and_leaderboard(server, dataset):
    _, gt = dataset
    r = server.submit("alice", results_csv(gt, "hard"), method="exact", public=True, authors="A. Lice")
    assert r.status_code == 201, r.text
    uid = r.json()["uid"]
    assert r.json()["status"] == "queued"
    server.submit("alice", results_csv(gt, "hard", shift_mm=60.0), method="off", public=True)
    server.submit("bob", results_csv(gt, "hard"), method="private-one")
    assert run_worker(server.cfg, once=True) == 3
    s = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()
    with server.engine.begin() as c:  # the worker's full result, kept on the server
        stored = json.loads(c.execute(select(submissions.c.result).where(submissions.c.uid == uid)).scalar_one())
    assert s["status"] == "done" and stored["summary"]["mean"]["add_s"] == 1.0
    # shown: 9 targets are too few for any cell (docs/server.md, the disclosure rule)
    assert s["result"]["summary"]["mean"]["add_s"] is None and "fewer than 200" in s["result"]["summary"]["mean"]["withheld"]
    board = server.client.get("/api/leaderboard", params={"split": "hard"}).json()
    assert [b["method"] for b in board] == ["exact", "off"]  # bob's private one is not shown; equal: by time
    assert board[0]["score"] is None and board[0]["score_withheld"]
    html = server.client.get("/").text
    assert "exact" in html and "A. Lice" in html and "private-one" not in html
    page = server.client.get(f"/s/{uid}").text
    assert "Per object" in page and "handle_cup_280" in page and "multi/07" in page
    assert "plots" not in s["result"]  # figures are drawn by the server, not listed in the result
    with server.engine.begin() as c:
        assert {r.scored_count for r in c.execute(select(submissions.c.scored_count))} == {1}


def test_errors_are_line_numbered_and_nothing_is_queued(server, dataset):
    _, gt = dataset
    lines = results_csv(gt, "hard").decode().splitlines()
    lines[3] = lines[3].replace(",1.0,", ",nope,", 1)
    r = server.submit("alice", ("\n".join(lines) + "\n").encode())
    assert r.status_code == 400 and r.json()["detail"] == "line 4: score: 'nope' is not a number"
    r = server.submit("alice", results_csv(gt, "hard").replace(b"\n28,", b"\n99,", 1))
    assert r.status_code == 400 and r.json()["detail"].startswith("line 2: unknown scene_id 99")
    r = server.submit("alice", results_csv(gt, "nosuch") or b"x", split="nosuch")
    assert r.status_code == 400 and "split must be one of" in r.json()["detail"]
    assert _count(server.engine, submissions) == 0 and _count(server.engine, jobs) == 0
    data = server.cfg.data
    assert not list((data / "submissions").iterdir()) and not list((data / "tmp").iterdir())


def test_metres_are_refused_without_naming_test_labels(server, dataset):
    _, gt = dataset
    r = server.submit("alice", format_results_csv([(s, im, o, 1.0, R, t / 1000.0, 0.02)
                                                   for s, im, o, R, t in gt if s == 28]).encode())
    detail = r.json()["detail"]
    assert r.status_code == 400 and detail.startswith("line 2: translations look like metres")
    median = lambda rows: f"about {np.median(np.linalg.norm([g[4] for g in rows], axis=1)):.0f} mm"  # noqa: E731
    train = [g for g in gt if g[1] not in HIDDEN[g[0]]]
    test = [g for g in gt if g[0] == 28]
    assert median(train) in detail and median(test) != median(train) and median(test) not in detail


def test_pages_sign_in_submit_withdraw(server, dataset):
    _, gt = dataset
    c = server.sign_in("alice")
    form = c.get("/submit")
    assert form.status_code == 200
    r = c.post("/submit", data={"method": "paged", "split": "simple", "csrf": page_csrf(form.text)},
               files={"file": ("r.csv", results_csv(gt, "simple"), "text/csv")}, follow_redirects=False)
    assert r.status_code == 303, r.text
    uid = r.headers["location"].rsplit("/", 1)[1]
    status = c.get(f"/s/{uid}").text
    assert "queued" in status and 'http-equiv="refresh"' in status
    assert "paged" in c.get("/mine").text
    r = c.post(f"/s/{uid}/withdraw", data={"csrf": page_csrf(status)}, follow_redirects=False)
    assert r.status_code == 303 and "withdrawn" in c.get(f"/s/{uid}").text
    assert run_worker(server.cfg, once=True) == 0  # a withdrawn submission is not scored


def test_daily_limit_and_openapi(dataset, tmp_path):
    _, gt = dataset
    s = Server(dataset[0], tmp_path / "data", daily_limit=2)
    for _ in range(2):
        assert s.submit("alice", results_csv(gt, "hard")).status_code == 201
    r = s.submit("alice", results_csv(gt, "hard"))
    assert r.status_code == 429 and "2 submissions per user per 24 hours" in r.json()["detail"]
    assert s.submit("bob", results_csv(gt, "hard")).status_code == 201
    schema = s.client.get("/openapi.json").json()
    assert "/api/submissions" in schema["paths"] and "/api/leaderboard" in schema["paths"]


def test_user_commands(tmp_path):
    run = CliRunner().invoke
    data = str(tmp_path / "d")
    r = run(app, ["serve", "user", "add", "carol", "--data", data])
    assert r.exit_code == 0 and r.output.startswith("tdof20_")
    assert run(app, ["serve", "user", "revoke", "carol", "--data", data]).exit_code == 0
    assert "carol  (revoked)" in run(app, ["serve", "user", "list", "--data", data]).output
    r = run(app, ["serve", "user", "add", "carol", "--data", data])
    assert r.exit_code != 0 and "exists" in str(r.exception)
