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
import torch

from tdof20.experiments import reproduce as R
from tdof20.experiments.reproduce import make_config, reproduce, validation_images
from tdof20.errors import TdofError
from tdof20.formats.io import read_json
from tdof20.sim.scenes import get_scene, normalize_scene_id

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TEST = {"methods": ["pvnet", "densefusion", "ffb6d", "hff6dof"],
        "data": {"scenes": ["single/12", "multi/08"], "steps": 7, "step_deg": 5.0, "n_arms": 2, "width": 64,
                 "height": 48},
        "train": {"image_size": [32, 48], "batch_size": 8, "max_steps": 0, "num_workers": 0},
        "epochs": {"hff6dof": 1, "pvnet": 2, "densefusion": 1, "ffb6d": 1},
        "ablations": {"fuse_stages": [1, 3], "segmentation": True, "voting_3d": True},
        "profile": {"enabled": False}, "device": "cpu",
        "method_options": {"ffb6d": {"n_points": 256, "meanshift_iters": 5, "max_votes": 200},
                           "densefusion": {"n_points": 100, "crop_size": 32, "min_points": 10},
                           "pvnet": {"max_rounds": 2}, "hff6dof": {"n_hyp": 32, "max_points": 200}},
        "candidates": {"pvnet": {"inlier_cos": [0.99, 0.9]}}}


class Killed(RuntimeError):
    pass


#: validation figures the test imposes (on top of the real scorer's, which a one-step training
#: leaves at 0 % everywhere, so that every choice would be a tie): (run, step) -> ADD(S) for the
#: epochs, (run, inlier_cos) for PVNet's candidates, run -> ADD(S) for HFF6DoF's two rows
VAL_EPOCH = {("pvnet_simple", 2): 0.5, ("pvnet_simple", 1): 0.25, ("pvnet_hard", 1): 0.5, ("pvnet_hard", 2): 0.25}
VAL_OPTION = {("pvnet_simple", 0.9): 0.75, ("pvnet_hard", 0.99): 0.75}
VAL_ROW = {"hff6dof-3d_hard": 0.5, "hff6dof_simple": 0.5}


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A reproduce killed in its fourth training call (PVNet on hard, its second epoch, after its
    first epoch was validated), then resumed to the end; every training, prediction and scoring
    call logged with its part, and the jobs' ends in the same log."""
    out = tmp_path_factory.mktemp("repro") / "out"
    calls: list[tuple] = []
    log: list[tuple] = []
    real_train, real_predict, real_score, real_finish = R.train_run, R.predict_run, R.score_run, R.State.finish

    def flaky(root, split, run, method, cfg, epochs, show, stop_epoch=None, **options):
        calls.append((run.name, stop_epoch))
        if len(calls) == 4:
            raise Killed("simulated kill")
        return real_train(root, split, run, method, cfg, epochs, show, stop_epoch=stop_epoch, **options)

    def predict(run, root, split, out_csv, cfg, show, part="test", images=None, **options):
        log.append(("predict", part, out_csv.parent.name if part == "val" else out_csv.stem, out_csv.name, options))
        return real_predict(run, root, split, out_csv, cfg, show, part=part, images=images, **options)

    def scorer(results_csv, root, split, part="test", targets=None):
        s = real_score(results_csv, root, split, part=part, targets=targets)
        log.append(("score", part, results_csv.parent.name if part == "val" else results_csv.stem))
        if part == "val":
            name = results_csv.parent.name
            info = read_json(results_csv.with_name(results_csv.stem + "_info.json"))
            step = int(results_csv.stem[4:10])
            cos = info["method_config"].get("inlier_cos")
            s["mean"]["add_s"] = (VAL_EPOCH.get((name, step), 0.0) + VAL_OPTION.get((name, cos), 0.0)
                                  + VAL_ROW.get(name, 0.0))
        return s

    def finish(self, job, seconds, **info):
        log.append(("done", job))
        return real_finish(self, job, seconds, **info)

    mp = pytest.MonkeyPatch()
    mp.setattr(R, "train_run", flaky)
    mp.setattr(R, "predict_run", predict)
    mp.setattr(R, "score_run", scorer)
    mp.setattr(R.State, "finish", finish)
    try:
        with pytest.raises(Killed):
            reproduce(out, config=TEST, progress=False)
        state = read_json(out / "reproduce.json")
        first = dict(state["jobs"])
        first_val = json.loads(json.dumps(state.get("validation", {})))
        md = reproduce(out, config=TEST, progress=False)
    finally:
        mp.undo()
    return {"out": out, "md": md, "calls": calls, "first": first, "first_val": first_val, "log": log}


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
    # a finished training keeps its weights, not the optimiser's state; train refuses to go on with it
    from tdof20.methods.train import train

    ck = torch.load(out / "runs" / "hff6dof_simple" / "last.pt", map_location="cpu", weights_only=True)
    assert "model" in ck and "optimizer" not in ck and ck["step"] >= 1
    with pytest.raises(TdofError, match="holds the weights only") as e:
        train(out / "dataset", "simple", out / "runs" / "hff6dof_simple", image_size=(32, 32), epochs=5,
              progress=False)
    assert "last.pt" in str(e.value)


