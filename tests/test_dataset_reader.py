"""The one dataset reader (tdof20.dataset.reader) on a standard-layout BOP dataset written by the
independent fixture tests/fixtures/bop_standard.py (objects 1, 5 and 30; train_pbr and test split
folders; models_eval; test_targets_bop19.json; no restored depth), and on a tdof20 dataset built
with ``--layout bop``: stats, restored depth rendered once and cached, a few HFF6DoF steps,
prediction and scoring with objects numbered 1, 5, 30, and the one "not a dataset" line."""

from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest

from tdof20.errors import TdofError
from tdof20.dataset.reader import NOT_A_DATASET, composite_model_depth, open_dataset
from tdof20.formats.io import read_png

from fixtures.bop_standard import write_bop_dataset

pytestmark = pytest.mark.usefixtures("one_torch_thread")
OBJ_IDS = (1, 5, 30)


def cli(capsys, *args):
    """Run the console script in-process: (exit code, the last stderr line, stdout)."""
    import sys

    from tdof20.cli import main

    argv = sys.argv
    sys.argv = ["tdof20", *map(str, args)]
    try:
        main()
        rc = 0
    except SystemExit as e:
        rc = e.code or 0
    finally:
        sys.argv = argv
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, (cap.err.strip().splitlines() or [""])[-1], cap.out


@pytest.fixture(scope="module")
def bop(tmp_path_factory):
    root = tmp_path_factory.mktemp("bop") / "ds"
    truth = write_bop_dataset(root, obj_ids=OBJ_IDS, splits=("train_pbr", "test"), scenes_per_split=1,
                              images_per_scene=4, size=(64, 48), seed=0, rgb_ext={"train_pbr": "jpg"})
    return truth


def test_the_reader_answers_for_a_standard_bop_dataset(bop):
    root = bop["root"]
    ds = open_dataset(root)
    assert ds.layout == "bop" and ds.splits() == ["test", "train_pbr"]
    assert ds.obj_ids == list(OBJ_IDS) and ds.object_name(5) == "obj_000005"
    assert ds.models_eval_dir == root / "models_eval" and ds.targets_split() == "test"
    assert ds.scene_ids("train_pbr") == [0] and ds.scene_ids("test") == [1]
    assert ds.frames("train_pbr", "train") == [(0, i) for i in range(4)]
    assert ds.frames("test", "test") == sorted({(t["scene_id"], t["im_id"]) for t in bop["targets"]})
    assert ds.rgb_path(0, 2, "train_pbr").suffix == ".jpg" and ds.rgb_path(1, 2, "test").suffix == ".png"
    assert ds.scene(0, "train_pbr").rgb(2).shape == (48, 64, 3)  # a JPEG colour image
    assert ds.depth_modes("test") == ("raw", "filled", "restored") and ds.restored_source("test") == "rendered"
    kp = ds.keypoints()
    assert sorted(kp) == list(OBJ_IDS) and all(v.shape == (9, 3) for v in kp.values())
    # the poses as the fixture wrote them
    for sid, sc in bop["splits"]["test"].items():
        for im, frame in sc["images"].items():
            for g, p in enumerate(frame["poses"]):
                R, t = ds.scene(sid, "test").pose(im, g)
                assert np.allclose(R, p["R"], atol=1e-9) and np.allclose(t, p["t_mm"], atol=1e-9)
    with pytest.raises(TdofError, match="give a split"):
        ds.scene_ids()
    with pytest.raises(TdofError, match="no split folder 'val'"):
        ds.frames("val")


def test_names_file_names_the_objects(bop, tmp_path):
    names = tmp_path / "names.json"
    names.write_text(json.dumps({"1": "mug", "5": "can", "30": "box"}))
    assert open_dataset(bop["root"], names=names).object_name(30) == "box"


