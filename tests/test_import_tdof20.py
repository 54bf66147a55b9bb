"""`tdof20 dataset import-tdof20`: the released TDoF20 layout (written by the independent fixture of
tests/fixtures/tdof20_release.py from the README alone) imported as a tdof20 dataset."""

import json
import pickle
import pickletools
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tdof20.dataset import importer
from tdof20.dataset.importer import import_tdof20
from tdof20.errors import TdofError
from tdof20.formats import read_json, read_png, read_scene
from tdof20.formats.tdof20_release import load_pickle
from tests.fixtures.tdof20_release import write_tdof20_release
from tests.import_support import interrupt_import

SMALL = dict(classes=("cube_136", "goblet_180"), multi=("02",), frames_per_scene=3)
LIST_KEYS = {"simple_train": "train_data_list.txt", "simple_test": "test_data_list.txt",
             "hard_train": "hard_train_data_list.txt", "hard_test": "hard_test_data_list.txt"}


def _ids(w, out):
    """{fixture frame key: (scene_id, im_id)} through the dataset's own scene names."""
    info = read_json(out / "dataset_info.json")
    by_name = {v: int(k) for k, v in info["scenes"].items()}
    res = {}
    for key, f in w["frames"].items():
        name = f"single/{f['scene']}" if f["kind"] == "single" else f"multi/{f['scene']}"
        res[key] = (by_name[name], int(f["stem"]))
    return res


def _check_poses(w, out):
    ids = _ids(w, out)
    for key, f in w["frames"].items():
        sid, im = ids[key]
        sc = read_scene(out / "scenes" / f"{sid:06d}")
        assert [g["obj_id"] for g in sc.gt[im]] == [i["cls_id"] for i in f["instances"]]
        for gid, inst in enumerate(f["instances"]):
            R, t = sc.pose(im, gid)
            np.testing.assert_allclose(R, inst["R"], atol=1e-6)
            np.testing.assert_allclose(t, inst["t_mm"], atol=1e-6)


def test_check_prints_what_it_found_and_writes_nothing(tmp_path):
    w = write_tdof20_release(tmp_path / "src")
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "tdof20.cli", "dataset", "import-tdof20", str(tmp_path / "src"),
                          "--out", str(out), "--check"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    text = " ".join(res.stdout.split())
    for name, n in w["counts"].items():
        row = {"train_data_list.txt": "train", "test_data_list.txt": "test", "hard_train_data_list.txt": "hard_train",
               "hard_test_data_list.txt": "hard_test", "visual_data_list.txt": "visual"}[name]
        assert f"{row} │ {name} │ {n} │" in text, (row, text)
    assert "poses in m" in text and "model in m, diameter in m" in text and "cube_136, goblet_180, handle_cup_280" in text
    assert "single/cube_136 │ 1 │ 6" in text and "multi/02 │ 23 │ 6" in text
    assert "checked: nothing written" in res.stderr
    assert not out.exists()


