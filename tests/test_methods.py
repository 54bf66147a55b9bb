"""The method interface: the registry, every registered method's five pieces at a tiny size, the
profile (Table 3), and an HFF6DoF run folder written before the interface loading through it."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from tdof20.errors import TdofError
from tdof20.methods import registry
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PoseMethod, ReproduceSettings
from tdof20.methods.data import collate
from tdof20.methods.profile import count_macs, example_batch, format_profile, format_table, profile, \
    profile_method, synthetic_item, synthetic_meta, train_speed

pytestmark = pytest.mark.usefixtures("one_torch_thread")

HW = (48, 64)
#: small but valid options per method (the defaults are sized for 480x640)
TINY = {
    "hff6dof": {},
    "pvnet": {},
    "densefusion": {"n_points": 64, "n_model_points": 60, "crop_size": 32, "min_points": 10},
    "ffb6d": {"n_points": 256, "meanshift_iters": 20, "max_votes": 200},
}
EXPECTED = ("hff6dof", "pvnet", "densefusion", "ffb6d")


def tiny_cfg(m: registry.Method):
    return m.config_from(TINY.get(m.name, {}), "tiny")


def test_registry_lists_the_methods_and_stays_torch_free():
    names = registry.method_names()
    assert names == list(EXPECTED)
    for name in names:
        m = registry.get_method(name)
        assert m.name == name and m.inputs in registry.INPUTS and m.description and "\n" not in m.description
        assert len(m.default_image_size) == 2
    assert registry.get_method(" PVNet ").name == "pvnet"
    code = ("import sys, tdof20.methods.registry as r; r.method_names(); r.get_method('hff6dof').reproduce; "
            "import tdof20.methods.contract; assert 'torch' not in sys.modules, 'torch imported'")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


def test_each_method_implements_the_contract():
    """The registry holds contract objects; each record's implementation is a PoseMethod subclass
    with its config dataclass, and the hooks the shared loops ask replace tests of a method's name."""
    for m in registry.methods():
        assert isinstance(m, PoseMethod) and isinstance(m.impl, PoseMethod) and not type(m.impl).__abstractmethods__
        assert m.config_class is type(m.impl).config_class and isinstance(m.default_config(), m.config_class)
        assert m.reproduce.label and set(m.reproduce.candidates) <= set(m.reproduce.choice_options)
    hff = registry.get_method("hff6dof")
    assert hff.ddp_find_unused_parameters is False and hff.labels_are_classes is True
    assert all(m.ddp_find_unused_parameters and not m.labels_are_classes for m in registry.methods() if m is not hff)
    assert hff.missing_run_keys({"network": {"n_classes": 21}})[:1] == ["network.n_keypoints"]
    assert registry.get_method("pvnet").missing_run_keys({}) == ["method_config"]


def test_set_options_are_parsed_as_toml_and_checked_as_the_config():
    parse = registry.parse_set_options
    assert parse(["fuse_stages=2", "seg_head=false", "masks=gt", "voting = 3d", "bearing_tol=4e-2",
                  "decoder_channels=[8, 8, 8, 8, 8, 8]", 'backbone_weights="a b.pth"', "a.b.c=1"]) == {
        "fuse_stages": 2, "seg_head": False, "masks": "gt", "voting": "3d", "bearing_tol": 0.04,
        "decoder_channels": [8] * 6, "backbone_weights": "a b.pth", "a": {"b": {"c": 1}}}
    for bad in (["fuse_stages"], ["=2"], ["a..b=1"], ["a=1", "a.b=2"]):
        with pytest.raises(TdofError, match="--set"):
            parse(bad)
    m = registry.get_method("hff6dof")
    cfg = m.with_options(m.default_config(), parse(["fuse_stages=2", "masks=gt"]), "--set")
    assert cfg.fuse_stages == 2 and cfg.masks == "gt" and m.with_options(cfg, {}, "--set") is cfg
    for changes, key in (({"fuse_stage": 2}, "fuse_stage"), ({"fuse_stages": "two"}, "fuse_stages"),
                         ({"fuse_stages": 9}, "fuse_stages"), ({"masks": "oracle"}, "masks")):
        with pytest.raises(TdofError, match=f"--set: .*{key}") as e:
            m.with_options(cfg, changes, "--set")
        assert "\n" not in str(e.value)


