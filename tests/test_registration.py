"""Registration of raw sessions (opaque depth) against the simulator's truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tdof20.annotate import (RegistrationConfig, RegistrationResult, evaluate_against_truth,
                             register_session)
from tdof20.annotate.evaluate import truth_T_ref_frame
from tdof20.annotate.icp import edge_pairs as _edge_pairs
from tdof20.annotate.turntable import fit_axis as _fit_axis
from tdof20.capture import run_capture, sim_config
from tdof20.errors import TdofError
from tdof20.formats.io import read_png, write_png
from tdof20.geometry.transforms import rotation_about_axis, rotation_matrix

STEPS, STEP_DEG = 12, 30.0
SIZE = dict(width=320, height=240)


def _session(tmp_path_factory, scene: str):
    out = tmp_path_factory.mktemp("reg") / scene.replace("/", "_")
    run_capture(sim_config(scene, steps=STEPS, step_deg=STEP_DEG, n_arms=2, phases=("opaque",), **SIZE),
                out, yes=True, show_progress=False)
    return out


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    d = _session(tmp_path_factory, "multi/08")
    return d, register_session(d, progress=False)


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    d = _session(tmp_path_factory, "single/handle_cup_280")
    return d, register_session(d, progress=False)


# --- pure helpers -----------------------------------------------------------------------------
def test_fit_axis_recovers_a_known_axis():
    n = np.array([0.1, -0.9, -0.4])
    n /= np.linalg.norm(n)
    p = np.array([5.0, 50.0, 470.0])
    d = -float(n @ p)
    Ts = np.stack([rotation_about_axis(n, np.radians(-a), p) for a in range(0, 360, 30)])
    n2, p2 = _fit_axis(Ts, n, n, d)
    assert np.degrees(np.arccos(np.clip(n2 @ n, -1, 1))) < 1e-6
    assert np.linalg.norm(p2 - p) < 1e-6


def test_edge_pairs_close_the_loop():
    pairs = _edge_pairs(list(range(12)), 30.0, (0.0,))
    assert (0, 11) in pairs and (0, 1) in pairs and len(pairs) == 12
    # a partial turn does not wrap
    assert (0, 5) not in _edge_pairs(list(range(6)), 10.0, (0.0,))


# --- simulated sessions ------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["multi", "single"])
def test_accuracy_against_truth(which, request):
    d, res = request.getfixturevalue(which)
    ev = evaluate_against_truth(res, d)
    assert res.flagged_frames() == []
    assert ev["n_frames"] == 2 * STEPS
    for arm in ev["arms"]:
        assert arm["axis_deg"] < 1.0
        assert arm["axis_line_mm"] < 2.0
        assert arm["axis_point_mm"] < 3.0            # where the axis meets the table top
        assert arm["T_ref_arm_rot_deg"] < 0.5 and arm["T_ref_arm_trans_mm"] < 3.0
    for key in ("pairs", "consecutive", "frame_to_ref"):
        assert ev[key]["rot_deg"]["median"] < 0.3, (key, ev[key])
        assert ev[key]["trans_mm"]["median"] < 1.5, (key, ev[key])
        assert ev[key]["rot_deg"]["p95"] < 0.5, (key, ev[key])
        assert ev[key]["trans_mm"]["p95"] < 3.0, (key, ev[key])
    for f in res.frames:
        assert f.fitness > 0.4 and f.rmse < 3.0 and f.residual_deg < 1.0 and f.residual_mm < 5.0
        assert np.allclose(f.T_ref_frame[3], [0, 0, 0, 1])
    assert np.allclose(res.frame(0, 0).T_ref_frame, np.eye(4), atol=1e-6)


def test_truth_convention(multi):
    """T_ref_frame maps a table-fixed point seen in cam(a,k) onto where cam(0,0) sees it."""
    d, _ = multi
    truth = truth_T_ref_frame(d)
    cams = json.loads((d / "truth" / "scene_camera.json").read_text())
    x_table = np.array([30.0, -20.0, 15.0, 1.0])
    for a, k in [(0, 3), (1, 7)]:
        c = cams[str(a * STEPS + k)]
        T = np.eye(4)
        T[:3, :3] = np.reshape(c["cam_R_w2c"], (3, 3))
        T[:3, 3] = c["cam_t_w2c"]
        c0 = cams["0"]
        T0 = np.eye(4)
        T0[:3, :3] = np.reshape(c0["cam_R_w2c"], (3, 3))
        T0[:3, 3] = c0["cam_t_w2c"]
        assert np.allclose(truth[a, k] @ (T @ x_table), T0 @ x_table)


def test_save_load_round_trip(multi, tmp_path):
    _, res = multi
    p = res.save(tmp_path / "registration.json")
    back = RegistrationResult.load(p)
    assert back.scene_id == res.scene_id and back.steps == res.steps and back.n_arms == res.n_arms
    assert np.allclose(back.poses(), res.poses())
    for a, b in zip(res.frames, back.frames):
        assert (a.arm, a.step, a.flagged, a.reason) == (b.arm, b.step, b.flagged, b.reason)
        assert np.isclose(a.fitness, b.fitness) and np.isclose(a.rmse, b.rmse)
    for a, b in zip(res.arms, back.arms):
        assert np.allclose(a.axis_dir, b.axis_dir) and np.allclose(a.axis_point, b.axis_point)
        assert np.allclose(a.T_ref_arm, b.T_ref_arm)
    assert back.config == res.config
    (tmp_path / "bad.json").write_text('{"format": "something else"}')
    with pytest.raises(TdofError, match="not a registration result"):
        RegistrationResult.load(tmp_path / "bad.json")


def test_corrupt_frame_flagged_and_arm_prior_refined(multi, tmp_path):
    """A copy of the session with one shifted opaque depth image and a robot pose 1 deg / 5 mm off:
    the frame is flagged (and left out), and the arm-to-arm transform ends nearer the truth than
    the perturbed robot prior."""
    src, _ = multi
    d = tmp_path / "copy"
    shutil.copytree(src, d)
    png = d / "opaque" / "arm0" / "depth" / "000005.png"
    depth = read_png(png)
    write_png(png, np.roll(depth, 25, axis=1))           # the checksum no longer matches: never mind
    sj = json.loads((d / "session.json").read_text())
    T = np.asarray(sj["arm_positions"][1]["T_base_tcp"], float).reshape(4, 4)
    E = np.eye(4)
    E[:3, :3] = rotation_matrix(np.array([0.3, 1.0, 0.2]), np.radians(1.0))
    E[:3, 3] = [3.0, -4.0, 0.0]
    sj["arm_positions"][1]["T_base_tcp"] = [float(x) for x in (T @ E).reshape(-1)]
    (d / "session.json").write_text(json.dumps(sj))
    res = register_session(d, progress=False)
    flagged = {(a, k) for a, k, _ in res.flagged_frames()}
    assert flagged == {(0, 5)}
    assert res.frame(0, 5).reason
    assert not res.usable(0, 5) and res.usable(0, 4)
    ev = evaluate_against_truth(res, d)
    arm1 = ev["arms"][1]
    assert arm1["prior_rot_deg"] > 0.9
    assert arm1["T_ref_arm_rot_deg"] < 0.5 * arm1["prior_rot_deg"]
    assert arm1["T_ref_arm_trans_mm"] < arm1["prior_trans_mm"]
    assert ev["pairs"]["rot_deg"]["median"] < 0.3, ev


def test_session_without_opaque_phase(tmp_path):
    out = tmp_path / "t"
    run_capture(sim_config("multi/08", steps=2, step_deg=30.0, n_arms=1, phases=("transparent",),
                           width=160, height=120), out, yes=True, show_progress=False)
    with pytest.raises(TdofError, match="no opaque phase"):
        register_session(out, progress=False)


def test_config_round_trip():
    cfg = RegistrationConfig(voxel_sizes_mm=(6.0, 3.0), max_residual_deg=0.5)
    assert RegistrationConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(TdofError, match="unknown registration option"):
        RegistrationConfig.from_dict({"voxel": 3})
