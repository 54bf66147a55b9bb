"""``tdof20 reproduce`` end to end on a config still smaller than smoke: a simulated dataset
(single/12 = juice_cup_340 and multi/08, 2 arm positions x 7 steps at 64x48), every method trained
on both protocols with the same budget (8 images: two steps of 4), the fusion ablation with 1 and 3
stages, the segmentation ablation, two candidate sets chosen on validation for every compared
row, predictions, scores and the tables; PVNet alone with 16 images (two epochs, one chosen on
validation) killed half-way and resumed; a changed config refused, the unfair configs refused,
and the segmentation ablation's masks. Table 3's profiling is left out here (its own tests:
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
        "train": {"image_size": [32, 48], "batch_size": 4, "images": 8, "num_workers": 0},
        "ablations": {"fuse_stages": [1, 3], "segmentation": True, "voting_3d": True},
        "profile": {"enabled": False}, "device": "cpu",
        "method_options": {"ffb6d": {"n_points": 256, "meanshift_iters": 5, "max_votes": 200},
                           "densefusion": {"n_points": 100, "crop_size": 32, "min_points": 10},
                           "pvnet": {"max_rounds": 2}, "hff6dof": {"n_hyp": 32, "max_points": 200}},
        "candidates": {"pvnet": {"inlier_cos": [0.99, 0.9]}, "hff6dof": {"depth_mode": ["filled", "raw"]},
                       "densefusion": {"refine_iterations": [1, 0]}, "ffb6d": {"bandwidth_mm": [40.0, 20.0]}}}


#: PVNet alone, two epochs (16 images), its epoch and its inlier_cos chosen on validation
PVNET = {**json.loads(json.dumps(TEST)), "methods": ["pvnet"], "train": {**TEST["train"], "batch_size": 8,
                                                                          "images": 16},
         "ablations": {"fuse_stages": [], "segmentation": False, "voting_3d": False},
         "candidates": {"pvnet": {"inlier_cos": [0.99, 0.9]}}}


class Killed(RuntimeError):
    pass


#: validation figures the test imposes (on top of the real scorer's, which a one-step training
#: leaves at 0 % everywhere, so that every choice would be a tie): (run, step) -> ADD(S) for the
#: epochs, (run, inlier_cos) for PVNet's candidates, run -> ADD(S) for HFF6DoF's two rows
VAL_EPOCH = {("pvnet_simple", 2): 0.5, ("pvnet_simple", 1): 0.25, ("pvnet_hard", 1): 0.5, ("pvnet_hard", 2): 0.25}
VAL_OPTION = {("pvnet_simple", 0.9): 0.75, ("pvnet_hard", 0.99): 0.75}
VAL_EPOCH = {(f"{r}_s0", k): v for (r, k), v in VAL_EPOCH.items()}
VAL_OPTION = {(f"{r}_s0", k): v for (r, k), v in VAL_OPTION.items()}


def _run(out, config, kill_at=None, **kw):
    """A reproduce of ``config`` into ``out``, killed in its ``kill_at``-th training call (then
    resumed to the end); every training, prediction and scoring call logged with its part, and the
    jobs' ends in the same log."""
    calls: list[tuple] = []
    log: list[tuple] = []
    real_train, real_predict, real_score, real_finish = R.train_run, R.predict_run, R.score_run, R.State.finish

    def flaky(root, split, run, method, cfg, schedule, show, stop_epoch=None, **options):
        calls.append((run.name, stop_epoch))
        log.append(("train", run.name, dict(schedule)))
        if len(calls) == kill_at:
            raise Killed("simulated kill")
        return real_train(root, split, run, method, cfg, schedule, show, stop_epoch=stop_epoch, **options)

    def predict(run, root, split, out_csv, cfg, show, part="test", images=None, seed=0, **options):
        log.append(("predict", part, out_csv.parent.name if part == "val" else out_csv.stem, out_csv.name, options))
        return real_predict(run, root, split, out_csv, cfg, show, part=part, images=images, seed=seed, **options)

    def scorer(results_csv, root, split, part="test", targets=None):
        s = real_score(results_csv, root, split, part=part, targets=targets)
        log.append(("score", part, results_csv.parent.name if part == "val" else results_csv.stem))
        if part == "val":
            name = results_csv.parent.name
            info = read_json(results_csv.with_name(results_csv.stem + "_info.json"))
            step = int(results_csv.stem[4:10])
            cos = info["method_config"].get("inlier_cos")
            s["mean"]["add_s"] = VAL_EPOCH.get((name, step), 0.0) + VAL_OPTION.get((name, cos), 0.0)
        return s

    def finish(self, job, seconds, **info):
        log.append(("done", job))
        return real_finish(self, job, seconds, **info)

    mp = pytest.MonkeyPatch()
    mp.setattr(R, "train_run", flaky)
    mp.setattr(R, "predict_run", predict)
    mp.setattr(R, "score_run", scorer)
    mp.setattr(R.State, "finish", finish)
    first, first_val = {}, {}
    try:
        if kill_at:
            with pytest.raises(Killed):
                reproduce(out, config=config, progress=False)
            state = read_json(out / "reproduce.json")
            first = dict(state["jobs"])
            first_val = json.loads(json.dumps(state.get("validation", {})))
        md = reproduce(out, config=config, progress=False, **kw)
    finally:
        mp.undo()
    return {"out": out, "md": md, "calls": calls, "first": first, "first_val": first_val, "log": log}


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """Every method, both protocols, both ablations, to the end."""
    return _run(tmp_path_factory.mktemp("repro") / "out", TEST)


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """PVNet alone killed in its fourth training call (on hard, its second epoch, after its first
    epoch was validated), then resumed to the end."""
    return _run(tmp_path_factory.mktemp("repro") / "out", PVNET, kill_at=4)


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
    assert all(c["present"] and c["seeds"] == 1 for c in t["table1"]["columns"])
    body = list(csv.reader(io.StringIO((out / "tables" / "table2_proj2d.csv").read_text())))
    assert len(body) == 1 + len(objs) + 1 and len(body[0]) == 3 + 10  # one seed: no spread columns
    fz = {r["fuse_stages"]: r for r in t["ablation_fusion"]["rows"]}
    assert fz[1]["add_s"] is not None and fz[3]["add_s"] is not None and fz[2]["add_s"] is None
    assert {c["id"] for c in t["agreement"]} >= {"hff6dof_hard_add_s", "best_fuse_stages", "seg_gain_add_s"}
    # one seed: no claim about a difference between rows is judged
    verdicts = {c["id"]: c["agrees"] for c in t["agreement"]}
    assert verdicts["best_fuse_stages"] is None and verdicts["simple_above_hard"] is None
    for m in ("PVNet", "DenseFusion", "FFB6D", "HFF6DoF__bearing___PnP", "HFF6DoF__3D_voting___LSQ"):
        assert (out / "tables" / "plots" / f"accuracy_{m}.png").stat().st_size > 2000
    state = read_json(out / "reproduce.json")
    assert all(not k.startswith("train/") or (out / "runs" / k[6:] / "last.pt").exists() for k in state["jobs"])
    trains = {k: v for k, v in state["jobs"].items() if k.startswith("train/")}
    # this version has the separately trained segmentation network (it once looked for it among the
    # pose methods only, found none, and gave the ablation ground-truth masks without a word in a test)
    assert R.segnet_available() is True
    # 4 methods x 2 protocols, hff6dof-3d on both, fuse1, noseg + the segmentation network
    assert len(trains) == 4 * 2 + 2 + 2 + 1
    # the same budget for every compared row: 16 images seen, whatever the method; the row without
    # the head counts the segmentation network's images in its own
    seen = {k[6:-3]: v["images_seen"] for k, v in trains.items()}
    row = {k: v for k, v in seen.items() if k not in ("hff6dof_noseg_hard", "segnet_hard")}
    assert set(row.values()) == {8}
    assert seen["hff6dof_noseg_hard"] + seen.get("segnet_hard", 0) == 8
    assert "8 images seen" in md and "1 seed(s) per row" in md
    # a finished training keeps its weights, not the optimiser's state; train refuses to go on with it
    from tdof20.methods.train import train

    ck = torch.load(out / "runs" / "hff6dof_simple_s0" / "last.pt", map_location="cpu", weights_only=True)
    assert "model" in ck and "optimizer" not in ck and ck["step"] == 2
    with pytest.raises(TdofError, match="holds the weights only") as e:
        train(out / "dataset", "simple", out / "runs" / "hff6dof_simple_s0", image_size=(32, 32), epochs=5,
              progress=False)
    assert "last.pt" in str(e.value)


