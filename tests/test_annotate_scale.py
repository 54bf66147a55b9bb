"""Many sessions in one ``tdof20 annotate RAW... --out DIR``: one scene folder per scene id, the
checks before anything runs (a RAW that is no session, two sessions of one scene id), a failing
session beside finished ones, each scene resuming on its own, and the same label files whether a
session runs alone, beside another on local worker processes, or on a local Ray instance.

Sessions: multi/08 at 160x120, 2 arm positions x 4 steps of 30 deg, two noise seeds; the second
is relabelled multi/09 in its session.json (the scene id only names the scene: annotate reads
the objects from session.json), a copy of it relabelled multi/10 without arm 0's opaque depth
fails in its register stage. The label gate is off ([label] gate = false) and the place stage's
fit gate loose (a pixel here is ~4 mm on the objects), and a cluster of 150 points an object
(its smallest object fuses to ~320 points from these 8 frames, at the default 300's edge: the
depth scale measured on a perfect sensor, 1.0019 applied, took it under), so that every frame is written and
compared, whatever the accuracy of sessions this small: these tests are about where the work
runs (the gates and the accuracy are tested in test_annotate_pipeline.py and
test_annotate_lab.py)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tdof20.annotate.batch import SUMMARY, annotate_many, batch_text, plan_batch, scene_folder
from tdof20.annotate.config import load_annotate_config
from tdof20.annotate.pipeline import annotate
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import read_json
from tests.cli_support import run_here

EXE = [sys.executable, "-m", "tdof20.cli"]
TOML = "[label]\ngate = false\nchunk = 3\n[reconstruct]\nmin_cluster_points = 150\n[place]\nmin_fitness = 0.05\nmax_score_mm = 8.0\n[qa]\nsample = 1\nevaluate = false\n"
LABEL_DIRS = ("rgb", "depth", "depth_opaque", "depth_restored", "mask", "mask_visib", "models")
LABEL_FILES = ("scene_gt.json", "scene_gt_info.json", "scene_camera.json", "scene_info.json")


def run(*args):
    return subprocess.run(EXE + [str(a) for a in args], capture_output=True, text=True, timeout=600)



def one_line_error(res, *needles):
    assert res.returncode != 0
    # the progress bar's last state (stderr is no terminal) aside, one line
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip() and "━" not in ln]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error:") and "Traceback" not in res.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def relabel(raw: Path, scene_id: str) -> None:
    p = raw / "session.json"
    d = json.loads(p.read_text())
    d["scene_id"] = scene_id
    p.write_text(json.dumps(d, indent=2))


def label_files(scene: Path) -> dict[str, bytes]:
    """Every label file of a scene folder (the BOP files and images, its models)."""
    out = {n: (scene / n).read_bytes() for n in LABEL_FILES}
    for d in LABEL_DIRS:
        for p in sorted((scene / d).iterdir()):
            out[f"{d}/{p.name}"] = p.read_bytes()
    return out


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    base = tmp_path_factory.mktemp("scale")
    raws = {}
    for seed, sid in ((0, "multi/08"), (1, "multi/09")):
        p = base / f"raw_{seed}"
        run_capture(sim_config("multi/08", steps=4, step_deg=30.0, n_arms=2, width=160, height=120, seed=seed), p,
                    yes=True, show_progress=False)
        relabel(p, sid)
        raws[sid] = p
    bad = base / "raw_bad"
    shutil.copytree(raws["multi/09"], bad)
    relabel(bad, "multi/10")
    for f in (bad / "opaque" / "arm0" / "depth").iterdir():
        f.unlink()
    raws["multi/10"] = bad
    cfg = base / "scale.toml"
    cfg.write_text(TOML)
    return {"base": base, "raws": raws, "config": cfg, "models": raws["multi/08"] / "truth" / "models"}


@pytest.fixture(scope="module")
def local_run(sessions):
    """The three sessions in one command, two side by side on local worker processes."""
    s = sessions
    out = s["base"] / "local"
    r = s["raws"]
    res = run("annotate", r["multi/08"], r["multi/09"], r["multi/10"], "--out", out, "--models", s["models"],
              "--config", s["config"], "--workers", "2")
    return {"out": out, "res": res}


def test_several_sessions_one_failing_the_others_finish_and_resume(sessions, local_run, capfd, monkeypatch):
    res, out = local_run["res"], local_run["out"]
    # the failing session names itself; the others finished
    err = one_line_error(res, "1 of 3 scenes failed: multi/10", "the others finished", SUMMARY)
    assert "multi/08" not in err and "multi/09" not in err
    rows = {ln.split()[0]: ln.split() for ln in res.stdout.splitlines() if ln.startswith("multi/")}
    assert rows["multi/08"][1:4] == ["annotated", "8/8", "0"] and rows["multi/09"][1:4] == ["annotated", "8/8", "0"]
    assert rows["multi/10"][1] == "failed"
    assert "multi/10 failed in stage 'register':" in res.stdout
    # one scene folder per scene id: DIR/multi/08 ...
    summary = read_json(out / SUMMARY)
    assert [r["scene"] for r in summary["scenes"]] == ["multi/08", "multi/09", "multi/10"]
    assert summary["failed"] == ["multi/10"] and summary["scenes_side_by_side"] == 2
    for sid in ("multi/08", "multi/09"):
        scene = out / sid
        assert scene == scene_folder(out, sid)
        assert read_json(scene / "scene_info.json")["scene_id"] == sid
        assert len(read_json(scene / "scene_gt.json")) == 8
        assert read_json(scene / "work" / "summary.json")["raw"] == str(sessions["raws"][sid].resolve())
    bad = read_json(out / "multi/10" / "work" / "summary.json")
    assert bad["stages"]["register"]["status"] == "failed" and not (out / "multi/10" / "scene_gt.json").exists()
    # a rerun of the two that finished: each scene resumes on its own, nothing is redone
    before = {sid: (out / sid / "scene_gt.json").stat().st_mtime_ns for sid in ("multi/08", "multi/09")}
    r = sessions["raws"]
    res2 = run_here(capfd, monkeypatch, "annotate", r["multi/08"], r["multi/09"], "--out", out, "--models",
                    sessions["models"], "--config", sessions["config"], "--workers", "1")
    assert res2.returncode == 0, res2.stderr
    assert [ln.split()[1:3] for ln in res2.stdout.splitlines() if ln.startswith("multi/")] == \
        [["up", "to"], ["up", "to"]]
    assert "2 of 2 scenes annotated" in res2.stdout
    assert before == {sid: (out / sid / "scene_gt.json").stat().st_mtime_ns for sid in before}


def test_bad_raw_and_duplicate_scene_ids_stop_before_anything_runs(sessions, tmp_path, capfd, monkeypatch):
    r = sessions["raws"]
    out = tmp_path / "batch"
    not_a_session = tmp_path / "notes"
    not_a_session.mkdir()
    one_line_error(run_here(capfd, monkeypatch, "annotate", r["multi/08"], not_a_session, "--out", out),
                   str(not_a_session), "not a raw session")
    twin = tmp_path / "twin"
    shutil.copytree(r["multi/08"], twin, ignore=shutil.ignore_patterns("rgb", "depth"))
    one_line_error(run_here(capfd, monkeypatch, "annotate", r["multi/08"], r["multi/09"], twin, "--out", out),
                   "both hold scene multi/08", str(twin))
    assert not out.exists()
    # a Ray cluster that cannot be reached: one line, fast, before anything is written
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    one_line_error(run("annotate", r["multi/08"], r["multi/09"], "--out", out, "--executor", "ray",
                       "--ray-address", f"127.0.0.1:{port}"), f"cannot reach the Ray cluster at 127.0.0.1:{port}")
    assert not out.exists()
    # --out that is one annotated scene is not a folder of scenes
    scene = tmp_path / "scene"
    (scene / "work").mkdir(parents=True)
    (scene / "work" / "state.json").write_text("{}")
    with pytest.raises(TdofError, match="holds one annotated scene"):
        plan_batch([r["multi/08"], r["multi/09"]], scene)
    with pytest.raises(TdofError, match="cannot name a scene folder"):
        scene_folder(tmp_path, "multi/../../etc")


def test_alone_side_by_side_and_on_ray_give_the_same_labels(sessions, local_run, tmp_path, monkeypatch):
    """multi/08 alone in this process, both sessions on a local Ray instance of 2 CPUs (scenes as
    tasks, their arm positions and label chunks as tasks inside them): the label files are the
    bytes the side-by-side local run wrote."""
    pytest.importorskip("ray")
    s, local = sessions, local_run["out"]
    cfg = load_annotate_config(s["config"])
    alone = tmp_path / "alone"
    annotate(s["raws"]["multi/08"], alone, s["models"], cfg=cfg.with_label_options(workers=1), progress=False)
    assert label_files(alone) == label_files(local / "multi/08")

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray_out = tmp_path / "ray"
    summary = annotate_many([s["raws"]["multi/08"], s["raws"]["multi/09"]], ray_out, s["models"],
                            cfg=cfg.with_label_options(executor="ray", workers=2), progress=False)
    assert summary["failed"] == [] and summary["executor"] == "ray", batch_text(summary)
    for sid in ("multi/08", "multi/09"):
        assert read_json(ray_out / sid / "work" / "label.json")["executor"] == "ray"
        assert label_files(ray_out / sid) == label_files(local / sid), sid
    import ray

    assert not ray.is_initialized()   # the run shut down the instance it started
    assert os.environ.get("RAY_ADDRESS") is None


def test_an_object_dropped_as_noise_is_named_with_its_points(sessions, tmp_path):
    """An object the reconstruction keeps too few points of (here: reconstruct.min_cluster_points
    raised to 400 over the smallest object's ~320) is said as such, with the cluster's size and the
    option to lower, not as objects touching."""
    import dataclasses

    s = sessions
    cfg = load_annotate_config(s["config"])
    cfg = dataclasses.replace(cfg, reconstruct=dataclasses.replace(cfg.reconstruct, min_cluster_points=400))
    with pytest.raises(TdofError) as e:
        annotate(s["raws"]["multi/08"], tmp_path / "out", s["models"], cfg=cfg.with_label_options(workers=1),
                 progress=False)
    msg = str(e.value)
    assert "reconstruction.json" in msg and "4 objects in session.json" in msg and "3 clusters" in msg
    assert "reconstruct.min_cluster_points = 400" in msg and "touching" not in msg
    small = read_json(tmp_path / "out" / "work" / "reconstruction" / "reconstruction.json")["dropped_clusters"]
    assert 133 <= small[0] < 400 and f"had {small[0]} points" in msg