def test_stats_of_a_bop_dataset(bop, capsys):
    from tdof20.dataset.build import stats

    st = stats(bop["root"])
    assert st["layout"] == "bop" and st["images"] == 8 and st["scenes"] == 2
    assert st["split_folders"]["train_pbr"]["images"] == 4
    assert st["split_folders"]["test"]["targets"] == len(bop["targets"]) == st["splits"]["targets"]
    assert st["per_object"] == {1: 8, 5: 8, 30: 8} and st["objects"][30] == "obj_000030"
    rc, _, out = cli(capsys, "dataset", "stats", bop["root"])
    assert rc == 0 and "obj_000030" in out and "train_pbr" in out


def test_restored_depth_is_rendered_once_and_cached(bop, tmp_path):
    ds = open_dataset(bop["root"])
    frames = ds.frames("test", "test")
    assert ds.missing_restored(frames, "test") == frames
    assert ds.render_restored(frames, "test", show_progress=False) == len(frames)
    p = ds.restored_path(*frames[0], "test")
    assert p is not None and p.is_relative_to(bop["root"] / ".cache" / "depth_restored" / "test")
    stamp = p.stat().st_mtime_ns
    assert open_dataset(bop["root"]).render_restored(frames, "test", show_progress=False) == 0  # cached
    assert p.stat().st_mtime_ns == stamp
    # the fixture's scene is opaque: the restored depth is its true depth where the sensor has it
    # (or where it has a hole on an object), within the rounding of the depth units
    sid, im = frames[0]
    truth = bop["splits"]["test"][sid]["images"][im]
    scale = bop["splits"]["test"][sid]["depth_scale"]
    rest = read_png(p, kind="depth").astype(np.float32) * scale
    raw = read_png(ds.depth_path(sid, im, "raw", "test"), kind="depth").astype(np.float32) * scale
    obj = truth["inst"] >= 0
    assert np.all(rest[raw > 0] <= raw[raw > 0] + 1e-3)
    holes = obj & (raw == 0)
    assert holes.any() and np.abs(rest[holes] - truth["depth_mm"][holes]).max() < 0.6 * scale + 0.5
    assert np.abs(rest[obj] - truth["depth_mm"][obj]).max() < 0.6 * scale + 0.5


def test_a_read_only_root_takes_a_cache_folder(bop, tmp_path):
    import shutil

    ro = tmp_path / "ro"
    shutil.copytree(bop["root"], ro, ignore=shutil.ignore_patterns(".cache"))
    os.chmod(ro, 0o555)
    (tmp_path / "a_file").write_text("x")
    try:
        if os.geteuid() != 0:  # root writes anywhere: a cache under a file stands in for read-only
            ds = open_dataset(ro)
            with pytest.raises(TdofError, match="not writable.*--cache-dir"):
                ds.render_restored(ds.frames("train_pbr"), "train_pbr", show_progress=False)
        ds = open_dataset(ro, cache_dir=tmp_path / "a_file" / "cache")
        with pytest.raises(TdofError, match="not writable.*--cache-dir"):
            ds.render_restored(ds.frames("train_pbr"), "train_pbr", show_progress=False)
        assert sorted(p.name for p in ro.iterdir()) == sorted(p.name for p in bop["root"].iterdir() if p.name != ".cache")
        ds = open_dataset(ro, cache_dir=tmp_path / "cache")
        assert ds.render_restored(ds.frames("train_pbr")[:1], "train_pbr", show_progress=False) == 1
        assert (tmp_path / "cache" / "depth_restored" / "train_pbr" / "000000" / "000000.png").is_file()
    finally:
        os.chmod(ro, 0o755)


def test_composite_takes_the_model_where_nearer_or_the_sensor_has_none():
    sensor = np.array([[0.0, 500.0, 500.0, 0.0]], np.float32)
    model = np.array([[400.0, 450.0, 600.0, 0.0]], np.float32)
    assert composite_model_depth(sensor, model).tolist() == [[400.0, 450.0, 500.0, 0.0]]


