"""What researchers ask of a challenge server (issue 32 part 6): failed sign-ins and refused tokens
limited per client address, the 'test labels derivable from public images' note from publish's
rule, queue position and ETA, phases with a held-back private part only the operator reveals,
method descriptions, per-condition cells under the disclosure rule, an exported leaderboard, and
scores versioned and re-computed when the dataset or the scorer changes."""

from __future__ import annotations

import csv
import io
import json
import shutil
import time

import pytest
from sqlalchemy import select, update
from typer.testing import CliRunner

from tdof20.dataset.results import format_results_csv
from tdof20.errors import TdofError
from tdof20.server.cells import dataset_version, scorer_version
from tdof20.server.cli import app
from tdof20.server.db import held_back, held_back_part, hold_back, init_db, jobs, make_engine, submissions
from tdof20.server.disclosure import disclose
from tdof20.server.worker import run_worker
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


# ------------------------------------------------------------------ queue position and ETA
def test_queue_position_and_eta_from_recent_scorings(server, dataset):
    _, gt = dataset
    uids = [server.submit("alice", results_csv(gt, "hard"), method=f"m{i}").json()["uid"] for i in range(3)]
    q = [server.client.get(f"/api/submissions/{u}", headers=server.headers("alice")).json()["queue"] for u in uids]
    assert [x["position"] for x in q] == [1, 2, 3] and [x["ahead"] for x in q] == [0, 1, 2]
    assert q[0]["eta_s"] is None and q[0]["typical_s"] is None  # no scoring yet: no estimate, said so
    alice = server.sign_in("alice")
    page = alice.get(f"/s/{uids[2]}").text
    assert 'id="queue"' in page and "in the queue" in page and "no scoring finished yet" in page
    bobs = [server.submit("bob", results_csv(gt, "hard")).json()["uid"] for _ in range(2)]
    with server.engine.begin() as c:  # bob's two, scored in 120 s and 60 s, finished a minute ago
        for u, d in zip(bobs, (120.0, 60.0)):
            sid = c.execute(select(submissions.c.id).where(submissions.c.uid == u)).scalar_one()
            c.execute(update(jobs).where(jobs.c.submission_id == sid).values(
                state="done", worker="w1", started=time.time() - 60 - d, finished=time.time() - 60))
    q = server.client.get(f"/api/submissions/{uids[2]}", headers=server.headers("alice")).json()["queue"]
    assert q["typical_s"] == 90.0 and q["workers"] == 1 and q["based_on"] == 2
    assert q["eta_s"] == 270  # 2 ahead + itself, one worker: 3 x 90 s
    assert "~4 min" in alice.get(f"/s/{uids[2]}").text
    assert run_worker(server.cfg, once=True, max_jobs=1) == 1
    r = server.client.get(f"/api/submissions/{uids[2]}", headers=server.headers("alice")).json()
    assert r["queue"]["position"] == 2
    mine = server.client.get("/api/submissions", headers=server.headers("alice")).json()
    assert [m.get("queue", {}).get("position") for m in mine] == [2, 1, None]
    cells = alice.get("/mine").text.split('class="l queue-cell">')[1:]
    assert [c.split("</td>")[0] for c in cells] == [f"#{m['queue']['position']} · ~{m['queue']['eta_s']} s"
                                                    for m in mine[:2]] + ["—"]  # (under 90 s: in seconds)
    assert "queue" not in server.client.get(f"/api/submissions/{uids[0]}", headers=server.headers("alice")).json()


# ------------------------------------------------------------------ phases and the held-back part
def _pool(cells):
    n = sum(c["n"] for c in cells)
    return n, sum(c["add_s"] * c["n"] for c in cells) / n


