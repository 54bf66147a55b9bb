"""The segmentation network ('segnet') and HFF6DoF's masks = 'segnet': the seg-off ablation's masks
from a separately trained network, not from the ground truth.

One tiny simulated dataset (module fixture): single/juice_cup_340 (id 12), 4 arm positions x 6
turntable steps at 80x60 (20 training images). One segnet training (15 steps of 4 images at 32x48)
serves the tests; the pose run is an untrained HFF6DoF without its segmentation head (max_steps=0):
its poses come from whatever pixels the masks give it, which is what is tested.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from tdof20.capture import run_capture, sim_config
from tdof20.dataset.build import build_dataset, split_images
from tdof20.errors import TdofError
from tdof20.methods.data import SceneImages, collate
from tdof20.methods.predict import impossible_pose, predict, predict_rows, prediction_config, segmentation_iou
from tdof20.methods.registry import get_method, method_names
from tdof20.methods.runs import open_run
from tdof20.methods.train import train
from tdof20.sim.truth import oracle_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SIZE = (32, 48)
OPTS = dict(image_size=SIZE, batch_size=4, num_workers=0, progress=False, device="cpu", seed=0)
SEG_STEPS = 15
POSE_CFG = {"seg_head": False, "n_hyp": 16, "max_points": 100}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    base = tmp_path_factory.mktemp("seg")
    raw = base / "raw"
    run_capture(sim_config("single/juice_cup_340", steps=6, step_deg=5.0, n_arms=4, width=80, height=60), raw,
                yes=True, show_progress=False)
    root = base / "root"
    build_dataset([oracle_scene(raw, base / "labels", show_progress=False)], root, show_progress=False)
    return root


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    base = tmp_path_factory.mktemp("segruns")
    seg = train(dataset, "simple", base / "seg", method="segnet", max_steps=SEG_STEPS, epochs=100, lr=2e-3, **OPTS)
    pose = train(dataset, "simple", base / "pose", method_config=POSE_CFG, max_steps=0, **OPTS)
    return {"seg": seg, "pose": pose, "base": base}


def _fg_fraction(dataset, images) -> float:
    items = SceneImages(dataset, images, labels=True, restored=False)
    return float(np.mean([(items[i]["label"] > 0).float().mean().item() for i in range(len(items))]))


def test_segnet_is_registered_as_a_mask_producer_not_a_compared_pose_method():
    m = get_method("segnet")
    assert m.produces == "masks" and m.inputs == "rgb"
    assert "segnet" in method_names(None) and "segnet" not in method_names()
    assert all(x.produces == "poses" for x in map(get_method, method_names()))
    with pytest.raises(TdofError, match="produces masks, not poses"):
        m.predict_poses(None, {}, m.default_config(), None)
    with pytest.raises(TdofError, match="produces poses, not masks"):
        get_method("hff6dof").predict_masks(None, {}, None, None)
    with pytest.raises(TdofError, match="backbone"):
        m.config_from({"backbone": "vgg"})


def test_segnet_trains_and_its_masks_beat_chance_on_training_images(runs, dataset):
    cfg = json.loads((runs["seg"] / "config.json").read_text())
    assert cfg["method"] == "segnet" and cfg["image_size"] == list(SIZE) and cfg["dataset_sha256"]
    hist = json.loads((runs["seg"] / "history.json").read_text())
    assert hist["steps"] == SEG_STEPS
    images = split_images(dataset, "simple", "train")
    iou = segmentation_iou(runs["seg"], dataset, "simple", "train", device="cpu", images=images)
    chance = _fg_fraction(dataset, images)  # the IoU of calling every pixel the object (all background: 0)
    assert set(iou["per_class"]) == {12} and 0.01 < chance < 0.1
    assert iou["mean"] > 2.5 * chance, (iou, chance)


def test_hff6dof_predicts_with_the_segnet_masks(runs, dataset, tmp_path):
    """predict gives the pose method the segmentation run's masks: its rows are those of the method's
    own predict_poses fed, image by image, with the segnet's classes as its labels; an empty
    segmentation gives no pose at all."""
    images = split_images(dataset, "simple", "train")[:6]
    opts = dict(device="cpu", num_workers=0, progress=False, images=images, min_pixels=1)
    rows, info = predict_rows(runs["pose"], dataset, "simple", masks="segnet", seg_run=str(runs["seg"]), **opts)
    assert info["masks"] == "segnet" and info["seg_run"] == str(runs["seg"].resolve())
    assert info["method_config"]["seg_run"] == str(runs["seg"])
    seg, pose = open_run(runs["seg"], "cpu"), open_run(runs["pose"], "cpu")
    cfg = prediction_config(pose.method, pose.cfg, {"masks": "segnet", "seg_run": str(runs["seg"]), "min_pixels": 1},
                            seed=0)
    items = SceneImages(dataset, images, restored=False)
    expect, n_pixels = [], 0
    for n, (sid, im) in enumerate(images):
        item = items[n]
        classes, _ = seg.method.predict_masks(seg.net, collate([seg.method.transform(seg.cfg, seg.meta)(item)]),
                                              seg.cfg, seg.meta)
        n_pixels += int((classes == seg.meta.class_of(12)).sum())
        batch = collate([pose.method.transform(cfg, pose.meta)(item)]) | {"label": classes}
        found = pose.method.predict_poses(pose.net, batch, cfg, pose.meta)
        expect += [(sid, im, obj, R, t) for _, obj, _, R, t in found
                   if obj == 12 and not impossible_pose(R, t, pose.meta.diameters[12])]
    assert n_pixels > 0 and expect and len(rows) == len(expect)
    for r, e in zip(rows, expect):
        assert r[:3] == e[:3] and np.allclose(r[4], e[3], atol=1e-5) and np.allclose(r[5], e[4], atol=1e-3)
    # the same pose run with an empty segmentation (its background logit raised) finds nothing
    empty = tmp_path / "empty"
    shutil.copytree(runs["seg"], empty, ignore=shutil.ignore_patterns("data"))
    ckpt = torch.load(empty / "last.pt", map_location="cpu", weights_only=True)
    ckpt["model"]["net.final.0.bias"][0] += 1e3
    torch.save(ckpt, empty / "last.pt")
    rows0, info0 = predict_rows(runs["pose"], dataset, "simple", masks="segnet", seg_run=str(empty), **opts)
    assert rows0 == [] and info0["images"] == info["images"] == len(images) and info0["dropped_impossible_poses"] == 0
    # ground-truth masks stay possible, reported as such (an oracle)
    _, gt = predict_rows(runs["pose"], dataset, "simple", masks="gt", **opts)
    assert gt["masks"] == "gt" and "seg_run" not in gt


def _one_line(exc_info, *words):
    msg = str(exc_info.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_segnet_masks_refuse_what_does_not_fit(runs, dataset, tmp_path):
    pose = runs["pose"]
    kw = dict(device="cpu", num_workers=0, progress=False, masks="segnet")
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", device="cpu", num_workers=0, progress=False, masks="segnet")
    _one_line(e, "seg_run")
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", **kw, seg_run=str(tmp_path / "nothing"))
    _one_line(e, "no such segmentation run", "nothing")
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", **kw, seg_run=str(pose))
    _one_line(e, "hff6dof run", "not a segmentation run")
    with pytest.raises(TdofError) as e:  # seg_run without masks = 'segnet' would be silently ignored
        predict_rows(pose, dataset, "simple", device="cpu", num_workers=0, progress=False, masks="gt",
                     seg_run=str(runs["seg"]))
    _one_line(e, "seg_run is read only with masks = 'segnet'")
    # trained on other data: the train part without its validation part
    other = train(dataset, "simple", runs["base"] / "seg-tv", method="segnet", max_steps=0, part="train-val", **OPTS)
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", **kw, seg_run=str(other))
    _one_line(e, "trained on other data", "dataset digest")
    # at another image size
    small = train(dataset, "simple", runs["base"] / "seg-32", method="segnet", max_steps=0,
                  **{**OPTS, "image_size": (32, 32)})
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", **kw, seg_run=str(small))
    _one_line(e, "image size 32x32", "32x48")
    # on other objects (its classes in another order)
    moved = tmp_path / "moved"
    shutil.copytree(runs["seg"], moved, ignore=shutil.ignore_patterns("data"))
    cfg = json.loads((moved / "config.json").read_text())
    cfg["meta"]["obj_ids"] = cfg["meta"]["obj_ids"][::-1]
    (moved / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(TdofError) as e:
        predict_rows(pose, dataset, "simple", **kw, seg_run=str(moved))
    _one_line(e, "trained on other objects")
    # a segmentation run is not a pose method's run: predict refuses it in one line, writing nothing
    with pytest.raises(TdofError) as e:
        predict(runs["seg"], dataset, "simple", tmp_path / "r.csv", device="cpu", num_workers=0, progress=False)
    _one_line(e, "segnet run", "not poses", "seg_run=")
    assert not (tmp_path / "r.csv").exists()
