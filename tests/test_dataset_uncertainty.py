"""scene_gt_uncertainty.json (issue 34, part 3): a scene's 95 % bounds on its labels' own errors go
into the built dataset (tdof20's layout: the scene whole; BOP's: cut to each part's images like
scene_gt.json), checked against scene_gt.json first (one-line errors, nothing written), and
``dataset stats`` gives each object's label-noise floor. Fixtures written by hand from the format
(docs/formats.md), on tiny simulated scenes labelled from the simulator's truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from tdof20.cli import app
from tdof20.dataset.build import build_dataset, build_dataset_in_layout, stats
from tdof20.errors import TdofError
from tdof20.formats import read_json
from tdof20.formats.bop_uncertainty import SCENE_GT_UNCERTAINTY
from tests.test_dataset_reliability import cli, make_scene

UNC = SCENE_GT_UNCERTAINTY


def bounds_for(gt: dict) -> dict:
    """A scene_gt_uncertainty.json for scene_gt.json ``gt``: numbers that differ per image and instance."""
    return {k: [{"obj_id": g["obj_id"], "rot_deg": 0.1 + 0.05 * int(k) + 0.01 * n, "trans_mm": 0.5 + 0.1 * int(k) + 0.02 * n,
                 "surface_mm": 0.3 + 0.03 * int(k)} for n, g in enumerate(lst)] for k, lst in gt.items()}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """{"single": single/03 (no bounds), "multi": multi/08 (bounds for every label)}, 64x48, 4 steps x 2 arms."""
    base = tmp_path_factory.mktemp("unc")
    single = make_scene(base, "single/03", steps=4, n_arms=2, width=64, height=48)
    multi = make_scene(base, "multi/08", steps=4, n_arms=2, width=64, height=48)
    (multi / UNC).write_text(json.dumps(bounds_for(read_json(multi / "scene_gt.json"))))
    return {"single": single, "multi": multi}


def _sid(scene) -> str:
    from tdof20.dataset.splits import scene_number

    return f"{scene_number(read_json(scene / 'scene_info.json')['scene_id']):06d}"


def test_tdof20_build_copies_the_bounds_and_stats_give_the_floor(scenes, tmp_path):
    out = tmp_path / "ds"
    s = build_dataset([scenes["single"], scenes["multi"]], out, show_progress=False)
    multi = out / "scenes" / _sid(scenes["multi"])
    assert read_json(multi / UNC) == read_json(scenes["multi"] / UNC)
    assert not (out / "scenes" / _sid(scenes["single"]) / UNC).exists()  # a scene without bounds builds as before
    src = read_json(scenes["multi"] / UNC)
    multi_objs = {e["obj_id"] for lst in src.values() for e in lst}
    single_objs = {g["obj_id"] for lst in read_json(scenes["single"] / "scene_gt.json").values() for g in lst}
    assert single_objs.isdisjoint(multi_objs)
    for o in multi_objs:
        f = s["label_noise"][o]
        v = {k: [e[k] for lst in src.values() for e in lst if e["obj_id"] == o] for k in ("trans_mm", "rot_deg", "surface_mm")}
        assert f["bounded"] == f["labels"] == len(v["trans_mm"]) == s["per_object"][o]
        for k, xs in v.items():
            assert f[k]["median"] == pytest.approx(np.median(xs), abs=1e-4)
            assert f[k]["p95"] == pytest.approx(np.percentile(xs, 95), abs=1e-4)
    for o in single_objs:
        f = s["label_noise"][o]
        assert f["bounded"] == 0 and f["labels"] > 0 and f["trans_mm"] is None and f["rot_deg"] is None
    assert stats(out)["label_noise"] == s["label_noise"]
    r = CliRunner().invoke(app, ["dataset", "stats", str(out)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "label-noise floor per object" in r.output and "not recorded" in r.output
    o = min(multi_objs)
    f = s["label_noise"][o]
    assert f"{f['trans_mm']['median']:.2f} / {f['trans_mm']['p95']:.2f}" in r.output
    r = CliRunner().invoke(app, ["dataset", "stats", str(out), "--json"])
    assert r.exit_code == 0
    js = json.loads(r.output)
    assert js["label_noise"][str(o)]["trans_mm"] == f["trans_mm"]
    assert js["label_noise"][str(min(single_objs))]["trans_mm"] is None


def test_bop_build_cuts_the_bounds_to_each_part(scenes, tmp_path):
    single = tmp_path / "single_03"  # (simple: single-object scenes, their arcs in train/ and test/)
    shutil.copytree(scenes["single"], single)
    (single / UNC).write_text(json.dumps(bounds_for(read_json(single / "scene_gt.json"))))
    out = tmp_path / "bop"
    s = build_dataset_in_layout("bop", [single, scenes["multi"]], out, split="simple", show_progress=False)
    src = read_json(single / UNC)
    seen = set()
    for folder in ("train", "test"):
        d = out / folder / _sid(single)
        got = read_json(d / UNC)
        assert set(got) == set(read_json(d / "scene_gt.json")) and got == {k: src[k] for k in got}
        seen |= set(got)
    assert seen == set(src) and len(seen) > len(got) > 0  # each image's bounds in its own part, none lost
    o = next(iter({e["obj_id"] for lst in src.values() for e in lst}))
    assert s["label_noise"][o]["bounded"] == s["label_noise"][o]["labels"] == len(src)


def _first(d: dict) -> str:
    return min(d, key=int)


def _wrong_length(u):
    u[_first(u)].pop()
    return u


def _wrong_obj(u):
    u[_first(u)][1]["obj_id"] = 99
    return u


def _negative(u):
    u[_first(u)][0]["trans_mm"] = -0.5
    return u


def _nan(u):
    u[_first(u)][0]["rot_deg"] = float("nan")
    return u


def _missing_image(u):
    del u[max(u, key=int)]
    return u


def _missing_field(u):
    del u[_first(u)][0]["surface_mm"]
    return u


BAD = {
    "wrong length": (_wrong_length, "entries but scene_gt.json has"),
    "wrong obj_id": (_wrong_obj, "entry 1 is obj 99 but scene_gt.json has obj"),
    "negative": (_negative, "entry 0: trans_mm must be a finite number >= 0, got -0.5"),
    "NaN": (_nan, "entry 0: rot_deg must be a finite number >= 0, got nan"),
    "missing image": (_missing_image, "is in scene_gt.json but has no entry here"),
    "missing field": (_missing_field, "entry 0: missing field 'surface_mm'"),
    "not JSON": (None, "malformed JSON at line 1"),
}


@pytest.mark.parametrize("case", list(BAD))
@pytest.mark.parametrize("layout", ["tdof20", "bop"])
def test_malformed_bounds_are_one_line_and_nothing_is_written(scenes, tmp_path, case, layout):
    scene = tmp_path / "multi_08"
    shutil.copytree(scenes["multi"], scene)
    change, expect = BAD[case]
    gt = read_json(scene / "scene_gt.json")
    n = len(gt[_first(gt)])
    assert n >= 2  # (multi/08: several objects in every image)
    if change is None:
        (scene / UNC).write_text('{"0": [{"obj_id": 6, "rot_deg": 0.1,')
    else:
        (scene / UNC).write_text(json.dumps(change(read_json(scene / UNC))))
    out = tmp_path / "out"
    with pytest.raises(TdofError) as e:
        build_dataset_in_layout(layout, [scenes["single"], scene], out, split="simple" if layout == "bop" else None,
                                show_progress=False)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{scene / UNC}: ") and expect in msg, msg
    if case == "wrong length":
        assert f"image {_first(gt)} lists {n - 1} entries but scene_gt.json has {n} instances" in msg
    if case == "wrong obj_id":
        assert f"image {_first(gt)} entry 1 is obj 99 but scene_gt.json has obj {gt[_first(gt)][1]['obj_id']}" in msg
    assert not out.exists()


def test_cli_build_names_the_file(scenes, tmp_path, capsys):
    scene = tmp_path / "multi_08"
    shutil.copytree(scenes["multi"], scene)
    u = read_json(scene / UNC)
    (scene / UNC).write_text(json.dumps(_wrong_obj(u)))
    rc, line = cli(capsys, "dataset", "build", scene, "--out", tmp_path / "o")  # (one "error:" line, no traceback)
    assert rc != 0 and line.startswith(f"error: {scene / UNC}: image ") and not (tmp_path / "o").exists()
