"""Issue 22 (reliability round 2), the dataset layer: a hostile dataset cannot make tdof20 write
outside it through a symlink (S5). Real scenes and files, run through the console entry point."""

import os
from pathlib import Path

import pytest

from tdof20.dataset.build import build_dataset
from tdof20.dataset.validation import write_val_targets
from tdof20.errors import TdofError
from tdof20.formats.io import safe_inside

from test_dataset_reliability import cli, make_scene, tree


def test_safe_inside_refuses_a_symlinked_component_and_a_way_out(tmp_path):
    root = tmp_path / "R"
    (root / "scenes").mkdir(parents=True)
    home = tmp_path / "home"
    home.mkdir()
    assert safe_inside(root, root / ".cache" / "x.png") == root / ".cache" / "x.png"
    (root / ".cache").symlink_to(home)
    with pytest.raises(TdofError, match=r"\.cache: is a symbolic link inside the dataset: tdof20 does not write "
                                        r"through a symlink inside a dataset \(give --cache-dir"):
        safe_inside(root, root / ".cache" / "depth_restored" / "a.png")
    with pytest.raises(TdofError, match="outside the dataset folder"):
        safe_inside(root, root / ".." / "home" / "a.png")
    # the root itself may be reached through a link
    link = tmp_path / "L"
    link.symlink_to(root)
    assert safe_inside(link, link / "scenes" / "a.png") == link / "scenes" / "a.png"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    base = tmp_path_factory.mktemp("h2")
    root = base / "R"
    build_dataset([make_scene(base, "multi/08")], root, show_progress=False)
    return root


def test_pack_does_not_write_through_a_symlinked_cache(dataset, tmp_path, capsys):
    import shutil

    root = tmp_path / "R"
    shutil.copytree(dataset, root, symlinks=True)
    for d in list(root.rglob("depth_restored")):  # the restored depth must be rendered into the cache
        shutil.rmtree(d)
    home = tmp_path / "home"
    home.mkdir()
    (home / "precious.txt").write_text("mine")
    shutil.rmtree(root / ".cache", ignore_errors=True)
    (root / ".cache").symlink_to(home)
    before = tree(home)
    rc, msg = cli(capsys, "dataset", "pack", root, "--split", "hard", "--part", "test", "--out", tmp_path / "t.h5")
    assert rc != 0 and msg.startswith(f"error: {root / '.cache'}: is a symbolic link inside the dataset"), msg
    assert "--cache-dir" in msg
    assert tree(home) == before and sorted(os.listdir(home)) == ["precious.txt"]
    assert not (tmp_path / "t.h5").exists()
    # --cache-dir writes elsewhere, as the message says
    rc, _ = cli(capsys, "dataset", "pack", root, "--split", "hard", "--part", "test", "--out", tmp_path / "t.h5",
                "--cache-dir", tmp_path / "cache")
    assert rc == 0 and (tmp_path / "t.h5").is_file() and tree(home) == before


def test_validation_targets_do_not_follow_a_symlinked_cache(tmp_path):
    root = tmp_path / "R"
    root.mkdir()
    home = tmp_path / "home"
    home.mkdir()
    (root / ".cache").symlink_to(home)
    with pytest.raises(TdofError, match="symbolic link inside the dataset"):
        write_val_targets(root, "hard")
    assert os.listdir(home) == []


# ------------------------------------------------------------------ ids beyond int32 (then pack's OverflowError)
@pytest.mark.parametrize("edit,needle", [
    (lambda gt: {k: [{**g, "obj_id": 10**30} for g in v] for k, v in gt.items()}, "obj_id must be an integer from 1 to"),
    (lambda gt: {"9999999999" if i == 0 else k: v for i, (k, v) in enumerate(gt.items())},
     "key '9999999999': image ids are at most 2147483647"),
])
def test_ids_beyond_int32_in_scene_gt_are_one_line_errors(dataset, tmp_path, capsys, edit, needle):
    import json
    import shutil

    root = tmp_path / "R"
    shutil.copytree(dataset, root, symlinks=True)
    gt_path = next(root.glob("scenes/*/scene_gt.json"))
    gt_path.write_text(json.dumps(edit(json.loads(gt_path.read_text()))))
    rc, msg = cli(capsys, "dataset", "pack", root, "--split", "hard", "--part", "test", "--out", tmp_path / "t.h5")
    assert rc != 0 and msg.startswith(f"error: {gt_path}: ") and needle in msg, msg
    assert not (tmp_path / "t.h5").exists()


# ------------------------------------------------------------------ a full disk during `dataset build`
def test_a_full_disk_during_build_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    import errno
    import shutil

    base = tmp_path / "in"
    scene = make_scene(base, "single/12", steps=3, n_arms=1, width=64, height=48)
    real = shutil.copyfile

    def full(src, dst, *a, **k):
        if ".tmp/" in str(dst) and str(dst).endswith(".png"):  # the scene's copy: every image fails
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(shutil, "copyfile", full)
    out = tmp_path / "R"
    rc, msg = cli(capsys, "dataset", "build", scene, "--out", out)
    assert rc != 0 and len(msg) < 400 and "[Errno 28] No space left on device" in msg, msg
    assert msg.startswith(f"error: {out / 'scenes'}") and "more files failed too" in msg and "(" in msg
    assert "', '" not in msg  # not a printed list of tuples


# ------------------------------------------------------------------ models_eval/ without its models_info.json
def test_models_eval_without_its_models_info_is_refused(dataset, tmp_path, capsys):
    import shutil

    from test_dataset_reliability import good_csv

    root = tmp_path / "R"
    shutil.copytree(dataset, root, symlinks=True)
    (root / "models_eval").mkdir()
    for ply in (root / "models").glob("*.ply"):
        shutil.copy(ply, root / "models_eval" / ply.name)
    csv = good_csv(tmp_path / "m.csv", root)
    rc, msg = cli(capsys, "benchmark", "score", csv, "--dataset", root, "--split", "hard")
    assert rc != 0 and msg == (f"error: {root / 'models_eval' / 'models_info.json'}: not found: a models_eval/ folder "
                               "needs its own models_info.json (its objects' diameters and symmetries; models/'s are "
                               "not used for it): add it, or remove models_eval/"), msg