def test_resume_after_a_kill_reuses_finished_work(killed):
    done = killed
    first, calls = done["first"], done["calls"]
    trained_first = [k for k in first if k.startswith("train/")]
    assert first["dataset"] and trained_first == ["train/pvnet_simple_s0"]
    # PVNet on simple trained epoch by epoch; on hard epoch 1 was trained and validated, the kill came
    # in epoch 2; the resumed run did not train epoch 1 again (its figure was kept) but epoch 2
    assert calls[:5] == [("pvnet_simple_s0", 1), ("pvnet_simple_s0", 2), ("pvnet_hard_s0", 1),
                         ("pvnet_hard_s0", 2), ("pvnet_hard_s0", 2)]
    assert all(calls.count((n, e)) == 1 for n, e in calls if n != "pvnet_hard_s0")
    assert [f["step"] for f in done["first_val"]["pvnet_hard_s0"]] == [1]
    val_predictions = [e for e in done["log"] if e[:3] == ("predict", "val", "pvnet_hard_s0")]
    assert len(val_predictions) == len({(e[3], json.dumps(e[4], sort_keys=True)) for e in val_predictions})
    state = read_json(done["out"] / "reproduce.json")
    for k, v in first.items():
        assert state["jobs"][k] == v  # finished jobs kept as they were
    # a third call does no work at all
    again = reproduce(done["out"], config=PVNET, progress=False)
    assert read_json(done["out"] / "reproduce.json")["jobs"] == state["jobs"] and again.exists()


