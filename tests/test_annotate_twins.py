"""Opaque twins off their slots (issue 34, part 2): the labels are fitted to the twins, but the
transparent objects stood a millimetre or two and a degree away. The place stage's twin check
(tdof20.annotate.twins) measures each glass object's offset from its twin in the transparent
phase's glass returns, corrects the pose where the evidence is strong, and otherwise says so
(flagged: off for certain; noted: inconclusive), never silently.

Sizes: the estimator on synthetic rays; the simulator at the demo's size (4 arm positions x 16
steps, 320x240), where the evidence is strong enough to correct."""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np
import pytest

from tdof20.annotate.config import AnnotateConfig, PlaceConfig
from tdof20.annotate.label import LabelConfig
from tdof20.annotate.pipeline import annotate, summary_text
from tdof20.annotate.twins import TwinEstimate, _fit, _offset, _Surface, twin_decision
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats import read_json
from tdof20.objects import get_object

UP = np.array([0.0, 0.0, 1.0])
C = np.array([10.0, -5.0, 0.0])


def _est(move_mm, turn, ci_mm, ci_deg=None) -> TwinEstimate:
    return TwinEstimate(np.array([move_mm, 0.0, 0.0]), turn, ci_mm, ci_deg, 5000, 12, C, UP)


@pytest.mark.parametrize("est, action", [
    (_est(2.0, 0.0, 0.3), "corrected"),                 # strong evidence, within the gate
    (_est(2.0, 1.0, 0.3, 0.4), "corrected"),
    (_est(2.0, 1.0, 0.3, 0.9), "corrected"),            # moved; the turn's bound too loose, and within its noise
    (_est(2.0, 2.5, 0.3, 0.9), "flagged"),              # moved; turned beyond doubt but too loosely bound
    (_est(0.3, 0.0, 0.65), "within"),                   # weak, but the bound keeps it within 1 mm: kept
    (_est(0.6, 0.0, 0.9), "noted"),                     # inconclusive: neither within nor off
    (_est(2.6, 0.0, 0.9), "flagged"),                   # weak, but off by more than 1 mm beyond doubt
    (_est(7.0, 0.0, 0.2), "flagged"),                   # beyond place.twin_max_mm
    (_est(1.0, 8.0, 0.2, 0.2), "flagged"),              # beyond place.twin_max_deg
    ("12 glass returns on it (< place.twin_min_points = 200)", "noted"),
])
def test_each_estimate_gets_one_action_and_a_line_that_says_it(est, action):
    got, line, D = twin_decision(est, PlaceConfig())
    assert got == action
    moved = not isinstance(est, str) and est.ci95_mm <= 0.6 and est.move_mm <= 5 and abs(est.turn_deg) <= 5
    assert (D is not None) == moved
    if D is not None:
        turned = est.ci95_deg is not None and est.ci95_deg <= 0.6
        assert (abs(D[1, 0]) > 1e-6) == turned
    assert "\n" not in line and ("twin" in line)
    if action == "flagged":
        assert "check the slot" in line


def test_the_applied_offset_is_shrunk_by_its_own_noise_and_turns_about_the_centre():
    e = _est(2.0, 1.0, 0.3, 0.4)
    D = e.transform(shrink=False)
    assert np.allclose(D[:3, :3] @ C + D[:3, 3], C + [2.0, 0, 0])   # the centre moves by the move alone
    assert math.degrees(math.atan2(D[1, 0], D[0, 0])) == pytest.approx(1.0)
    Ds = e.transform()
    sigma2 = (0.3 / 1.96) ** 2
    assert np.allclose(Ds[:3, :3] @ C + Ds[:3, 3] - C, [2.0 * 4.0 / (4.0 + sigma2), 0, 0])
    weak = _est(0.2, 0.0, 0.8).transform()   # within its noise: shrunk most of the way to nothing
    assert np.linalg.norm(weak[:3, :3] @ C + weak[:3, 3] - C) < 0.05


def test_the_fit_finds_the_glass_in_noisy_returns_along_the_rays():
    """Glass returns drawn as a stereo camera gives them on glass: 10 % the glass surface with 6 mm
    noise along the ray, 25 % the background 40 mm behind it; the model starts at the twin's pose."""
    obj = get_object(8)   # handle_cup_440: asymmetric, so the turn is estimated too
    surf = _Surface(obj.vertices, obj.faces)
    rng = np.random.default_rng(0)
    T_twin = np.eye(4)
    centre = 0.5 * (obj.vertices.min(0) + obj.vertices.max(0))
    centre[2] = obj.vertices[:, 2].min()
    true_move, true_turn = np.array([1.6, -1.2, 0.0]), math.radians(1.0)
    T_glass = _offset(true_move, true_turn, centre, UP) @ T_twin
    O, D, R = [], [], []
    for az in np.linspace(0, 2 * np.pi, 24, endpoint=False):
        for el in (0.4, 0.8):
            o = centre + 450.0 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
            tgt = centre + [0, 0, 50] + rng.uniform(-70, 70, (3000, 3)) * [1, 1, 0.7]
            d = tgt - o
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            t, _ = surf.cast(T_glass, np.broadcast_to(o, d.shape), d)
            hit = np.isfinite(t)
            u = rng.random(hit.sum())
            keep = u > 0.65
            r = t[hit][keep] + np.where(u[keep] > 0.9, rng.normal(0, 6.0, keep.sum()), 40.0)
            O.append(np.broadcast_to(o, (keep.sum(), 3)))
            D.append(d[hit][keep])
            R.append(r)
    O, D, R = np.concatenate(O), np.concatenate(D), np.concatenate(R)
    move, ang = _fit(surf, T_twin, O, D, R, centre, UP, True, 4.0, 15.0)
    assert np.linalg.norm(move - true_move) < 0.3
    assert abs(math.degrees(ang - true_turn)) < 0.3
    move0, _ = _fit(surf, T_glass, O, D, R, centre + true_move, UP, True, 4.0, 15.0)   # from the truth: stays
    assert np.linalg.norm(move0) < 0.3


