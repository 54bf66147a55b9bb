"""What `dataset build / pack` and `benchmark score` refuse, and that a refusal changes nothing
(issue 11). Real scenes: tiny simulated captures labelled from the simulator's truth, run
through the console entry point (`tdof20.cli.main`) where the user would see the message."""

import hashlib
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tdof20.dataset import build as dataset_mod
from tdof20.dataset.build import BUILD_MARKER, build_dataset, split_images
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.sim.truth import oracle_scene
from tdof20.sim.scenes import normalize_scene_id

HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def make_scene(base: Path, name: str, steps=8, n_arms=2, width=80, height=60) -> Path:
    raw = base / "raw" / name.replace("/", "_")
    run_capture(sim_config(name, steps=steps, step_deg=360.0 / steps, n_arms=n_arms, width=width, height=height),
                raw, yes=True, show_progress=False)
    return oracle_scene(raw, base / "labels" / name.replace("/", "_"), show_progress=False)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """single/12 and multi/08 at 80x60 (8 steps, 2 arm positions); single/05 at 64x48 (3 steps, 1 arm)."""
    base = tmp_path_factory.mktemp("rel")
    return {"single/12": make_scene(base, "single/12"), "multi/08": make_scene(base, "multi/08"),
            "single/05@64x48": make_scene(base, "single/05", steps=3, n_arms=1, width=64, height=48)}


def cli(capsys, *args) -> tuple[int, str]:
    """Run the console script in-process: (exit code, the one stderr line or stdout)."""
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
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert "Traceback" not in err
    if rc:
        assert len(lines) == 1, err
        return rc, lines[0]
    return rc, out