def test_unknown_method_is_one_line_listing_the_known_ones(tmp_path):
    with pytest.raises(TdofError) as e:
        registry.get_method("posecnn")
    msg = str(e.value)
    assert "\n" not in msg and "posecnn" in msg and all(n in msg for n in registry.method_names())
    with pytest.raises(TdofError, match="config.json.*the run's method.*unknown method 'x'"):
        registry.run_method({"method": "x"}, tmp_path / "config.json")
    with pytest.raises(TdofError, match="no \"method\""):
        registry.run_method({"network": {}}, tmp_path / "config.json")
    with pytest.raises(ValueError, match="registered already"):
        registry.register(registry.get_method("pvnet"))
    with pytest.raises(ValueError, match="'all'"):
        registry.register(registry.Method("all", "d", "rgb", lambda: None, ReproduceSettings("All")))
    with pytest.raises(TdofError, match="tiny: .*fuse_stage"):
        registry.get_method("hff6dof").config_from({"fuse_stage": 2}, "tiny")
    res = subprocess.run([sys.executable, "-m", "tdof20.cli", "benchmark", "profile", "posecnn"],
                         capture_output=True, text=True, timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode != 0 and len(lines) == 1 and "posecnn" in lines[0] and "hff6dof" in lines[0], res.stderr


@pytest.mark.parametrize("name", EXPECTED)
def test_every_method_builds_trains_and_predicts_through_the_interface(name):
    if name not in registry.method_names():
        pytest.skip(f"{name} is not registered (its module is missing)")
    m = registry.get_method(name)
    cfg = tiny_cfg(m)
    data = m.config_to_data(cfg)
    assert json.loads(json.dumps(data)) == data                         # what a run records
    assert m.config_from(data, "round trip") == cfg
    meta = synthetic_meta(3, HW)
    torch.manual_seed(0)
    net = m.build(cfg, meta)
    tf = m.transform(cfg, meta, train=True)
    items = [synthetic_item(meta, n_objects=2, seed=s) for s in range(2)]
    batch = collate([tf(it) for it in items])
    assert batch["rgb"].shape == (2, 3, *HW)
    net.train()
    total, parts = m.loss(net, batch, cfg, meta)
    assert total.dim() == 0 and math.isfinite(float(total.detach())) and float(total.detach()) > 0
    assert parts and all(isinstance(v, float) for v in parts.values())
    total.backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)

    pbatch = collate([m.transform(cfg, meta, train=False)(it) for it in items])
    out = m.forward(net.eval(), {**pbatch, **(m.example_batch(cfg, meta, 2) or {})})
    assert isinstance(out, dict) and "seg" in out
    rows = m.predict_poses(net, pbatch, cfg, meta)
    assert isinstance(rows, list)
    for b, obj, score, R, t in rows:
        assert isinstance(b, int) and 0 <= b < 2 and obj in meta.obj_ids and isinstance(score, float)
        assert isinstance(R, np.ndarray) and R.shape == (3, 3) and isinstance(t, np.ndarray) and t.shape == (3,)
        assert np.isfinite(R).all() and np.isfinite(t).all()


def test_hff6dof_with_ground_truth_masks_gives_a_pose_per_object():
    m = registry.get_method("hff6dof")
    cfg = m.config_from({"masks": "gt", "voting": "bearing"})
    meta = synthetic_meta(3, HW)
    torch.manual_seed(0)
    net = m.build(cfg, meta).eval()
    item = synthetic_item(meta, n_objects=3, seed=1)
    rows = m.predict_poses(net, collate([m.transform(cfg, meta)(item)]), cfg, meta)
    # the untrained vectors still vote; each object of the ground-truth masks gets at most one row
    objs = [r[1] for r in rows]
    assert len(objs) == len(set(objs)) and set(objs) <= set(item["obj_id"].tolist())
    with pytest.raises(TdofError, match="masks"):
        m.config_from({"masks": "oracle"})


def test_profile_of_every_method_at_a_tiny_size():
    rows = []
    for name in registry.method_names():
        m = registry.get_method(name)
        p = profile_method(name, "cpu", *HW, repeats=1, warmup=0, n_objects=3, cfg=tiny_cfg(m), macs_size=HW)
        assert p["parameters"] > 1e5 and p["macs_480x640"] > 1e6 and p["macs_size"] == list(HW)
        assert p["network_ms"] > 0 and p["end_to_end_ms"] > 0 and p["pose_ms"] >= 0 and p["input_ms"] > 0
        assert p["untrained"] and p["inputs"] == m.inputs and isinstance(p["poses"], int)
        assert "multiply-adds" in format_profile(p) and name in format_profile(p)
        rows.append(p)
    rows.append({"method": "broken", "error": "it failed"})
    text = format_table(rows)
    assert all(p["method"] in text for p in rows) and "broken" in text and "untrained" in text
    with pytest.raises(TdofError, match="unknown method"):
        profile("posecnn", "cpu")
    with pytest.raises(TdofError, match="height and width"):
        profile_method("pvnet", "cpu", 8, 8)


def test_table3_counts_of_hff6dof_at_480x640():
    """The paper's network: 56.82 M parameters (ours 56.76 M), under 85.12 G multiply-adds."""
    m = registry.get_method("hff6dof")
    cfg = m.default_config()
    meta = synthetic_meta(20, (480, 640))
    with torch.device("meta"):
        net = m.build(cfg, meta)
    assert sum(p.numel() for p in net.parameters()) == 56_758_992
    batch = {"rgb": torch.zeros(1, 3, 480, 640), "geo": torch.zeros(1, 6, 480, 640)}
    assert abs(count_macs(m, cfg, meta, batch) / 1e9 - 84.273) < 0.001