def test_place_twin_options_are_checked():
    with pytest.raises(TdofError, match="place.twin_groups"):
        PlaceConfig(twin_groups=0)


# ---------------------------------------------------------------------------------------------
# the simulator: twins 2 mm and 1 deg off their slots
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def twin_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("twins")
    raw = root / "raw"
    run_capture(sim_config("multi/08", steps=16, step_deg=22.5, n_arms=4, width=320, height=240, seed=3,
                           twin_offset_mm=2.0, twin_offset_deg=1.0), raw, yes=True, show_progress=False)
    out = root / "scene"
    summary = annotate(raw, out, models_dir=raw / "truth" / "models", cfg=AnnotateConfig(label=LabelConfig(workers=1)),
                       progress=False)
    return raw, out, summary


def _centre_errors(raw, out) -> dict[int, list[float]]:
    """{obj_id: |label centre - true centre| mm per labelled instance}."""
    truth = read_json(raw / "truth" / "scene_gt.json")
    labels = read_json(out / "scene_gt.json")
    err: dict[int, list[float]] = {}
    for im, ents in labels.items():
        for e in ents:
            t = [g for g in truth[im] if g["obj_id"] == e["obj_id"]][0]
            V = get_object(e["obj_id"]).vertices
            c = 0.5 * (V.min(0) + V.max(0))
            a = np.reshape(e["cam_R_m2c"], (3, 3)) @ c + np.asarray(e["cam_t_m2c"])
            b = np.reshape(t["cam_R_m2c"], (3, 3)) @ c + np.asarray(t["cam_t_m2c"])
            err.setdefault(int(e["obj_id"]), []).append(float(np.linalg.norm(a - b)))
    return err


def test_twins_off_their_slots_are_measured_and_the_labels_follow_the_glass(twin_scene):
    raw, out, summary = twin_scene
    pl = read_json(out / "work" / "placements.json")["placements"]
    err = _centre_errors(raw, out)
    unresolved = {f["obj_id"] for f in summary["unresolved_flags"]}
    actions = {p["obj_id"]: p["twin"]["action"] for p in pl}
    assert sum(a == "corrected" for a in actions.values()) >= 3, actions   # measured: 4 of 4
    for p in pl:
        tw = p["twin"]
        assert tw["points"] >= 1000 and 1.0 <= tw["offset_mm"] <= 3.0   # measured 1.7-2.5 (truth 2)
        if tw["action"] == "corrected":
            assert p["T_ref_twin"] != p["T_ref_model"]
            assert np.median(err[p["obj_id"]]) <= 1.0, (p["obj_id"], tw)
        else:   # never silently off: flagged (an unresolved flag) or noted with its bound
            assert tw["action"] in ("flagged", "noted")
        assert (p["obj_id"] in unresolved) == (tw["action"] == "flagged")
    every = [e for v in err.values() for e in v]
    assert np.median(every) <= 1.0   # the twins' pose: 2 mm
    assert len(read_json(out / "scene_gt.json")) >= 0.9 * 64
    text = summary_text(summary)
    assert "twin corrected: the glass stands" in text
    qa = read_json(out / "qa" / "qa.json")
    assert {t["obj_id"] for t in qa["twins"]} == set(actions)
    assert "Twin placement" in (out / "qa" / "report.html").read_text()


def test_the_twin_check_can_be_turned_off(twin_scene, tmp_path):
    """Without it the labels are the twins': ~2 mm off (what annotation wrote before)."""
    raw, out, _ = twin_scene
    cfg = AnnotateConfig(label=LabelConfig(workers=1), place=dataclasses.replace(PlaceConfig(), twin_check=False))
    off = tmp_path / "scene"
    shutil.copytree(out, off)   # registered and reconstructed already: place and label again
    annotate(raw, off, models_dir=raw / "truth" / "models", cfg=cfg, progress=False, stages="place..label")
    assert not any("twin" in p for p in read_json(off / "work" / "placements.json")["placements"])
    every = [e for v in _centre_errors(raw, off).values() for e in v]
    assert np.median(every) > 1.5