def test_import_splits_poses_masks_depths_keypoints(tmp_path):
    w = write_tdof20_release(tmp_path / "src")
    out = tmp_path / "out"
    s = import_tdof20(tmp_path / "src", out, show_progress=False)
    assert s["written"] and not (out / importer.MARKER).exists()
    info = read_json(out / "dataset_info.json")
    assert info["source"] == "tdof20-release" and set(info["depth_modes"]) == {"raw", "stabilized", "restored"}
    assert info["scenes"] == {"1": "single/cube_136", "2": "single/goblet_180", "3": "single/handle_cup_280",
                              "21": "multi/00", "23": "multi/02"}
    ids = _ids(w, out)
    # splits exactly from the lists
    for split, fname in LIST_KEYS.items():
        want = {}
        for key in w["lists"][fname]:
            sid, im = ids[key]
            want.setdefault(str(sid), []).append(im)
        assert read_json(out / "splits" / f"{split}.json") == {k: sorted(v) for k, v in want.items()}
    visual = read_json(out / "splits" / "visual.json")
    assert sum(len(v) for v in visual.values()) == w["counts"]["visual_data_list.txt"]
    targets = read_json(out / "test_targets_hard.json")
    assert {(t["scene_id"], t["im_id"]) for t in targets} <= {ids[k] for k in w["lists"]["hard_test_data_list.txt"]}
    _check_poses(w, out)
    for key, f in w["frames"].items():
        sid, im = ids[key]
        d = out / "scenes" / f"{sid:06d}"
        src = tmp_path / "src" / key.rsplit("/", 1)[0]
        stem = f["stem"]
        assert (d / "rgb" / f"{im:06d}.jpg").read_bytes() == (src / "rgb" / f"{stem}.jpg").read_bytes()
        assert np.array_equal(read_png(d / "depth" / f"{im:06d}.png"), read_png(src / "broken_depth" / f"{stem}.png"))
        stab = read_png(src / "depth" / f"{stem}.png")
        assert np.array_equal(read_png(d / "depth_stabilized" / f"{im:06d}.png"), stab)
        cmask = cv2.imread(str(src / "mask" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        gt_info = read_json(d / "scene_gt_info.json")[str(im)]
        restored = read_png(d / "depth_restored" / f"{im:06d}.png").astype(float)
        for gid, inst in enumerate(f["instances"]):
            vis = read_png(d / "mask_visib" / f"{im:06d}_{gid:06d}.png") > 0
            assert np.array_equal(vis, cmask == inst["cls_id"])            # visible = the class-id mask
            full = read_png(d / "mask" / f"{im:06d}_{gid:06d}.png") > 0
            assert (full | vis).sum() == full.sum() and full.sum() >= vis.sum()
            assert abs(int(full.sum()) - inst["px_all"]) <= max(3, 0.05 * inst["px_all"])  # rendered silhouette
            assert gt_info[gid]["px_count_visib"] == inst["px_visib"]
            # restored depth = the models' surface where they are seen (the fixture's exact render)
            np.testing.assert_allclose(restored[vis], f["depth_mm"][vis], atol=1.0)
    kps = read_json(out / "models" / "keypoints.json")
    info_m = read_json(out / "models" / "models_info.json")
    for name, cid in w["class_ids"].items():
        kp = np.asarray(kps[str(cid)])
        assert kp.shape == (9, 3)
        np.testing.assert_allclose(kp[1:], w["farthest_mm"][name], atol=1e-3)   # the released 8, in mm
        assert np.abs(kp[0]).max() < 1e-3                                    # the bbox centre (fixture: origin)
        assert info_m[str(cid)]["diameter"] == pytest.approx(w["diameters_mm"][name], abs=1e-3)
    assert "symmetries_discrete" in info_m["1"] and "symmetries_continuous" in info_m["2"]
    assert "symmetries_continuous" not in info_m["3"] and "symmetries_discrete" not in info_m["3"]
    # the dataset tools read it
    from tdof20.dataset.build import stats
    st = stats(out)
    assert st["splits"]["simple_train"] == w["counts"]["train_data_list.txt"]
    assert st["splits"]["hard_test"] == w["counts"]["hard_test_data_list.txt"]


@pytest.mark.parametrize("pose_units,model_units,diameter_units", [("m", "mm", "mm"), ("mm", "m", "m"),
                                                                   ("mm", "mm", "mm"), ("m", "m", "mm")])
def test_units_are_detected_and_converted(tmp_path, pose_units, model_units, diameter_units):
    w = write_tdof20_release(tmp_path / "src", pose_units=pose_units, model_units=model_units,
                             diameter_units=diameter_units, **SMALL)
    s = import_tdof20(tmp_path / "src", tmp_path / "out", show_progress=False)
    assert s["units"]["poses"].startswith(f"poses in {pose_units} ")
    assert all(v.startswith(f"model in {model_units}, diameter in {diameter_units}")
               for v in s["units"]["models"].values())
    _check_poses(w, tmp_path / "out")
    from tdof20.formats import read_model_mesh
    for name, cid in w["class_ids"].items():
        V, _ = read_model_mesh(tmp_path / "out" / "models" / f"obj_{cid:06d}.ply")
        assert np.ptp(V, axis=0).max() == pytest.approx(w["diameters_mm"][name], rel=0.5)  # mm, not m


def _one_line(e, *needles):
    msg = str(e.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, msg


def test_ambiguous_or_wrong_units_are_refused(tmp_path):
    w = write_tdof20_release(tmp_path / "src", **SMALL)
    out = tmp_path / "out"
    # one frame's pose in mm among poses in m
    key = next(iter(w["frames"]))
    pkl = tmp_path / "src" / key.replace(f"/{w['frames'][key]['stem']}", f"/pose/{w['frames'][key]['stem']}.pkl")
    d = load_pickle(pkl)
    d["poses"][:, 3] *= 1000.0
    d["center_3ds"] *= 1000.0
    pkl.write_bytes(pickle.dumps(d))
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "src", out, show_progress=False)
    _one_line(e, str(pkl), "poses are in mm", "one unit")
    # translations of 20 (neither m nor mm from a camera)
    d["poses"][:, 3] *= 20.0 / np.linalg.norm(d["poses"][:, 3], axis=0)
    pkl.write_bytes(pickle.dumps(d))
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "src", out, show_progress=False)
    _one_line(e, str(pkl), "ambiguous")
    # a diameter that fits the model neither in m nor in mm
    w = write_tdof20_release(tmp_path / "src2", **SMALL)
    dia = tmp_path / "src2" / "diameters" / "goblet_180_diameter.txt"
    dia.write_text(f"{float(dia.read_text()) * 3:.6f}\n")
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "src2", out, check=True, show_progress=False)
    _one_line(e, "goblet_180.ply", "goblet_180_diameter.txt", "neither in mm nor in m")
    assert not out.exists()


