"""Issue 22 (reliability round 2), the TDoF20 import: `--check` reads what the import reads; a
refusal half-way leaves --out as it was; a resumed import's mask IoU covers every frame. Real
release files (tests/fixtures/tdof20_release.py), real PNGs."""

import sys
import subprocess

import cv2
import numpy as np
import pytest

from tdof20.dataset import importer
from tdof20.dataset.importer import import_tdof20
from tdof20.errors import TdofError
from tdof20.formats import read_json
from tests.fixtures.tdof20_release import write_tdof20_release
from tests.import_support import interrupt_import

SMALL = dict(classes=("cube_136", "goblet_180"), multi=("02",), frames_per_scene=3)


def _last_mask(src):
    return sorted((src / "multi_data" / "02" / "mask").glob("*.png"))[-1]


def _unknown_class_id(src):
    p = _last_mask(src)
    m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    m[0, 0] = 9
    cv2.imwrite(str(p), m)
    return p


def _damaged_depth(src):
    p = sorted((src / "multi_data" / "02" / "depth").glob("*.png"))[-1]
    data = p.read_bytes()
    p.write_bytes(data[:60] + b"\0" * (len(data) - 60))  # a good header, garbage after it
    return p


@pytest.mark.parametrize("damage,needle", [(_unknown_class_id, "holds class id 9, which is not in classes.txt"),
                                           (_damaged_depth, "corrupt PNG")])
def test_check_reads_what_the_import_reads_and_a_refusal_leaves_out_untouched(tmp_path, damage, needle):
    src = tmp_path / "src"
    write_tdof20_release(src, **SMALL)
    bad = damage(src)
    res = subprocess.run([sys.executable, "-m", "tdof20.cli", "dataset", "import-tdof20", str(src), "--check"],
                         capture_output=True, text=True, timeout=300)
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert res.returncode != 0 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert str(bad) in lines[0] and needle in lines[0], lines
    # the import (without --check) refuses too, and --out is as it was: absent, or the empty folder given
    for out in (tmp_path / "new", tmp_path / "empty"):
        if out.name == "empty":
            out.mkdir()
        with pytest.raises(TdofError, match=needle):
            import_tdof20(src, out, show_progress=False)
        assert (not out.exists()) if out.name == "new" else list(out.iterdir()) == []
        # nothing beside it either (the work folder of the refused import is gone)
        assert sorted(p.name for p in tmp_path.iterdir()) == (["empty", "src"] if out.name == "empty" else ["src"])


def test_a_resumed_import_s_mask_iou_covers_every_frame(tmp_path, monkeypatch):
    src = tmp_path / "src"
    write_tdof20_release(src, **SMALL)
    # the first frame of scene 2 gets a worse mask (half its pixels gone): its IoU differs from the others'
    p = sorted((src / "single_data" / "goblet_180" / "mask").glob("*.png"))[0]
    m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    ys, xs = np.nonzero(m)
    m[:, : int(np.median(xs))] = 0
    cv2.imwrite(str(p), m)
    ref = tmp_path / "ref"
    import_tdof20(src, ref, show_progress=False)
    out = tmp_path / "out"
    interrupt_import(src, out, monkeypatch)
    assert import_tdof20(src, out, show_progress=False)["resumed"]
    a = read_json(out / "scenes" / "000002" / "scene_info.json")
    b = read_json(ref / "scenes" / "000002" / "scene_info.json")
    assert b["mask_iou_mean"] < 0.9 and a["mask_iou_mean"] == b["mask_iou_mean"], (a, b)
    assert not list(out.rglob(importer.IOU_FILE))


# ------------------------------------------------------------------ item 3/4: tracebacks and misleading lines
def _pose_file(tmp_path, **over):
    import pickle

    rec = {"poses": np.concatenate([np.eye(3), [[0.0], [0.0], [0.5]]], axis=1)[:, :, None], "cls_ids": np.array([1])}
    rec.update(over)
    p = tmp_path / "000000.pkl"
    p.write_bytes(pickle.dumps(rec))
    return p


@pytest.mark.parametrize("over,needle", [
    ({"center_3ds": "abc"}, "'center_3ds' must be a numeric (N,3) array with N = 1, got str"),
    ({"center_3ds": {"x": 1}}, "'center_3ds' must be a numeric (N,3) array with N = 1, got dict"),
    ({"center_3ds": [[1, 2, 3], [1, 2]]}, "'center_3ds' must be a numeric (N,3) array with N = 1, got list"),
    ({"cls_ids": [10**40]}, "class id 1e+40 is not in classes.txt (ids 1..2)"),
])
def test_bad_pose_pickles_are_one_line(tmp_path, over, needle):
    from tdof20.formats.tdof20_files import read_pose

    p = _pose_file(tmp_path, **over)
    with pytest.raises(TdofError) as e:
        read_pose(p, 2)
    assert str(e.value) == f"{p}: {needle}"


def _check(src, timeout=60):
    res = subprocess.run([sys.executable, "-m", "tdof20.cli", "dataset", "import-tdof20", str(src), "--check"],
                         capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert res.returncode != 0 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    return " ".join(lines[0].split())


def _png_header_only(path, w, h, bits=16, colour=0):
    import struct
    import zlib

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, colour, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def test_hostile_release_files_are_one_line(tmp_path):
    import os

    src = tmp_path / "src"
    write_tdof20_release(src, **SMALL)
    cfg = src / "dataset_config"
    lst = cfg / "train_data_list.txt"
    text = lst.read_text()
    # a list line naming multi_data/² (int() of a Unicode digit)
    lst.write_text(text + "multi_data/\u00b2/000000\n")
    assert "names no scene of the release" in _check(src)
    lst.write_text(text)
    # a multi_data folder named ² or 9999999999
    for name in ("\u00b2", "9999999999"):
        (src / "multi_data" / name).mkdir()
        msg = _check(src)
        assert f"multi_data/{name}: a multi_data sequence folder must be named by its number" in msg, msg
        (src / "multi_data" / name).rmdir()
    # a list file that is a link to /dev/zero, or a FIFO: refused, not read (MemoryError) or waited on (a hang)
    lst.unlink()
    lst.symlink_to("/dev/zero")
    assert f"{lst}: is not a regular file (a device, pipe or socket): not a list file" in _check(src)
    lst.unlink()
    os.mkfifo(lst)
    assert f"{lst}: is not a regular file (a device, pipe or socket): not a list file" in _check(src, timeout=60)
    lst.unlink()
    lst.write_text(text)
    # a ~100-megapixel depth PNG (its header): refused from the header, before anything decodes it
    d = sorted((src / "multi_data" / "02" / "depth").glob("*.png"))[-1]
    _png_header_only(d, 10000, 10000)
    assert f"{d}: the image is 10000x10000 (100 megapixels), more than the 67 megapixels tdof20 reads" in _check(src)


def test_a_huge_mask_is_refused_from_its_header(tmp_path):
    from tdof20.formats.tdof20_files import read_class_mask

    p = tmp_path / "m.png"
    _png_header_only(p, 10000, 10000, bits=8)
    with pytest.raises(TdofError, match="10000x10000 .100 megapixels."):
        read_class_mask(p)


def test_frame_numbers_beyond_int32_number_frames_by_position():
    from tdof20.formats.tdof20_release import _im_ids

    ids, rule = _im_ids(["frame_1700000000123", "frame_1700000000456"])
    assert ids == {0: "frame_1700000000123", 1: "frame_1700000000456"} and "position" in rule
