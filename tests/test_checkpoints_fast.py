"""Cheaper checkpoint handling, and the same results: a run opened without computing the initial
weights its checkpoint replaces is the network built and loaded as before, bit for bit; the CRC
check of every member still refuses a damaged byte anywhere; a training that ends leaves out the
optimiser's state when asked (reproduce's runs) and then trains no further; loss.png drawn on one
reused figure is the picture a fresh figure draws; the UR5 refuses a pose beyond its reach at once.

One tiny simulated dataset (tests.test_train_reliability's), small runs of the real methods."""

from __future__ import annotations

import hashlib
import json
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from tdof20.dataset.build import split_images
from tdof20.dataset.reader import open_dataset
from tdof20.errors import TdofError
from tdof20.methods.data import SceneImages, TransformedDataset, collate
from tdof20.methods.history import plot_losses
from tdof20.methods.runs import (drop_optimizer, network_with_weights, open_config, open_run,
                                 read_checkpoint, read_run_config)
from tdof20.methods.train import train
from tdof20.sim.rig import UR5_FLANGE_REACH_MM, UR5_SHOULDER, ur5_fk, ur5_ik
from tests.test_train_reliability import data  # noqa: F401 (fixture)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = {"image_size": (32, 32), "batch_size": 2, "num_workers": 0, "progress": False, "device": "cpu"}
PVNET = {"method": "pvnet", "method_config": {"fcdim": 32, "raw_dim": 16}}


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def runs(data, tmp_path_factory):  # noqa: F811
    """An HFF6DoF run trained 2 steps to its end without the optimiser's state, and a PVNet run of
    2 steps that keeps it (BatchNorm statistics moved from their initial values in both)."""
    base = tmp_path_factory.mktemp("fast")
    images = split_images(data["root"], "simple", "train")[:4]
    hff = train(data["root"], "simple", base / "hff6dof", epochs=1, images=images, keep_optimizer=False, **TINY)
    pv = train(data["root"], "simple", base / "pvnet", epochs=1, images=images, **PVNET, **TINY)
    return {"hff6dof": hff, "pvnet": pv, "images": images, "root": data["root"]}