@pytest.mark.parametrize("variant,needle", [
    ({"missing_list": "train_data_list.txt"}, ("train_data_list.txt", "list file not found")),
    ({"pkl_drop_keys": ("poses",)}, ("pose/000000.pkl", "has no 'poses'")),
    ({"bad_cls_id": True}, ("cube_136/pose/000000.pkl", "class id 3 is not in classes.txt")),
    ({"classes_txt": ["cube_136"]}, ("single_data/goblet_180", "not a class of classes.txt")),
    ({"drop_file": ("broken_depth", 1)}, ("_data_list.txt: line", "has no broken_depth/000001.png")),
])
def test_bad_release_one_line_naming_the_file(tmp_path, variant, needle):
    write_tdof20_release(tmp_path / "src", **SMALL, **variant)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "src", out, show_progress=False)
    _one_line(e, *needle)
    assert list(out.iterdir()) == []


def test_rgb_masks_of_equal_channels_are_read(tmp_path):
    """docs/tdof20_release.md: a mask may be an RGB(A) PNG whose channels are equal (an image editor's
    save): the same labels as grey masks; one with unequal channels is a one-line error naming it."""
    from PIL import Image

    write_tdof20_release(tmp_path / "src", **SMALL)
    masks = sorted((tmp_path / "src" / "single_data" / "goblet_180" / "mask").glob("*.png"))
    grey = [np.asarray(Image.open(m)) for m in masks]
    for m, g in zip(masks, grey):
        mode = "RGBA" if m == masks[0] else "RGB"
        Image.fromarray(np.stack([g] * len(mode), axis=-1).astype(np.uint8), mode).save(m)
    ref = tmp_path / "ref"
    write_tdof20_release(tmp_path / "src_grey", **SMALL)
    import_tdof20(tmp_path / "src_grey", ref, show_progress=False)
    out = tmp_path / "out"
    import_tdof20(tmp_path / "src", out, show_progress=False)
    visib = sorted((ref / "scenes").rglob("mask_visib/*.png"))
    assert len(visib) >= len(masks)
    for a in visib:
        np.testing.assert_array_equal(read_png(out / a.relative_to(ref)), read_png(a))
    rgb = np.stack([grey[1]] * 3, axis=-1).astype(np.uint8)
    rgb[0, 0, 1] = 7
    Image.fromarray(rgb, "RGB").save(masks[1])
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "src", tmp_path / "out2", show_progress=False)
    _one_line(e, masks[1].name, "unequal channels")
    # found while importing: --out is as it was (absent), and no work folder is left beside it
    assert not (tmp_path / "out2").exists() and not (tmp_path / ".out2.importing").exists()