def test_not_a_dataset_is_one_line_everywhere(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "test").mkdir()  # a split folder without scenes is no BOP dataset
    line = f"error: {empty}: {NOT_A_DATASET}"
    for args in (("dataset", "stats", empty),
                 ("dataset", "pack", empty, "--split", "simple", "--part", "train", "--out", tmp_path / "x.h5"),
                 ("train", "hff6dof", "--dataset", empty, "--split", "simple", "--out", tmp_path / "run"),
                 ("predict", tmp_path / "run", "--dataset", empty, "--split", "simple", "--out", tmp_path / "r.csv"),
                 ("benchmark", "score", tmp_path / "r.csv", "--dataset", empty, "--split", "simple")):
        rc, err, _ = cli(capsys, *args)
        assert rc == 2 and err == line, args
    assert not (tmp_path / "run").exists() and not (tmp_path / "x.h5").exists()


def test_train_predict_score_on_a_bop_dataset_with_objects_1_5_30(bop, tmp_path):
    from tdof20.scoring.scoring import score
    from tdof20.methods.predict import predict
    from tdof20.methods.train import load_run, train

    root = bop["root"]
    run = train(root, "train_pbr", tmp_path / "run", image_size=(32, 48), batch_size=2, max_steps=2, lr=1e-3,
                num_workers=0, device="cpu", progress=False)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["classes"] == list(OBJ_IDS) and cfg["network"]["n_classes"] == 4 and cfg["layout"] == "bop"
    assert sorted(int(k) for k in cfg["keypoints"]) == list(OBJ_IDS)
    assert (root / ".cache" / "depth_restored" / "train_pbr" / "000000").is_dir()  # rendered for training
    import h5py
    with h5py.File(run / "data" / "train_pbr_train.h5") as f:
        assert f["depth_restored"][:].max() > 0 and set(np.unique(f["label"][:])) <= {0, *OBJ_IDS}
    out = predict(run, root, "test", tmp_path / "res.csv", device="cpu", num_workers=0, masks="gt", progress=False)
    with open(out) as f:
        rows = list(csv.DictReader(f))
    # two training steps: a pose may be dropped as impossible or fail to vote (no row), so the rows
    # are checked for what they name, and the summary for every test image predicted
    info = json.loads((tmp_path / "res_info.json").read_text())
    assert info["images"] == len({(t["scene_id"], t["im_id"]) for t in bop["targets"]})
    assert info["predictions"] == len(rows)
    assert {int(r["obj_id"]) for r in rows} <= set(OBJ_IDS) and {int(r["scene_id"]) for r in rows} <= {1}
    s = score(out, root, "test", metrics="add,proj,mssd,mspd")
    assert sorted(int(k) for k in s["objects"]) == list(OBJ_IDS)
    assert s["all"]["n"] == len(bop["targets"])
    # a run recorded before class lists (config without "classes") reads as ids 1..n_classes-1
    from tdof20.methods.train import run_classes
    assert run_classes({"network": {"n_classes": 21}}) == list(range(1, 21))
    net, _ = load_run(run)
    assert net is not None


def test_predict_renders_restored_depth_into_a_cache_folder(bop, tmp_path):
    """predict(cache_dir=) (`tdof20 predict --cache-dir`), as train: a run on restored depth predicts
    a dataset without it, rendering into the given folder, not into ROOT/.cache."""
    from tdof20.methods.predict import predict
    from tdof20.methods.train import train

    root, cache = bop["root"], tmp_path / "cache"
    run = train(root, "train_pbr", tmp_path / "run", image_size=(32, 48), batch_size=2, max_steps=0,
                depth_mode="restored", num_workers=0, device="cpu", progress=False, cache_dir=cache)
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    out = predict(run, root, "test", tmp_path / "res.csv", device="cpu", num_workers=0, masks="gt", progress=False,
                  cache_dir=cache)
    assert json.loads((tmp_path / "res_info.json").read_text())["depth_mode"] == "restored"
    assert out.is_file() and sorted((cache / "depth_restored" / "test").rglob("*.png"))
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before