def test_held_back_part_is_shown_only_once_revealed(server, dataset):
    root, gt = dataset
    run = CliRunner().invoke
    data = ["--data", str(server.cfg.data)]
    early = server.submit("alice", results_csv(gt, "hard", shift_mm=4.0), method="early", public=True).json()["uid"]
    assert run_worker(server.cfg, once=True) == 1
    r = run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), "--fraction", "0.34", *data])
    assert r.exit_code == 0 and "held back 1 of 3 hard test images (by image)" in r.output, r.output
    r = run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), *data])
    assert r.exit_code != 0 and "has a held-back part already" in str(r.exception)
    part = held_back_part(server.engine, "hard")
    private = {tuple(x) for x in part["images"]}
    assert len(private) == 1 and private <= {(28, 0), (28, 1), (28, 2)}
    # chosen deterministically from the recorded seed: the same seed chooses the same images
    with server.engine.begin() as c:
        seed = c.execute(select(held_back.c.seed)).scalar_one()
    assert len(seed) == 32
    # an earlier result has no parts: no figure of it until it is scored again
    e = server.client.get(f"/api/submissions/{early}", headers=server.headers("alice")).json()
    assert "scored before" in e["result"]["summary"]["withheld"] and e["version"]["current"] is False
    uid = server.submit("alice", results_csv(gt, "hard", shift_mm=4.0), method="MyNet", public=True).json()["uid"]
    assert run_worker(server.cfg, once=True) == 1
    with server.engine.begin() as c:
        stored = json.loads(c.execute(select(submissions.c.result).where(submissions.c.uid == uid)).scalar_one())
    pub, priv = stored["parts"]["public"]["summary"], stored["parts"]["private"]["summary"]
    assert (pub["all"]["n"], priv["all"]["n"]) == (6, 3)  # 3 objects on each of 2 and 1 images
    n, v = _pool([pub["all"], priv["all"]])
    assert n == stored["summary"]["all"]["n"] and v == pytest.approx(stored["summary"]["all"]["add_s"])
    s = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()
    shown = s["result"]
    assert shown["disclosure"]["held_back"] and not shown["disclosure"]["revealed"] and "private" not in shown
    assert shown["summary"]["all"]["n"] == 6  # the public part's, never the whole test set's
    assert all(c["n"] <= 6 for bins in shown["conditions"].values() for c in bins.values())
    r = server.client.get("/api/leaderboard", params={"split": "hard", "phase": "final"})
    assert r.status_code == 403 and "once the server's operators reveal" in r.json()["detail"]
    page = server.client.get("/", params={"split": "hard", "phase": "final"}).text
    assert 'id="not-revealed"' in page and "MyNet" not in page
    assert "public part" in server.client.get("/", params={"split": "hard"}).text
    assert 'id="held-note"' in server.client.get(f"/s/{uid}").text
    r = run(app, ["serve", "reveal", "--split", "hard", *data])
    assert r.exit_code == 0 and "revealed the final leaderboard of hard" in r.output
    shown = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()["result"]
    assert shown["disclosure"]["revealed"] and shown["private"]["summary"]["all"]["n"] == 3
    board = server.client.get("/api/leaderboard", params={"split": "hard", "phase": "final"}).json()
    assert [b["method"] for b in board] == ["early", "MyNet"] and board[1]["rank"] == 2
    assert 'id="private"' in server.client.get(f"/s/{uid}").text
    r = run(app, ["serve", "reveal", "--split", "simple", *data])
    assert r.exit_code != 0 and "simple has no held-back part" in str(r.exception)


def test_hold_back_by_scene_and_its_limits(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'a.db'}")
    init_db(engine)
    frames = [(s, i) for s in (1, 2, 3, 4) for i in range(10)]
    part = hold_back(engine, "x", frames, 0.5, by="scene", seed="s" * 32)
    scenes = {s for s, _ in part["images"]}
    assert len(scenes) == 2 and part["n_images"] == 20  # whole scenes
    by_image = hold_back(engine, "y", frames, 0.3, seed="s" * 32)
    assert sorted({s for s, _ in by_image["images"]}) == [1, 2, 3, 4] and by_image["n_images"] == 12  # 3 per scene
    other = make_engine(f"sqlite:///{tmp_path / 'b.db'}")
    init_db(other)
    again = hold_back(other, "y", frames, 0.3, seed="s" * 32)
    assert again["images"] == by_image["images"]  # deterministic from the seed
    with pytest.raises(TdofError, match="both parts must hold some"):
        hold_back(engine, "z", frames[:1], 0.5)
    with pytest.raises(TdofError, match="between 0 and 1"):
        hold_back(engine, "z", frames, 1.0)


# ------------------------------------------------------------------ per-condition cells
def test_condition_cells_are_computed_and_disclosed_by_their_counts(server, dataset):
    _, gt = dataset
    uid = server.submit("alice", results_csv(gt, "hard", shift_mm=4.0)).json()["uid"]
    assert run_worker(server.cfg, once=True) == 1
    with server.engine.begin() as c:
        stored = json.loads(c.execute(select(submissions.c.result).where(submissions.c.uid == uid)).scalar_one())
    cond, objs = stored["conditions"], stored["summary"]["objects"]
    for kind in ("occlusion", "distance", "symmetry"):  # each a partition of the 9 targets
        n, v = _pool(list(cond[kind].values()))
        assert n == 9 and v == pytest.approx(stored["summary"]["all"]["add_s"]), kind
    assert len(objs) == 3
    shown = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()["result"]
    cells = [c for bins in shown["conditions"].values() for c in bins.values()]
    assert cells and all(c["add_s"] is None and "fewer than 200" in c["withheld"] for c in cells)
    assert 'id="per-condition"' in server.sign_in("alice").get(f"/s/{uid}").text
    # the rule by each cell's own count: 400 targets at 5 % ... 2,000 at 0.5 %, 150 withheld
    stored = {"summary": {}, "conditions": {"occlusion": {"a": {"n": 400, "add_s": 0.4321},
                                                          "b": {"n": 2000, "add_s": 0.4321},
                                                          "c": {"n": 150, "add_s": 0.4321}}}}
    out = disclose(stored, "test", b"k" * 32, "u1")["conditions"]["occlusion"]
    assert (out["a"]["step"], out["b"]["step"], out["c"].get("step")) == (0.05, 0.005, None)
    assert out["a"]["add_s"] in (0.4, 0.45) and out["b"]["add_s"] in (0.43, 0.435) and out["c"]["add_s"] is None


