"""A submission's figures are drawn by the server when its results page or a figure is first asked
for, not by the worker: the page's figures load as real PNGs, are cached in the store, come out
whole when requested at once from threads or from two processes, and nothing but the figures is
served from the results folder."""

from __future__ import annotations

import io
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

from PIL import Image

from tdof20.scoring import evaluate, report
from tdof20.server.figures import FIGURE_DATA, FIGURES, figures
from tdof20.server.worker import run_worker
from tests.test_server_support import dataset, results_csv, server  # noqa: F401

METHOD = "cost $5 & <b>ours</b>"  # an odd '$' (matplotlib's mathtext) and markup in the legend


def _png(data: bytes) -> tuple[int, int]:
    """The size of a whole PNG (PIL decodes every row: a cut file fails)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    im = Image.open(io.BytesIO(data))
    im.load()
    return im.size


def test_page_draws_its_figures_once_and_they_load(server, dataset):
    _, gt = dataset
    uid = server.submit("alice", results_csv(gt, "hard", shift_mm=8.0), method=METHOD, public=True).json()["uid"]
    assert run_worker(server.cfg, once=True) == 1
    folder = server.cfg.data / "results" / uid
    assert sorted(p.name for p in folder.iterdir()) == [FIGURE_DATA]  # the worker drew nothing
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


def test_concurrent_requests_get_whole_figures(server, dataset, tmp_path):
    root, gt = dataset
    csv = results_csv(gt, "hard", shift_mm=8.0)
    uid = server.submit("alice", csv, method="m", public=True).json()["uid"]
    run_worker(server.cfg, once=True)
    folder = server.cfg.data / "results" / uid
    url = f"/s/{uid}/plots/accuracy_add_s.png"
    with ThreadPoolExecutor(max_workers=4) as pool:  # the first requests for it, at once
        answers = list(pool.map(lambda _: server.client.get(url), range(4)))
    assert {r.status_code for r in answers} == {200} and len({r.content for r in answers}) == 1
    _png(answers[0].content)
    # the very figure the scorer's report draws for this results file
    (tmp_path / "r.csv").write_bytes(csv)
    ev = evaluate(tmp_path / "r.csv", root, "hard")
    ev.method = "m"
    direct = {p.name: p.read_bytes() for p in report.write_plots([ev], tmp_path / "direct")}
    assert answers[0].content == direct["accuracy_add_s.png"]
    # another process (no lock shared) drawing the same folder while this one does: whole files, no leftovers
    (folder / FIGURES).unlink()
    code = ("import sys; from pathlib import Path; from tdof20.server.figures import figures; "
            "print(','.join(figures(Path(sys.argv[1]), 'm', {})))")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True)
    while proc.poll() is None and not list(folder.glob(".drawing-*")):
        time.sleep(0.01)  # (bounded by the other process: it draws or ends)
    outs = [",".join(figures(folder, "m", {})), proc.communicate(timeout=120)[0].strip()]
    assert outs[0] == outs[1] and "accuracy_add_s.png" in outs[0].split(",")
    for name in outs[0].split(","):
        _png((folder / name).read_bytes())
    assert sorted(p.name for p in folder.iterdir()) == sorted([FIGURE_DATA, FIGURES, *outs[0].split(",")])
    assert server.client.get(url).content == (folder / "accuracy_add_s.png").read_bytes()
