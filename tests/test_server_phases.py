"""Issue 32 part 6 on a dataset large enough that the disclosure rule shows figures (1,800 hard test
targets, tests/test_server_support.py's rich dataset): the condition cells and the held-back part's
public and private summaries shown at the steps their counts allow, within a step of the stored
values and never finer; the final leaderboard ranked by the private part once revealed; a
validation result's conditions exact; a dataset changed under a running server gets a new version
at once and the server says at start how many scores are behind; a figure drawn again after a
rescoring, never left from an older result."""

from __future__ import annotations

import json
import shutil

import pytest
from sqlalchemy import select
from typer.testing import CliRunner

from tdof20.server.app import create_app
from tdof20.server.cells import dataset_version
from tdof20.server.cli import app
from tdof20.server.config import ServerConfig
from tdof20.server.db import submissions
from tdof20.server.disclosure import MIN_TARGETS, STEPS
from tdof20.server.figures import SHOWN_FIGURE, SHOWN_FIGURES
from tdof20.server.worker import run_worker
from tests.test_server_support import Server, build_rich_dataset, rich_results_csv


@pytest.fixture(scope="module")
def rich(tmp_path_factory):
    root = tmp_path_factory.mktemp("rich")
    return root, build_rich_dataset(root)


def _stored(server, uid) -> dict:
    with server.engine.begin() as c:
        return json.loads(c.execute(select(submissions.c.result).where(submissions.c.uid == uid)).scalar_one())


def _check_cell(shown: dict, stored: dict, key: str = "add_s", n: int | None = None) -> None:
    """A shown cell: the step its count allows (n q >= 10, the finest; ``n``: the count the rule
    takes, the cell's own by default), within a step of the stored value."""
    assert shown["n"] == stored["n"]
    n = stored["n"] if n is None else n
    if n < MIN_TARGETS:
        assert shown[key] is None and shown["withheld"]
        return
    q = min(s for s in STEPS if n * s >= 10)
    assert shown["step"] == q, (n, shown)
    assert abs(shown[key] - stored[key]) <= q + 1e-9
    assert abs(shown[key] / q - round(shown[key] / q)) < 1e-6  # on the grid: nothing finer leaves


def _counts(o) -> list[int]:
    """Every cell's target count in a shown result."""
    if isinstance(o, dict):
        return ([o["n"]] if "n" in o and "step" in o else []) + [n for v in o.values() for n in _counts(v)]
    return []


def test_condition_cells_are_shown_at_their_steps(rich, tmp_path):
    root, gt = rich
    s = Server(root, tmp_path / "data")
    uid = s.submit("alice", rich_results_csv(gt), method="MyNet", public=True).json()["uid"]
    assert run_worker(s.cfg, once=True) == 1
    stored = _stored(s, uid)
    shown = s.client.get(f"/api/submissions/{uid}", headers=s.headers("alice")).json()["result"]
    bins = {k: set(v) for k, v in stored["conditions"].items()}
    assert bins["occlusion"] == {"occlusion < 10 %", "occlusion 10-50 %", "occlusion > 50 %"}
    assert bins["symmetry"] == {"symmetric", "not symmetric"} and len(bins["distance"]) == 3
    for kind, cells in stored["conditions"].items():
        assert sum(c["n"] for c in cells.values()) == 1800, kind  # each a partition of the targets
        for b, c in cells.items():
            _check_cell(shown["conditions"][kind][b], c)
    occ = stored["conditions"]["occlusion"]  # the file is worse on the occluded ones: the cells say so
    assert occ["occlusion < 10 %"]["add_s"] > occ["occlusion > 50 %"]["add_s"] + 0.1
    for o, c in stored["summary"]["objects"].items():
        _check_cell(shown["summary"]["objects"][o], c)
    _check_cell(shown["summary"]["mean"], stored["summary"]["mean"], n=3 * 600)  # objects x the smallest
    page = s.sign_in("alice").get(f"/s/{uid}").text
    assert 'id="per-condition"' in page and "occlusion &gt; 50 %" in page and "not symmetric" in page


