"""A submission's figures are drawn by the server when its results page or a figure is first asked
for, not by the worker: the page's figures load as real PNGs, are cached in the store, come out
whole when requested at once from threads or from two processes, and nothing but the figures is
served from the results folder. Accuracy curves are drawn for a validation part only (public
labels); a test part's figure is drawn from its disclosed values alone (docs/server.md)."""

from __future__ import annotations

import io
import json
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from PIL import Image

import pytest

from tdof20.dataset.results import format_results_csv
from tdof20.scoring import evaluate, report
from tdof20.server.figures import FIGURE_DATA, FIGURES, SHOWN_FIGURES, figures
from tdof20.server.worker import run_worker
from tests.test_server_support import Server, dataset, results_csv, server  # noqa: F401

VAL = {"disclosure": {"part": "val"}}  # a validation result as shown: its figures are the curves


@pytest.fixture
def val_server(dataset, tmp_path):  # noqa: F811
    """The tiny dataset with a validation part (simple: images 0 and 1 of scene 8)."""
    root, gt = dataset
    ds = tmp_path / "ds"
    shutil.copytree(root, ds)
    targets = [{"scene_id": 8, "im_id": im, "obj_id": 7, "inst_count": 1} for im in (0, 1)]
    (ds / ".cache" / "val_targets_simple.json").write_text(json.dumps(targets))
    rows = [(s, im, o, 1.0, R, t + [0.0, 0.0, 8.0], 0.02) for s, im, o, R, t in gt if s == 8 and im in (0, 1)]
    return Server(ds, tmp_path / "data"), format_results_csv(rows).encode(), ds

METHOD = "cost $5 & <b>ours</b>"  # an odd '$' (matplotlib's mathtext) and markup in the legend


def _png(data: bytes) -> tuple[int, int]:
    """The size of a whole PNG (PIL decodes every row: a cut file fails)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    im = Image.open(io.BytesIO(data))
    im.load()
    return im.size


def test_page_draws_its_figures_once_and_they_load(val_server, dataset):
    server, csv, _ = val_server
    _, gt = dataset
    uid = server.submit("alice", csv, split="simple", part="val", method=METHOD, public=True).json()["uid"]
    tuid = server.submit("alice", results_csv(gt, "hard", shift_mm=8.0), method=METHOD, public=True).json()["uid"]
    assert run_worker(server.cfg, once=True) == 2
    # a test part on 9 targets shows no cell, so its figure (drawn from what is shown) is none, no curve
    assert "/plots/" not in server.client.get(f"/s/{tuid}").text
    assert sorted(p.name for p in (server.cfg.data / "results" / tuid).iterdir()) == [FIGURE_DATA, SHOWN_FIGURES]
    assert server.client.get(f"/s/{tuid}/plots/accuracy_add_s.png").status_code == 404
    folder = server.cfg.data / "results" / uid
    assert sorted(p.name for p in folder.iterdir()) == [FIGURE_DATA, "val_targets.json"]  # the worker drew nothing
    page = server.client.get(f"/s/{uid}")
    srcs = re.findall(r'<img[^>]* src="(/s/[^"]+/plots/[^"]+)"', page.text)
    names = {s.rsplit("/", 1)[1] for s in srcs}
    assert {"accuracy_add_s.png", "accuracy_adds_mm.png", "accuracy_proj2d.png"} <= names, srcs
    drawn = {n: (folder / n).stat().st_mtime_ns for n in names}
    for src in srcs:
        r = server.client.get(src)  # anonymous: the submission is public
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        w, h = _png(r.content)
        assert w >= 400 and h >= 300
    assert server.client.get(f"/s/{uid}").text.count("/plots/") == len(srcs)
    assert {n: (folder / n).stat().st_mtime_ns for n in names} == drawn  # cached: not drawn again
    # only the figures are served from the results folder
    for name in (FIGURE_DATA, FIGURES, "..%2F..%2Fsubmissions", "nosuch.png"):
        assert server.client.get(f"/s/{uid}/plots/{name}").status_code == 404


def test_concurrent_requests_get_whole_figures(val_server, tmp_path):
    server, csv, root = val_server
    uid = server.submit("alice", csv, split="simple", part="val", method="m", public=True).json()["uid"]
    run_worker(server.cfg, once=True)
    folder = server.cfg.data / "results" / uid
    url = f"/s/{uid}/plots/accuracy_add_s.png"
    with ThreadPoolExecutor(max_workers=4) as pool:  # the first requests for it, at once
        answers = list(pool.map(lambda _: server.client.get(url), range(4)))
    assert {r.status_code for r in answers} == {200} and len({r.content for r in answers}) == 1
    _png(answers[0].content)
    # the very figure the scorer's report draws for this results file
    (tmp_path / "r.csv").write_bytes(csv)
    ev = evaluate(tmp_path / "r.csv", root, None, folder / "val_targets.json")
    ev.method = "m"
    direct = {p.name: p.read_bytes() for p in report.write_plots([ev], tmp_path / "direct")}
    assert answers[0].content == direct["accuracy_add_s.png"]
    # another process (no lock shared) drawing the same folder while this one does: whole files, no leftovers
    (folder / FIGURES).unlink()
    code = ("import sys; from pathlib import Path; from tdof20.server.figures import figures; "
            "print(','.join(figures(Path(sys.argv[1]), 'm', {'disclosure': {'part': 'val'}})))")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True)
    while proc.poll() is None and not list(folder.glob(".drawing-*")):
        time.sleep(0.01)  # (bounded by the other process: it draws or ends)
    outs = [",".join(figures(folder, "m", VAL)), proc.communicate(timeout=120)[0].strip()]
    assert outs[0] == outs[1] and "accuracy_add_s.png" in outs[0].split(",")
    for name in outs[0].split(","):
        _png((folder / name).read_bytes())
    assert sorted(p.name for p in folder.iterdir()) == sorted([FIGURE_DATA, FIGURES, "val_targets.json",
                                                               *outs[0].split(",")])
    assert server.client.get(url).content == (folder / "accuracy_add_s.png").read_bytes()