def test_cli_error_is_one_line(tmp_path):
    write_tdof20_release(tmp_path / "src", **SMALL, pkl_drop_keys=("poses",))
    res = subprocess.run([sys.executable, "-m", "tdof20.cli", "dataset", "import-tdof20", str(tmp_path / "src"),
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:") and "has no 'poses'" in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("variant", [{"list_form": "short"}, {"list_form": "rgb_path"},
                                     {"visual_name": "visual_data.txt", "intrinsics_form": "K"},
                                     {"pose_layout": "Nx3x4", "cls_ids_shape": "column", "extra_pkl_keys": True},
                                     {"depth_scale": 0.5, "ply_encoding": "binary"}])
def test_documented_variants_are_read(tmp_path, variant):
    w = write_tdof20_release(tmp_path / "src", **SMALL, **variant)
    s = import_tdof20(tmp_path / "src", None, check=True, show_progress=False)
    names = {"train_data_list.txt": "train", "test_data_list.txt": "test", "hard_train_data_list.txt": "hard_train",
             "hard_test_data_list.txt": "hard_test", w["visual_name"]: "visual"}
    assert s["lists"] == {names[k]: n for k, n in w["counts"].items()}
    assert s["units"]["depth"] == f"{variant.get('depth_scale', 1.0):g} mm per unit"
    assert min(s["mask_iou_first_frame"].values()) > 0.9


def _py2_pickle(obj) -> bytes:
    """A pickle as Python 2 writes it: byte strings as (SHORT_)BINSTRING, which Python 3 only
    reads with encoding='latin1'."""
    data = bytearray(pickle.dumps(obj, protocol=3))
    for op, _, pos in pickletools.genops(bytes(data)):
        if op.name == "SHORT_BINBYTES":
            data[pos] = ord("U")
        elif op.name == "BINBYTES":
            data[pos] = ord("T")
    return bytes(data)


def test_python2_pickles_load(tmp_path):
    w = write_tdof20_release(tmp_path / "src", **SMALL)
    n = 0
    for key, f in w["frames"].items():
        p = tmp_path / "src" / key.rsplit("/", 1)[0] / "pose" / f"{f['stem']}.pkl"
        d = pickle.loads(p.read_bytes())
        raw = _py2_pickle(d)
        if n == 0:
            with pytest.raises(UnicodeDecodeError):
                pickle.loads(raw)   # really a Python 2 pickle: Python 3's default encoding refuses it
        p.write_bytes(raw)
        n += 1
    w2 = import_tdof20(tmp_path / "src", tmp_path / "out", show_progress=False)
    assert w2["written"]
    _check_poses(w, tmp_path / "out")


def test_interrupted_import_resumes(tmp_path, monkeypatch):
    write_tdof20_release(tmp_path / "src", **SMALL)
    ref = tmp_path / "ref"
    import_tdof20(tmp_path / "src", ref, show_progress=False)
    out = tmp_path / "out"
    interrupt_import(tmp_path / "src", out, monkeypatch)
    # the import works beside --out and moves its folder into place at the end
    work = tmp_path / ".out.importing"
    assert not out.exists()
    assert (work / importer.MARKER).exists() and not (work / "dataset_info.json").exists()
    assert (work / "scenes" / "000001" / "scene_info.json").exists()
    assert len(read_json(work / "scenes" / "000002" / "scene_gt.json")) == 1  # one frame of scene 2 kept
    # another import into it is refused; the same one finishes it
    write_tdof20_release(tmp_path / "other", **SMALL, seed=1)
    with pytest.raises(TdofError) as e:
        import_tdof20(tmp_path / "other", out, show_progress=False)
    _one_line(e, "unfinished import")
    s = import_tdof20(tmp_path / "src", out, show_progress=False)
    assert s["written"] and s["resumed"] and not (out / importer.MARKER).exists() and not work.exists()
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    for p in files:
        if p.suffix == ".json" and p.name != "dataset_info.json":
            assert json.loads((out / p).read_text()) == json.loads((ref / p).read_text()), p
        elif p.suffix in (".png", ".jpg", ".ply"):
            assert (out / p).read_bytes() == (ref / p).read_bytes(), p