def tree(root: Path) -> dict[str, str]:
    """Every file under root (hidden ones too) -> its sha256."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def load(p: Path):
    return json.loads(p.read_text())


# ------------------------------------------------------------------------------------- F1
def test_build_into_another_dataset_is_refused_and_changes_nothing(scenes, tmp_path, capsys):
    root = tmp_path / "R"
    assert cli(capsys, "dataset", "build", scenes["multi/08"], "--out", root)[0] == 0
    n_hard = len(load(root / "test_targets_hard.json"))
    assert n_hard > 0
    before = tree(root)
    rc, msg = cli(capsys, "dataset", "build", scenes["single/12"], "--out", root)
    assert rc == 2
    assert msg == (f"error: {root}: holds the dataset of multi/08; building single/juice_cup_340 here would drop multi/08: "
                   "add scenes with --add, rebuild it with its full scene list, or choose another --out")
    assert tree(root) == before  # no orphan, no new scene, same targets


def test_rebuilding_the_same_scenes_is_idempotent(scenes, tmp_path):
    root = tmp_path / "R"
    build_dataset([scenes["single/12"], scenes["multi/08"]], root, show_progress=False)
    first = tree(root)
    build_dataset([scenes["multi/08"], scenes["single/12"]], root, show_progress=False)
    assert tree(root) == first
    assert not (root / BUILD_MARKER).exists()


def test_add_gives_the_dataset_a_full_build_gives(scenes, tmp_path, capsys):
    full, grown = tmp_path / "full", tmp_path / "grown"
    build_dataset([scenes["single/12"], scenes["multi/08"]], full, show_progress=False)
    build_dataset([scenes["multi/08"]], grown, show_progress=False)
    hard_before = load(grown / "test_targets_hard.json")
    rc, _ = cli(capsys, "dataset", "build", scenes["single/12"], "--out", grown, "--add")
    assert rc == 0
    for name in ("splits/simple_train.json", "splits/simple_test.json", "splits/hard_train.json",
                 "splits/hard_test.json", "test_targets_simple.json", "test_targets_hard.json",
                 "models/models_info.json"):
        assert load(grown / name) == load(full / name), name
    for key in ("scenes", "layout", "splits"):
        assert load(grown / "dataset_info.json")[key] == load(full / "dataset_info.json")[key]
    assert load(grown / "test_targets_hard.json") == hard_before  # multi/08's targets are kept
    assert sorted(p.name for p in (grown / "models").glob("*.ply")) == \
        sorted(p.name for p in (full / "models").glob("*.ply"))
    assert sorted(p.name for p in (grown / "scenes").iterdir()) == ["000012", "000029"]
    assert tree(grown / "scenes") == tree(full / "scenes")
    assert len(split_images(grown, "simple", "train")) > 0


def test_add_refusals_leave_the_dataset_as_it_was(scenes, tmp_path, capsys):
    root = tmp_path / "R"
    build_dataset([scenes["multi/08"]], root, show_progress=False)
    before = tree(root)
    rc, msg = cli(capsys, "dataset", "build", scenes["multi/08"], "--out", root, "--add")
    assert rc == 2 and msg.startswith(f"error: {root}: multi/08 is already in the dataset: --add adds new scenes only")
    # a scene whose model of a shared object differs from the dataset's
    other = tmp_path / "s12"
    shutil.copytree(scenes["single/12"], other)
    shared = sorted(set(load(other / "models" / "models_info.json")) & set(load(root / "models" / "models_info.json")))
    obj = int(shared[0]) if shared else None
    if obj is None:  # give single/12 a different model of one of multi/08's objects
        obj = int(sorted(load(root / "models" / "models_info.json"))[0])
        info = load(other / "models" / "models_info.json")
        info[str(obj)] = load(root / "models" / "models_info.json")[str(obj)]
        (other / "models" / "models_info.json").write_text(json.dumps(info))
        shutil.copyfile(root / "models" / f"obj_{obj:06d}.ply", other / "models" / f"obj_{obj:06d}.ply")
    ply = other / "models" / f"obj_{obj:06d}.ply"
    data = bytearray(ply.read_bytes())
    data[-5] ^= 0xFF
    ply.write_bytes(bytes(data))
    rc, msg = cli(capsys, "dataset", "build", other, "--out", root, "--add")
    assert rc == 2 and f"object {obj} has a different model in the dataset's models/ and {other}" in msg
    rc, msg = cli(capsys, "dataset", "build", scenes["single/12"], "--out", tmp_path / "none", "--add")
    assert rc == 2 and "--add needs an existing dataset" in msg
    # another image size than the dataset's
    rc, msg = cli(capsys, "dataset", "build", scenes["single/05@64x48"], "--out", root, "--add")
    assert rc == 2 and msg == (f"error: {scenes['single/05@64x48']}: its images are 64x48 (width x height), those of "
                               f"the dataset {root} (camera.json) are 80x60: a dataset has one image size")
    # absurd turntable steps in scene_info.json (a MemoryError in the split rules, after new model
    # files had been written beside an unchanged dataset_info.json)
    huge = tmp_path / "s12big"
    shutil.copytree(scenes["single/12"], huge)
    info = load(huge / "scene_info.json")
    info["steps"] = 10**30
    (huge / "scene_info.json").write_text(json.dumps(info))
    rc, msg = cli(capsys, "dataset", "build", huge, "--out", root, "--add")
    assert rc == 2 and msg.startswith(f"error: {huge / 'scene_info.json'}: steps must be an integer in 1..36000")
    assert tree(root) == before
    assert not (tmp_path / "none").exists()


def test_an_interrupted_build_resumes_and_blocks_other_builds(scenes, tmp_path, monkeypatch):
    root = tmp_path / "R"
    real = dataset_mod.copy_scene
    calls = []

    def flaky(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(src, dst)

    monkeypatch.setattr(dataset_mod, "copy_scene", flaky)
    with pytest.raises(KeyboardInterrupt):
        build_dataset([scenes["single/12"], scenes["multi/08"]], root, show_progress=False)
    monkeypatch.setattr(dataset_mod, "copy_scene", real)
    assert (root / BUILD_MARKER).exists() and not (root / "dataset_info.json").exists()
    with pytest.raises(TdofError, match="an unfinished build of other scenes is here"):
        build_dataset([scenes["single/12"]], root, show_progress=False)
    build_dataset([scenes["single/12"], scenes["multi/08"]], root, show_progress=False)  # resumes
    names = {k: normalize_scene_id(v) for k, v in load(root / "dataset_info.json")["scenes"].items()}
    assert names == {"12": "single/juice_cup_340", "29": "multi/08"}
    assert not (root / BUILD_MARKER).exists()
    assert sorted(p.name for p in (root / "scenes").iterdir()) == ["000012", "000029"]


# ------------------------------------------------------------------------------------- F2
def test_output_inside_an_input_and_input_inside_the_output(scenes, tmp_path, capsys):
    scene = tmp_path / "s12"
    shutil.copytree(scenes["single/12"], scene)
    before = tree(scene)
    rc, msg = cli(capsys, "dataset", "build", scene, "--out", scene / "ds")
    assert rc == 2 and msg == (f"error: {scene / 'ds'}: --out is inside the scene folder {scene}: the scene would be "
                               "copied into itself; choose an --out outside every scene folder")
    assert tree(scene) == before and not (scene / "ds").exists()
    rc, msg = cli(capsys, "dataset", "build", scene, "--out", scene)
    assert rc == 2 and "is inside the scene folder" in msg
    outer = tmp_path / "outer"
    shutil.copytree(scene, outer / "s12")
    rc, msg = cli(capsys, "dataset", "build", outer / "s12", "--out", outer)
    assert rc == 2 and msg.startswith(f"error: {outer / 's12'}: the scene folder lies inside --out {outer}")
    assert sorted(p.name for p in outer.iterdir()) == ["s12"]


# ------------------------------------------------------------------------------------- F3
@pytest.mark.parametrize("case", ["jpeg", "depth8", "size", "missing", "cam_K"])
def test_every_image_is_checked_before_anything_is_copied(scenes, tmp_path, capsys, case):
    scene = tmp_path / "s12"
    shutil.copytree(scenes["single/12"], scene)
    rgb = cv2.imread(str(scene / "rgb" / "000001.png"))
    if case == "jpeg":  # a JPEG under a .png name (the capture's checksum would match it)
        ok, jpg = cv2.imencode(".jpg", rgb)
        (scene / "rgb" / "000001.png").write_bytes(jpg.tobytes())
        bad, why = scene / "rgb" / "000001.png", "not a PNG file (bad signature): it holds a JPEG image"
    elif case == "depth8":
        d = cv2.imread(str(scene / "depth" / "000002.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(scene / "depth_restored" / "000002.png"), (d // 16).astype(np.uint8))
        bad, why = scene / "depth_restored" / "000002.png", ("expected a 16-bit single-channel depth PNG, found a "
                                                             "grey PNG of 8 bits per sample")
    elif case == "size":
        cv2.imwrite(str(scene / "rgb" / "000001.png"), cv2.resize(rgb, (40, 30)))
        bad, why = scene / "rgb" / "000001.png", "the image is 40x30 (width x height), rgb/000000.png is 80x60"
    elif case == "missing":
        (scene / "mask_visib" / "000003_000000.png").unlink()
        bad, why = scene / "mask_visib" / "000003_000000.png", "file not found: scene_gt.json lists instance 0 of image 3"
    else:
        cams = load(scene / "scene_camera.json")
        cams["4"]["cam_K"][2] = 400.0
        (scene / "scene_camera.json").write_text(json.dumps(cams))
        bad, why = scene / "scene_camera.json", "image 4: the principal point (cx, cy) = (400, "
    out = tmp_path / "R"
    rc, msg = cli(capsys, "dataset", "build", scene, "--out", out)
    assert rc == 2 and msg.startswith(f"error: {bad}: {why}"), msg
    assert not out.exists()


@pytest.mark.parametrize("case", ["unknown_obj", "t_metres", "depth_scale", "diameter_metres", "garbage_ply",
                                  "ply_metres"])
@pytest.mark.parametrize("layout", ["tdof20", "bop"])
def test_labels_and_models_are_checked_before_anything_is_copied(scenes, tmp_path, capsys, case, layout):
    """Labels a dataset must not take: an object the scene has no model of, translations, depth or
    models in metres, a model file that is not one. Each refused in one line naming the file."""
    scene = tmp_path / "s12"
    shutil.copytree(scenes["single/12"], scene)
    gt_path, cam_path, info_path = scene / "scene_gt.json", scene / "scene_camera.json", scene / "models" / "models_info.json"
    gt, info = load(gt_path), load(info_path)
    (obj,) = [int(k) for k in info]
    ply = scene / "models" / f"obj_{obj:06d}.ply"
    if case == "unknown_obj":
        gt["3"][0]["obj_id"] = 99
        gt_path.write_text(json.dumps(gt))
        bad, why = gt_path, f"image 3 instance 0 is object 99, which the scene's models/models_info.json does not list"
    elif case == "t_metres":
        for insts in gt.values():
            for e in insts:
                e["cam_t_m2c"] = [v / 1000 for v in e["cam_t_m2c"]]
        gt_path.write_text(json.dumps(gt))
        bad, why = gt_path, "the objects lie "
    elif case == "depth_scale":
        cams = load(cam_path)
        for c in cams.values():
            c["depth_scale"] = 0.001
        cam_path.write_text(json.dumps(cams))
        bad, why = cam_path, "image 0: depth x depth_scale is "
    elif case == "diameter_metres":
        info[str(obj)]["diameter"] = info[str(obj)]["diameter"] / 1000
        info_path.write_text(json.dumps(info))
        bad, why = info_path, f"object {obj}: diameter "
    elif case == "garbage_ply":
        ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n\x00\xff garbage")
        bad, why = ply, ""
    else:
        import trimesh

        m = trimesh.load(ply, process=False)
        m.apply_scale(0.001)
        ply.write_bytes(trimesh.exchange.ply.export_ply(m, encoding="binary"))
        bad, why = ply, "the model is "
    out = tmp_path / "R"
    args = ["dataset", "build", scene, "--out", out] + (["--layout", "bop", "--split", "hard"] if layout == "bop" else [])
    rc, msg = cli(capsys, *args)
    assert rc == 2 and msg.startswith(f"error: {bad}: {why}"), msg
    assert not out.exists()


def test_scenes_of_two_image_sizes_are_refused(scenes, tmp_path, capsys):
    rc, msg = cli(capsys, "dataset", "build", scenes["single/12"], scenes["single/05@64x48"], "--out", tmp_path / "R")
    assert rc == 2 and msg == (f"error: {scenes['single/12']}: its images are 80x60 (width x height), those of "
                               f"single/cuboid_330 ({scenes['single/05@64x48']}) are 64x48: a dataset has one image size")
    assert not (tmp_path / "R").exists()


# ------------------------------------------------------------------------------------- F6 / F5 / pack
@pytest.fixture(scope="module")
def multi_only(scenes, tmp_path_factory):
    root = tmp_path_factory.mktemp("m08") / "R"
    build_dataset([scenes["multi/08"]], root, show_progress=False)
    return root


def good_csv(path: Path, root: Path) -> Path:
    t = load(root / "test_targets_hard.json")[0]
    gt = load(root / "scenes" / f"{t['scene_id']:06d}" / "scene_gt.json")[str(t["im_id"])]
    g = next(g for g in gt if g["obj_id"] == t["obj_id"])
    R, tt = " ".join(map(str, g["cam_R_m2c"])), " ".join(map(str, g["cam_t_m2c"]))
    path.write_text(f"{HEADER}\n{t['scene_id']},{t['im_id']},{t['obj_id']},1.0,{R},{tt},0.1\n")
    return path


def test_scoring_without_test_targets_is_refused(multi_only, tmp_path, capsys):
    csv = good_csv(tmp_path / "m.csv", multi_only)
    assert cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "hard")[0] == 0
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "simple")
    assert rc == 2 and msg == (f"error: {multi_only / 'test_targets_simple.json'}: no test targets in this file: the "
                               "simple split of the dataset has none to score: the dataset has 0 single-object and 1 "
                               "multi-object scene (multi/08); simple needs single-object scenes (single/<class>)")
    (tmp_path / "none.json").write_text("[]")
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--targets", tmp_path / "none.json")
    assert rc == 2 and msg == f"error: {tmp_path / 'none.json'}: no test targets in this file: nothing to score"


def test_simple_split_of_too_few_steps_says_so(scenes, tmp_path, capsys):
    root = tmp_path / "R"
    build_dataset([scenes["single/05@64x48"]], root, show_progress=False)  # 3 steps: no test arc
    assert split_images(root, "simple", "test") == [] and len(split_images(root, "simple", "train")) == 3
    rc, msg = cli(capsys, "dataset", "pack", root, "--split", "simple", "--part", "test", "--out", tmp_path / "t.h5")
    assert rc == 2 and msg.endswith("its single-object scenes have 3 steps per arm position: a test arc needs at least 4")
    rc, msg = cli(capsys, "benchmark", "score", tmp_path / "any.csv", "--dataset", root, "--split", "simple")
    assert rc == 2 and "no test targets in this file: the simple split of the dataset has none" in msg


def test_ids_beyond_int64_are_one_line_errors(multi_only, tmp_path, capsys):
    csv = good_csv(tmp_path / "big.csv", multi_only)
    lines = csv.read_text().splitlines()
    f = lines[1].split(",")
    lines.append(",".join(["99999999999999999999999", *f[1:]]))
    csv.write_text("\n".join(lines) + "\n")
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "hard")
    assert rc == 2 and msg == (f"error: {csv}: line 3: scene_id 99999999999999999999999 is too large for an id "
                               f"(at most {2**63 - 1})")
    t = load(multi_only / "test_targets_hard.json")[:1]
    t[0]["im_id"] = 2**64
    (tmp_path / "t.json").write_text(json.dumps(t))
    rc, msg = cli(capsys, "benchmark", "score", good_csv(tmp_path / "g.csv", multi_only), "--dataset", multi_only,
                  "--targets", tmp_path / "t.json")
    assert rc == 2 and msg == f"error: {tmp_path / 't.json'}: target 0: im_id {2**64} is too large (at most {2**63 - 1})"


def test_outputs_are_checked_before_the_work(multi_only, scenes, tmp_path, capsys):
    csv = good_csv(tmp_path / "m.csv", multi_only)
    plots = tmp_path / "plots"
    plots.write_text("keep me")
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "hard", "--plots", plots)
    assert rc == 2 and msg == f"error: {plots}: --plots names a file: give a folder for the plots and report.md"
    assert plots.read_text() == "keep me"
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "hard", "--json", tmp_path)
    assert rc == 2 and msg == f"error: {tmp_path}: --json names a folder: give the JSON file to write"
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", multi_only, "--split", "hard",
                  "--json", plots / "s.json")
    assert rc == 2 and msg == f"error: {plots / 's.json'}: --json: {plots} is a file, so nothing can be written under it"
    target = tmp_path / "dataset.txt"
    target.write_text("keep me")
    rc, msg = cli(capsys, "dataset", "build", scenes["multi/08"], "--out", target)
    assert rc == 2 and msg == f"error: {target}: --out names a file: give a folder for the dataset"
    assert target.read_text() == "keep me"
    (tmp_path / "shard").mkdir()
    rc, msg = cli(capsys, "dataset", "pack", multi_only, "--split", "hard", "--part", "test", "--out",
                  tmp_path / "shard")
    assert rc == 2 and msg == f"error: {tmp_path / 'shard'}: --out names a folder: give the HDF5 file to write"
    assert list((tmp_path / "shard").iterdir()) == []


def test_packing_an_empty_part_names_split_part_root_and_contents(multi_only, tmp_path, capsys):
    rc, msg = cli(capsys, "dataset", "pack", multi_only, "--split", "simple", "--part", "train",
                  "--out", tmp_path / "s.h5")
    assert rc == 2 and msg == (f"error: {multi_only}: nothing to pack: the simple split's train part has no images "
                               "(splits/simple_train.json): the dataset has 0 single-object and 1 multi-object scene "
                               "(multi/08); simple needs single-object scenes (single/<class>)")
    rc, msg = cli(capsys, "dataset", "pack", multi_only, "--split", "hard", "--part", "train",
                  "--out", tmp_path / "h.h5")
    assert rc == 2 and msg.endswith("hard trains on single-object scenes (single/<class>) and the multi-object "
                                    "scenes not in its test set (multi/00, 01, 03-07, 12-14, 16-19)")
    assert not (tmp_path / "s.h5").exists() and not (tmp_path / "h.h5").exists()



def test_a_splits_file_naming_an_unknown_scene_is_named(multi_only, tmp_path, capsys):
    root = tmp_path / "R"
    shutil.copytree(multi_only, root)
    f = root / "splits" / "hard_test.json"
    m = load(f)
    m["39"] = [0, 1]
    f.write_text(json.dumps(m))
    rc, msg = cli(capsys, "dataset", "pack", root, "--split", "hard", "--part", "test", "--out", tmp_path / "h.h5")
    assert rc == 2 and msg == (f"error: {f}: names scene 39, which the dataset does not hold (scenes/: 29)"), msg
    assert not (tmp_path / "h.h5").exists()

# ------------------------------------------------------------------------------------- one reader
def test_one_file_reader_names_the_file_and_the_problem(tmp_path):
    from tdof20.dataset.results import read_results
    from tdof20.formats import read_json, read_model_mesh, read_png
    from tdof20.formats.io import read_toml

    folder = tmp_path / "d.csv"
    folder.mkdir()
    with pytest.raises(TdofError, match=r"d\.csv: is a folder, not a results file$"):
        read_results(folder)
    with pytest.raises(TdofError, match=r"d\.csv: is a folder, not a model file$"):
        read_model_mesh(folder)
    with pytest.raises(TdofError, match=r"d\.csv: is a folder, not a file$"):
        read_json(folder)
    with pytest.raises(TdofError, match=r"d\.csv: is a folder, not a file$"):
        read_png(folder)
    (tmp_path / "f").write_text("x")
    with pytest.raises(TdofError, match=r"a part of its path is a file"):
        read_json(tmp_path / "f" / "scene_gt.json")
    latin = tmp_path / "x.json"
    latin.write_bytes(b'{\n "name": "caf\xe9"\n}\n')
    with pytest.raises(TdofError, match=r"x\.json: line 2: not UTF-8 text$"):
        read_json(latin)
    latin_csv = tmp_path / "x.csv"
    latin_csv.write_bytes((HEADER + "\n").encode() + b"1,2,3,caf\xe9\n")
    with pytest.raises(TdofError, match=r"x\.csv: line 2: not UTF-8 text$"):
        read_results(latin_csv)
    with pytest.raises(TdofError, match=r"nope\.toml: config file not found$"):
        read_toml(tmp_path / "nope.toml")
    with pytest.raises(TdofError, match=r"nope\.csv: results file not found$"):
        read_results(tmp_path / "nope.csv")


def test_oracle_labels_refuse_a_corrupt_truth_png(scenes, tmp_path, capsys):
    """`sim label` decodes the truth's own PNGs (no checksum guards them) before copying: a
    truncated mask is one line naming it, not a scene that dataset build refuses later."""
    raw = tmp_path / "raw"
    shutil.copytree(scenes["single/05@64x48"].parent.parent / "raw" / "single_05", raw)
    mask = sorted((raw / "truth" / "mask_visib").glob("*.png"))[1]
    mask.write_bytes(mask.read_bytes()[:50])
    rc, msg = cli(capsys, "sim", "label", raw, "--out", tmp_path / "scene")
    assert rc == 2 and msg.startswith(f"error: {mask}: corrupt PNG")
