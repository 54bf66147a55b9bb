"""Dataset assembly, the two protocols, test targets, HDF5 shards."""

import json
import shutil

import numpy as np
import pytest

from tdof20.dataset.build import build_dataset, pack, split_images, stats
from tdof20.dataset.splits import (HARD_TEST_MULTI, PAPER_HARD, PAPER_SIMPLE, part_of, scene_name,
                                     scene_number)
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import read_scene
from tdof20.dataset.shards import ShardDataset
from tdof20.sim.scenes import normalize_scene_id
from tdof20.sim.truth import oracle_scene


def test_scene_ids():
    assert scene_number("single/07") == scene_number("single/handle_cup_280") == 7
    assert scene_number("multi/08") == 29 and scene_number("multi/00") == 21 and scene_number("multi/19") == 40
    assert scene_name(1) == "single/cube_136" and scene_name(21) == "multi/00"
    assert all(scene_name(scene_number(n)) == n for n in ("single/cube_136", "single/whisky_cup_270", "multi/19"))
    assert scene_name(scene_number("single/01")) == "single/cube_136"
    for bad in ("multi/20", "multi/21", "single/mug"):
        with pytest.raises(TdofError, match="unknown scene"):
            scene_number(bad)


def test_protocols_follow_the_paper_on_its_layout():
    """40 scenes of 4 arm positions x 400 steps, counted without any images."""
    n_arms, steps = 4, 400
    counts = {}
    for split in ("simple", "hard"):
        for sid in range(1, 41):
            for im in range(n_arms * steps):
                part = part_of(split, sid, im, steps, n_arms)
                if part:
                    counts[(split, part)] = counts.get((split, part), 0) + 1
    simple_ratio = counts[("simple", "test")] / (counts[("simple", "train")] + counts[("simple", "test")])
    assert simple_ratio == pytest.approx(PAPER_SIMPLE[1] / sum(PAPER_SIMPLE), abs=0.002)
    hard_ratio = counts[("hard", "test")] / (counts[("hard", "train")] + counts[("hard", "test")])
    assert hard_ratio == pytest.approx(PAPER_HARD[1] / sum(PAPER_HARD), abs=0.005)
    assert counts[("simple", "train")] + counts[("simple", "test")] == 20 * 1600
    assert counts[("hard", "test")] == 6 * 1600
    # hard: exactly the six unseen multi-object scenes are test
    test_scenes = {sid for sid in range(1, 41) if part_of("hard", sid, 0, steps, n_arms) == "test"}
    assert test_scenes == {21 + m for m in HARD_TEST_MULTI} == {23, 29, 30, 31, 32, 36}
    # simple: test frames form one contiguous arc per arm position, rotated between arms
    for arm in range(n_arms):
        test = [k for k in range(steps) if part_of("simple", 3, arm * steps + k, steps, n_arms) == "test"]
        assert len(test) == 60
        assert len({(k - test[0]) % steps for k in test}) == 60 and max((k - test[0]) % steps for k in test) == 59


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    base = tmp_path_factory.mktemp("ds")
    scenes = []
    for sc in ("single/03", "multi/08"):
        raw = base / "raw" / sc.replace("/", "_")
        run_capture(sim_config(sc, steps=8, step_deg=45.0, n_arms=2, width=80, height=60), raw, yes=True,
                    show_progress=False)
        scenes.append(oracle_scene(raw, base / "labels" / sc.replace("/", "_"), show_progress=False))
    return base, scenes


@pytest.fixture(scope="module")
def dataset(labelled):
    base, scenes = labelled
    root = base / "root"
    build_dataset(scenes, root, show_progress=False)
    return root


def test_oracle_scene_is_a_complete_annotated_scene(labelled):
    _, scenes = labelled
    s = read_scene(scenes[1])
    assert len(s.im_ids()) == 16
    for sub in ("rgb", "depth", "depth_opaque", "depth_restored"):
        assert len(list((scenes[1] / sub).glob("*.png"))) == 16
    # restored depth is complete where the raw transparent depth is mostly missing on the glass
    im = s.im_ids()[5]
    raw = s.depth(im)
    rest = s.image("depth_restored", im)
    glass = np.any([s.mask(im, g, visib=True) for g in range(len(s.gt[im]))], axis=0)
    assert (rest[glass] > 0).mean() > 0.99 and (raw[glass] > 0).mean() < 0.6


def test_dataset_info_names_scenes_given_by_their_alias(labelled, tmp_path):
    _, scenes = labelled
    alias = tmp_path / "s03"
    shutil.copytree(scenes[0], alias)
    p = alias / "scene_info.json"
    d = json.loads(p.read_text())
    assert d["scene_id"] == "single/cube_216"
    p.write_text(json.dumps(d | {"scene_id": "single/03"}))  # an older or hand-written scene_info.json
    build_dataset([alias], tmp_path / "root", show_progress=False)
    info = json.loads((tmp_path / "root" / "dataset_info.json").read_text())
    assert info["scenes"] == {"3": "single/cube_216"} and normalize_scene_id("single/03") == "single/cube_216"