def test_held_back_part_public_and_private_figures(rich, tmp_path):
    root, gt = rich
    s = Server(root, tmp_path / "data")
    run = CliRunner().invoke
    data = ["--data", str(s.cfg.data)]
    r = run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), *data])
    assert r.exit_code == 0 and r.output.strip() == "held back 300 of 600 hard test images (by image)", r.output
    uids = [s.submit("alice", rich_results_csv(gt, seed=i, bad=b), method=f"m{i}", public=True).json()["uid"]
            for i, b in enumerate((0.45, 0.1))]
    assert run_worker(s.cfg, once=True) == 2
    for uid in uids:
        stored = _stored(s, uid)
        shown = s.client.get(f"/api/submissions/{uid}", headers=s.headers("alice")).json()["result"]
        pub, priv = stored["parts"]["public"], stored["parts"]["private"]
        assert pub["summary"]["all"]["n"] == priv["summary"]["all"]["n"] == 900
        assert "private" not in shown and shown["summary"]["all"]["n"] == 900
        _check_cell(shown["summary"]["all"], pub["summary"]["all"])
        for o, c in pub["summary"]["objects"].items():  # 300 each: shown at 5 %
            _check_cell(shown["summary"]["objects"][o], c)
        for kind, cells in pub["conditions"].items():
            for b, c in cells.items():
                _check_cell(shown["conditions"][kind][b], c)
        # nothing of the whole test set is shown: with the public part's it would give the private part's
        assert max(_counts(shown)) == 900
    board = s.client.get("/api/leaderboard", params={"split": "hard"}).json()
    assert [b["method"] for b in board] == ["m1", "m0"]  # by the public part's shown mean
    assert s.client.get("/api/leaderboard", params={"split": "hard", "phase": "final"}).status_code == 403
    assert run(app, ["serve", "reveal", "--split", "hard", *data]).exit_code == 0
    final = s.client.get("/api/leaderboard", params={"split": "hard", "phase": "final"}).json()
    assert [b["method"] for b in final] == ["m1", "m0"]
    for b in final:
        priv = _stored(s, b["uid"])["parts"]["private"]["summary"]
        shown = b["result"]["private"]["summary"]
        assert b["score"] == shown["mean"]["add_s"] and b["score_step"] == shown["mean"]["step"]
        _check_cell(shown["all"], priv["all"])
    html = s.client.get("/", params={"split": "hard", "phase": "final"}).text
    assert "Revealed by the server's operators on" in html and "m1" in html
    # a second hold-back is refused, and one after scored results warns what they let be estimated
    r = run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), *data])
    assert r.exit_code != 0 and "has a held-back part already" in str(r.exception)


def test_hold_back_after_scores_warns(rich, tmp_path):
    root, gt = rich
    s = Server(root, tmp_path / "data")
    s.submit("alice", rich_results_csv(gt), public=True)
    assert run_worker(s.cfg, once=True) == 1
    r = CliRunner().invoke(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), "--by", "scene",
                                 "--data", str(s.cfg.data)])
    assert r.exit_code == 0, r.output
    lines = r.output.strip().splitlines()
    assert lines[0] == (f"held back 300 of 600 hard test images (by scene); run tdof20 serve rescore --dataset {root} "
                        "for the 1 result(s) scored before")
    assert lines[1].startswith("warning: 1 hard test result(s) were shown on the whole test set before this part")


