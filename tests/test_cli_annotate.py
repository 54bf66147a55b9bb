"""``tdof20 annotate`` as a user meets it: the console script in a subprocess on a small
simulated session — the whole pipeline, a resumed rerun, stages alone, evaluate, and bad input
as one-line errors (the first in a subprocess, the others through the same entry point,
``tdof20.cli.main``, in this process: each subprocess costs ~3 s of imports)."""

import json
import subprocess
import sys

import pytest

from tdof20.capture import run_capture, sim_config
from tdof20.formats import read_json, read_scene
from tests.cli_support import run_here

EXE = [sys.executable, "-m", "tdof20.cli"]


def run(*args):
    return subprocess.run(EXE + [str(a) for a in args], capture_output=True, text=True, timeout=600)



def one_line_error(res, *needles):
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error:") and "Traceback" not in res.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    p = tmp_path_factory.mktemp("cli_annotate") / "raw"
    run_capture(sim_config("multi/08", steps=12, step_deg=30.0, n_arms=1, width=160, height=120), p, yes=True,
                show_progress=False)
    return p


def test_annotate_runs_resumes_and_evaluates(raw, tmp_path):
    out = tmp_path / "scene"
    res = run("annotate", raw, "--out", out, "--models", raw / "truth" / "models", "--workers", "1")
    assert res.returncode == 0, res.stderr
    assert "labelled 12 of 12 frames" in res.stdout and "report:" in res.stdout
    scene = read_scene(out)
    assert scene.im_ids() == list(range(12))
    assert (out / "qa" / "report.html").exists()
    st = read_json(out / "work" / "state.json")
    # a rerun finds every stage up to date and changes nothing
    before = (out / "scene_gt.json").stat().st_mtime_ns
    res = run("annotate", raw, "--out", out, "--models", raw / "truth" / "models")
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("up to date") == 6, res.stdout
    assert (out / "scene_gt.json").stat().st_mtime_ns == before
    assert read_json(out / "work" / "state.json") == st
    # one stage alone, forced
    res = run("annotate", raw, "--out", out, "--models", raw / "truth" / "models", "--stages", "qa", "--force")
    assert res.returncode == 0 and "qa" in res.stdout and "ran" in res.stdout
    # evaluate prints JSON with the targets
    res = run("annotate", "evaluate", out, "--truth", raw / "truth", "--points", "500")
    assert res.returncode == 0, res.stderr
    ev = json.loads(res.stdout)
    assert ev["all"]["iou_visib"]["median"] >= 0.9 and ev["all"]["surface_mm"]["median"] <= 2.0
    assert set(ev["objects"]) == {str(e["obj_id"]) for e in read_json(raw / "session.json")["objects"]}


def test_annotate_bad_input_is_one_line(raw, tmp_path, capfd, monkeypatch):
    one_line_error(run("annotate", tmp_path / "nope", "--out", tmp_path / "s"), "nope")

    def here(*args):
        return run_here(capfd, monkeypatch, *args)

    one_line_error(here("annotate", raw, "--out", tmp_path / "s", "--stages", "labels"), "labels")
    cfg = tmp_path / "a.toml"
    cfg.write_text("[label]\nmethdo = 1\n")
    one_line_error(here("annotate", raw, "--out", tmp_path / "s", "--config", cfg), str(cfg), "methdo")
    one_line_error(here("annotate", raw, "--out", tmp_path / "s", "--models", tmp_path / "nomodels"), "nomodels")
    one_line_error(here("annotate", "evaluate", tmp_path / "s2", "--truth", raw / "truth"), "s2")
    assert not (tmp_path / "s" / "scene_gt.json").exists()