def test_resume_after_a_kill_reuses_finished_work(done):
    first, calls = done["first"], done["calls"]
    trained_first = [k for k in first if k.startswith("train/")]
    assert first["dataset"] and trained_first == ["train/pvnet_simple"]
    # PVNet on simple trained epoch by epoch; on hard epoch 1 was trained and validated, the kill came
    # in epoch 2; the resumed run did not train epoch 1 again (its figure was kept) but epoch 2
    assert calls[:5] == [("pvnet_simple", 1), ("pvnet_simple", 2), ("pvnet_hard", 1), ("pvnet_hard", 2),
                         ("pvnet_hard", 2)]
    assert all(calls.count((n, e)) == 1 for n, e in calls if n != "pvnet_hard")
    assert [f["step"] for f in done["first_val"]["pvnet_hard"]] == [1]
    val_predictions = [e for e in done["log"] if e[:3] == ("predict", "val", "pvnet_hard")]
    assert len(val_predictions) == len({(e[3], json.dumps(e[4], sort_keys=True)) for e in val_predictions})
    state = read_json(done["out"] / "reproduce.json")
    for k, v in first.items():
        assert state["jobs"][k] == v  # finished jobs kept as they were
    # a third call does no work at all
    again = reproduce(done["out"], config=TEST, progress=False)
    assert read_json(done["out"] / "reproduce.json")["jobs"] == state["jobs"] and again.exists()


