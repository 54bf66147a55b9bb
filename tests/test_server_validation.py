"""Per-image detail only on a validation part: a validation submission's results page lists each
image's errors; a test submission's result, pages and API answers hold no per-image figure (its
results folder holds the figures and what they are drawn from, served only as the pooled figures), and a validation target on a test image (TDoF20's simple test images are hard train
images) is dropped before scoring."""

from __future__ import annotations

import json
import shutil

import pytest
from sqlalchemy import select

from tdof20.dataset.results import format_results_csv
from tdof20.server.db import submissions
from tdof20.server.worker import run_worker
from tests.test_server_support import Server, dataset, results_csv  # noqa: F401

SHIFT = 60.0  # mm along z: ADD is exactly 60 mm


@pytest.fixture
def val_server(dataset, tmp_path):  # noqa: F811
    root, gt = dataset
    ds = tmp_path / "ds"
    shutil.copytree(root, ds)
    # the dataset's validation cache (BOP targets): simple's val images 0 and 1 of scene 8, and a
    # test image (8, 2) that must not be scored or shown
    (ds / ".cache" / "val_targets_simple.json").write_text(json.dumps(
        [{"scene_id": 8, "im_id": im, "obj_id": 7, "inst_count": 1} for im in (0, 1, 2)]))
    return Server(ds, tmp_path / "data"), gt


def _val_csv(gt) -> bytes:
    rows = [(s, im, o, 1.0, R, t + [0.0, 0.0, SHIFT if im == 0 else 0.0], 0.02) for s, im, o, R, t in gt
            if s == 8 and im in (0, 1, 2)]
    return format_results_csv(rows).encode()


def test_per_image_errors_only_for_a_validation_part(val_server):
    s, gt = val_server
    r = s.submit("alice", results_csv(gt, "hard"), split="hard", part="val")
    assert r.status_code == 400 and r.json()["detail"].startswith("part must be one of test for hard")
    val = s.submit("alice", _val_csv(gt), split="simple", part="val", method="val-run", public=True)
    test = s.submit("alice", results_csv(gt, "simple", shift_mm=SHIFT), split="simple", method="test-run",
                    public=True)
    assert val.status_code == 201 and test.status_code == 201, (val.text, test.text)
    vuid, tuid = val.json()["uid"], test.json()["uid"]
    assert run_worker(s.cfg, once=True) == 2
    alice = s.sign_in("alice")

    v = s.client.get(f"/api/submissions/{vuid}", headers=s.headers("alice")).json()
    per = {(e["scene_id"], e["im_id"], e["obj_id"]): e for e in v["result"]["per_image"]}
    assert set(per) == {(8, 0, 7), (8, 1, 7)}  # the test image (8, 2) is not among them
    assert per[(8, 0, 7)]["add_mm"] == pytest.approx(SHIFT, abs=1e-3) and not per[(8, 0, 7)]["add_s_ok"]
    assert per[(8, 1, 7)]["add_mm"] == pytest.approx(0.0, abs=1e-3) and per[(8, 1, 7)]["add_s_ok"]
    assert v["result"]["summary"]["all"]["n"] == 2
    page = alice.get(f"/s/{vuid}").text
    assert 'id="per-image"' in page and "60.0" in page and "validation part" in page

    # the test submission: no per-image figure anywhere
    t = s.client.get(f"/api/submissions/{tuid}", headers=s.headers("alice")).json()
    assert t["status"] == "done" and "per_image" not in t["result"]
    with s.engine.begin() as c:
        stored = json.loads(c.execute(select(submissions.c.result).where(submissions.c.uid == tuid)).scalar_one())
    assert "per_image" not in stored and set(stored) == {"summary", "conditions", "warnings", "object_names", "scene_names"}
    assert set(stored["summary"]) - {"proj_px"} == {"objects", "mean", "all", "scenes"}  # aggregates (and the
    assert all("im_id" not in json.dumps(v) for v in stored["summary"].values())  # 2D threshold) only
    answers = [alice.get(f"/s/{tuid}").text, s.client.get(f"/s/{tuid}").text, alice.get("/mine").text,
               s.client.get("/", params={"split": "simple"}).text,
               json.dumps(s.client.get("/api/leaderboard", params={"split": "simple"}).json()),
               json.dumps(s.client.get("/api/submissions", headers=s.headers("alice")).json())]
    for text in answers[:2]:
        assert 'id="per-image"' not in text and "ADD (mm)" not in text
    for text in answers[4:]:
        ims = [e for e in json.loads(text) if e["uid"] == tuid]
        assert ims and all("per_image" not in (e["result"] or {}) for e in ims)
    files = sorted(p.name for p in (s.cfg.data / "results" / tuid).iterdir())
    assert all(f.startswith(("accuracy_", "recall_", "shown_")) and f.endswith(".png")
               or f in ("figure_data.npz", "figures.json", "figures_shown.json")
               for f in files), files  # what the figures are drawn from (errors only), and the figures
    # validation runs are not ranked
    board = s.client.get("/api/leaderboard", params={"split": "simple"}).json()
    assert [b["method"] for b in board] == ["test-run"]