def test_build_layout_splits_and_targets(dataset):
    root = dataset
    info = json.loads((root / "dataset_info.json").read_text())
    assert info["scenes"] == {"3": "single/cube_216", "29": "multi/08"}  # capture stored the alias's name
    assert (root / "scenes" / "000003" / "rgb").is_dir() and (root / "scenes" / "000029").is_dir()
    assert sorted(p.name for p in (root / "models").glob("*.ply"))[0] == "obj_000003.ply"
    cam = json.loads((root / "camera.json").read_text())
    assert (cam["width"], cam["height"]) == (80, 60)
    simple_train, simple_test = split_images(root, "simple", "train"), split_images(root, "simple", "test")
    assert not set(simple_train) & set(simple_test)
    assert {s for s, _ in simple_train + simple_test} == {3}
    assert len(simple_test) == 2 * round(8 * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE))
    assert {s for s, _ in split_images(root, "hard", "test")} == {29}  # multi/08 is a hard test scene
    assert {s for s, _ in split_images(root, "hard", "train")} == {3}
    targets = json.loads((root / "test_targets_hard.json").read_text())
    scene = read_scene(root / "scenes" / "000029")
    for t in targets:
        gt = scene.gt[t["im_id"]]
        assert t["obj_id"] in [g["obj_id"] for g in gt] and t["inst_count"] == 1
    st = stats(root)
    assert st["images"] == 32 and st["splits"]["hard_test"] == 16 and st["per_object"][3] == 16


def test_build_refuses_conflicts(labelled, tmp_path):
    base, scenes = labelled
    with pytest.raises(TdofError, match="given twice"):
        build_dataset([scenes[0], scenes[0]], tmp_path / "a", show_progress=False)
    other = tmp_path / "other"
    shutil.copytree(scenes[1], other)
    ply = other / "models" / "obj_000003.ply"
    if not ply.exists():  # multi/08 may not hold object 3: give it a conflicting copy of another
        ply = sorted((other / "models").glob("*.ply"))[0]
    from tdof20.formats.bop import read_model_mesh, write_model_mesh

    V, F = read_model_mesh(ply)
    V[0] += 0.5  # another model of the same object, sound and of the same size
    write_model_mesh(ply, V, F)
    shutil.copytree(scenes[1], tmp_path / "m08b")
    (tmp_path / "m08b" / "scene_info.json").write_text(
        (tmp_path / "m08b" / "scene_info.json").read_text().replace("multi/08", "multi/09"))
    with pytest.raises(TdofError, match="different model"):
        build_dataset([tmp_path / "m08b", other], tmp_path / "b", show_progress=False)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "x").write_text("x")
    with pytest.raises(TdofError, match="not empty"):
        build_dataset(scenes, tmp_path / "c", show_progress=False)


def test_pack_and_torch_dataset_round_trip(dataset, tmp_path):
    out = pack(dataset, "hard", "test", tmp_path / "hard_test.h5", show_progress=False)
    ds = ShardDataset(out)
    ims = split_images(dataset, "hard", "test")
    assert len(ds) == len(ims)
    scene = read_scene(dataset / "scenes" / "000029")
    for n in (0, 7):
        item = ds[n]
        sid, im = ims[n]
        assert (item["scene_id"], item["im_id"]) == (sid, im)
        assert np.array_equal(item["rgb"].permute(1, 2, 0).numpy(), scene.rgb(im))
        assert np.allclose(item["depth"].numpy(), scene.depth_mm(im))
        for g, entry in enumerate(scene.gt[im]):
            R, t = scene.pose(im, g)
            assert item["obj_id"][g] == entry["obj_id"]
            assert np.allclose(item["R"][g].numpy(), R, atol=1e-6) and np.allclose(item["t"][g].numpy(), t, atol=1e-3)
            assert np.array_equal(item["label"].numpy() == entry["obj_id"], scene.mask(im, g, visib=True))
    import torch
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2)
    batch = next(iter(loader))
    assert batch["rgb"].shape == (4, 3, 60, 80)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(TdofError, match="bad.h5"):
        ShardDataset(tmp_path / "bad.h5")
    # contents a training must not take (a shard edited or written by other code): a NaN pose,
    # translations in metres, depth of another dtype
    import shutil

    import h5py

    def edited(name, edit):
        path = tmp_path / f"{name}.h5"
        shutil.copyfile(out, path)
        with h5py.File(path, "a") as f:
            edit(f)
        return path

    def nan(f):
        t = f["t"][:]
        t[0, 0, 0] = np.nan
        f["t"][...] = t

    def metres(f):
        f["t"][...] = f["t"][:] / 1000.0

    def float_depth(f):
        d = f["depth"][:].astype(np.float64)
        del f["depth"]
        f["depth"] = d

    for name, edit, needle in (("nan", nan, "not finite"), ("metres", metres, "look like metres"),
                               ("f64", float_depth, "depth is float64, uint16 expected")):
        with pytest.raises(TdofError, match=needle) as e:
            ShardDataset(edited(name, edit))
        assert f"{name}.h5" in str(e.value)
