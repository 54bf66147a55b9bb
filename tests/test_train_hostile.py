"""Hostile inputs to train and predict (issue 22): a checkpoint with a damaged weight, a disk that
fills while a checkpoint is saved, implausible or damaged shards. Each is one line naming the file."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from tdof20.dataset.shards import ShardDataset
from tdof20.errors import TdofError
from tests.test_train_reliability import cli, data, files, one_line_error, sha  # noqa: F401 (fixture)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_a_checkpoint_with_a_damaged_weight_is_refused(data, tmp_path, capsys):
    """4 KB of one weight overwritten: torch.load would take it; the zip's CRC does not match."""
    run = tmp_path / "run"
    shutil.copytree(data["run"], run, symlinks=False, ignore=shutil.ignore_patterns("data"))
    raw = bytearray((run / "last.pt").read_bytes())
    mid = len(raw) // 2
    raw[mid:mid + 4096] = b"\x7f" * 4096
    (run / "last.pt").write_bytes(bytes(raw))
    code, err = cli(capsys, "predict", run, "--dataset", data["root"], "--split", "simple", "--out",
                    tmp_path / "r.csv", "--device", "cpu", "--workers", "0")
    one_line_error(code, err, str(run / "last.pt"), "fails its CRC check")
    assert not (tmp_path / "r.csv").exists()


def test_disk_full_while_saving_a_checkpoint_keeps_the_previous_one(tmp_path):
    """A real failed write (the file-size limit, as a full disk: the write fails part-way)."""
    path = tmp_path / "last.pt"
    torch.save({"model": {"w": torch.zeros(4)}}, path)
    before = sha(path)
    code = f"""
import resource, signal, sys, torch
from pathlib import Path
from tdof20.errors import TdofError
from tdof20.methods.runs import save_atomic
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
try:
    save_atomic({{"model": {{"w": torch.zeros(4 << 20)}}}}, Path({str(path)!r}))
except TdofError as e:
    print(e); sys.exit(2)
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "the previous last.pt is kept" in lines[0], p.stdout
    assert sha(path) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["last.pt"]  # no .last.pt.tmp left


def _shard_copy(data, tmp_path: Path) -> Path:
    dst = tmp_path / "s.h5"
    shutil.copy(data["run"] / "data" / "simple_train.h5", dst)
    return dst


def _set(path: Path, name: str, index: tuple, value) -> None:
    with h5py.File(path, "r+") as f:
        a = f[name][:]
        a[index] = value
        f[name][...] = a


@pytest.mark.parametrize("name,index,value,says", [
    ("R", (3, 0), np.diag([2.0, 1.0, 1.0]), "its array R is not a rotation at [3, 0]"),
    ("t", (2, 0), [0, 0, 1e30], "its array t is beyond"),
    ("obj_id", (1, 0), 999, "its array obj_id holds 999 at [1, 0]"),
    ("K", (4,), np.zeros((3, 3)), "its array K is not a camera matrix at [4]"),
    ("K", (5, 0, 0), np.nan, "its array K is not a camera matrix at [5]"),
])
def test_an_implausible_shard_is_refused_when_opened(data, tmp_path, name, index, value, says):
    shard = _shard_copy(data, tmp_path)
    _set(shard, name, index, value)
    with pytest.raises(TdofError) as e:
        ShardDataset(shard)
    assert says in str(e.value) and str(shard) in str(e.value)


def test_train_refuses_an_implausible_shard(data, tmp_path, capsys):
    shard = _shard_copy(data, tmp_path)
    _set(shard, "K", (0, 0, 0), np.nan)
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], "--split", "simple", "--shard", shard,
                    "--out", tmp_path / "run", "--image-size", "32x32", "--batch-size", "2", "--workers", "0",
                    "--device", "cpu", "--max-steps", "1")
    one_line_error(code, err, str(shard), "its array K is not a camera matrix at [0]")


def test_a_damaged_compressed_chunk_names_the_shard_and_the_array(data, tmp_path):
    shard = _shard_copy(data, tmp_path)
    with h5py.File(shard, "r") as f:
        info = f["rgb"].id.get_chunk_info(1)
    raw = bytearray(shard.read_bytes())
    raw[info.byte_offset:info.byte_offset + info.size] = b"\x00\xff" * (info.size // 2) + b"\x00" * (info.size % 2)
    shard.write_bytes(bytes(raw))
    ds = ShardDataset(shard)
    ds[0]
    with pytest.raises(TdofError) as e:
        ds[1]
    assert "its array rgb cannot be read at image 1" in str(e.value) and str(shard) in str(e.value)


# ------------------------------------------------------------------------------ data a run claims


def _copy_dataset(data, dst: Path) -> Path:
    shutil.copytree(data["root"], dst, ignore=shutil.ignore_patterns(".cache"))
    return dst


def _other_dataset(data, dst: Path) -> Path:
    """The same images with other labels and other objects (ids meaning other things)."""
    import json

    root = _copy_dataset(data, dst)
    for p in root.rglob("models_info.json"):
        info = json.loads(p.read_text())
        for v in info.values():
            v["diameter"] = float(v["diameter"]) * 2
        p.write_text(json.dumps(info))
    return root


def test_resume_with_another_dataset_is_refused(data, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["--split", "simple", "--out", run, "--image-size", "32x32", "--batch-size", "2", "--workers", "0",
            "--device", "cpu"]
    code, err = cli(capsys, "train", "hff6dof", "--dataset", data["root"], *args, "--max-steps", "1")
    assert code == 0, err
    config = (run / "config.json").read_text()
    other = _other_dataset(data, tmp_path / "other")
    code, err = cli(capsys, "train", "hff6dof", "--dataset", other, *args, "--max-steps", "2")
    one_line_error(code, err, str(run / "config.json"), "the dataset's content")
    assert (run / "config.json").read_text() == config  # the run still names the data it saw


def test_a_shard_of_another_dataset_is_refused(data, tmp_path, capsys):
    other = _other_dataset(data, tmp_path / "other")
    shard = data["run"] / "data" / "simple_train.h5"
    code, err = cli(capsys, "train", "hff6dof", "--dataset", other, "--split", "simple", "--shard", shard,
                    "--out", tmp_path / "run", "--image-size", "32x32", "--batch-size", "2", "--workers", "0",
                    "--device", "cpu", "--max-steps", "1")
    one_line_error(code, err, str(shard), "was made from another dataset")
    assert not (tmp_path / "run" / "last.pt").exists()


def test_a_cache_symlinked_out_of_the_dataset_is_refused(data, tmp_path, capsys):
    root = _copy_dataset(data, tmp_path / "ds")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("mine")
    (root / ".cache").symlink_to(outside)
    code, err = cli(capsys, "train", "hff6dof", "--dataset", root, "--split", "simple", "--out", tmp_path / "run",
                    "--image-size", "32x32", "--batch-size", "2", "--workers", "0", "--device", "cpu",
                    "--max-steps", "1")
    one_line_error(code, err, str(root / ".cache"), "symbolic link")
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"]