def test_score_command_names_the_bop_objects(bop, tmp_path, capsys):
    from tdof20.dataset.reader import open_dataset as od

    ds = od(bop["root"], "test")
    sid, im = ds.frames("test", "test")[0]
    sc = ds.scene(sid)
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for g, e in enumerate(sc.gt[im]):
        R, t = sc.pose(im, g)
        lines.append(f"{sid},{im},{e['obj_id']},1.0,{' '.join(map(str, R.reshape(-1)))},{' '.join(map(str, t))},0.1")
    (tmp_path / "gt.csv").write_text("\n".join(lines) + "\n")
    rc, _, out = cli(capsys, "benchmark", "score", tmp_path / "gt.csv", "--dataset", bop["root"], "--split", "test",
                     "--metrics", "add,proj")
    assert rc == 0 and "obj_000030" in out
    rc, err, _ = cli(capsys, "benchmark", "score", tmp_path / "gt.csv", "--dataset", bop["root"], "--split",
                     "train_pbr")
    assert rc == 2 and "holds the targets of the split folder test/" in err
    # a results file made by `tdof20 predict` has its sidecar: the scorer says how it was made, and
    # marks poses recovered on ground-truth masks in its output, its JSON and report.md
    (tmp_path / "gt_info.json").write_text(json.dumps({"method": "pvnet", "input": "rgb", "depth_mode": "none",
                                                       "masks": "gt", "method_config": {"vote_max_pixels": 100}}))
    rc, _, out = cli(capsys, "benchmark", "score", tmp_path / "gt.csv", "--dataset", bop["root"], "--split", "test",
                     "--metrics", "add,proj", "--json", tmp_path / "s.json", "--plots", tmp_path / "plots")
    assert rc == 0
    text = " ".join(out.split())  # the console wraps long lines
    assert 'gt: method pvnet (rgb), depth none, masks gt ORACLE MASKS' in text and '"vote_max_pixels": 100' in text
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["run"]["oracle_masks"] is True and summary["run"]["method"] == "pvnet"
    assert "ORACLE MASKS" in (tmp_path / "plots" / "report.md").read_text()


# ------------------------------------------------------------------------------ --layout bop


@pytest.fixture(scope="module")
def annotated(tmp_path_factory):
    """Two simulated, oracle-labelled scenes: a single-object one (simple and hard train) and multi/02
    (a hard test scene)."""
    from tdof20.capture import run_capture, sim_config
    from tdof20.sim.truth import oracle_scene

    base = tmp_path_factory.mktemp("sim")
    out = []
    for sc, steps, deg, arms in (("single/01", 4, 10.0, 2), ("multi/02", 1, 30.0, 2)):
        raw = base / "raw" / sc.replace("/", "_")
        run_capture(sim_config(sc, steps=steps, step_deg=deg, n_arms=arms, width=64, height=48), raw, yes=True,
                    show_progress=False)
        out.append(oracle_scene(raw, base / "labels" / sc.replace("/", "_"), show_progress=False))
    return base, out


def _bop_json(path):
    """Read a scene JSON the way bop_toolkit's inout.load_json(keys_to_int=True) and load_scene_gt /
    load_scene_camera do: int keys, numpy 3x3 rotations and 3x1 translations."""
    with open(path) as f:
        content = {int(k): v for k, v in json.load(f).items()}
    for v in content.values():
        for e in (v if isinstance(v, list) else [v]):
            for k in ("cam_R_m2c", "cam_R_w2c", "cam_K"):
                if k in e:
                    e[k] = np.array(e[k], np.float64).reshape((3, 3))
            for k in ("cam_t_m2c", "cam_t_w2c"):
                if k in e:
                    e[k] = np.array(e[k], np.float64).reshape((3, 1))
    return content