def test_choices_are_the_validation_best_and_the_test_part_plays_no_part(done):
    out, log = done["out"], done["log"]
    state = read_json(out / "reproduce.json")
    jobs = state["jobs"]
    # the kept epoch is the validation-best one: epoch 2 on simple (the last), epoch 1 on hard
    for name, best, last in (("pvnet_simple", 2, 2), ("pvnet_hard", 1, 2)):
        j = jobs[f"train/{name}"]
        figs = {f["epoch"]: f["add_s"] for f in j["validation"]}
        assert sorted(figs) == [1, 2] and figs[1] != figs[2]
        assert j["kept_epoch"] == best == max(figs, key=figs.get) and j["epochs"] == last
        kept = out / "runs" / name / "kept"
        assert j["kept"] == str(kept) and read_json(kept / "kept.json")["epoch"] == best
        k = torch.load(kept / "last.pt", weights_only=True)
        last_pt = torch.load(out / "runs" / name / "last.pt", weights_only=True)
        assert k["epoch"] == best and last_pt["epoch"] == last
        same = all(torch.equal(k["model"][w], last_pt["model"][w]) for w in k["model"])
        assert same == (best == last)
        info = read_json(out / "results" / f"{name}_info.json")
        assert info["run"] == str(kept.resolve()) and info["part"] == "test"
    # PVNet's candidate inlier_cos chosen on validation and used for the test part
    for name, cos in (("pvnet_simple", 0.9), ("pvnet_hard", 0.99)):
        assert jobs[f"choose/{name}"]["options"] == {"inlier_cos": cos}
        assert [f["options"]["inlier_cos"] for f in jobs[f"choose/{name}"]["validation"]] == [0.99, 0.9]
        assert read_json(out / "results" / f"{name}_info.json")["method_config"]["inlier_cos"] == cos
    # HFF6DoF's two rows: bearing + PnP on simple, 3D voting + LSQ on hard; the claims use the choice
    assert jobs["choose/formulation/simple"]["primary"] == "hff6dof_simple"
    assert jobs["choose/formulation/hard"]["primary"] == "hff6dof-3d_hard"
    t = json.loads((out / "tables" / "tables.json").read_text())
    claim = [c for c in t["agreement"] if c["id"] == "hff6dof_hard_add_s"][0]
    assert "3D voting + LSQ" in claim["ours"]
    md = done["md"].read_text()
    assert "**Chosen on validation**" in md and "| pvnet_hard | epoch | epoch 1 of 2 (step 1) |" in md
    assert "| pvnet_simple | options | inlier_cos 0.9 |" in md
    assert {r["result"] for r in t["choices"]} >= {"pvnet_simple", "pvnet_hard", "HFF6DoF · simple", "HFF6DoF · hard"}
    # the test part is predicted and scored only by the predict/score jobs, after every choice; every
    # call inside a training or a choice is on the validation part
    done_at = {e[1]: i for i, e in enumerate(log) if e[0] == "done"}
    last_choice = max(i for j, i in done_at.items() if j.startswith(("choose/", "train/")))
    for i, e in enumerate(log):
        if e[0] in ("predict", "score"):
            job = next(log[k][1] for k in range(i, len(log)) if log[k][0] == "done")
            if e[1] == "test":
                assert job.startswith(("predict/", "score/")) and i > last_choice
            else:
                assert e[1] == "val" and job.startswith(("train/", "choose/"))
    assert any(e[:2] == ("score", "val") for e in log) and any(e[:2] == ("score", "test") for e in log)


def test_changed_config_is_refused(done):
    other = json.loads(json.dumps(TEST))
    other["epochs"]["pvnet"] = 3
    other["train"]["batch_size"] = 2
    other["candidates"]["pvnet"]["inlier_cos"] = [0.99]
    before = (done["out"] / "reproduce.json").read_bytes()
    with pytest.raises(TdofError, match=r"another config \(changed: candidates.pvnet.inlier_cos \[0.99, 0.9\] -> "
                                        r"\[0.99\]; epochs.pvnet 2 -> 3; train.batch_size 8 -> 2"):
        reproduce(done["out"], config=other, progress=False)
    other = json.loads(json.dumps(TEST))
    other["select"] = {"epochs": "last"}
    with pytest.raises(TdofError, match=r"changed: select.epochs 'best' -> 'last'"):
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
    for text, msg in (('[candidates.hff6dof]\nvoting = ["bearing", "3d"]\n', r"candidates.hff6dof.voting: not an option "
                       r"chosen on validation \(for hff6dof: depth_mode, "),
                      ('[candidates.hff6dof]\ndepth_mode = ["filled", "restored"]\n', "derived from the ground truth"),
                      ('[candidates.pvnet]\ninlier_cos = []\n', "must be a non-empty list"),
                      ('[candidates.ffb6d]\ndepth_mode = ["raw", "raw"]\n', "lists a value twice"),
                      ('[candidates.ffb6d]\ndepth_mode = ["raw", "holes"]\n', r"candidates.ffb6d.depth_mode: "),
                      ('[candidates.posecnn]\nx = [1]\n', "unknown candidates.posecnn"),
                      ('[select]\nepochs = "first"\n', "select.epochs must be one of best, last")):
        bad.write_text(text)
        with pytest.raises(TdofError, match=msg):
            make_config(None, bad)
    bad.write_text('[method_options.ffb6d]\nn_pts = 3\n')
    with pytest.raises(TdofError, match=r"method_options.ffb6d: unknown option 'n_pts'"):
        make_config(None, bad)
    ok = tmp_path / "ok.toml"
    ok.write_text('preset = "cpu"\nmethods = ["hff6dof"]\n[epochs]\nhff6dof = 3\n')
    c = make_config(None, ok)
    assert c.preset == "cpu" and c.methods == ("hff6dof",) and c.epochs.hff6dof == 3 and c.data.steps == 12
    assert c.candidates["hff6dof"]["depth_mode"] == ["filled", "raw"] and c.select.every == 2
    assert make_config("smoke").candidates == {} and make_config("smoke").select.epochs == "best"


