"""The simulated lab (tdof20.sim.lab): clutter, the table's direction, hand-eye error and
step-angle error — each on a tiny session, against the simulator's exact truth."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tdof20.capture import load_config, run_capture, sim_config
from tdof20.capture.plan import hand_eye
from tdof20.capture.rig import build_rig
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, read_scene, read_session
from tdof20.geometry import invert, look_at, rotation_angle
from tdof20.objects import get_object
from tdof20.sim.lab import CLUTTER, TableMotion, hand_eye_offset, true_hand_eye
from tdof20.sim.render import SimRenderer
from tdof20.sim.rig import DEFAULT_T_TCP_CAM, RigLayout, oakd_camera
from tdof20.sim.scenes import get_scene

TINY = dict(steps=3, step_deg=30.0, n_arms=1, width=160, height=120)


def capture(tmp_path_factory, name, **kw):
    cfg = sim_config("multi/08", **{**TINY, **kw})
    out = tmp_path_factory.mktemp("lab") / name
    run_capture(cfg, out, yes=True, show_progress=False)
    return cfg, out


def truth_table_angles(session_dir) -> np.ndarray:
    """Physical table angles (deg, ccw from above) of the transparent frames, from truth/'s
    cam_R_w2c and the true camera pose of step 0's arm: Rz(theta) = T_table0_base T_base_cam T_w2c."""
    info = read_session(session_dir)
    truth = read_scene(session_dir / "truth")
    rig = read_json(session_dir / "truth" / "rig.json")
    T_base_table0 = RigLayout().T_base_table0
    out = []
    for im_id in sorted(truth.im_ids()):
        arm = im_id // info.steps
        cam = truth.camera[im_id]
        T_w2c = np.eye(4)
        T_w2c[:3, :3] = np.asarray(cam["cam_R_w2c"]).reshape(3, 3)
        T_w2c[:3, 3] = cam["cam_t_w2c"]
        T_base_cam = np.asarray(rig["T_base_cam"][arm]).reshape(4, 4)
        Rz = invert(T_base_table0) @ T_base_cam @ T_w2c
        assert np.allclose(Rz[2, :3], [0, 0, 1], atol=1e-9) and abs(Rz[2, 3]) < 1e-6
        out.append(np.degrees(np.arctan2(Rz[1, 0], Rz[0, 0])))
    return np.array(out)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    return capture(tmp_path_factory, "plain")


# ------------------------------------------------------------------------------- defaults
def test_default_options_are_the_clean_rig(plain):
    cfg, out = plain
    s = cfg.sim
    assert (s.clutter, s.record_direction, s.hand_eye_error_mm, s.hand_eye_error_deg, s.step_jitter_deg) == \
        ((), True, 0.0, 0.0, 0.0) and cfg.turntable.direction == "ccw"
    d = json.loads((out / "session.json").read_text())
    assert d["turntable"]["direction"] == "ccw"
    assert "lab" not in d["sim"] and "direction" not in d["capture"]["turntable"]
    rig = build_rig(cfg)
    assert rig.world.table.is_nominal and rig.world.renderer.clutter == ()
    # the camera renders where session.json says it is, at the angle the table was told
    info = read_session(out)
    assert np.array_equal(rig.world.renderer.T_base_cams[0], info.T_base_cam(0))
    assert np.allclose(truth_table_angles(out), [0.0, 30.0, 60.0], atol=1e-9)
    r = SimRenderer(get_scene("multi/08"), oakd_camera(160, 120), RigLayout(), rig.world.renderer.T_base_cams)
    assert np.array_equal(RawSession.open(out).load_rgb("transparent", 0, 1), r.render(0, 30.0, "transparent").rgb)


