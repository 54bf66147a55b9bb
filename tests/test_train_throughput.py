"""Training at the hardware's limit (issue 23 part 8): the HFF6DoF transform's dense part run
batched (on the training device) gives the very batch of the per-item transform, its faster vector
targets and hole filling are bit-identical to the whole-frame definitions, and a training with
loader workers (persistent over epochs), resumed, ends with the weights of one without workers.
benchmarks/train_throughput.py measures the speed; nothing here is timed."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from tdof20.methods.data import backproject, collate, fill_depth_holes
from tdof20.methods.hff6dof_data import HFFTransform
from tdof20.methods.profile import synthetic_item, synthetic_meta
from tdof20.methods.runs import load_run, parameters_digest
from tdof20.methods.train import train
from tests.fixtures.bop_standard import write_bop_dataset

pytestmark = pytest.mark.usefixtures("one_torch_thread")

META = synthetic_meta(20, (48, 64))


def _items(n: int = 3) -> list[dict]:
    # frames with holes in the sensor depth (glass), none, and no depth on the objects at all
    return [synthetic_item(META, (60, 80), n_objects=3, seed=s, holes=h) for s, h in zip(range(n), (0.6, 0.0, 1.0))]


def _transform(mode: str, origin: str) -> HFFTransform:
    return HFFTransform({o: META.keypoints[o] for o in META.obj_ids}, (48, 64), mode, classes=list(META.obj_ids),
                        vector_origin=origin)


def _equal(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for k in a:
        if isinstance(a[k], torch.Tensor):
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and torch.equal(a[k], b[k]), k
        else:
            assert a[k] == b[k], k


@pytest.mark.parametrize("mode", ["filled", "raw", "restored"])
@pytest.mark.parametrize("origin", ["restored", "observed"])
def test_the_deferred_dense_part_gives_the_per_item_batch(mode, origin):
    items = _items()
    per_item = collate([_transform(mode, origin)(it) for it in items])
    tf = _transform(mode, origin)
    stage = tf.defer_to_device()
    light = tf(items[0])
    assert "vec" not in light and "geo" not in light and light["depth_raw"].shape == (48, 64)
    _equal(per_item, stage(collate([tf(it) for it in items])))
    assert per_item["mask"].any() and per_item["vec"].shape == (3, 27, 48, 64)


def test_vector_targets_are_the_whole_frame_definition():
    """The targets computed on the object pixels only equal the documented whole-frame field:
    unit vectors from each visible object pixel's back-projected point to its instance's
    keypoints in the true pose, 0 elsewhere."""
    tf = _transform("filled", "restored")
    for it in _items():
        lab, ins, dep = it["label"], it["instance"], it["depth_restored"]
        lab = torch.where(lab > 0, lab, 0)
        got = tf.vector_targets(lab, ins, dep, it["K"], it["obj_id"], it["R"], it["t"])
        kp = tf.kp_table[it["obj_id"]]                                            # (M,K,3) model mm
        kp_cam = torch.einsum("mij,mkj->mki", it["R"], kp) + it["t"][:, None]
        P = backproject(dep, it["K"])
        d = kp_cam[(ins - 1).clamp_min(0)] - P[:, :, None]                        # (H,W,K,3)
        vec = F.normalize(d, dim=-1, eps=1e-6)
        ok = (ins > 0) & (lab > 0) & (dep > 0) & torch.isfinite(vec).all(-1).all(-1)
        vec = torch.where(ok[..., None, None], vec, torch.zeros_like(vec))
        H, W = lab.shape
        assert torch.equal(got["mask"], ok) and ok.any()
        assert torch.equal(got["vec"], vec.reshape(H, W, -1).permute(2, 0, 1))


def test_hole_filling_that_stops_early_fills_as_eight_passes():
    def eight_passes(depth, iterations=8, kernel=5):
        d = depth[:, None]
        valid = (d > 0).to(d.dtype)
        for _ in range(iterations):
            s = F.avg_pool2d(d * valid, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
            c = F.avg_pool2d(valid, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
            fill = (valid == 0) & (c > 0)
            d = torch.where(fill, s / c.clamp_min(1e-12), d)
            valid = torch.maximum(valid, fill.to(d.dtype))
        return d[:, 0]

    g = torch.Generator().manual_seed(0)
    depth = 500 + 100 * torch.rand(3, 40, 50, generator=g)
    depth[0, 10:14, 10:14] = 0        # a small hole: filled in the first passes
    depth[1, :, 20:] = 0              # a wide one: some of it stays 0 after 8 passes
    depth[2] = 0                      # nothing to fill from
    assert torch.equal(fill_depth_holes(depth), eight_passes(depth))
    assert torch.equal(fill_depth_holes(depth[0]), eight_passes(depth[:1])[0])


@pytest.fixture(scope="module")
def bop(tmp_path_factory):
    return write_bop_dataset(tmp_path_factory.mktemp("thr") / "ds", obj_ids=(1, 5), splits=("train_pbr",),
                             images_per_scene=2, size=(64, 48), seed=0)["root"]


def test_workers_resume_and_epochs_give_the_weights_of_one_plain_run(bop, tmp_path):
    """Without workers, and with one persistent loader worker over the epochs, stopped after the
    first epoch and resumed by a second call: the same weights. Each epoch records its loader
    wait, CPU seconds and threads. (PVNet with small heads: the loop is every method's; HFF6DoF's
    56.8 M parameters would make this the slowest test of the file for nothing more.)"""
    opts = dict(image_size=(32, 48), batch_size=2, epochs=2, lr=1e-3, seed=0, progress=False, device="cpu",
                method="pvnet", method_config={"fcdim": 32, "raw_dim": 16})
    plain = train(bop, "train_pbr", tmp_path / "plain", num_workers=0, **opts)
    resumed = tmp_path / "resumed"
    train(bop, "train_pbr", resumed, num_workers=1, stop_epoch=1, **opts)
    train(bop, "train_pbr", resumed, num_workers=1, **opts)
    assert parameters_digest(load_run(plain)[0]) == parameters_digest(load_run(resumed)[0])
    for run in (plain, resumed):
        epochs = json.loads((run / "history.json").read_text())["epochs"]
        assert [e["epoch"] for e in epochs] == [1, 2]
        for e in epochs:
            assert 0 <= e["data_seconds"] <= e["seconds"] and e["cpu_seconds"] > 0
            assert e["threads"] == torch.get_num_threads() == 1


def test_the_gpu_session_script_runs_and_counts_an_epoch(tmp_path):
    """benchmarks/gpu_session.py (the one prepared run for a lent GPU) runs here with --quick on the
    CPU, without open3d, trimesh or ray (the GPU machine's image lacks them), and its epoch figure is
    the gpu preset's steps per epoch (reproduce.plan) times the measured step."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    block = tmp_path / "block"
    block.mkdir()
    (block / "sitecustomize.py").write_text(
        "import sys\nclass _B:\n    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in {'open3d', 'trimesh', 'pymeshlab', 'manifold3d', 'ray', 'depthai'}:\n"
        "            raise ImportError('blocked: ' + name)\nsys.meta_path.insert(0, _B())\n")
    env = {**__import__("os").environ, "PYTHONPATH": f"{block}:{repo}", "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, str(repo / "benchmarks" / "gpu_session.py"), "--device", "cpu", "--quick",
                        "--methods", "pvnet", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                       env=env, cwd=repo, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads((tmp_path / "out" / "gpu_session.json").read_text())
    r = res["methods"]["pvnet"]
    assert r["profile"]["end_to_end_fps"] > 0 and r["train"]["images_per_s"] > 0
    assert r["pipeline"]["frames_per_s"]["0"] > 0
    sys.path.insert(0, str(repo / "benchmarks"))
    from gpu_session import steps_per_epoch

    steps = steps_per_epoch("gpu")["pvnet"]
    assert steps["simple"] > steps["hard"] / 3 > 0                       # hard has ~2x simple's train-val images
    assert r["epoch_s"]["simple"] == pytest.approx(steps["simple"] * r["train"]["step_ms"] / 1000, rel=1e-3, abs=0.1)
    assert "pvnet" in p.stdout.splitlines()[-2]