@pytest.mark.parametrize("protocol", ["simple", "hard"])
def test_layout_bop_reads_back_the_frames_and_poses(annotated, protocol, tmp_path, capsys):
    from tdof20.dataset.build import build_dataset, split_images

    base, scenes = annotated
    ours = base / "tdof20_ds"
    if not ours.exists():
        build_dataset(scenes, ours, show_progress=False)
    out = tmp_path / "bop"
    rc, err, _ = cli(capsys, "dataset", "build", *scenes, "--out", out, "--layout", "bop", "--split", protocol)
    assert rc == 0, err
    ds = open_dataset(out)
    assert ds.layout == "bop" and set(ds.splits()) <= {"train", "test"}
    assert ds.obj_ids == open_dataset(ours).obj_ids
    assert ds.object_name(1) == open_dataset(ours).object_name(1)
    tdof = open_dataset(ours)
    for part in ("train", "test"):
        want = split_images(ours, protocol, part)
        got = ds.frames(part, part) if part in ds.splits() else []
        assert got == want, part
        for sid, im in got:
            mine, theirs = ds.scene(sid, part), tdof.scene(sid)
            assert ds.scene_name(sid, part) == tdof.scene_name(sid)
            for g in range(len(theirs.gt[im])):
                assert all(np.array_equal(a, b) for a, b in zip(mine.pose(im, g), theirs.pose(im, g)))
            assert np.array_equal(mine.rgb(im), theirs.rgb(im))
            assert np.array_equal(ds.depth_mm(sid, im, "restored", part), tdof.depth_mm(sid, im, "restored"))
        for sid in ({s for s, _ in got}):  # what bop_toolkit's loaders read
            d = out / part / f"{sid:06d}"
            gt, cam = _bop_json(d / "scene_gt.json"), _bop_json(d / "scene_camera.json")
            assert sorted(gt) == sorted(cam) == sorted(i for s, i in got if s == sid)
            assert all(e["cam_t_m2c"].shape == (3, 1) for v in gt.values() for e in v)
            assert (d / "mask_visib" / f"{min(gt):06d}_000000.png").is_file()
    with open(out / "test_targets_bop19.json") as f:
        targets = json.load(f)
    assert targets == json.loads((ours / f"test_targets_{protocol}.json").read_text())
    assert json.loads((out / "camera.json").read_text())["width"] == 64
    # scoring against the BOP build with the ground truth is perfect
    from tdof20.scoring.scoring import score
    rows = []
    for t in targets:
        sc = ds.scene(t["scene_id"], "test")
        for g, e in enumerate(sc.gt[t["im_id"]]):
            if e["obj_id"] == t["obj_id"]:
                R, tt = sc.pose(t["im_id"], g)
                rows.append((t["scene_id"], t["im_id"], t["obj_id"], 1.0, R, tt, 0.0))
    assert targets
    s = score(rows, out, "test", metrics="add,proj")
    assert s["all"]["add_s"] == 1.0 and s["all"]["n"] == sum(t["inst_count"] for t in targets)
    # a rebuild of the same scenes is allowed; another protocol is refused in one line
    assert cli(capsys, "dataset", "build", *scenes, "--out", out, "--layout", "bop", "--split", protocol)[0] == 0
    other = "hard" if protocol == "simple" else "simple"
    rc, err, _ = cli(capsys, "dataset", "build", *scenes, "--out", out, "--layout", "bop", "--split", other)
    assert rc == 2 and "another protocol" in err
    rc, err, _ = cli(capsys, "dataset", "build", *scenes, "--out", tmp_path / "x", "--layout", "bop")
    assert rc == 2 and "--layout bop needs --split" in err