def test_every_training_gets_the_same_schedule_from_the_budget(done, killed):
    """The schedule each training call got: 2 steps of 4 images (8 seen), 1 epoch, seed 0; PVNet
    alone with 16 images: 2 steps of 8, 2 epochs."""
    scheds = {e[1]: e[2] for e in done["log"] if e[0] == "train" and not e[1].startswith("segnet")}
    assert len(scheds) == 12
    assert all((v["batch"], v["steps"], v["images_seen"], v["epochs"], v["seed"]) == (4, 2, 8, 1, 0)
               for k, v in scheds.items() if "noseg" not in k)
    scheds = {e[1]: e[2] for e in killed["log"] if e[0] == "train"}
    assert set(scheds) == {"pvnet_simple_s0", "pvnet_hard_s0"}
    assert all(v["steps"] == 2 and v["epochs"] == 2 and v["images_seen"] == 16 for v in scheds.values())


def test_choices_are_the_validation_best_and_the_test_part_plays_no_part(done, killed):
    out, log = killed["out"], killed["log"]
    state = read_json(out / "reproduce.json")
    jobs = state["jobs"]
    # the kept epoch is the validation-best one: epoch 2 on simple (the last), epoch 1 on hard
    for name, best, last in (("pvnet_simple_s0", 2, 2), ("pvnet_hard_s0", 1, 2)):
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
    for name, cos in (("pvnet_simple_s0", 0.9), ("pvnet_hard_s0", 0.99)):
        assert jobs[f"choose/{name}"]["options"] == {"inlier_cos": cos}
        assert [f["options"]["inlier_cos"] for f in jobs[f"choose/{name}"]["validation"]] == [0.99, 0.9]
        assert read_json(out / "results" / f"{name}_info.json")["method_config"]["inlier_cos"] == cos
    md = killed["md"].read_text()
    assert "**Chosen on validation**" in md and "| pvnet_hard_s0 | epoch | epoch 1 of 2 (step 1) |" in md
    assert "| pvnet_simple_s0 | options | inlier_cos 0.9 |" in md
    t = json.loads((out / "tables" / "tables.json").read_text())
    assert {r["result"] for r in t["choices"]} >= {"pvnet_simple_s0", "pvnet_hard_s0"}
    # every compared row chose among two candidate sets; HFF6DoF's two pose recoveries are two rows,
    # none chosen between: the claims take the default one (bearing + PnP)
    jobs = read_json(done["out"] / "reproduce.json")["jobs"]
    chooses = [k for k in jobs if k.startswith("choose/")]
    assert len(chooses) == 10 and all(len(jobs[k]["validation"]) == 2 for k in chooses)
    assert not any("formulation" in k for k in jobs)
    t = json.loads((done["out"] / "tables" / "tables.json").read_text())
    claim = [c for c in t["agreement"] if c["id"] == "hff6dof_hard_add_s"][0]
    assert "bearing + PnP" in claim["ours"]
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