# ------------------------------------------------------------------------------- clutter
def test_clutter_is_static_opaque_and_not_in_truth(tmp_path_factory, plain):
    cfg_p, out_p = plain
    cfg, out = capture(tmp_path_factory, "clutter", clutter=("cabinet", "wall"))
    r, rp = build_rig(cfg).world.renderer, build_rig(cfg_p).world.renderer
    z_clutter, z_plain = r._background(0)["z"], rp._background(0)["z"]
    static = z_clutter < z_plain - 20  # pixels that see the clutter where the clean rig sees the room
    assert static.mean() > 0.15
    s, sp = RawSession.open(out), RawSession.open(out_p)
    truth, truth_p = read_scene(out / "truth"), read_scene(out_p / "truth")
    labels = []
    for k in range(3):
        label = np.full(static.shape, -1)
        for g in range(len(truth.gt[k])):
            label[truth.mask(k, g, visib=True)] = g
        labels.append(label)
        # truth: the same objects, and their visible masks are what the clutter leaves
        assert [g["obj_id"] for g in truth.gt[k]] == [g["obj_id"] for g in truth_p.gt[k]]
        for g in range(len(truth.gt[k])):
            assert not (truth.mask(k, g, visib=True) & ~truth_p.mask(k, g, visib=True)).any()
        near_obj = cv2.dilate((label >= 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        free = static & ~near_obj  # clear of the objects and their flying pixels
        bound = 6 * r.sensor.depth_sigma(z_clutter, r.camera.fx) + 2
        for phase in ("transparent", "opaque"):
            z = s.load_depth_mm(phase, 0, k)
            ok = free & (z > 0)
            assert ok.sum() > 0.8 * free.sum()  # seen in depth in both phases ...
            assert np.all(np.abs(z - z_clutter)[ok] < bound[ok])  # ... where the clutter is, every step
            assert np.median(sp.load_depth_mm(phase, 0, k)[ok]) > np.median(z[ok]) + 100
            # and in colour
            diff = np.abs(s.load_rgb(phase, 0, k).astype(int) - sp.load_rgb(phase, 0, k)).mean(axis=2)
            assert diff[free].mean() > 15
    # while the objects move
    assert (labels[0] != labels[1]).sum() > 100 and (labels[1] != labels[2]).sum() > 100
    assert read_json(out / "truth" / "rig.json")["clutter"] == ["cabinet", "wall"]
    assert json.loads((out / "session.json").read_text())["sim"]["lab"] == {"clutter": ["cabinet", "wall"]}


def test_every_preset_is_seen_from_the_default_arm_positions():
    cfg = sim_config("multi/08", n_arms=4, width=160, height=120)
    base = build_rig(cfg).world.renderer
    for name in CLUTTER:
        r = build_rig(sim_config("multi/08", n_arms=4, width=160, height=120, clutter=(name,))).world.renderer
        seen = [(r._background(a)["z"] < base._background(a)["z"] - 5).mean() for a in range(4)]
        assert max(seen) > 0.05, (name, seen)  # a real part of the picture from some arm position
        assert sum(v > 0.005 for v in seen) >= 2, (name, seen)


def test_clutter_hides_objects_where_the_geometry_says_so():
    """A camera behind the cabinet, looking at the table past it: the truth labels are the
    objects' pixels the cabinet leaves; the full masks do not change."""
    layout = RigLayout()
    scene = get_scene("multi/08")
    cx, cy, cz = layout.table_centre
    a = np.radians(CLUTTER["cabinet"].azimuth_deg)
    eye = np.array([cx + 900 * np.cos(a), cy + 900 * np.sin(a), cz + 60])
    T = look_at(eye, np.array([cx, cy, cz + 40]))
    cam = oakd_camera(160, 120)
    with_c = SimRenderer(scene, cam, layout, [T], clutter=("cabinet",), threads=False)
    without = SimRenderer(scene, cam, layout, [T], threads=False)
    for angle in (0.0, 90.0, 200.0):
        f, g = with_c.truth(0, angle), without.truth(0, angle)
        z_cab = with_c._background(0)["z"]
        hidden = (g.label >= 0) & (z_cab < g.depth_true)
        assert np.array_equal(f.label, np.where(hidden, -1, g.label))
        assert np.array_equal(f.depth_true, np.minimum(g.depth_true, z_cab))
        full_c, full = with_c.full_masks(f.poses), without.full_masks(g.poses)
        assert all(np.array_equal(x, y) for x, y in zip(full_c, full))
    assert hidden.sum() > 50


# ------------------------------------------------------------------------------- direction
def test_clockwise_table(tmp_path_factory, plain):
    _, out_ccw = plain
    cfg, out = capture(tmp_path_factory, "cw", direction="cw")
    ccw, cw = truth_table_angles(out_ccw), truth_table_angles(out)
    assert np.allclose(cw, -ccw, atol=1e-9) and np.allclose(cw, [0.0, -30.0, -60.0], atol=1e-9)
    assert read_session(out).turntable["direction"] == "cw"
    rig = read_json(out / "truth" / "rig.json")
    assert rig["direction"] == "cw" and rig["table_angle_deg"]["opaque"] == [[0.0, -30.0, -60.0]]
    # the journal records what the table was told
    assert [e.angle_deg for e in RawSession.open(out).entries[:3]] == [0.0, 30.0, 60.0]
    r = build_rig(cfg).world.renderer
    assert np.array_equal(RawSession.open(out).load_rgb("opaque", 0, 1), r.render(0, -30.0, "opaque").rgb)


def test_direction_can_be_left_out_of_session_json(tmp_path_factory):
    _, out = capture(tmp_path_factory, "nodir", direction="cw", record_direction=False, steps=2)
    d = json.loads((out / "session.json").read_text())
    assert "direction" not in d["turntable"] and "direction" not in json.dumps(d)
    assert np.allclose(truth_table_angles(out), [0.0, -30.0], atol=1e-9)  # still turned clockwise


# ------------------------------------------------------------------------------- hand-eye
def test_hand_eye_error(tmp_path_factory):
    cfg, out = capture(tmp_path_factory, "handeye", hand_eye_error_mm=2.0, hand_eye_error_deg=0.5, steps=2)
    info = read_session(out)
    assert np.array_equal(info.T_tcp_cam, DEFAULT_T_TCP_CAM)  # the recorded calibration: nominal
    truth = read_scene(out / "truth")
    cam = truth.camera[0]  # step 0: table at angle 0, so T_w2c = T_cam_base T_base_table0
    T_w2c = np.eye(4)
    T_w2c[:3, :3] = np.asarray(cam["cam_R_w2c"]).reshape(3, 3)
    T_w2c[:3, 3] = cam["cam_t_w2c"]
    T_base_cam_true = RigLayout().T_base_table0 @ invert(T_w2c)
    T_true = invert(info.arm_positions[0].T_base_tcp) @ T_base_cam_true
    assert np.linalg.norm(T_true[:3, 3] - info.T_tcp_cam[:3, 3]) == pytest.approx(2.0, abs=1e-6)
    assert np.degrees(rotation_angle(T_true[:3, :3], info.T_tcp_cam[:3, :3])) == pytest.approx(0.5, abs=1e-6)
    rig = read_json(out / "truth" / "rig.json")
    assert np.allclose(np.reshape(rig["T_tcp_cam"], (4, 4)), T_true, atol=1e-6)
    assert np.allclose(np.reshape(rig["T_tcp_cam_recorded"], (4, 4)), info.T_tcp_cam)
    # the frames are rendered from the true camera: the truth poses follow it
    g = truth.gt[1][0]
    T_cam_obj = np.eye(4)
    T_cam_obj[:3, :3] = np.asarray(g["cam_R_m2c"]).reshape(3, 3)
    T_cam_obj[:3, 3] = g["cam_t_m2c"]
    T_table_obj = get_scene("multi/08").placements[0].T_table_obj
    T_nominal = invert(info.T_base_cam(0)) @ RigLayout().T_base_table(30.0) @ T_table_obj
    assert np.allclose(T_cam_obj, invert(T_base_cam_true) @ RigLayout().T_base_table(30.0) @ T_table_obj, atol=1e-6)
    assert np.linalg.norm(T_cam_obj[:3, 3] - T_nominal[:3, 3]) > 1.0
    # seeded: the same seed gives the same mount, another seed another one
    assert np.array_equal(hand_eye_offset(2.0, 0.5, 0), hand_eye_offset(2.0, 0.5, 0))
    assert not np.allclose(hand_eye_offset(2.0, 0.5, 0), hand_eye_offset(2.0, 0.5, 1))
    assert np.array_equal(true_hand_eye(DEFAULT_T_TCP_CAM, 0.0, 0.0), DEFAULT_T_TCP_CAM)


# ------------------------------------------------------------------------------- step jitter
def test_step_jitter(tmp_path_factory):
    cfg, out = capture(tmp_path_factory, "jitter", step_jitter_deg=0.05, steps=4)
    nominal = np.arange(4) * 30.0
    actual = truth_table_angles(out)
    err = actual - nominal
    assert np.abs(err).max() <= 0.05 + 1e-9 and np.abs(err).max() > 1e-3 and len(set(np.round(err, 9))) == 4
    s = RawSession.open(out)
    assert [e.angle_deg for e in s.entries if e.phase == "transparent"] == nominal.tolist()
    assert all(e.extra["table_angle_reported_deg"] == e.angle_deg for e in s.entries)
    rig = read_json(out / "truth" / "rig.json")
    assert np.allclose(rig["table_angle_deg"]["transparent"][0], actual, atol=1e-9)
    opaque = np.array(rig["table_angle_deg"]["opaque"][0])
    assert np.abs(opaque - nominal).max() <= 0.05 and not np.allclose(opaque, actual)  # drawn per visit
    r = build_rig(cfg).world.renderer
    assert np.array_equal(s.load_depth("opaque", 0, 2), r.render(0, float(opaque[2]), "opaque").depth)
    # deterministic for the seed: a resumed capture puts the table where it was
    m = TableMotion("ccw", 0.05, cfg.sim.seed)
    assert m.actual("transparent", 0, 60.0) == pytest.approx(actual[2], abs=1e-12)


# ------------------------------------------------------------------------------- config and CLI
LAB_TOML = """
[session]
scene_id = "multi/08"
[turntable]
steps = 3
step_deg = 30.0
direction = "cw"
[camera]
width = 160
height = 120
[sim]
n_arms = 1
clutter = ["cabinet", "wall"]
record_direction = false
hand_eye_error_mm = 2.0
hand_eye_error_deg = 0.5
step_jitter_deg = 0.05
depth_bias = 1.02
twin_offset_mm = 2.0
twin_offset_deg = 1.0
"""


def test_lab_options_from_a_toml_config(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text(LAB_TOML)
    cfg = load_config(p)
    assert cfg.turntable.direction == "cw" and cfg.sim.clutter == ("cabinet", "wall")
    assert not cfg.sim.record_direction and cfg.sim.hand_eye_error_mm == 2.0 and cfg.sim.step_jitter_deg == 0.05
    rig = build_rig(cfg)
    assert cfg.sim.depth_bias == 1.02 and rig.world.renderer.sensor.depth_bias == 1.02
    # each opaque twin 2 mm along the table top and 1 deg about its vertical axis off its object
    for p, T in zip(rig.world.renderer.scene.placements, rig.world.renderer.T_table_twins):
        D = T @ np.linalg.inv(p.T_table_obj)
        assert np.degrees(np.arccos(np.clip(D[0, 0], -1, 1))) == pytest.approx(1.0)
        assert np.allclose(D[2, :3], [0, 0, 1]) and abs(D[2, 3]) < 1e-9   # a move along the top, a turn about z
        V = get_object(p.obj_id).vertices
        c = 0.5 * (V.min(0) + V.max(0))   # the object's centre moves by exactly 2 mm
        assert np.linalg.norm((T[:3, :3] @ c + T[:3, 3]) - (p.T_table_obj[:3, :3] @ c + p.T_table_obj[:3, 3])) == \
            pytest.approx(2.0)
    assert rig.world.table == TableMotion("cw", 0.05, 0) and rig.world.renderer.clutter == ("cabinet", "wall")
    assert np.array_equal(hand_eye(cfg), DEFAULT_T_TCP_CAM)


@pytest.mark.parametrize("edit, needle", [
    (("clutter = [\"cabinet\", \"wall\"]", "clutter = [\"cabinet\", \"sofa\"]"),
     "sim.clutter: unknown preset 'sofa' (known: cabinet, monitor, box, wall, cabinet_near, box_near)"),
    (("direction = \"cw\"", "direction = \"clockwise\""), "turntable.direction: must be one of ccw, cw"),
    (("step_jitter_deg = 0.05", "step_jitter_deg = 20.0"), "sim.step_jitter_deg: must be in [0, step_deg / 2"),
    (("hand_eye_error_deg = 0.5", "hand_eye_error_deg = -1.0"), "sim.hand_eye_error_deg: must be in [0, 10]"),
    (("hand_eye_error_mm = 2.0", "hand_eye_error_mm = 0.2e3"), "sim.hand_eye_error_mm: must be in [0, 50]"),
    (("depth_bias = 1.02", "depth_bias = 102"), "sim.depth_bias: must be in [0.9, 1.1] (reported / true depth"),
    (("twin_offset_mm = 2.0", "twin_offset_mm = 2e3"), "sim.twin_offset_mm: must be in [0, 20] mm"),
    (("twin_offset_deg = 1.0", "twin_offset_deg = -1"), "sim.twin_offset_deg: must be in [0, 20] degrees"),
])
def test_lab_config_mistakes_are_one_line(tmp_path, edit, needle):
    p = tmp_path / "lab.toml"
    p.write_text(LAB_TOML.replace(*edit))
    with pytest.raises(TdofError) as e:
        load_config(p)
    assert needle in str(e.value) and "\n" not in str(e.value) and str(p) in str(e.value)


def test_capture_run_cli_lab_options(tmp_path):
    exe = [sys.executable, "-m", "tdof20.cli", "capture", "run", "--sim", "--steps", "2", "--step-deg", "30",
           "--arm-positions", "1", "--width", "80", "--height", "60", "--yes", "--out"]
    res = subprocess.run(exe + [str(tmp_path / "s"), "--clutter", "cabinet,wall", "--direction", "cw",
                                "--hand-eye-error", "2,0.5", "--step-jitter", "0.05", "--no-record-direction",
                                "--depth-bias", "1.02", "--twin-offset", "2,1"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    d = json.loads((tmp_path / "s" / "session.json").read_text())
    assert "direction" not in d["turntable"]
    assert d["sim"]["lab"] == {"clutter": ["cabinet", "wall"], "hand_eye_error_mm": 2.0, "hand_eye_error_deg": 0.5,
                               "step_jitter_deg": 0.05}
    rig = read_json(tmp_path / "s" / "truth" / "rig.json")
    assert rig["depth_bias"] == 1.02  # in the truth only: session.json does not tell annotation
    assert rig["twin_offset_mm"] == 2.0 and rig["twin_offset_deg"] == 1.0 and len(rig["T_table_twin"]) >= 1
    assert rig["direction"] == "cw" and rig["table_angle_deg"]["transparent"][0][1] < -29.9
    res = subprocess.run(exe + [str(tmp_path / "t"), "--clutter", "cabinet,sofa"], capture_output=True, text=True,
                         timeout=300)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode != 0 and len(lines) == 1 and "Traceback" not in res.stderr
    assert "unknown preset 'sofa' (known: cabinet, monitor, box, wall, cabinet_near, box_near)" in lines[0]
    assert not (tmp_path / "t").exists()
