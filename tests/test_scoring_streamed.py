"""A results file is scored from its parts, keeping only each target's top inst_count rows
(:func:`tdof20.dataset.results.read_top_results`): the same scores, warnings and row counts as the
whole file read into memory, the whole-file checks still made across parts, and memory bounded by
the targets."""

from __future__ import annotations

import numpy as np
import pytest

from tdof20.dataset import results as results_mod
from tdof20.dataset.results import read_results, read_top_results
from tdof20.errors import TdofError
from tdof20.scoring.scoring import evaluate
from tests.test_scoring import HEADER, csv_line, dataset, write_csv  # noqa: F401  (the fixture)

ARRAYS = ("add", "adds", "proj", "add_ok", "adds_ok", "proj_ok", "adds_exact", "scene")


def _many_rows(gt, rng) -> list[str]:
    """Every target's ground truth among 3-5 perturbed estimates (scores with ties), rows that match
    no target, some targets left out, an image without a time (-1)."""
    lines = [HEADER]
    for k, (s, im, o, R, t) in enumerate(gt):
        if k % 7 == 3:
            continue  # no estimate
        tm = -1 if (s, im) == (28, 1) else 0.25
        for j in range(int(rng.integers(3, 6))):
            sc = [0.9, 0.5, 0.9, 0.7, 0.2][j]  # a tie at the top: the earlier line wins
            lines.append(csv_line(s, im, o, sc, R, t + rng.normal(0, 3.0 * j, 3), tm))
    for s, im, o, R, t in gt[:4]:  # object 17 is no target of scene 8: these rows are ignored
        lines.append(csv_line(8, 0, 17, 0.99, R, t, 0.25))
    return lines


def _same(a, b) -> None:
    assert a.summary() == b.summary()
    assert a.warnings == b.warnings
    assert a.n_rows == b.n_rows
    for ob in a.objects:
        for k in ARRAYS:
            np.testing.assert_array_equal(getattr(a.objects[ob], k), getattr(b.objects[ob], k))


@pytest.mark.parametrize("part_bytes", [300, 1 << 20])
def test_streamed_file_scores_as_the_whole_file(dataset, tmp_path, monkeypatch, part_bytes):
    root, gt = dataset
    path = write_csv(tmp_path / "m.csv", _many_rows(gt, np.random.default_rng(3)))
    whole = evaluate(read_results(path), root, split="hard")  # every row in memory
    monkeypatch.setattr(results_mod, "STREAM_BYTES", part_bytes)
    streamed = evaluate(path, root, split="hard")
    _same(streamed, whole)
    assert any("row(s) match no target" in w for w in streamed.warnings)
    assert any("report no time" in w for w in streamed.warnings)
    assert streamed.n_rows == len(read_results(path))


def test_only_the_top_rows_are_kept(dataset, tmp_path):
    root, gt = dataset
    path = write_csv(tmp_path / "m.csv", _many_rows(gt, np.random.default_rng(4)))
    counts = {}
    for s, im, o, _, _ in gt:
        counts[(s, im, o)] = counts.get((s, im, o), 0) + 1
    if (8, 0, 17) in counts:
        del counts[(8, 0, 17)]

    def keep(part):
        return np.array([counts.get(k, 0) for k in zip(part.scene_id.tolist(), part.im_id.tolist(),
                                                          part.obj_id.tolist())])

    whole = read_results(path)
    res = read_top_results(path, keep, part_bytes=400)
    assert res.n_read == len(whole) and res.n_unmatched == 4
    assert len(res) <= sum(counts.values())
    # each kept row is one of its key's best inst_count rows by score (ties: the earlier line)
    for key, k in counts.items():
        sel = np.flatnonzero((whole.scene_id == key[0]) & (whole.im_id == key[1]) & (whole.obj_id == key[2]))
        best = sorted(sel, key=lambda i: (-whole.score[i], whole.line[i]))[:k]
        got = np.flatnonzero((res.scene_id == key[0]) & (res.im_id == key[1]) & (res.obj_id == key[2]))
        assert sorted(res.line[got].tolist()) == sorted(whole.line[best].tolist())
    assert np.all(np.diff(res.line) > 0)  # file order


def test_whole_file_checks_span_parts(dataset, tmp_path, monkeypatch):
    root, gt = dataset
    monkeypatch.setattr(results_mod, "STREAM_BYTES", 300)
    good = [csv_line(s, im, o, 1.0, R, t, 0.25) for s, im, o, R, t in gt]
    dup = write_csv(tmp_path / "dup.csv", [HEADER] + good + [good[0]])
    with pytest.raises(TdofError, match=f"line {len(good) + 2}: duplicates line 2 "):
        evaluate(dup, root, split="hard")
    s, im, o, R, t = gt[0]
    tm = write_csv(tmp_path / "time.csv", [HEADER] + good + [csv_line(s, im, o, 0.5, R, t + 1.0, 0.75)])
    with pytest.raises(TdofError, match="time 0.75 differs from 0.25 on line 2"):
        evaluate(tm, root, split="hard")
    metres = write_csv(tmp_path / "metres.csv", [HEADER] + [csv_line(s, im, o, 1.0, R, t / 1000.0, 0.25)
                                                            for s, im, o, R, t in gt])
    with pytest.raises(TdofError, match="line 2: translations look like metres"):
        evaluate(metres, root, split="hard")
    unknown = write_csv(tmp_path / "unknown.csv", [HEADER] + good + [csv_line(99, 0, 1, 1.0, R, t, 0.25)])
    with pytest.raises(TdofError, match="unknown scene_id 99"):
        evaluate(unknown, root, split="hard")