def test_validation_only_never_touches_test_and_the_same_line_goes_on(tmp_path):
    """--validation-only: the trainings and choices, no test prediction nor score; its tables give each
    result's validation figure with the options its test prediction will use (the chosen inlier_cos,
    not the first candidate the epochs were validated with); the same call without it then predicts
    the test part and trains nothing again."""
    out = tmp_path / "out"
    v = _run(out, PVNET, validation_only=True)
    assert v["log"] and not [e for e in v["log"] if e[0] in ("predict", "score") and e[1] != "val"]
    assert not (out / "results").exists() and not (out / "scores").exists()
    jobs = read_json(out / "reproduce.json")["jobs"]
    assert {k.split("/")[0] for k in jobs} == {"dataset", "train", "choose"}
    md = v["md"].read_text()
    assert "**On validation**" in md and "Validation only (--validation-only)" in md
    rows = list(csv.DictReader(io.StringIO((out / "tables" / "validation.csv").read_text())))
    assert sorted((r["result"], r["protocol"], float(r["add_s"])) for r in rows) == [("PVNet", "hard", 1.25),
                                                                                 ("PVNet", "simple", 1.25)]
    val = json.loads((out / "tables" / "tables.json").read_text())["validation"]
    by = {r["split"]: r for r in val}
    # simple: epoch 2 (0.5) + inlier_cos 0.9 (0.75), chosen over 0.99's 0.5; hard: epoch 1 (0.5) + 0.99 (0.75)
    assert by["simple"]["add_s"] == pytest.approx(1.25) and by["hard"]["add_s"] == pytest.approx(1.25)
    assert all(r["same_options"] and r["seeds"] == [0] for r in val)
    g = _run(out, PVNET)
    assert not [e for e in g["log"] if e[0] == "train"]
    assert {e[2] for e in g["log"] if e[:2] == ("predict", "test")} == {"pvnet_simple_s0", "pvnet_hard_s0"}
    assert "Validation only" not in g["md"].read_text() and (out / "tables" / "table1_add_s.csv").exists()


