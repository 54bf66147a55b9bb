"""VSD's ground-truth half kept in ROOT/.cache/vsd/ (:mod:`tdof20.scoring.vsd_cache`): a scoring
that reads it gives the very same matches as one that computes everything (bit for bit, the
thresholds' decisions and the summary); a changed depth image, a damaged file or a folder that
cannot be written is never a wrong score."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from tdof20.formats.io import read_png, write_png
from tdof20.scoring import evaluate
from tdof20.scoring.metrics import vsd as V
from tdof20.scoring.vsd_cache import GtCache, encode, unpack
from tests.test_bop_metrics import bop_dataset, noisy_rows, scenes3  # noqa: F401  (the fixtures)


def _same(a, b) -> None:
    assert a.summary() == b.summary()
    for ob in a.objects:
        assert a.objects[ob].bop.keys() == b.objects[ob].bop.keys()
        for k in a.objects[ob].bop:
            np.testing.assert_array_equal(a.objects[ob].bop[k], b.objects[ob].bop[k])


@pytest.fixture
def ds(bop_dataset, tmp_path):  # noqa: F811
    root, gt = bop_dataset
    dst = tmp_path / "ds"
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns(".cache"))
    return dst, gt


def _files(root):
    return sorted((root / ".cache" / "vsd").rglob("*.npz"))


def test_kept_ground_truth_scores_as_computed(ds):
    root, gt = ds
    rows = noisy_rows(gt)
    off = evaluate(rows, root, split="hard", metrics="ar", vsd_cache=False)
    assert not (root / ".cache" / "vsd").exists()
    # a first submission without some targets still keeps every target's ground truth
    cold = evaluate(rows[2:], root, split="hard", metrics="ar")
    assert _files(root) and cold.timings["vsd_cache_hits"] == 0
    warm = evaluate(rows, root, split="hard", metrics="ar")
    assert warm.timings["vsd_cache_hits"] == len(_files(root))
    _same(warm, off)
    assert 0.05 < warm.summary()["all"]["ar_vsd"] < 0.95  # the thresholds are exercised
    _same(evaluate(rows[2:], root, split="hard", metrics="ar", vsd_cache=False), cold)


def test_a_changed_depth_image_or_a_damaged_file_is_recomputed(ds):
    root, gt = ds
    rows = noisy_rows(gt)
    evaluate(rows, root, split="hard", metrics="vsd")
    files = _files(root)
    # the depth of scene 28's image 1 changes: its block's file is not used (and is replaced)
    p = root / "scenes" / "000028" / "depth" / "000001.png"
    d = read_png(p)
    d[d > 0] -= 40  # nearer by 20 mm (depth_scale 0.5): pixels that were visible are no longer
    write_png(p, d)
    again = evaluate(rows, root, split="hard", metrics="vsd")
    _same(again, evaluate(rows, root, split="hard", metrics="vsd", vsd_cache=False))
    assert again.timings["vsd_cache_hits"] == len(files) - 1
    # a damaged file (truncated) and one of another's content: computed again
    for f in _files(root):
        f.write_bytes(f.read_bytes()[:100])
    hurt = evaluate(rows, root, split="hard", metrics="vsd")
    assert hurt.timings["vsd_cache_hits"] == 0
    _same(hurt, again)
    assert evaluate(rows, root, split="hard", metrics="vsd").timings["vsd_cache_hits"] == len(files)


def test_a_folder_that_cannot_be_written_is_scored_without(ds):
    root, gt = ds
    rows = noisy_rows(gt)
    (root / ".cache").write_text("not a folder")  # nothing can be kept under ROOT/.cache/
    ev = evaluate(rows, root, split="hard", metrics="vsd")
    assert not GtCache(root).writable()
    _same(ev, evaluate(rows, root, split="hard", metrics="vsd", vsd_cache=False))


def test_encoding_round_trip():
    rng = np.random.default_rng(0)
    boxes = np.array([[10, 30, 5, 25], [0, 0, 0, 0], [40, 43, 100, 197]])
    area = [(b[1] - b[0]) * (b[3] - b[2]) for b in boxes]
    idx = [np.sort(rng.choice(a, size=a // 3, replace=False)) if a else np.zeros(0, np.int64) for a in area]
    cnt = np.array([len(i) for i in idx])
    qi = rng.integers(0, 65535, cnt.sum()).astype(np.uint16)
    gt = V.VisibleGt(boxes, np.r_[0, np.cumsum(cnt)], np.concatenate(idx), np.zeros(cnt.sum()), qi)
    back = unpack(encode(gt))
    for k in ("boxes", "start", "idx", "qi"):
        np.testing.assert_array_equal(getattr(back, k), getattr(gt, k))