@pytest.mark.parametrize("toml,needle", [
    ("[train]\nnum_workers = -1\n", "train.num_workers must be >= 0"),
    ("[train]\nimage_size = [100000, 100000]\n", "train.image_size must be within 4096"),
    ("[data]\nseed = -1\n", "data.seed must be >= 0"),
    ('[data]\nscenes = ["multi/08", "multi/08"]\n', "data.scenes names a scene twice"),
    ('[data]\nscenes = ["single/nope"]\n', "data.scenes: unknown scene 'single/nope'"),
    ('device = "tpu"\n', "device"),
])
def test_config_values_that_would_fail_later_are_refused_first(tmp_path, toml, needle):
    """Refused before anything is written, naming the TOML file (they failed after the dataset was
    simulated, some as tracebacks)."""
    cfg = tmp_path / "x.toml"
    cfg.write_text(toml)
    with pytest.raises(TdofError) as e:
        reproduce(tmp_path / "o", config=cfg, progress=False)
    assert str(cfg) in str(e.value) and needle in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "o").exists()


def test_digest_ignores_the_simulated_scenes_with_a_given_dataset(tmp_path):
    """With --dataset the [data] table is not used: changing it does not refuse a resume; without a
    dataset it does."""
    a, b = {"data": {"steps": 6}}, {"data": {"steps": 12}}
    assert R.config_digest(make_config("smoke", a, tmp_path)) == R.config_digest(make_config("smoke", b, tmp_path))
    assert R.config_digest(make_config("smoke", a)) != R.config_digest(make_config("smoke", b))
    assert R.config_digest(make_config("smoke", a, tmp_path)) != R.config_digest(make_config("smoke", a))


def test_cli_command(tmp_path):
    from typer.testing import CliRunner

    from tdof20.cli import app

    res = CliRunner().invoke(app, ["reproduce", "--out", str(tmp_path / "o"), "--preset", "huge"])
    assert isinstance(res.exception, TdofError) and "preset must be one of" in str(res.exception)
    assert not (tmp_path / "o").exists()
    res = CliRunner().invoke(app, ["reproduce", "--out", str(tmp_path / "o"), "--dataset", str(tmp_path)])
    assert isinstance(res.exception, TdofError) and not (tmp_path / "o").exists()


def test_validation_arcs_are_contiguous_and_apart_from_test():
    from tdof20.dataset.splits import simple_test_steps

    steps, arms = 40, 4
    images = [(12, a * steps + k) for a in range(arms) for k in range(steps)
              if k not in simple_test_steps(a, steps, arms)]
    train, val = validation_images(images, "simple", steps, arms, 0.1)
    assert len(train) + len(val) == len(images) and not set(train) & set(val)
    for a in range(arms):
        ks = sorted(im - a * steps for _, im in val if im // steps == a)
        assert len(ks) == 4 and (ks[-1] - ks[0]) % steps == 3  # one arc of 4 steps
        assert not set(ks) & simple_test_steps(a, steps, arms)
