"""Scoring of BOP results: metrics by hand, matching conventions, the fast path against the
straightforward computation, strict validation of results files, JSON and reports.

Datasets are built in tmp_path with real files: catalog models (export_models) and BOP scenes
written by BopSceneWriter with tiny masks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tdof20.scoring import metrics as M
from tdof20.scoring import report, scorer, scoring
from tdof20.dataset.results import HEADER, Results, read_results, write_results_csv
from tdof20.scoring.scoring import evaluate, score, score_command
from tdof20.errors import TdofError
from tdof20.formats import BopSceneWriter, write_json
from tdof20.objects import export_models, get_object

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
OBJS = (1, 7, 17)  # cube_136 (4-fold symmetry), handle_cup_280 (asymmetric), water_cup_270 (continuous)
KEYS = {"n", "add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s", "ar_mssd", "ar_mspd"}  # no depth: no VSD, AR
PARTS = {"objects", "mean", "all", "scenes", "proj_px"}  # proj_px: the 2D projection threshold used


def rot(axis, deg) -> np.ndarray:
    a = np.asarray(axis, float)
    return Rotation.from_rotvec(np.deg2rad(deg) * a / np.linalg.norm(a)).as_matrix()


def rand_pose(rng) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
    return R, np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(600, 800)])


# ---------------------------------------------------------------------------------------------
# a tiny dataset on disk
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """scene 8 (single/handle_cup_440, holding object 7 here): 3 images of object 7; scene 28
    (multi/07): 3 images of objects 1, 7, 17, and image 3 with two instances of object 7.
    Returns (root, gt rows)."""
    root = tmp_path_factory.mktemp("ds")
    export_models(root / "models", OBJS)
    rng = np.random.default_rng(7)
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:5] = True
    gt, targets = [], []
    layout = {8: [[7]] * 3, 28: [[1, 7, 17]] * 3 + [[7, 7, 1]]}
    for sid, images in layout.items():
        with BopSceneWriter(root / "scenes" / f"{sid:06d}") as w:
            for im, objs in enumerate(images):
                poses = [(o, *rand_pose(rng)) for o in objs]
                w.add_frame(im, K, 1.0, poses, [mask] * len(poses), [mask] * len(poses))
                for o in sorted(set(objs)):
                    targets.append({"scene_id": sid, "im_id": im, "obj_id": o, "inst_count": objs.count(o)})
                gt += [(sid, im, o, R, t) for o, R, t in poses]
    write_json(root / "dataset_info.json", {"name": "tdof20", "scenes": {"8": "single/handle_cup_440", "28": "multi/07"}})
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_json(root / "test_targets_hard.json", targets)
    write_json(root / "test_targets_simple.json", [t for t in targets if t["scene_id"] == 8])
    return root, gt


def rows_of(gt, score_=1.0, time_=0.25):
    return [(s, im, o, score_, R, t, time_) for s, im, o, R, t in gt]


def write_csv(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def csv_line(s, im, o, sc, R, t, tm) -> str:
    nums = lambda a: " ".join(repr(float(x)) for x in np.ravel(a))  # noqa: E731
    return f"{s},{im},{o},{sc},{nums(R)},{nums(t)},{tm}"


# ---------------------------------------------------------------------------------------------
# metrics by hand
# ---------------------------------------------------------------------------------------------
def test_identity_pose_has_zero_error():
    P = get_object(7).vertices
    R, t = rot([1, 2, 3], 40), np.array([10.0, -20.0, 700.0])
    assert M.add(R, t, R, t, P) == 0.0
    assert M.adds(R, t, R, t, P) == pytest.approx(0.0, abs=1e-9)
    assert M.proj2d(R, t, R, t, P, K) == 0.0


def test_pure_translation():
    P = get_object(7).vertices
    R, t = rot([0, 1, 1], 30), np.array([0.0, 0.0, 700.0])
    dt = np.array([3.0, -4.0, 12.0])  # |dt| = 13
    assert M.add(R, t + dt, R, t, P) == pytest.approx(13.0, abs=1e-9)
    e = M.adds(R, t + dt, R, t, P)
    assert 0.0 < e <= 13.0 + 1e-9


def test_symmetric_object_turned_about_its_axis():
    for obj_id, deg in ((17, 45.0), (1, 90.0)):  # 64-segment revolution; square section
        P = get_object(obj_id).vertices
        Rg, t = rot([1, 0, 0], 20), np.array([0.0, 0.0, 700.0])
        Re = Rg @ rot([0, 0, 1], deg)
        assert M.adds(Re, t, Rg, t, P) < 1e-9
        assert M.add(Re, t, Rg, t, P) > 10.0


def test_proj2d_of_a_known_shift():
    P = np.array([[x, y, 0.0] for x in (-20, 0, 20) for y in (-10, 10)])  # a plane facing the camera
    t = np.array([5.0, -3.0, 750.0])
    dx = 2.5
    assert M.proj2d(np.eye(3), t + [dx, 0, 0], np.eye(3), t, P, K) == pytest.approx(600 * dx / 750, abs=1e-9)
    behind = M.proj2d(np.eye(3), np.array([0.0, 0.0, -10.0]), np.eye(3), t, P, K)
    assert behind == np.inf


def test_batched_forms_match_single_poses():
    rng = np.random.default_rng(1)
    P = get_object(17).vertices
    poses = [rand_pose(rng) for _ in range(4)]
    Rg, tg = rand_pose(rng)
    Re = np.stack([p[0] for p in poses])
    te = np.stack([p[1] for p in poses])
    Rgs, tgs = np.broadcast_to(Rg, Re.shape), np.broadcast_to(tg, te.shape)
    for fb, f in ((M.add_batch, M.add), (M.adds_batch, M.adds)):
        np.testing.assert_allclose(fb(Re, te, Rgs, tgs, P), [f(R, t, Rg, tg, P) for R, t in poses])
    np.testing.assert_allclose(M.proj2d_batch(Re, te, Rgs, tgs, P, K), [M.proj2d(R, t, Rg, tg, P, K) for R, t in poses])


# ---------------------------------------------------------------------------------------------
# the fast path agrees with the straightforward computation
# ---------------------------------------------------------------------------------------------
def _poses_near_threshold(model, rng, B):
    d = model.diameter
    Rg = Rotation.random(B, random_state=int(rng.integers(2**31))).as_matrix()
    tg = np.c_[rng.uniform(-80, 80, (B, 2)), rng.uniform(550, 900, B)]
    kind = rng.integers(0, 3, B)  # close, around the 10% threshold, far
    deg = np.where(kind == 0, rng.uniform(0, 4, B), np.where(kind == 1, rng.uniform(0, 12, B), rng.uniform(0, 120, B)))
    tau = d * np.where(kind == 0, rng.uniform(0, 0.04, B), np.where(kind == 1, rng.uniform(0.03, 0.14, B),
                                                                   rng.uniform(0.1, 1.5, B)))
    ax = rng.normal(size=(B, 3))
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    Re = Rotation.from_rotvec(np.deg2rad(deg)[:, None] * ax).as_matrix() @ Rg
    if model.symmetric:
        Re = Re @ Rotation.from_rotvec(np.c_[np.zeros((B, 2)), rng.uniform(0, 2 * np.pi, B)]).as_matrix()
    v = rng.normal(size=(B, 3))
    te = tg + tau[:, None] * v / np.linalg.norm(v, axis=1, keepdims=True)
    return Re, te, Rg, tg


@pytest.mark.parametrize("obj_id", [1, 7])
def test_fast_path_equals_straightforward(obj_id):
    rng = np.random.default_rng(obj_id)
    m = get_object(obj_id)
    model = M.ModelPoints(m.sample_surface(3000, seed=3), m.diameter, obj_id == 1)
    B = 300
    Re, te, Rg, tg = _poses_near_threshold(model, rng, B)
    Ks = np.broadcast_to(K, (B, 3, 3))
    single = {"Re": Re, "te": te, "Rg": Rg, "tg": tg, "K": Ks}
    ev = scorer.evaluate_object(model, obj_id, single, [], 0)
    thr = 0.1 * model.diameter
    add = M.add_batch(Re, te, Rg, tg, model.pts)
    adds = M.adds_batch(Re, te, Rg, tg, model.pts)
    proj = M.proj2d_batch(Re, te, Rg, tg, model.pts, Ks)
    assert np.array_equal(ev.add_ok, add < thr)
    assert np.array_equal(ev.adds_ok, adds < thr)
    assert np.array_equal(ev.proj_ok, proj < scoring.PROJ_THRESHOLD)
    assert ev.adds_ok.sum() not in (0, B) and abs(np.median(adds) - thr) < thr  # the threshold is exercised
    auc = lambda e: float(np.mean(np.maximum(0, 1 - e / 100)))  # noqa: E731
    assert abs(auc(ev.adds) - auc(adds)) < 1e-3
    assert abs(auc(ev.add) - auc(add)) < 1e-6
    np.testing.assert_allclose(ev.add, add, atol=1e-3)
    near = proj < scoring.PROJ_PLOT_MAX  # plotted values: estimates (exact near the threshold)
    assert np.median(np.abs(ev.proj[near] - proj[near])) < 0.2
    close = np.abs(proj - scoring.PROJ_THRESHOLD) < 0.05
    np.testing.assert_allclose(ev.proj[close], proj[close], atol=1e-3)


def test_bounds_contain_the_exact_error():
    rng = np.random.default_rng(3)
    m = get_object(17)
    model = M.ModelPoints(m.sample_surface(2000, seed=1), m.diameter, True)
    Re, te, Rg, tg = _poses_near_threshold(model, rng, 120)
    A, b = M.relative_transform(Re, te, Rg, tg)
    exact = M.adds_exact(model, A, b)
    for bd in (M.adds_cluster_bounds(model, A, b, "coarse"), M.adds_cluster_bounds(model, A, b, "fine"),
               M.adds_point_bounds(model, A, b)):
        assert np.all(bd.lo <= exact) and np.all(exact <= bd.hi)
    thr = float(np.median(exact))
    d = M.adds_decide(model, A, b, thr)
    assert np.all(d.lo <= exact + 1e-9) and np.all(exact <= d.hi + 1e-9)
    assert np.all((d.hi < thr) | (d.lo >= thr))
    proj = M.proj2d_batch(Re, te, Rg, tg, model.pts, K)
    pb = M.proj2d_bounds(model, Re, te, Rg, tg, K)
    assert np.all(pb.lo <= proj) and np.all(proj <= pb.hi)


# ---------------------------------------------------------------------------------------------
# scoring conventions
# ---------------------------------------------------------------------------------------------
def test_ground_truth_scores_one_everywhere(dataset, tmp_path):
    root, gt = dataset
    csv = write_results_csv(tmp_path / "gt_tdof20-hard.csv", rows_of(gt))
    out = score(csv, root, split="hard")
    assert set(out) == PARTS
    assert set(out["objects"]) == {"1", "7", "17"}
    for part in list(out["objects"].values()) + [out["mean"], out["all"]]:
        assert set(part) == KEYS
        for k in KEYS - {"n"}:
            assert part[k] == pytest.approx(1.0, abs=1e-9)
    assert out["objects"]["7"]["n"] == 3 + 3 + 2 and out["all"]["n"] == len(gt)
    assert out["mean"]["n"] == 3
    simple = score(rows_of(gt), root, split="simple")  # a list of rows works too
    assert simple["all"]["n"] == 3 and simple["all"]["add"] == 1.0


def test_missing_prediction_is_a_failure(dataset):
    root, gt = dataset
    rows = rows_of(gt)
    drop = next(i for i, r in enumerate(rows) if r[0] == 28 and r[2] == 17)
    ev = evaluate(rows[:drop] + rows[drop + 1:], root, split="hard")
    s = ev.summary()["objects"]["17"]
    assert s["n"] == 3 and s["add"] == pytest.approx(2 / 3) and s["adds"] == pytest.approx(2 / 3)
    assert s["auc_adds"] == pytest.approx(2 / 3, abs=1e-9)
    assert any("no estimate" in w for w in ev.warnings)


def test_top_scored_prediction_counts(dataset):
    root, gt = dataset
    rows = rows_of(gt, score_=0.5)
    s, im, o, R, t = next(g for g in gt if g[0] == 8)
    wrong = (s, im, o, 0.9, R, t + [0.0, 0.0, 80.0], 0.25)
    low = (s, im, o, 0.1, R, t + [0.0, 0.0, 80.0], 0.25)
    assert score(rows + [low], root, split="simple")["all"]["add"] == 1.0
    assert score(rows + [wrong], root, split="simple")["all"]["add"] == pytest.approx(2 / 3)


def test_several_instances_are_matched_by_error(dataset):
    root, gt = dataset
    inst = [g for g in gt if g[:3] == (28, 3, 7)]
    others = [g for g in gt if g[:3] != (28, 3, 7)]
    assert len(inst) == 2
    swapped = [(28, 3, 7, 0.9, inst[1][3], inst[1][4], 0.25), (28, 3, 7, 0.8, inst[0][3], inst[0][4], 0.25)]
    s5 = score(rows_of(others) + swapped, root, split="hard")["objects"]["7"]
    assert s5["add"] == 1.0 and s5["n"] == 8
    one = score(rows_of(others) + swapped[:1], root, split="hard")["objects"]["7"]
    assert one["add"] == pytest.approx(7 / 8)
    # a wrong estimate scored higher pushes the correct one for instance 0 beyond inst_count = 2
    wrong = (28, 3, 7, 0.95, inst[0][3], inst[0][4] + [0.0, 0.0, 90.0], 0.25)
    assert score(rows_of(others) + swapped + [wrong], root, split="hard")["objects"]["7"]["add"] == pytest.approx(7 / 8)


def test_json_report_and_plots(dataset, tmp_path):
    root, gt = dataset
    good = write_results_csv(tmp_path / "good_tdof20-hard.csv", rows_of(gt))
    rng = np.random.default_rng(0)
    noisy_rows = [(s, im, o, 1.0, R @ rot(rng.normal(size=3), 6), t + rng.normal(size=3) * 8, 0.3)
                  for s, im, o, R, t in gt]
    noisy = write_results_csv(tmp_path / "noisy_tdof20-hard.csv", noisy_rows)
    js, plots = tmp_path / "out.json", tmp_path / "plots"
    text = score_command([good, noisy], root, "hard", None, js, plots)
    data = json.loads(js.read_text())
    assert set(data) == {"good_tdof20-hard", "noisy_tdof20-hard"}
    for summ in data.values():
        assert set(summ) == PARTS
        for part in list(summ["objects"].values()) + [summ["mean"], summ["all"]]:
            assert set(part) == KEYS
            assert all(0.0 <= part[k] <= 1.0 for k in KEYS - {"n"})
    assert data["noisy_tdof20-hard"]["all"]["adds"] < 1.0
    assert "Table 1" in text and "Table 2" in text and "good_tdof20-hard" in text and "noisy_tdof20-hard" in text
    assert "handle_cup_280 *" in text and "water_cup_270 *" not in text
    md = (plots / "report.md").read_text()
    assert "**7 handle_cup_280**" in md and "| 1 cube_136 |" in md
    for name in ("accuracy_add_s.png", "accuracy_adds_mm.png", "accuracy_proj2d.png"):
        assert (plots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    one = tmp_path / "one.json"
    score_command([good], root, None, root / "test_targets_simple.json", one, None)
    assert set(json.loads(one.read_text())) == PARTS


def test_report_marks_asymmetric_objects(dataset):
    root, gt = dataset
    ev = evaluate(rows_of(gt), root, split="hard")
    txt = report.table_text([ev], "add_s")
    md = report.table_markdown([ev], "proj2d")
    assert "7 handle_cup_280 *" in txt and "17 water_cup_270 *" not in txt
    assert "**7 handle_cup_280**" in md
    assert "all metrics" in report.metrics_table(ev)


# ---------------------------------------------------------------------------------------------
# strict validation of results files
# ---------------------------------------------------------------------------------------------
def _good_lines(gt) -> list[str]:
    return [HEADER] + [csv_line(*r) for r in rows_of(gt)]


def _expect(path: Path, root: Path, *fragments: str, split: str = "hard"):
    with pytest.raises(TdofError) as e:
        evaluate(path, root, split=split)
    msg = str(e.value)
    assert str(path) in msg, msg
    for f in fragments:
        assert f in msg, msg
    assert "\n" not in msg
    return msg


def test_malformed_header(dataset, tmp_path):
    root, gt = dataset
    lines = _good_lines(gt)
    _expect(write_csv(tmp_path / "a.csv", ["scene,im,obj,score,R,t,time"] + lines[1:]), root, "line 1", "header")
    _expect(write_csv(tmp_path / "b.csv", ["scene_id,im_id,obj_id,score,R,t"] + lines[1:]), root, "line 1",
            "time column")
    _expect(write_csv(tmp_path / "c.csv", []), root, "line 1")


def test_wrong_field_counts(dataset, tmp_path):
    root, gt = dataset
    lines = _good_lines(gt)
    bad = lines[:3] + [lines[3].rsplit(",", 1)[0]] + lines[4:]
    _expect(write_csv(tmp_path / "a.csv", bad), root, "line 4", "7 comma-separated fields")
    f = lines[2].split(",")
    f[4] = " ".join(f[4].split()[:8])
    _expect(write_csv(tmp_path / "b.csv", lines[:2] + [",".join(f)] + lines[3:]), root, "line 3", "R must hold 9")
    f = lines[2].split(",")
    f[5] += " 1.0"
    _expect(write_csv(tmp_path / "c.csv", lines[:2] + [",".join(f)] + lines[3:]), root, "line 3", "t must hold 3")


def test_not_numbers_nan_and_inf(dataset, tmp_path):
    root, gt = dataset
    lines = _good_lines(gt)
    for k, (field, value, frag) in enumerate([(4, "nan", "R holds NaN or inf"), (5, "inf", "t holds NaN or inf"),
                                              (3, "nan", "score holds NaN"), (5, "abc", "'abc' is not a number"),
                                              (0, "x1", "scene_id must be a non-negative integer"),
                                              (2, "-3", "obj_id must be a non-negative integer")]):
        f = lines[5].split(",")
        parts = f[field].split()
        parts[0] = value
        f[field] = " ".join(parts)
        _expect(write_csv(tmp_path / f"n{k}.csv", lines[:5] + [",".join(f)] + lines[6:]), root, "line 6", frag)


def test_rotation_not_orthonormal(dataset, tmp_path):
    root, gt = dataset
    rows = rows_of(gt)
    s, im, o, sc, R, t, tm = rows[2]
    lines = _good_lines(gt)
    lines[3] = csv_line(s, im, o, sc, R * 1.01, t, tm)
    _expect(write_csv(tmp_path / "a.csv", lines), root, "line 4", "not a rotation")
    lines[3] = csv_line(s, im, o, sc, -R, t, tm)  # orthonormal, det -1
    _expect(write_csv(tmp_path / "b.csv", lines), root, "line 4", "det")
    lines[3] = csv_line(s, im, o, sc, np.round(R, 4), t, tm)  # 4 decimals: within the tolerance
    assert read_results(write_csv(tmp_path / "c.csv", lines)).R.shape == (len(rows), 3, 3)


def test_unknown_ids(dataset, tmp_path):
    root, gt = dataset
    lines = _good_lines(gt)
    for k, (field, value, frag) in enumerate([(0, "9", "unknown scene_id 9"), (1, "42", "scene 8 has no image 42"),
                                              (2, "99", "unknown obj_id 99")]):
        f = lines[2].split(",")
        f[field] = value
        _expect(write_csv(tmp_path / f"u{k}.csv", lines[:2] + [",".join(f)] + lines[3:]), root, "line 3", frag)


def test_duplicated_rows(dataset, tmp_path):
    root, gt = dataset
    lines = _good_lines(gt)
    _expect(write_csv(tmp_path / "a.csv", lines + [lines[4]]), root, f"line {len(lines) + 1}", "duplicates line 5")


def test_times_within_an_image(dataset, tmp_path):
    root, gt = dataset
    rows = rows_of(gt)
    i = next(k for k in range(1, len(rows)) if rows[k][:2] == rows[k - 1][:2])
    lines = _good_lines(gt)
    f = lines[i + 1].split(",")
    f[6] = "0.5"
    _expect(write_csv(tmp_path / "a.csv", lines[:i + 1] + [",".join(f)] + lines[i + 2:]), root, f"line {i + 2}",
            "differs from 0.25")
    f[6] = "-2"
    _expect(write_csv(tmp_path / "b.csv", lines[:i + 1] + [",".join(f)] + lines[i + 2:]), root, "time must be >= 0")
    unmeasured = write_results_csv(tmp_path / "c.csv", rows_of(gt, time_=None))  # -1 everywhere: a warning
    ev = evaluate(unmeasured, root, split="hard")
    assert any("no time" in w for w in ev.warnings)
    assert ev.summary()["all"]["add"] == 1.0


def test_translations_in_metres(dataset, tmp_path):
    root, gt = dataset
    metres = [(s, im, o, 1.0, R, t / 1000.0, 0.1) for s, im, o, R, t in gt]
    _expect(write_results_csv(tmp_path / "m.csv", metres), root, "line 2", "look like metres")


def test_results_round_trip_and_rows_in_memory(dataset, tmp_path):
    root, gt = dataset
    path = write_results_csv(tmp_path / "r.csv", rows_of(gt))
    res = read_results(path)
    assert len(res) == len(gt) and res.line[0] == 2
    np.testing.assert_array_equal(res.R[0], gt[0][3])
    np.testing.assert_array_equal(res.t[-1], gt[-1][4])
    bad = [(8, 0, 5, 1.0, np.eye(3) * 2, np.zeros(3), 0.1)]
    with pytest.raises(TdofError, match="row 1: R is not a rotation"):
        Results.from_rows(bad)


def test_bad_targets_and_split(dataset, tmp_path):
    root, gt = dataset
    rows = rows_of(gt)
    t = tmp_path / "t.json"
    write_json(t, [{"scene_id": 8, "im_id": 0, "obj_id": 7, "inst_count": 2}])
    with pytest.raises(TdofError, match="2 instances of object 7"):
        score(rows, root, targets=t)
    write_json(t, [{"scene_id": 8, "im_id": 77, "obj_id": 7, "inst_count": 1}])
    with pytest.raises(TdofError, match="no image 77"):
        score(rows, root, targets=t)
    with pytest.raises(TdofError, match="exactly one of"):
        score(rows, root)
    with pytest.raises(TdofError, match="unknown split"):
        score(rows, root, split="medium")