def test_imported_release_round_trip_stats_train_predict_score(tmp_path):
    """import -> stats equal the lists -> a few training steps -> predict -> score, on the fixture."""
    import csv

    from tdof20.dataset.build import stats
    from tdof20.scoring.scoring import score
    from tdof20.methods.predict import predict
    from tdof20.methods.train import train

    w = write_tdof20_release(tmp_path / "TDoF20", **SMALL)
    out = tmp_path / "ds"
    import_tdof20(tmp_path / "TDoF20", out, show_progress=False)
    s = stats(out)
    lists = {k: len((tmp_path / "TDoF20" / "dataset_config" / f).read_text().split()) for k, f in LIST_KEYS.items()}
    assert {k: s["splits"][k] for k in LIST_KEYS} == lists
    run = train(out, "simple", tmp_path / "run", image_size=(48, 64), batch_size=2, max_steps=2, lr=1e-3,
                num_workers=0, device="cpu", progress=False)
    cfg = json.loads((run / "config.json").read_text())
    assert np.allclose(cfg["keypoints"]["1"][1:], w["farthest_mm"]["cube_136"], atol=1e-3)  # the released ones
    res = predict(run, out, "simple", tmp_path / "res.csv", device="cpu", num_workers=0, masks="gt", progress=False)
    with open(res) as f:
        rows = list(csv.DictReader(f))
    assert {int(r["obj_id"]) for r in rows} <= {1, 2}  # an untrained network may find no pose at all
    assert json.loads((tmp_path / "res_info.json").read_text())["images"] == lists["simple_test"]
    sc = score(res, out, "simple", metrics="add,proj")
    assert sc["all"]["n"] == lists["simple_test"]  # one target per single-object test frame


@pytest.mark.usefixtures("one_torch_thread")
def test_reproduce_on_an_imported_release(tmp_path):
    """`tdof20 reproduce --dataset ROOT` on a release written from the README alone and imported:
    validation arcs carved from the released train lists (epochs chosen on them), trained, predicted
    and scored on both protocols, every released object a row of Tables 1-2; the given dataset is
    only read (not a byte of it changes). Every method end to end: tests/test_reproduce.py."""
    import hashlib

    from tdof20.experiments.reproduce import reproduce
    from tdof20.dataset.validation import part_images

    write_tdof20_release(tmp_path / "TDoF20", classes=("cube_136", "handle_cup_280"), multi=("00", "02"),
                         frames_per_scene=16)  # 4 per arm position: a validation arc of 1
    ds = tmp_path / "ds"
    import_tdof20(tmp_path / "TDoF20", ds, show_progress=False)

    def digest():
        return {p.relative_to(ds).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest()
                for p in sorted(ds.rglob("*")) if p.is_file()}

    before = digest()
    for split in ("simple", "hard"):
        val, fit = part_images(ds, split, "val"), part_images(ds, split, "train-val")
        assert val and fit and not set(val) & set(fit)
        assert sorted(val + fit) == sorted(part_images(ds, split, "train"))
        assert not set(val) & set(part_images(ds, split, "test"))
    cfg = tmp_path / "c.toml"
    cfg.write_text('preset = "smoke"\ndevice = "cpu"\nmethods = ["pvnet"]\n'
                   '[train]\nimage_size = [32, 48]\nbatch_size = 4\nimages = 40\nnum_workers = 0\n'
                   '[ablations]\nfuse_stages = []\nsegmentation = false\nvoting_3d = false\n'
                   '[profile]\nenabled = false\n')
    md = reproduce(tmp_path / "out", config=cfg, dataset=ds, progress=False)
    tables = json.loads((md.parent / "tables.json").read_text())
    text = md.read_text()
    assert f"the given dataset, imported from the TDoF20 release at {tmp_path / 'TDoF20'}: 4 scenes, 2 objects" in text
    for name in ("cube_136", "handle_cup_280"):
        assert f"| {name} |" in text or f"| **{name}** \\* |" in text
    assert "**handle_cup_280** \\*" in text  # the asymmetric one marked
    cols = {(c["label"], c["split"]) for t in ("table1", "table2") for c in tables[t]["columns"] if c["present"]}
    assert {("PVNet", "simple"), ("PVNet", "hard")} <= cols
    # two epochs: the kept one was chosen on the validation part carved from the released lists
    state = json.loads((tmp_path / "out" / "reproduce.json").read_text())
    for split in ("simple", "hard"):
        job = state["jobs"][f"train/pvnet_{split}_s0"]
        assert [v["epoch"] for v in job["validation"]] == [1, 2] and job["kept_epoch"] in (1, 2)
    assert digest() == before