def _tensors(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Every parameter, buffer (persistent or not) and plain tensor attribute of the network."""
    out = dict([*net.named_parameters(), *net.named_buffers()])
    for prefix, module in net.named_modules():
        out.update({f"{prefix}.{k}": v for k, v in vars(module).items() if isinstance(v, torch.Tensor)})
    return out


def _leaves(x) -> list[torch.Tensor]:
    if isinstance(x, torch.Tensor):
        return [x]
    if isinstance(x, dict):
        return [t for k in sorted(x) for t in _leaves(x[k])]
    if isinstance(x, (list, tuple)):
        return [t for v in x for t in _leaves(v)]
    return []


@pytest.mark.parametrize("name", ["hff6dof", "pvnet"])
def test_an_opened_run_is_the_network_built_and_loaded_as_before(runs, name):
    """open_run (no initial weights computed, the checkpoint's assigned) against the network built
    for real and loaded with load_state_dict: every tensor, its dtype, layout and device, and the
    network's outputs on a test image, equal bit for bit."""
    run = runs[name]
    opened = open_run(run, "cpu")
    config = read_run_config(run)
    method, cfg, before, meta = open_config(config)
    before.load_state_dict(torch.load(run / "last.pt", map_location="cpu", weights_only=True)["model"])
    before.eval()
    a, b = _tensors(opened.net), _tensors(before)
    assert a.keys() == b.keys() and any(k.endswith("num_batches_tracked") for k in a)
    for k in a:
        assert a[k].device == b[k].device and a[k].dtype == b[k].dtype, k
        assert a[k].stride() == b[k].stride() and a[k].requires_grad == b[k].requires_grad, k
        assert torch.equal(a[k], b[k]), k
    assert not opened.net.training
    ds = open_dataset(runs["root"])
    images = ds.part_frames("simple", "test", "predict")[:1]
    items = TransformedDataset(SceneImages(runs["root"], images, split=ds.scene_folder("simple")),
                               method.transform(cfg, meta, train=False))
    batch = collate([items[0]])
    with torch.inference_mode():
        out_a, out_b = _leaves(method.forward(opened.net, batch)), _leaves(method.forward(before, batch))
    assert out_a and len(out_a) == len(out_b)
    assert all(torch.equal(x, y) for x, y in zip(out_a, out_b))


class _Filled(torch.nn.Module):
    """A layer with a weight and two buffers that are no weights: one made with its values, one
    filled into a ``torch.empty`` (which the weightless build cannot know)."""

    def __init__(self, filled: bool):
        super().__init__()
        self.lin = torch.nn.Linear(3, 2)
        self.register_buffer("mean", torch.tensor([1.0, 2.0, 3.0]), persistent=False)
        if filled:
            self.register_buffer("scale", torch.empty(3).fill_(2.0), persistent=False)


def test_a_network_with_a_buffer_it_cannot_rebuild_is_left_to_a_real_build():
    state = _Filled(False).state_dict()
    net = network_with_weights(lambda: _Filled(False), state)
    assert net is not None and torch.equal(net.lin.weight, state["lin.weight"])
    assert torch.equal(net.mean, torch.tensor([1.0, 2.0, 3.0]))  # made with its values: kept
    assert net.lin.weight.data_ptr() != state["lin.weight"].data_ptr()  # its own copy
    assert network_with_weights(lambda: _Filled(True), _Filled(True).state_dict()) is None


def test_a_damaged_byte_anywhere_in_a_checkpoint_is_refused(runs, tmp_path):
    """The CRC of every member is checked, the optimiser's moments (the file's last tensors) too,
    not only what a caller loads; one line naming the file and the member."""
    src = runs["pvnet"] / "last.pt"
    assert read_checkpoint(src)["model"]  # whole: read
    with zipfile.ZipFile(src) as z:
        last = max((i for i in z.infolist() if "/data/" in i.filename), key=lambda i: i.header_offset)
    raw = bytearray(src.read_bytes())
    # the zip format's local header: 30 bytes, then the name and the extra field (their lengths at 26, 28)
    n_name, n_extra = struct.unpack_from("<HH", raw, last.header_offset + 26)
    first = last.header_offset + 30 + n_name + n_extra
    raw[first + last.file_size // 2] ^= 0x01  # one bit of the last tensor
    bad = tmp_path / "last.pt"
    bad.write_bytes(bytes(raw))
    with pytest.raises(TdofError, match="fails its CRC check") as e:
        read_checkpoint(bad)
    assert str(bad) in str(e.value) and last.filename in str(e.value)
    assert len(str(e.value).splitlines()) == 1


def test_a_run_ended_without_its_optimiser_trains_no_further(data, tmp_path):  # noqa: F811
    """keep_optimizer=False: a call that stops before the end keeps the optimiser's state, the one
    that reaches it leaves it out (weights, counters and history kept); calling again for no
    further step is a no-op, asking for more is refused; drop_optimizer then has nothing to do."""
    images = split_images(data["root"], "simple", "train")[:4]
    run = tmp_path / "run"
    opts = dict(epochs=2, images=images, keep_optimizer=False, **PVNET, **TINY)
    train(data["root"], "simple", run, stop_epoch=1, **opts)
    assert "optimizer" in read_checkpoint(run / "last.pt", needs=("optimizer",))
    train(data["root"], "simple", run, stop_epoch=2, **opts)
    ck = read_checkpoint(run / "last.pt", needs=("model", "epoch", "step", "history"))
    assert "optimizer" not in ck and "scaler" not in ck and ck["step"] == 4 and len(ck["history"]) == 4
    before = sha(run / "last.pt")
    train(data["root"], "simple", run, stop_epoch=2, **opts)  # nothing to do: as before the drop
    train(data["root"], "simple", run, **opts)
    assert sha(run / "last.pt") == before
    with pytest.raises(TdofError, match="holds the weights only") as e:
        train(data["root"], "simple", run, **{**opts, "epochs": 3})
    assert str(run / "last.pt") in str(e.value) and sha(run / "last.pt") == before
    assert drop_optimizer(run) == 0 and sha(run / "last.pt") == before
    assert open_run(run).net is not None  # predicted as before


def test_drop_optimizer_still_drops_what_an_older_run_kept(runs, tmp_path):
    run = tmp_path / "pvnet"
    run.mkdir()
    for f in ("config.json", "last.pt"):
        (run / f).write_bytes((runs["pvnet"] / f).read_bytes())
    assert drop_optimizer(run) > 0
    ck = read_checkpoint(run / "last.pt", needs=("model", "epoch", "step", "history"))
    old = read_checkpoint(runs["pvnet"] / "last.pt")
    assert "optimizer" not in ck and all(torch.equal(ck["model"][k], v) for k, v in old["model"].items())


def _history(n: int, keys=("loss", "seg", "vec"), seed: int = 0) -> list[dict]:
    r = np.random.default_rng(seed)
    return [{"step": i + 1, "epoch": i // 10, "lr": 1e-3 * (1 - i / n),
             **{k: float((3 - j) * np.exp(-3 * i / n) * (0.5 + r.random())) for j, k in enumerate(keys)}}
            for i in range(n)]


def test_loss_png_from_the_reused_figure_is_the_fresh_figures_picture(tmp_path):
    """A picture drawn after others (another method's parts, a long history) is pixel for pixel
    the one a new process draws; a 5,000-step history (thinned to bins) is drawn too."""
    from PIL import Image

    plot_losses(_history(5_000), tmp_path / "long.png", "long")
    plot_losses(_history(5, keys=("loss", "kp", "ctr")), tmp_path / "other.png", "other")
    plot_losses(_history(7, seed=1), tmp_path / "reused.png", "hff6dof training")
    (tmp_path / "h.json").write_text(json.dumps(_history(7, seed=1)))
    code = ("import json, sys; from pathlib import Path; from tdof20.methods.history import plot_losses; "
            "plot_losses(json.loads(Path(sys.argv[1]).read_text()), Path(sys.argv[2]), 'hff6dof training')")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "h.json"), str(tmp_path / "fresh.png")], check=True,
                   timeout=120)
    (tmp_path / "h.json").unlink()
    a = np.asarray(Image.open(tmp_path / "reused.png"))
    assert a.shape == (450, 800, 4) and np.array_equal(a, np.asarray(Image.open(tmp_path / "fresh.png")))
    assert Image.open(tmp_path / "long.png").size == (800, 450)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh.png", "long.png", "other.png", "reused.png"]


def test_ur5_refuses_a_pose_beyond_its_reach_at_once_and_reaches_what_it_can():
    rng = np.random.default_rng(0)
    far = [np.linalg.norm(ur5_fk(q)[:3, 3] - UR5_SHOULDER) for q in rng.uniform(-np.pi, np.pi, (20_000, 6))]
    assert max(far) <= UR5_FLANGE_REACH_MM  # a bound: no pose the arm takes lies beyond it
    T = ur5_fk(np.array([0.4, -0.2, 0.1, -0.3, 1.2, 0.0]))  # nearly stretched out, 900+ mm
    assert np.linalg.norm(T[:3, 3] - UR5_SHOULDER) > 850
    assert np.allclose(ur5_fk(ur5_ik(T, np.array([0.3, -0.3, 0.2, -0.2, 1.1, 0.1]))), T, atol=1e-6)
    T[:3, 3] = UR5_SHOULDER + [0.0, 1200.0, 0.0]
    with pytest.raises(ValueError, match=r"UR5 cannot reach .*1200 mm from the shoulder, the arm reaches 1001 mm"):
        ur5_ik(T, np.zeros(6))