def test_validation_result_has_exact_conditions(rich, tmp_path):
    root, gt = rich
    s = Server(root, tmp_path / "data")
    val = rich_results_csv(gt, split="val")
    assert s.submit("alice", val, split="simple", part="val", method="tuned").status_code == 201
    assert s.submit("alice", rich_results_csv(gt, split="simple", seed=3), split="simple",
                    method="tested").status_code == 201
    assert run_worker(s.cfg, once=True) == 2
    mine = {m["method"]: m for m in s.client.get("/api/submissions", headers=s.headers("alice")).json()}
    v = mine["tuned"]["result"]
    assert v["disclosure"]["part"] == "val" and v["conditions"]["symmetry"]["not symmetric"]["n"] == 4
    assert "step" not in v["conditions"]["symmetry"]["not symmetric"]  # public labels: exact
    assert v["conditions"]["occlusion"]["occlusion < 10 %"]["n"] == 4  # scene 8: fully visible
    page = s.sign_in("alice").get(f"/s/{mine['tuned']['uid']}").text
    assert 'id="per-condition"' in page and 'id="per-image"' in page
    # simple's 12 test targets: every condition cell withheld
    t = mine["tested"]["result"]
    assert all(c["withheld"] for cells in t["conditions"].values() for c in cells.values())


def test_a_changed_dataset_is_a_new_version_at_once(rich, tmp_path, capsys):
    root, gt = rich
    ds = tmp_path / "ds"
    shutil.copytree(root, ds)
    s = Server(ds, tmp_path / "data")
    uid = s.submit("alice", rich_results_csv(gt), public=True).json()["uid"]
    assert run_worker(s.cfg, once=True) == 1
    before = dataset_version(ds, "hard")
    assert s.client.get(f"/api/submissions/{uid}", headers=s.headers("alice")).json()["version"]["current"]
    info = ds / "scenes" / "000029" / "scene_gt_info.json"
    data = json.loads(info.read_text())
    data["0"][0]["visib_fract"] = 0.5  # the operator corrects one label
    info.write_text(json.dumps(data))
    after = dataset_version(ds, "hard")
    assert after != before and dataset_version(ds, "simple") == dataset_version(root, "simple")
    v = s.client.get(f"/api/submissions/{uid}", headers=s.headers("alice")).json()["version"]
    assert v == {"scorer": v["scorer"], "dataset": before, "current": False}  # the running server sees it
    assert "an older version" in s.client.get(f"/s/{uid}").text
    capsys.readouterr()
    create_app(ServerConfig(dataset=ds, data=tmp_path / "data"))
    err = capsys.readouterr().err
    assert "server: 1 scored submission(s) are on an older scorer or dataset version" in err
    assert f"run tdof20 serve rescore --dataset {ds}" in err


def test_a_figure_is_drawn_again_after_rescoring(rich, tmp_path):
    root, gt = rich
    s = Server(root, tmp_path / "data")
    uid = s.submit("alice", rich_results_csv(gt), public=True).json()["uid"]
    assert run_worker(s.cfg, once=True) == 1
    folder = s.cfg.data / "results" / uid
    assert f"/s/{uid}/plots/{SHOWN_FIGURE}" in s.client.get(f"/s/{uid}").text  # drawn from the whole test set
    first = json.loads((folder / SHOWN_FIGURES).read_text())["key"]
    run = CliRunner().invoke
    data = ["--data", str(s.cfg.data)]
    assert run(app, ["serve", "hold-back", "--split", "hard", "--dataset", str(root), *data]).exit_code == 0
    page = s.client.get(f"/s/{uid}").text  # scored before the part: no figure, and the old one is gone
    assert "scored before this protocol&#39;s test images were split" in page and SHOWN_FIGURE not in page
    assert not (folder / SHOWN_FIGURE).exists()
    assert s.client.get(f"/s/{uid}/plots/{SHOWN_FIGURE}").status_code == 404
    r = run(app, ["serve", "rescore", "--dataset", str(root), *data])
    assert r.exit_code == 0 and "queued again 1 submission(s)" in r.output
    assert run_worker(s.cfg, once=True) == 1
    assert f"/s/{uid}/plots/{SHOWN_FIGURE}" in s.client.get(f"/s/{uid}").text  # the public part's
    assert json.loads((folder / SHOWN_FIGURES).read_text())["key"] != first
    assert s.client.get(f"/s/{uid}/plots/{SHOWN_FIGURE}").status_code == 200
