"""``reproduce --executor ray`` on a local Ray instance with CPU resources: the same jobs as a local
run (the trainings, choices and predictions as Ray tasks, each recorded as it ends), the same
tables, and either executor resumes the other's run. PVNet on TDoF20-simple with two seeds at a
size below smoke (2 scenes, 2 arm positions x 7 steps at 64x48, two steps of 8 images)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("ray")

from tdof20.errors import TdofError
from tdof20.experiments import reproduce as R
from tdof20.formats.io import read_json

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {"methods": ["pvnet"], "protocols": ["simple"],
         "data": {"scenes": ["single/12", "multi/08"], "steps": 7, "step_deg": 5.0, "n_arms": 2, "width": 64,
                  "height": 48},
         "train": {"image_size": [32, 48], "batch_size": 8, "images": 16, "num_workers": 0, "seeds": [0, 1]},
         "ablations": {"fuse_stages": [], "segmentation": False, "voting_3d": False},
         "profile": {"enabled": False}, "device": "cpu",
         "method_options": {"pvnet": {"max_rounds": 2}},
         "candidates": {"pvnet": {"inlier_cos": [0.99, 0.9]}}}


def _tables(out):
    t = json.loads((out / "tables" / "tables.json").read_text())
    return {k: t[k] for k in ("table1", "table2", "agreement")}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("RAY_AUTH_MODE", "disabled")  # the local instance and this driver share no token
    base = tmp_path_factory.mktemp("ray")
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in a Ray task of one CPU (reproduce sets its threads): the same arithmetic
    try:
        local = R.reproduce(base / "local", config=SMALL, progress=False)
        ray_md = R.reproduce(base / "ray", config=SMALL, progress=False, executor="ray", workers=2)
    finally:
        mp.undo()
        torch.set_num_threads(threads)
    return base, local, ray_md


def test_ray_runs_the_same_jobs_and_makes_the_same_tables(runs):
    base, _, ray_md = runs
    a, b = read_json(base / "local" / "reproduce.json"), read_json(base / "ray" / "reproduce.json")
    assert a["digest"] == b["digest"] and set(a["jobs"]) == set(b["jobs"])
    assert {k for k in b["jobs"] if k.startswith("train/")} == {"train/pvnet_simple_s0", "train/pvnet_simple_s1"}
    # each Ray task of one CPU trained on one thread (two at once on two cores, not four threads)
    assert {v["threads"] for k, v in b["jobs"].items() if k.startswith("train/")} == {1}
    for k, v in a["jobs"].items():
        w = b["jobs"][k]
        for key in ("kept_epoch", "kept_step", "images_seen", "options", "add_s", "proj2d"):
            assert v.get(key) == w.get(key), (k, key)
    # every validation figure the tasks made was merged into the state; no task file is left
    assert {n: len(f) for n, f in a["validation"].items()} == {n: len(f) for n, f in b["validation"].items()}
    assert not list((base / "ray" / "tasks").glob("*.json"))
    assert _tables(base / "local") == _tables(base / "ray")
    t = json.loads((base / "ray" / "tables" / "tables.json").read_text())
    assert [c["seeds"] for c in t["table1"]["columns"] if c["present"]] == [2]
    assert "2 seed(s) per row (0, 1)" in ray_md.read_text()


def test_either_executor_resumes_the_others_run(runs, monkeypatch):
    base, _, _ = runs
    before = read_json(base / "ray" / "reproduce.json")["jobs"]
    R.reproduce(base / "ray", config=SMALL, progress=False)  # local, on the Ray run: nothing left to do
    assert read_json(base / "ray" / "reproduce.json")["jobs"] == before
    # a Ray run resumes a local one stopped after its trainings: only the rest runs
    state = read_json(base / "local" / "reproduce.json")
    kept = {k: v for k, v in state["jobs"].items() if not k.startswith(("predict/", "score/"))}
    (base / "local" / "reproduce.json").write_text(json.dumps({**state, "jobs": kept}))
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    R.reproduce(base / "local", config=SMALL, progress=False, executor="ray", workers=2)
    after = read_json(base / "local" / "reproduce.json")["jobs"]
    assert set(after) == set(state["jobs"]) and all(after[k] == v for k, v in kept.items())


def test_executor_options_are_checked():
    with pytest.raises(TdofError, match="--executor must be one of local, ray"):
        R.reproduce("x", config=SMALL, executor="dask")
    with pytest.raises(TdofError, match="--ray-address and --gpus-per-job go with --executor ray"):
        R.reproduce("x", config=SMALL, ray_address="10.0.0.5:6379")
    specs = {s["name"]: s for s in R.job_plan(R.make_config(config=SMALL))}
    assert specs["predict/pvnet_simple_s1"]["needs"] == ["train/pvnet_simple_s1", "choose/pvnet_simple_s1"]
    assert R.job_resources(R.make_config("gpu"), "train", 1.0) == {"num_cpus": 9, "num_gpus": 1.0}