# ---------------------------------------------------------------------------------------------
# the layouts' interface and registry
# ---------------------------------------------------------------------------------------------
def test_a_new_layout_is_one_registered_class(bop, tmp_path, monkeypatch):
    """A layout of its own: one DatasetReader subclass, registered with one line, is detected and opened,
    and the shared members (scenes, images, keypoints, depth, stats) work through it."""
    import shutil
    from pathlib import Path

    from tdof20.dataset import layouts
    from tdof20.dataset.build import stats
    from tdof20.dataset.layouts.base import DatasetReader

    monkeypatch.setattr(layouts, "LAYOUTS", dict(layouts.LAYOUTS))  # the registry as it was, after the test

    class FlatReader(DatasetReader):
        """ROOT/flat.json {"scenes": {id: name}}; ROOT/scenes/{id:06d}/; one split 'all', every image in both parts."""

        layout = "flat"
        info_file = "flat.json"
        split_hint = "all"

        @classmethod
        def detect(cls, root: Path) -> bool:
            return (root / "flat.json").is_file()

        def _read_info(self) -> dict:
            return json.loads((self.root / "flat.json").read_text())

        def splits(self):
            return ["all"]

        def check_split(self, split):
            if split not in (None, "all"):
                raise TdofError(f"unknown split '{split}'", self.root)
            return "all"

        def scene_folder(self, split):
            return None

        def _scenes_root(self, split=None):
            return self.root / "scenes"

        def _default_scene_name(self, scene_id, split):
            return f"flat/{scene_id}"

        def targets_split(self):
            return None

        def targets_path(self, split=None):
            return self.root / "targets.json"

        def _frames_of(self, split, part):
            return [(s, i) for s in self.scene_ids() for i in self.image_ids(s)]

        def _cache_key(self, split):
            return "scenes"

        def check_train_split(self, split):
            return self.check_split(split)

        def part_frames(self, split, part, purpose):
            return self.frames(split, part)

        def empty_part_text(self, split, part):
            return "the dataset has no images"

        def scoring_targets_path(self, split):
            return self.targets_path()

        def stats_folders(self):
            return [None]

        def split_counts(self):
            return {"all": len(self.frames("all"))}

    root = tmp_path / "flat"
    shutil.copytree(bop["root"] / "train_pbr" / "000000", root / "scenes" / "000007")
    shutil.copytree(bop["root"] / "models", root / "models")
    (root / "flat.json").write_text(json.dumps({"scenes": {"7": "seven"}}))
    with pytest.raises(TdofError, match="not a dataset"):
        layouts.open_dataset(root)
    assert layouts.register_layout(FlatReader) is FlatReader  # the one line a layout adds
    assert list(layouts.LAYOUTS) == ["tdof20", "bop", "flat"]
    assert layouts.detect_layout(root) == "flat" and layouts.detect_layout(bop["root"]) == "bop"
    ds = open_dataset(root, "all")
    assert isinstance(ds, FlatReader) and ds.split == "all" and ds.layout == "flat"
    assert not ds.uses_catalog_ids and not ds.has_validation_arcs
    assert ds.scene_ids() == [7] and ds.scene_name(7) == "seven" and ds.obj_ids == list(OBJ_IDS)
    assert ds.frames() == [(7, i) for i in range(4)] and ds.scene(7).rgb(0).shape == (48, 64, 3)
    assert ds.depth_modes() == ("raw", "filled", "restored") and sorted(ds.keypoints()) == list(OBJ_IDS)
    assert ds.depth_mm(7, 0).shape == (48, 64)
    s = stats(root)
    assert s["layout"] == "flat" and s["images"] == 4 and s["splits"] == {"all": 4}
    assert ds.describe()["layout"] == "flat"
    with pytest.raises(ValueError, match="already registered"):
        layouts.register_layout(type("Other", (FlatReader,), {}))
    with pytest.raises(TypeError):
        layouts.register_layout(dict)


