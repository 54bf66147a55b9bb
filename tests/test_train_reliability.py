"""What train and predict refuse, and the multi-process training (issue 11).

Every refusal is one line through the real command line (``tdof20.cli.main``: ``error: <msg>``,
exit 2, no traceback), comes before the long work, and leaves the user's files as they were.
One tiny simulated dataset (single/12, 4 arm positions x 8 turntable steps at 80x60: 28 train and
4 test images of the simple split), one untrained run (max_steps=0) and a dataset of a hard-test
scene only (its simple split is empty) serve every test.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tdof20.dataset.build import build_dataset, split_images
from tdof20.capture import run_capture, sim_config
from tdof20.methods.train import train
from tdof20.sim.truth import oracle_scene

TINY = dict(image_size=(32, 32), batch_size=2, num_workers=0, progress=False, device="cpu")
TORCHRUN_TIMEOUT_S = 240  # a guard against a hang (the run takes well under a minute on an idle machine)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _scene(base: Path, name: str, steps: int, deg: float, arms: int) -> Path:
    raw = base / "raw" / name.replace("/", "_")
    run_capture(sim_config(name, steps=steps, step_deg=deg, n_arms=arms, width=80, height=60), raw, yes=True,
                show_progress=False)
    return oracle_scene(raw, base / "labels" / name.replace("/", "_"), show_progress=False)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("rel")
    root = base / "root"
    build_dataset([_scene(base, "single/12", 8, 2.0, 4)], root, show_progress=False)
    hard_only = base / "hard_only"  # multi/08 is a test scene of the hard split: simple has nothing
    build_dataset([_scene(base, "multi/08", 2, 45.0, 1)], hard_only, show_progress=False)
    run = train(root, "simple", base / "untrained", max_steps=0, **TINY)
    return {"root": root, "hard_only": hard_only, "run": run}


def cli(capsys, *args) -> tuple[int, str]:
    """(exit code, stderr) of ``tdof20 ARGS`` run in this process."""
    from tdof20.cli import main

    argv = sys.argv
    sys.argv = ["tdof20", *(str(a) for a in args)]
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code
    finally:
        sys.argv = argv
    return code, capsys.readouterr().err


def one_line_error(code: int, err: str, *needles: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("error: ") and "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def files(folder: Path) -> dict[str, str]:
    return {p.name: sha(p) for p in sorted(folder.iterdir()) if p.is_file()}


def _run_copy(src: Path, dst: Path, last_pt: bytes | None = None) -> Path:
    """A run folder with src's config.json and either src's last.pt (linked) or ``last_pt`` bytes."""
    dst.mkdir()
    shutil.copy(src / "config.json", dst / "config.json")
    if last_pt is None:
        (dst / "last.pt").symlink_to(src / "last.pt")
    else:
        (dst / "last.pt").write_bytes(last_pt)
    return dst


def damaged_checkpoints(run: Path) -> dict[str, tuple[bytes, str]]:
    """name -> (bytes of a damaged last.pt, what the message says about it)."""
    with open(run / "last.pt", "rb") as f:
        head = f.read(1 << 20)
    return {"truncated": (head, "1.0 MB; truncated: it begins like a torch checkpoint but its end is missing"),
            "random": (os.urandom(4096), "4096 bytes; not a torch checkpoint"),
            "empty": (b"", "the file is empty"),
            "a list": (_pickled([1, 2, 3]), "is not an HFF6DoF checkpoint (it holds a list")}


def _pickled(obj) -> bytes:
    import io

    b = io.BytesIO()
    torch.save(obj, b)
    return b.getvalue()


# ------------------------------------------------------------------------------ damaged checkpoints


@pytest.mark.parametrize("kind", ["truncated", "random", "empty", "a list"])
def test_predict_and_resume_refuse_a_damaged_checkpoint_and_keep_it(data, tmp_path, capsys, kind):
    content, says = damaged_checkpoints(data["run"])[kind]
    run = _run_copy(data["run"], tmp_path / "run", content)
    before = files(run)
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    tmp_path / "r.csv", "--device", "cpu", "--workers", "0")
    one_line_error(code, err, str(run / "last.pt"), says, "restore it from a copy")
    assert not (tmp_path / "r.csv").exists()
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out", run,
                    "--image-size", "32x32", "--batch-size", "2", "--workers", "0", "--device", "cpu")
    one_line_error(code, err, str(run / "last.pt"), says, "move last.pt out of the run folder", "another --out")
    assert files(run) == before  # the damaged checkpoint (and config.json) untouched, nothing added


def test_a_checkpoint_of_another_network_is_refused(data, tmp_path, capsys):
    """last.pt of a 3-stage network beside a config.json that describes 2 fused stages."""
    run = _run_copy(data["run"], tmp_path / "run")
    cfg = json.loads((run / "config.json").read_text())
    cfg["network"]["fuse_stages"] = 2
    (run / "config.json").write_text(json.dumps(cfg))
    before = files(run)
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    tmp_path / "r.csv", "--device", "cpu", "--workers", "0")
    one_line_error(code, err, str(run / "last.pt"), "holds another network than the run's config.json",
                   "fuse_stages 3 here, 2 in config.json", "weights")
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out", run,
                    "--image-size", "32x32", "--batch-size", "2", "--set", "fuse_stages=2", "--workers", "0",
                    "--device", "cpu")
    one_line_error(code, err, str(run / "last.pt"), "fuse_stages 3 here, 2 in config.json", "another --out")
    assert files(run) == before and sha(data["run"] / "last.pt") == sha(run / "last.pt")
    # a checkpoint of the same network but written by a run at another image size
    cfg["network"]["fuse_stages"] = 3
    cfg["image_size"] = [64, 64]
    (run / "config.json").write_text(json.dumps(cfg))
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    tmp_path / "r.csv", "--device", "cpu", "--workers", "0")
    one_line_error(code, err, "image_size [32, 32] here, [64, 64] in config.json")


def test_a_run_without_its_config_or_with_a_foreign_one(data, tmp_path, capsys):
    run = _run_copy(data["run"], tmp_path / "run")
    (run / "config.json").unlink()
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out", run,
                    "--image-size", "32x32", "--workers", "0", "--device", "cpu")
    one_line_error(code, err, str(run / "config.json"), "missing", "move last.pt out")
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text('{"method": "something else"}')
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out", other,
                    "--image-size", "32x32", "--workers", "0", "--device", "cpu")
    one_line_error(code, err, "not a training run's", "would overwrite it")
    assert (other / "config.json").read_text() == '{"method": "something else"}'


# ------------------------------------------------------------------------------ outputs, before the work


def test_predict_checks_its_output_before_the_work(data, tmp_path, capsys):
    # the run's checkpoint is damaged: an --out error reported first proves it came before reading it
    run = _run_copy(data["run"], tmp_path / "run", b"junk")
    folder = tmp_path / "results"
    folder.mkdir()
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out", folder)
    one_line_error(code, err, str(folder), "--out is a folder, not a file")
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    afile / "sub" / "r.csv")
    one_line_error(code, err, f"{afile} is a file, so nothing can be written under it")
    assert afile.read_text() == "keep me"
    (tmp_path / "r_info.json").mkdir()
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    tmp_path / "r.csv")
    one_line_error(code, err, "r_info.json", "the summary beside --out is a folder, not a file", "move the folder away")


def test_train_checks_its_output_before_the_work(data, tmp_path, capsys):
    afile = tmp_path / "run.txt"
    afile.write_text("keep me")
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out", afile)
    one_line_error(code, err, str(afile), "--out is a file, not a run folder")
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out",
                    afile / "run")
    one_line_error(code, err, f"{afile} is a file, so nothing can be written under it")
    assert afile.read_text() == "keep me"
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--out",
                    data["root"])
    one_line_error(code, err, "--out is a dataset root")
    assert not (data["root"] / "config.json").exists() and not (data["root"] / "data").exists()


# ------------------------------------------------------------------------------ empty split parts


def test_an_empty_split_part_is_named_before_anything_is_built(data, tmp_path, capsys):
    root = data["hard_only"]
    assert split_images(root, "simple", "train") == [] and split_images(root, "hard", "test")
    out = tmp_path / "run"
    code, err = cli(capsys, "train", "hff6dof", "--dataset", root, "--split", "simple", "--out", out)
    one_line_error(code, err, f"{root}: the simple split's train part of this dataset is empty",
                   "splits/simple_train.json lists no images", "nothing to train on")
    assert not out.exists()  # no run folder, no shard packed
    code, err = cli(capsys, "train", "hff6dof", "--dataset", root, "--split", "hard", "--out", out)
    one_line_error(code, err, "the hard split's train part of this dataset is empty")
    # predict names the empty test part before it reads the run (here: no run at all)
    code, err = cli(capsys, "predict", tmp_path / "no_run", "--dataset", root, "--split", "simple", "--out",
                    tmp_path / "r.csv")
    one_line_error(code, err, f"{root}: the simple split's test part of this dataset is empty", "nothing to predict")
    assert not (tmp_path / "r.csv").exists()


# ------------------------------------------------------------------------------ several processes


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def torchrun(*args, timeout: float = TORCHRUN_TIMEOUT_S) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``python -m torch.distributed.run --nproc_per_node 2 -m tdof20 ARGS``
    on a free port; the launcher runs in its own session, so that a hang ends with it *and* its workers."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    if Path("/sys/class/net/lo").exists():
        env.setdefault("GLOO_SOCKET_IFNAME", "lo")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
           "--master_addr", "127.0.0.1", "--master_port", str(_free_port()), "-m", "tdof20", *map(str, args)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        pytest.fail(f"torchrun did not end within {timeout} s: {stderr[-3000:]}")
    return proc.returncode, stdout, stderr


needs_gloo = pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                                reason="this torch has no gloo backend")


@needs_gloo
def test_torchrun_two_processes_on_the_cpu(data, tmp_path):
    """torchrun, 2 processes, gloo: a few steps that train, keep both processes' weights identical,
    and write exactly one checkpoint, which predict reads."""
    from tdof20.methods.hff6dof import HFF6DoF
    from tdof20.methods.predict import predict
    from tdof20.methods.runs import parameters_digest, read_checkpoint

    root, run = data["root"], tmp_path / "ddp"
    code, stdout, stderr = torchrun("train", "hff6dof", "--dataset", root, "--split", "simple", "--out", run,
                                    "--image-size", "32x32", "--batch-size", "2", "--epochs", "1", "--max-steps", "3",
                                    "--workers", "0", "--device", "cpu", "--lr", "1e-3", "--seed", "0")
    assert code == 0, stdout[-3000:] + stderr[-3000:]
    assert "Traceback" not in stderr
    names = sorted(p.name for p in run.iterdir())
    assert [n for n in names if n.endswith(".pt") or ".tmp" in n] == ["last.pt"]  # one checkpoint, no leftovers
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["train"]["world_size"] == 2 and cfg["train"]["device"] == "cpu"
    hist = json.loads((run / "history.json").read_text())
    ranks = hist["processes"]
    assert ranks["world_size"] == 2 and ranks["backend"] == "gloo" and ranks["in_sync"] is True
    assert len(ranks["weights_sha256"]) == 2 and ranks["weights_sha256"][0] == ranks["weights_sha256"][1]
    ckpt = read_checkpoint(run / "last.pt", needs=("model", "optimizer", "step", "history"))
    n_train = len(split_images(root, "simple", "train"))
    assert ckpt["step"] == 3 == len(ckpt["history"]) and n_train // 2 // 2 >= 3  # 3 steps within the epoch
    net = HFF6DoF()
    torch.manual_seed(0)
    start = parameters_digest(HFF6DoF())  # the weights every process started from (seed 0)
    net.load_state_dict(ckpt["model"])
    assert parameters_digest(net) == ranks["weights_sha256"][0] != start  # trained; saved = both processes'
    out = predict(run, root, "simple", tmp_path / "ddp.csv", device="cpu", num_workers=0, progress=False)
    with open(out) as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
    info = json.loads((tmp_path / "ddp_info.json").read_text())
    assert info["images"] == len(split_images(root, "simple", "test"))


@needs_gloo
def test_torchrun_refusal_is_one_line_from_process_0(data, tmp_path):
    """Both processes meet the empty split before they meet each other; one line says it (torchrun
    then reports the failed processes in its own words), and nothing is made."""
    out = tmp_path / "ddp"
    code, stdout, stderr = torchrun("train", "hff6dof", "--dataset", data["hard_only"], "--split", "simple",
                                    "--out", out, "--device", "cpu", timeout=120)
    ours = [ln for ln in (stdout + stderr).splitlines() if ln.startswith("error: ")]
    assert code != 0 and len(ours) == 1, stdout + stderr
    assert "the simple split's train part of this dataset is empty" in ours[0]
    assert not out.exists()