def test_changed_config_is_refused(killed):
    done = killed
    other = json.loads(json.dumps(PVNET))
    other["train"]["images"] = 24
    other["train"]["batch_size"] = 4
    other["candidates"]["pvnet"]["inlier_cos"] = [0.99, 0.8]
    before = (done["out"] / "reproduce.json").read_bytes()
    with pytest.raises(TdofError, match=r"another config \(changed: candidates.pvnet.inlier_cos \[0.99, 0.9\] -> "
                                        r"\[0.99, 0.8\]; train.batch_size 8 -> 4; train.images 16 -> 24"):
        reproduce(done["out"], config=other, progress=False)
    other = json.loads(json.dumps(PVNET))
    other["select"] = {"epochs": "last"}
    with pytest.raises(TdofError, match=r"changed: select.epochs 'best' -> 'last'"):
        reproduce(done["out"], config=other, progress=False)
    with pytest.raises(TdofError, match="preset"):
        reproduce(done["out"], preset="cpu", config=PVNET, progress=False)
    assert (done["out"] / "reproduce.json").read_bytes() == before
    other = json.loads(json.dumps(PVNET))
    other["device"] = "auto"  # the device changes no result: accepted (nothing left to do)
    reproduce(done["out"], config=other, progress=False)


def test_segmentation_ablation_masks(done):
    """Without the head, the row takes the masks of the separately trained segmentation network
    (its training counted in the row's budget): no oracle in a compared row."""
    out = done["out"]
    s = read_json(out / "scores" / "hff6dof_noseg_hard_s0.json")
    assert read_json(out / "scores" / "hff6dof_hard_s0.json")["oracle_masks"] is False
    md = done["md"].read_text()
    t = json.loads((out / "tables" / "tables.json").read_text())
    claim = [c for c in t["agreement"] if c["id"] == "seg_gain_add_s"][0]
    assert s["oracle_masks"] is False and s["budget"]["segnet_images_seen"] + s["budget"]["images_seen"] == 8
    assert read_json(out / "results" / "hff6dof_noseg_hard_s0_info.json")["masks"] == "segnet"
    assert "separately trained segmentation network" in md
    assert t["ablation_segmentation"]["rows"][1]["oracle_masks"] is False
    assert "oracle" not in claim["ours"]


@pytest.mark.parametrize("toml,needle", [
    ('[method_options.hff6dof]\nmasks = "gt"\n',
     r"method_options.hff6dof.masks: the compared row 'HFF6DoF \(bearing \+ PnP\)' would predict with "
     r"ground-truth masks, a privileged input: refused"),
    ('[method_options.densefusion]\ndepth_mode = "restored"\n',
     r"method_options.densefusion.depth_mode: the compared row 'DenseFusion' would predict with restored depth"),
    ('[candidates.pvnet]\ninlier_cos = [0.99, 0.97]\n',
     r"different numbers of candidate sets chosen on validation \(PVNet 2, DenseFusion 1, FFB6D 1, "),
    ('[train]\nimages = 10\n[batch]\npvnet = 4\n', r"train.images \(10\) must be a multiple of every method's batch"),
])
def test_unfair_configs_are_refused_in_one_line(tmp_path, toml, needle):
    cfg = tmp_path / "x.toml"
    cfg.write_text('preset = "smoke"\n' + toml)
    with pytest.raises(TdofError, match=needle) as e:
        make_config(None, cfg)
    assert str(cfg) in str(e.value) and "\n" not in str(e.value)


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
    ok.write_text('preset = "cpu"\nmethods = ["hff6dof"]\n[train]\nimages = 96\n[batch]\nhff6dof = 8\n')
    c = make_config(None, ok)
    assert c.preset == "cpu" and c.methods == ("hff6dof",) and c.train.images == 96 and c.batch_of("hff6dof") == 8
    assert c.data.steps == 12 and c.train.seeds == (0, 1)
    assert c.candidates["hff6dof"]["depth_mode"] == ["filled", "raw"] and c.select.every == 1
    assert make_config("smoke").candidates == {} and make_config("smoke").select.epochs == "best"
    bad.write_text('[train]\nseeds = [0, 0]\n')
    with pytest.raises(TdofError, match="train.seeds names a seed twice"):
        make_config(None, bad)


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
