"""``tdof20 reproduce`` end to end on a config still smaller than smoke: a simulated dataset
(single/12 = juice_cup_340 and multi/08, 2 arm positions x 7 steps at 64x48), every method trained
one step on both protocols, the fusion ablation with 1 and 3 stages, the segmentation ablation,
predictions, scores and the tables; then a resume after a simulated kill, a changed config
refused, and the oracle-mask result marked. Table 3's profiling is left out here (its own tests:
test_methods.py); the tables' rendering is tested in test_reproduce_tables.py."""

from __future__ import annotations

import csv
import io
import json

import pytest

from tdof20.benchmark import reproduce as R
from tdof20.benchmark.reproduce import make_config, reproduce, validation_images
from tdof20.errors import TdofError
from tdof20.formats.io import read_json
from tdof20.sim.scenes import get_scene, normalize_scene_id

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TEST = {"methods": ["pvnet", "densefusion", "ffb6d", "hff6dof"],
        "data": {"scenes": ["single/12", "multi/08"], "steps": 7, "step_deg": 5.0, "n_arms": 2, "width": 64,
                 "height": 48},
        "train": {"image_size": [32, 48], "batch_size": 4, "max_steps": 1, "num_workers": 0},
        "epochs": {"hff6dof": 1, "pvnet": 1, "densefusion": 1, "ffb6d": 1},
        "ablations": {"fuse_stages": [1, 3], "segmentation": True, "voting_3d": True},
        "profile": {"enabled": False}, "device": "cpu",
        "method_options": {"ffb6d": {"n_points": 256, "meanshift_iters": 5, "max_votes": 200},
                           "densefusion": {"n_points": 100, "crop_size": 32, "min_points": 10},
                           "pvnet": {"max_rounds": 2}, "hff6dof": {"n_hyp": 32, "max_points": 200}}}