def test_training_speed_runs_a_few_real_steps():
    s = train_speed("pvnet", "cpu", batch_size=2, steps=1, image_size=HW, n_objects=3)
    assert s["images_per_s"] > 0 and s["image_size"] == list(HW) and math.isfinite(s["loss"])


def _old_run(tmp_path, classes=None):
    """A run folder as train.py wrote it before the interface: config.json + last.pt."""
    from tdof20.methods.hff6dof import HFF6DoF

    kp = synthetic_meta(20, (48, 64)).keypoints
    torch.manual_seed(1)
    small = dict(decoder_channels=(8, 8, 8, 8, 8, 8), head_channels=8)
    n = 21 if classes is None else len(classes) + 1
    net = HFF6DoF(n_classes=n, n_keypoints=9, fuse_stages=2, seg_head=True, **small)
    config = {"method": "hff6dof", "version": 1,
              "network": {k: list(v) if isinstance(v, tuple) else v for k, v in net.config.items()},
              "image_size": [48, 64], "depth_mode": "raw", "split": "simple",
              "keypoints": {str(o): kp[o].tolist() for o in (classes or range(1, 21))},
              "train": {"batch_size": 2, "epochs": 1}}
    if classes is not None:
        config["classes"] = list(classes)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(config))
    torch.save({"model": net.state_dict(), "epoch": 1, "step": 1}, run / "last.pt")
    return run, net


@pytest.mark.parametrize("classes", [None, (3, 7, 12)])
def test_an_hff6dof_run_from_before_the_interface_loads_through_the_registry(tmp_path, classes):
    run, net0 = _old_run(tmp_path, classes)
    config = json.loads((run / "config.json").read_text())
    m = registry.run_method(config, run / "config.json")
    assert m.name == "hff6dof"
    cfg, meta = m.config_from_run(config, run / "config.json")
    assert meta.obj_ids == (tuple(range(1, 21)) if classes is None else classes)
    assert meta.image_size == (48, 64) and cfg.depth_mode == "raw" and cfg.fuse_stages == 2
    net = m.build(cfg, meta)
    net.load_state_dict(torch.load(run / "last.pt", weights_only=True)["model"])   # strict: every weight fits
    x = torch.rand(1, 3, 48, 64), torch.rand(1, 6, 48, 64)
    with torch.no_grad():
        assert torch.equal(net.eval()(*x)["vec"], net0.eval()(*x)["vec"])
    item = synthetic_item(meta, n_objects=2, seed=0)
    rows = m.predict_poses(net, collate([m.transform(cfg, meta)(item)]), cfg, meta)
    assert all(r[1] in meta.obj_ids for r in rows)
    # a run written with the interface records its config and meta, and reads them back
    new = {"method": "hff6dof", "method_config": m.config_to_data(cfg), "meta": meta.to_json()}
    cfg2, meta2 = m.config_from_run(json.loads(json.dumps(new)))
    assert cfg2 == cfg and meta2.obj_ids == meta.obj_ids
    assert np.allclose(meta2.keypoints[meta.obj_ids[0]], meta.keypoints[meta.obj_ids[0]])


def test_a_damaged_old_run_config_is_one_line(tmp_path):
    run, _ = _old_run(tmp_path)
    config = json.loads((run / "config.json").read_text())
    m = registry.get_method("hff6dof")
    del config["keypoints"]["5"]
    with pytest.raises(TdofError, match=r"config.json: its keypoints lack objects \[5\]"):
        m.config_from_run(config, run / "config.json")
    del config["network"]
    with pytest.raises(TdofError, match="config.json: not a readable HFF6DoF run config"):
        m.config_from_run(config, run / "config.json")


@pytest.mark.parametrize("version", [99, "2", 0, True])
def test_a_run_of_an_unknown_version_is_refused(tmp_path, version):
    from tdof20.methods.runs import RUN_VERSION, read_run_config

    run, _ = _old_run(tmp_path)
    assert read_run_config(run)["version"] == 1
    config = json.loads((run / "config.json").read_text())
    config["version"] = version
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(TdofError, match=rf"config.json: is a run of version {version!r}; this tdof20 reads "
                                        rf"versions 1..{RUN_VERSION}"):
        read_run_config(run)


def test_example_batches_hold_what_forward_needs():
    for name in registry.method_names():
        m = registry.get_method(name)
        cfg = tiny_cfg(m)
        meta = MethodMeta.from_json(synthetic_meta(2, HW).to_json())
        b = example_batch(m, cfg, meta, 1)
        assert b["rgb"].shape == (1, 3, *HW) and b["K"].shape == (1, 3, 3)