# ------------------------------------------------------------------ method descriptions and the export
def test_method_links_and_the_exported_leaderboard(server, dataset):
    _, gt = dataset
    r = server.submit("alice", results_csv(gt, "hard"), method="bad", paper="javascript:alert(1)")
    assert r.status_code == 400 and r.json()["detail"] == "paper must be a link starting with http:// or https:// " \
                                                         "(or empty)"
    assert server.submit("alice", results_csv(gt, "hard"), method="=HYPERLINK(\"x\")", public=True,
                         paper="https://arxiv.org/abs/2401.00001", code="https://github.com/a/b",
                         hardware="RTX 4090", training_data="hard train").status_code == 201
    assert run_worker(server.cfg, once=True) == 1
    html = server.client.get("/", params={"split": "hard"}).text
    assert "hidden test labels,\nranked" in html  # (no held-back part: no aside, no stray parenthesis)
    assert 'href="https://arxiv.org/abs/2401.00001"' in html and 'href="https://github.com/a/b"' in html
    board = server.client.get("/api/leaderboard", params={"split": "hard"}).json()
    assert board[0]["paper"] == "https://arxiv.org/abs/2401.00001" and board[0]["version"]["current"] is True
    r = server.client.get("/api/leaderboard.csv", params={"split": "hard"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert rows[0]["method"] == "'=HYPERLINK(\"x\")"  # a spreadsheet does not run it
    assert rows[0]["rank"] == "1" and rows[0]["code"] == "https://github.com/a/b" and rows[0]["score_withheld"]
    assert "score (add_s, %, test)" in r.text.splitlines()[0]
    assert 'id="export-csv"' in html and 'id="export-json"' in html
    assert server.client.get("/api/leaderboard", params={"split": "hard", "phase": "nope"}).status_code == 400


# ------------------------------------------------------------------ versions and rescoring
def test_scores_are_versioned_and_rescored(server, dataset):
    root, gt = dataset
    uid = server.submit("alice", results_csv(gt, "hard"), public=True).json()["uid"]
    assert run_worker(server.cfg, once=True) == 1
    v = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()["version"]
    assert v["current"] is True and v["scorer"] == scorer_version() and v["dataset"] == dataset_version(root, "hard")
    run = CliRunner().invoke
    args = ["serve", "rescore", "--dataset", str(root), "--data", str(server.cfg.data)]
    r = run(app, args)
    assert r.exit_code == 0 and "queued again 0 submission(s)" in r.output
    with server.engine.begin() as c:  # as if it had been scored by an older scorer
        c.execute(update(submissions).values(scorer_version="0.0.9+deadbeef"))
    page = server.client.get(f"/s/{uid}").text
    assert "an older version" in page and "0.0.9+deadbeef" in page
    r = run(app, args)
    assert r.exit_code == 0 and f"queued again 1 submission(s) to score on scorer {scorer_version()}: {uid}" in r.output
    s = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()
    assert s["status"] == "done" and s["rescoring"] and s["result"] is not None  # its score stays shown meanwhile
    assert [b["uid"] for b in server.client.get("/api/leaderboard", params={"split": "hard"}).json()] == [uid]
    assert run_worker(server.cfg, once=True) == 1
    s = server.client.get(f"/api/submissions/{uid}", headers=server.headers("alice")).json()
    assert s["version"]["current"] is True and not s["rescoring"]
    with server.engine.begin() as c:
        assert c.execute(select(submissions.c.scored_count)).scalar_one() == 2
    assert "queued again 1" in run(app, args + ["--all"]).output


# ------------------------------------------------------------------ the validation phase
def test_validation_phase_is_a_leaderboard_of_its_own(dataset, tmp_path):
    root, gt = dataset
    ds = tmp_path / "ds"
    shutil.copytree(root, ds)
    (ds / ".cache" / "val_targets_simple.json").write_text(json.dumps(
        [{"scene_id": 8, "im_id": im, "obj_id": 7, "inst_count": 1} for im in (0, 1)]))
    s = Server(ds, tmp_path / "data")
    rows = [(sc, im, o, 1.0, R, t + [0.0, 0.0, 60.0 if im == 0 else 0.0], 0.02) for sc, im, o, R, t in gt
            if sc == 8 and im in (0, 1)]
    assert s.submit("alice", format_results_csv(rows).encode(), split="simple", part="val", method="tuned",
                    public=True).status_code == 201
    assert s.submit("alice", results_csv(gt, "simple"), split="simple", method="tested", public=True).status_code == 201
    assert run_worker(s.cfg, once=True) == 2
    val = s.client.get("/api/leaderboard", params={"split": "simple", "phase": "val"}).json()
    assert [b["method"] for b in val] == ["tuned"] and val[0]["score"] == 0.5  # exact: public labels
    assert [b["method"] for b in s.client.get("/api/leaderboard", params={"split": "simple"}).json()] == ["tested"]
    html = s.client.get("/", params={"split": "simple", "phase": "val"}).text
    assert 'id="phases"' in html and "Validation phase" in html and "tuned" in html and "tested" not in html
    assert "50.0" in html