class Killed(RuntimeError):
    pass


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A reproduce killed in its third training, then resumed to the end; the trainings called."""
    out = tmp_path_factory.mktemp("repro") / "out"
    calls: list[str] = []
    real = R.train_run

    def flaky(root, split, run, method, cfg, epochs, show, **options):
        calls.append(run.name)
        if len(calls) == 3:
            raise Killed("simulated kill")
        return real(root, split, run, method, cfg, epochs, show, **options)

    mp = pytest.MonkeyPatch()
    mp.setattr(R, "train_run", flaky)
    try:
        with pytest.raises(Killed):
            reproduce(out, config=TEST, progress=False)
        state = read_json(out / "reproduce.json")
        first = dict(state["jobs"])
        md = reproduce(out, config=TEST, progress=False)
    finally:
        mp.undo()
    return {"out": out, "md": md, "calls": calls, "first": first}


def test_end_to_end_tables_hold_every_method_and_object(done):
    out, md = done["out"], done["md"].read_text()
    for label in ("PVNet", "DenseFusion", "FFB6D", "HFF6DoF (bearing + PnP)", "HFF6DoF (3D voting + LSQ)"):
        for split in ("simple", "hard"):
            assert f"{label} · {split}" in md
    t = json.loads((out / "tables" / "tables.json").read_text())
    # every object of the test parts has its row: the scenes' objects, read from the scene specs
    objs = sorted({o for s in TEST["data"]["scenes"] for o in get_scene(normalize_scene_id(s)).obj_ids})
    assert [r["obj_id"] for r in t["table1"]["rows"][:-1]] == objs
    assert t["table1"]["rows"][-1]["name"].startswith("mean")
    assert all(c["present"] for c in t["table1"]["columns"])
    body = list(csv.reader(io.StringIO((out / "tables" / "table2_proj2d.csv").read_text())))
    assert len(body) == 1 + len(objs) + 1 and len(body[0]) == 3 + 10
    fz = {r["fuse_stages"]: r for r in t["ablation_fusion"]["rows"]}
    assert fz[1]["add_s"] is not None and fz[3]["add_s"] is not None and fz[2]["add_s"] is None
    assert {c["id"] for c in t["agreement"]} >= {"hff6dof_hard_add_s", "best_fuse_stages", "seg_gain_add_s"}
    for m in ("PVNet", "DenseFusion", "FFB6D", "HFF6DoF__bearing___PnP", "HFF6DoF__3D_voting___LSQ"):
        assert (out / "tables" / "plots" / f"accuracy_{m}.png").stat().st_size > 2000
    state = read_json(out / "reproduce.json")
    assert all(not k.startswith("train/") or (out / "runs" / k[6:] / "last.pt").exists() for k in state["jobs"])
    assert len([k for k in state["jobs"] if k.startswith("train/")]) == 4 * 2 + 2 + 2  # + hff6dof-3d on both protocols


def test_resume_after_a_kill_reuses_finished_work(done):
    first, calls = done["first"], done["calls"]
    trained_first = [k for k in first if k.startswith("train/")]
    assert first["dataset"] and len(trained_first) == 2
    # the killed third training was called again; the two finished ones were not
    assert calls.count(calls[2]) == 2 and all(calls.count(k[6:]) == 1 for k in trained_first)
    state = read_json(done["out"] / "reproduce.json")
    for k, v in first.items():
        assert state["jobs"][k] == v  # finished jobs kept as they were
    # a third call does no work at all
    again = reproduce(done["out"], config=TEST, progress=False)
    assert read_json(done["out"] / "reproduce.json")["jobs"] == state["jobs"] and again.exists()


def test_changed_config_is_refused(done):
    other = json.loads(json.dumps(TEST))
    other["epochs"]["pvnet"] = 2
    other["train"]["batch_size"] = 2
    before = (done["out"] / "reproduce.json").read_bytes()
    with pytest.raises(TdofError, match=r"another config \(changed: epochs.pvnet 1 -> 2; train.batch_size 4 -> 2"):
        reproduce(done["out"], config=other, progress=False)
    with pytest.raises(TdofError, match="preset"):
        reproduce(done["out"], preset="cpu", config=TEST, progress=False)
    assert (done["out"] / "reproduce.json").read_bytes() == before
    other = json.loads(json.dumps(TEST))
    other["device"] = "auto"  # the device changes no result: accepted (nothing left to do)
    reproduce(done["out"], config=other, progress=False)


def test_oracle_mask_result_is_marked(done):
    out = done["out"]
    s = read_json(out / "scores" / "hff6dof_noseg_hard.json")
    assert s["oracle_masks"] is True and read_json(out / "scores" / "hff6dof_hard.json")["oracle_masks"] is False
    assert read_json(out / "results" / "hff6dof_noseg_hard_info.json")["masks"] == "gt"
    md = done["md"].read_text()
    assert "without segmentation head (oracle masks)" in md
    t = json.loads((out / "tables" / "tables.json").read_text())
    assert t["ablation_segmentation"]["rows"][1]["oracle_masks"] is True
    assert "oracle masks" in [c for c in t["agreement"] if c["id"] == "seg_gain_add_s"][0]["ours"]


def test_config_errors_and_presets(tmp_path):
    for name in R.PRESETS:
        cfg = make_config(name)
        assert cfg.preset == name and set(cfg.methods) == set(R.METHODS)
    assert make_config("full").data.steps == 400 and make_config("full").train.image_size == (480, 640)
    bad = tmp_path / "bad.toml"
    bad.write_text('preset = "smoke"\n[train]\nbatchsize = 3\n')
    with pytest.raises(TdofError, match=r"bad.toml.*unknown option 'train.batchsize'"):
        make_config(None, bad)
    bad.write_text('[ablations]\nfuse_stages = [0, 3]\n')
    with pytest.raises(TdofError, match="fuse_stages must be in 1..5"):
        make_config(None, bad)
    with pytest.raises(TdofError, match="preset must be one of"):
        make_config("huge")
    with pytest.raises(TdofError, match="not empty"):
        (tmp_path / "x").mkdir()
        (tmp_path / "x" / "junk").write_text("1")
        reproduce(tmp_path / "x", config=TEST, progress=False)
    bad.write_text('[method_options.ffb6d]\nn_pts = 3\n')
    with pytest.raises(TdofError, match=r"method_options.ffb6d: unknown option 'n_pts'"):
        make_config(None, bad)
    ok = tmp_path / "ok.toml"
    ok.write_text('preset = "cpu"\nmethods = ["hff6dof"]\n[epochs]\nhff6dof = 3\n')
    c = make_config(None, ok)
    assert c.preset == "cpu" and c.methods == ("hff6dof",) and c.epochs.hff6dof == 3 and c.data.steps == 24


def test_cli_command(tmp_path):
    from typer.testing import CliRunner

    from tdof20.cli import app

    res = CliRunner().invoke(app, ["reproduce", "--out", str(tmp_path / "o"), "--preset", "huge"])
    assert isinstance(res.exception, TdofError) and "preset must be one of" in str(res.exception)
    assert not (tmp_path / "o").exists()
    res = CliRunner().invoke(app, ["reproduce", "--out", str(tmp_path / "o"), "--dataset", str(tmp_path)])
    assert isinstance(res.exception, TdofError) and not (tmp_path / "o").exists()


def test_validation_arcs_are_contiguous_and_apart_from_test():
    from tdof20.benchmark.splits import simple_test_steps

    steps, arms = 40, 4
    images = [(12, a * steps + k) for a in range(arms) for k in range(steps)
              if k not in simple_test_steps(a, steps, arms)]
    train, val = validation_images(images, "simple", steps, arms, 0.1)
    assert len(train) + len(val) == len(images) and not set(train) & set(val)
    for a in range(arms):
        ks = sorted(im - a * steps for _, im in val if im // steps == a)
        assert len(ks) == 4 and (ks[-1] - ks[0]) % steps == 3  # one arc of 4 steps
        assert not set(ks) & simple_test_steps(a, steps, arms)