def test_the_layouts_answer_the_decisions_callers_ask(bop, annotated, tmp_path):
    """The members that replace checks of the layout's name: catalog ids, scene folders, the split a
    training names, a part's frames with their one-line errors, validation arcs, the scorer's hints."""
    import shutil

    from tdof20.dataset.build import build_dataset
    from tdof20.dataset.splits import SPLIT_PART_SCENES

    b = open_dataset(bop["root"])
    assert not b.uses_catalog_ids and not b.has_validation_arcs and b.split_hint == "a split folder such as test"
    assert b.scene_folder("test") == "test" and b.check_train_split("train_pbr") == "train_pbr"
    with pytest.raises(TdofError, match="give a split"):
        b.scene_folder(None)
    assert b.part_frames("train_pbr", "train", "train on") == b.frames("train_pbr", "train")
    assert b.scoring_targets_path("test") == bop["root"] / "test_targets_bop19.json"
    with pytest.raises(TdofError, match="holds the targets of the split folder test/, not train_pbr/"):
        b.scoring_targets_path("train_pbr")
    empty = tmp_path / "bop_empty"
    shutil.copytree(bop["root"], empty)
    (empty / "test_targets_bop19.json").write_text("[]")
    with pytest.raises(TdofError) as e:
        open_dataset(empty).part_frames("test", "test", "predict")
    assert str(e.value) == f"{empty}: the split folder test/ of this dataset has no test images: nothing to predict"

    base, scenes = annotated
    root = base / "single_only"
    if not root.exists():
        build_dataset(scenes[:1], root, show_progress=False)  # single/01 only: no hard test scene
    t = open_dataset(root)
    assert t.uses_catalog_ids and t.has_validation_arcs and t.split_hint == "simple or hard"
    assert t.scene_folder("simple") is None and t.check_train_split("hard") == "hard"
    with pytest.raises(TdofError, match="^--split must be one of simple, hard, got 'x'$"):
        t.check_train_split("x")
    assert t.part_frames("simple", "train", "train on") == t.frames("simple", "train")
    with pytest.raises(TdofError) as e:
        t.part_frames("hard", "test", "predict")
    assert str(e.value) == (f"{root}: the hard split's test part of this dataset is empty (splits/hard_test.json "
                            f"lists no images; it takes {SPLIT_PART_SCENES[('hard', 'test')]}): nothing to predict")
    with pytest.raises(TdofError, match="split must be one of"):
        t.part_frames("val", "test", "predict")
    assert t.scoring_targets_path("hard") == root / "test_targets_hard.json"
    assert t.no_targets_reason("hard").startswith(": the dataset has 1 single-object and 0 multi-object scenes")
    assert "hard tests on multi-object scenes multi/02" in t.empty_part_text("hard", "test")


def test_build_dataset_in_layout_checks_the_options_then_writes(annotated, tmp_path):
    from tdof20.dataset.build import WRITERS, build_dataset_in_layout

    assert list(WRITERS) == ["tdof20", "bop"]
    none = [tmp_path / "no_scene"]
    for layout, kw, msg in (("coco", {}, "--layout must be tdof20 or bop, got 'coco'"),
                            ("bop", {}, "--layout bop needs --split simple or --split hard"),
                            ("bop", {"split": "simple", "add": True}, "--add grows a tdof20-layout dataset"),
                            ("tdof20", {"split": "simple"}, "--split is for --layout bop")):
        with pytest.raises(TdofError, match=msg.replace("(", r"\(")):
            build_dataset_in_layout(layout, none, tmp_path / "out", **kw)
    assert not (tmp_path / "out").exists()
    _, scenes = annotated
    s = build_dataset_in_layout("tdof20", scenes, tmp_path / "t", show_progress=False)
    assert s["layout"] == "tdof20" and open_dataset(tmp_path / "t").layout == "tdof20"
    s = build_dataset_in_layout("bop", scenes, tmp_path / "b", split="hard", show_progress=False)
    assert s["layout"] == "bop" and open_dataset(tmp_path / "b").splits() == ["test", "train"]


def test_no_module_outside_the_layouts_decides_on_a_layout_name():
    """A layout's name is for display only: outside tdof20/dataset/layouts/ no code compares a
    ``layout`` (a variable or an attribute) with ==, !=, in or not in."""
    import ast
    from pathlib import Path

    pkg = Path(__file__).resolve().parents[1] / "tdof20"
    own = pkg / "dataset" / "layouts"

    def is_layout(node) -> bool:
        return (isinstance(node, ast.Name) and node.id == "layout") or \
            (isinstance(node, ast.Attribute) and node.attr == "layout")

    found: dict[str, list[int]] = {}
    for path in sorted(pkg.rglob("*.py")):
        if own in path.parents:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Compare) and \
                    any(isinstance(op, (ast.Eq, ast.NotEq, ast.In, ast.NotIn)) for op in node.ops) and \
                    any(is_layout(x) for x in [node.left, *node.comparators]):
                found.setdefault(path.relative_to(pkg.parent).as_posix(), []).append(node.lineno)
    assert found == {}
