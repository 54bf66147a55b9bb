"""Raw session, journal, BOP scene and models-info formats, on real files in tmp_path."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tdof20.errors import TdofError
from tdof20.formats import (
    ArmPosition,
    BopSceneWriter,
    JournalEntry,
    RawSession,
    SessionInfo,
    append_journal,
    bbox_from_mask,
    encode_png,
    frame_paths,
    gt_info_from_masks,
    pose_from_bop,
    pose_to_bop,
    read_journal,
    read_models_info,
    read_png,
    read_scene,
    read_session,
    sha256_file,
    write_frame,
    write_json,
    write_models_info,
    write_session,
)
from tdof20.geometry import PinholeCamera, make_T, rotation_matrix

W, H = 32, 24


# ---------------------------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------------------------
def make_info(steps: int = 3) -> SessionInfo:
    cam = PinholeCamera.from_fov(W, H, 60.0, depth_scale=0.5)
    arms = [
        ArmPosition(q=np.array([0.1, -1.2, 1.5, -0.3, 1.57, 0.0]),
                    T_base_tcp=make_T(rotation_matrix([0, 1, 0], 2.5), [420.0, 15.0, 610.0])),
        ArmPosition(q=np.array([0.2, -1.0, 1.4, -0.5, 1.57, 0.1]),
                    T_base_tcp=make_T(rotation_matrix([1, 1, 0], 2.8), [380.0, -40.0, 540.0])),
    ]
    return SessionInfo(
        scene_id="multi/08",
        objects=[{"obj_id": 3, "name": "cube_216"}, {"obj_id": 11, "slot": 2}],
        camera=cam,
        arm_positions=arms,
        T_tcp_cam=make_T(rotation_matrix([0, 0, 1], 0.05), [0.0, 60.0, 45.0]),
        turntable={"step_deg": 0.9, "steps": steps, "port": "/dev/ttyUSB0"},
        phases=("transparent", "opaque"),
        extra={"operator": "sim", "rig": {"arm": "UR5"}, "camera": {"serial": "OAK-1944"},
               "hand_eye": {"method": "tsai", "residual_mm": 0.4}},
    )


def frame_images(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.integers(0, 4000, (H, W), dtype=np.uint16)
    depth[:3, :3] = 0
    return rgb, depth


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def session_dir(tmp_path: Path) -> Path:
    d = tmp_path / "sess"
    info = make_info()
    write_session(d, info)
    for i, (phase, arm, step) in enumerate([("transparent", 0, 0), ("transparent", 0, 1), ("opaque", 1, 2)]):
        rgb, depth = frame_images(i)
        write_frame(d, info, phase, arm, step, rgb, depth, t=1000.0 + i, extra={"exposure_us": 800})
    return d


def session_dict() -> dict:
    return json.loads(json.dumps(make_info().to_dict()))


def write_raw(d: Path, content) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    p = d / "session.json"
    p.write_text(content if isinstance(content, str) else json.dumps(content))
    return p


# ---------------------------------------------------------------------------------------------
# session.json
# ---------------------------------------------------------------------------------------------
def test_session_round_trip_keeps_extra_keys(tmp_path):
    info = make_info()
    write_session(tmp_path, info)
    back = read_session(tmp_path)
    assert back == info
    assert back.to_dict() == info.to_dict()
    d = json.loads((tmp_path / "session.json").read_text())
    assert d["format"] == "tdof20-raw-session" and d["version"] == 1
    assert d["operator"] == "sim" and d["rig"] == {"arm": "UR5"}
    assert d["camera"]["serial"] == "OAK-1944" and d["camera"]["depth_scale"] == 0.5
    assert d["hand_eye"]["method"] == "tsai" and len(d["hand_eye"]["T_tcp_cam"]) == 16
    assert d["turntable"]["port"] == "/dev/ttyUSB0"
    assert d["objects"][0]["name"] == "cube_216"
    # the file path works as well as the folder, and write -> read -> write is byte-identical
    assert read_session(tmp_path / "session.json") == info
    before = (tmp_path / "session.json").read_bytes()
    write_session(tmp_path, back)
    assert (tmp_path / "session.json").read_bytes() == before


def test_session_unknown_nested_keys_survive(tmp_path):
    d = session_dict()
    d["arm_positions"][1]["label"] = "left-high"
    d["future_field"] = {"a": [1, 2]}
    write_raw(tmp_path, d)
    info = read_session(tmp_path)
    out = info.to_dict()
    assert out["arm_positions"][1]["label"] == "left-high"
    assert out["future_field"] == {"a": [1, 2]}
    assert out == d


def test_session_to_dict_is_json_native(tmp_path):
    info = make_info()
    info.extra["sim"] = {"size": (3, 4), "seed": np.int64(7), "table": np.array([1.0, 2.0])}
    d = info.to_dict()
    assert d["sim"] == {"size": [3, 4], "seed": 7, "table": [1.0, 2.0]}
    write_session(tmp_path, info)
    assert read_session(tmp_path) == info  # equal to its read-back, tuples and numpy included


def test_session_properties():
    info = make_info(steps=400)
    assert info.steps == 400 and info.step_deg == 0.9 and info.n_arms == 2
    assert info.angle_deg(10) == pytest.approx(9.0)
    assert info.obj_ids == [3, 11]
    np.testing.assert_allclose(info.T_base_cam(1), info.arm_positions[1].T_base_tcp @ info.T_tcp_cam)
    assert frame_paths("opaque", 3, 7) == ("opaque/arm3/rgb/000007.png", "opaque/arm3/depth/000007.png")
    assert info.frame_paths("transparent", 1, 399)[1] == "transparent/arm1/depth/000399.png"
    with pytest.raises(ValueError):
        info.frame_paths("transparent", 2, 0)
    assert len(info.planned_frames()) == 2 * 2 * 400


def _set(d, path, value):
    *head, last = path
    for k in head:
        d = d[k]
    if value is _DEL:
        del d[last]
    else:
        d[last] = value


_DEL = object()
_T_ok = make_T(rotation_matrix([0, 1, 0], 2.5), [420.0, 15.0, 610.0])
_T_scaled = _T_ok.copy()
_T_scaled[:3, :3] *= 1.01
_T_metres = _T_ok.copy()
_T_metres[:3, 3] /= 1000.0
_T_lastrow = _T_ok.copy()
_T_lastrow[3, 0] = 0.5
_T_reflect = _T_ok.copy()
_T_reflect[:3, 0] *= -1
_HE_metres = make_T(rotation_matrix([0, 0, 1], 0.05), [0.0, 0.06, 0.045])  # the bracket in metres


@pytest.mark.parametrize("path,value,expect", [
    (("turntable", "steps"), _DEL, "missing field 'turntable.steps'"),
    (("camera",), _DEL, "missing field 'camera'"),
    (("hand_eye", "T_tcp_cam"), _DEL, "missing field 'hand_eye.T_tcp_cam'"),
    (("arm_positions", 0, "q"), _DEL, "missing field 'arm_positions[0].q'"),
    (("camera", "K"), [500.0, 0, 16, 0, 500, 12, 0, 0], "camera.K must be 9 numbers, got 8"),
    (("camera", "K"), [0.9, 0, 0.5, 0, 0.9, 0.5, 0, 0, 1], "camera.K"),
    (("camera", "K"), [500.0, 0, 16, 0, 500, 12, 0, 0, "1"], "camera.K[8] must be a number"),
    (("camera", "width"), 32.5, "camera.width must be an integer"),
    (("camera", "depth_scale"), 0, "camera.depth_scale must be > 0"),
    (("arm_positions", 1, "q"), [0.1, 0.2, 0.3, 0.4, 0.5], "arm_positions[1].q must be 6 joint angles (rad), got 5"),
    (("arm_positions", 0, "q"), [0, -90, 90, 0, 90, 0], "looks like degrees"),
    (("arm_positions", 0, "T_base_tcp"), list(_T_scaled.reshape(-1)), "arm_positions[0].T_base_tcp is not a rigid transform"),
    (("arm_positions", 0, "T_base_tcp"), list(_T_lastrow.reshape(-1)), "last row must be 0 0 0 1"),
    (("arm_positions", 0, "T_base_tcp"), list(_T_reflect.reshape(-1)), "reflection"),
    (("arm_positions", 0, "T_base_tcp"), list(_T_ok.reshape(-1))[:12], "must be 16 numbers"),
    (("arm_positions", 1, "T_base_tcp"), list(_T_metres.reshape(-1)), "looks like metres, millimetres expected"),
    (("hand_eye", "T_tcp_cam"), list(_T_scaled.reshape(-1)), "hand_eye.T_tcp_cam is not a rigid transform"),
    (("hand_eye", "T_tcp_cam"), list(_HE_metres.reshape(-1)),
     "hand_eye.T_tcp_cam translation has length 0.075: looks like metres, millimetres expected"),
    (("arm_positions",), [], "arm_positions must be a non-empty list"),
    (("scene_id",), "multi/21", "scene_id must look like"),
    (("scene_id",), "multi/20", "(NN in 00..19)"),  # the release numbers its multi scenes 00..19
    (("scene_id",), "single/21", "scene_id must look like"),
    (("scene_id",), "multi/8", "scene_id must look like"),
    (("scene_id",), "scene/01", "scene_id must look like"),
    (("scene_id",), 8, "scene_id must be a string"),
    (("objects", 0, "obj_id"), 21, "objects[0].obj_id must be 1..20, got 21"),
    (("objects", 1, "obj_id"), "3", "objects[1].obj_id must be an integer"),
    (("objects",), [], "objects must be a non-empty list"),
    (("turntable", "steps"), 0, "turntable.steps must be 1..36000"),
    (("turntable", "steps"), 10**30, "turntable.steps must be 1..36000"),
    (("turntable", "step_deg"), -0.9, "turntable.step_deg must be > 0"),
    (("turntable", "direction"), "clockwise", "turntable.direction must be one of ccw, cw"),
    (("phases",), ["transparent", "glass"], "phases[1] must be one of"),
    (("format",), "bop", "is not a tdof20 raw session"),
    (("version",), 2, "version 2 is newer"),
])
def test_session_validation(tmp_path, path, value, expect):
    d = session_dict()
    _set(d, path, value)
    p = write_raw(tmp_path, d)
    before = p.read_bytes()
    with pytest.raises(TdofError) as ei:
        read_session(tmp_path)
    msg = str(ei.value)
    assert "session.json" in msg and expect in msg, msg
    assert "\n" not in msg
    assert p.read_bytes() == before


def test_hand_eye_in_mm_and_zero_translation_pass(tmp_path):
    for t in ([0.0, 0.0, 0.0], [0.0, 6.0, 4.5], [1.0, 0.0, 0.0]):
        d = session_dict()
        d["hand_eye"]["T_tcp_cam"] = list(make_T(np.eye(3), t).reshape(-1))
        write_raw(tmp_path, d)
        np.testing.assert_allclose(read_session(tmp_path).T_tcp_cam[:3, 3], t)


def test_single_scene_holds_one_object(tmp_path):
    d = session_dict()
    d["scene_id"] = "single/20"
    write_raw(tmp_path, d)
    with pytest.raises(TdofError, match="single-object scene"):
        read_session(tmp_path)
    d["objects"] = d["objects"][:1]
    write_raw(tmp_path, d)
    assert read_session(tmp_path).scene_id == "single/20"
    for name in ("single/whisky_cup_270", "multi/00", "multi/19"):  # the names, and the release's multi numbers
        d["scene_id"] = name
        write_raw(tmp_path, d if name.startswith("single") else d | {"objects": session_dict()["objects"]})
        assert read_session(tmp_path).scene_id == name


@pytest.mark.parametrize("text,expect", [
    ("this is not json", "malformed JSON"),
    (None, "malformed JSON"),  # truncated
    ("[1, 2, 3]", "must hold a JSON object"),
    ("", "malformed JSON"),
])
def test_session_not_json(tmp_path, text, expect):
    if text is None:
        full = json.dumps(session_dict(), indent=2)
        text = full[: len(full) // 2]
    write_raw(tmp_path, text)
    with pytest.raises(TdofError) as ei:
        read_session(tmp_path)
    assert "session.json" in str(ei.value) and expect in str(ei.value)


def test_session_missing(tmp_path):
    with pytest.raises(TdofError, match="no such session folder"):
        read_session(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TdofError, match=r"session\.json: file not found"):
        RawSession.open(tmp_path / "empty")


def test_write_session_refuses_invalid(tmp_path):
    info = make_info()
    info.scene_id = "multi/99"
    with pytest.raises(TdofError, match="scene_id"):
        write_session(tmp_path, info)
    assert not (tmp_path / "session.json").exists()


# ---------------------------------------------------------------------------------------------
# frames and RawSession
# ---------------------------------------------------------------------------------------------
def test_write_frame_and_load(session_dir):
    s = RawSession.open(session_dir)
    assert s.frames() == [("transparent", 0, 0), ("transparent", 0, 1), ("opaque", 1, 2)]
    assert s.frames("opaque") == [("opaque", 1, 2)]
    assert s.has_frame("transparent", 0, 1) and not s.has_frame("transparent", 1, 1)
    rgb, depth = frame_images(1)
    np.testing.assert_array_equal(s.load_rgb("transparent", 0, 1), rgb)
    d = s.load_depth("transparent", 0, 1, verify=True)
    assert d.dtype == np.uint16
    np.testing.assert_array_equal(d, depth)
    np.testing.assert_allclose(s.load_depth_mm("transparent", 0, 1), depth * 0.5)
    assert len(s.missing_frames()) == 2 * 2 * 3 - 3
    assert ("opaque", 1, 2) not in s.missing_frames()
    assert s.missing_frames()[0] == ("transparent", 0, 2)
    assert s.truth_dir is None
    (session_dir / "truth").mkdir()
    assert RawSession.open(session_dir).truth_dir == session_dir / "truth"
    e = s.entry("opaque", 1, 2)
    assert e.extra == {"exposure_us": 800} and e.angle_deg == pytest.approx(1.8) and e.t == 1002.0


def test_write_frame_checksums(session_dir):
    for e in read_journal(session_dir):
        assert sha256_file(session_dir / e.rgb) == e.sha256["rgb"]
        assert sha256_file(session_dir / e.depth) == e.sha256["depth"]
        assert (e.rgb, e.depth) == frame_paths(e.phase, e.arm, e.step)
    assert RawSession.open(session_dir).verify_all() == []


def test_write_frame_rejects_wrong_shapes(tmp_path):
    info = make_info()
    write_session(tmp_path, info)
    rgb, depth = frame_images(0)
    with pytest.raises(TdofError, match="session camera needs"):
        write_frame(tmp_path, info, "transparent", 0, 0, rgb[:-1], depth)
    with pytest.raises(TdofError, match="uint16"):
        write_frame(tmp_path, info, "transparent", 0, 0, rgb, depth.astype(np.float32))
    assert read_journal(tmp_path) == []


def test_missing_frame_not_in_journal(session_dir):
    s = RawSession.open(session_dir)
    with pytest.raises(TdofError) as ei:
        s.load_rgb("opaque", 0, 1)
    msg = str(ei.value)
    assert "opaque/arm0/rgb/000001.png" in msg and "missing frame" in msg and "journal" in msg


def test_missing_frame_file_deleted(session_dir):
    (session_dir / "transparent/arm0/depth/000001.png").unlink()
    s = RawSession.open(session_dir)
    with pytest.raises(TdofError) as ei:
        s.load_depth("transparent", 0, 1)
    msg = str(ei.value)
    assert "transparent/arm0/depth/000001.png" in msg and "missing frame" in msg
    problems = s.verify_file(s.entry("transparent", 0, 1))
    assert len(problems) == 1 and "missing file" in problems[0]


@pytest.mark.parametrize("how", ["random", "truncated", "not_png"])
def test_corrupt_png(session_dir, how):
    p = session_dir / "transparent/arm0/rgb/000000.png"
    data = p.read_bytes()
    if how == "random":
        bad = b"\x89PNG\r\n\x1a\n" + np.random.default_rng(5).bytes(400)
    elif how == "truncated":
        bad = data[: len(data) // 2]
    else:
        bad = b"GIF89a" + data[6:]
    p.write_bytes(bad)
    s = RawSession.open(session_dir)
    with pytest.raises(TdofError) as ei:
        s.load_rgb("transparent", 0, 0)
    msg = str(ei.value)
    assert str(p) in msg and ("corrupt PNG" in msg or "not a PNG" in msg)
    problems = s.verify_file(s.entry("transparent", 0, 0))
    assert any("checksum mismatch" in x for x in problems)
    assert any("PNG" in x and str(p) in x for x in problems)


def test_verify_detects_tampered_file(session_dir):
    s = RawSession.open(session_dir)
    e = s.entry("opaque", 1, 2)
    assert s.verify_file(e) == []
    rgb, _ = frame_images(99)
    (session_dir / e.rgb).write_bytes(encode_png(rgb))  # a valid PNG, but not the one captured
    problems = s.verify_file(e)
    assert len(problems) == 1 and "checksum mismatch" in problems[0] and e.rgb in problems[0]
    with pytest.raises(TdofError, match="checksum mismatch"):
        s.load_rgb("opaque", 1, 2, verify=True)
    # a wrong-size image
    small = np.zeros((H // 2, W // 2), np.uint16)
    (session_dir / e.depth).write_bytes(encode_png(small))
    size = "depth image is 16x12 pixels but session.json's camera is 32x24"
    assert any(size in x for x in s.verify_file(e))
    with pytest.raises(TdofError, match=size):
        s.load_depth("opaque", 1, 2)


def test_reading_modifies_nothing(session_dir):
    jp = session_dir / "journal.jsonl"
    with open(jp, "ab") as f:
        f.write(b'{"phase": "opaque", "arm": 1, "st')  # a crash mid-append
    (session_dir / "transparent/arm0/rgb/000001.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
    before = snapshot(session_dir)
    listing = sorted(str(p) for p in session_dir.rglob("*"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = RawSession.open(session_dir)
        read_session(session_dir)
        read_journal(session_dir)
        s.load_rgb("transparent", 0, 0, verify=True)
        s.load_depth_mm("opaque", 1, 2)
        s.verify_all()
        s.missing_frames()
        with pytest.raises(TdofError):
            s.load_rgb("transparent", 0, 1)
        with pytest.raises(TdofError):
            s.load_rgb("opaque", 0, 0)
    assert snapshot(session_dir) == before
    assert sorted(str(p) for p in session_dir.rglob("*")) == listing


def test_journal_entry_outside_plan(session_dir):
    e = read_journal(session_dir)[0]
    e.arm = 5
    append_journal(session_dir, e)
    with pytest.raises(TdofError, match=r"journal\.jsonl: line 4: frame transparent arm 5 step 0 is outside the plan"):
        RawSession.open(session_dir)


def test_rewritten_frame_last_line_wins(session_dir):
    info = read_session(session_dir)
    rgb, depth = frame_images(42)
    write_frame(session_dir, info, "transparent", 0, 1, rgb, depth)
    s = RawSession.open(session_dir)
    assert len(s.entries) == 4 and len(s) == 3
    np.testing.assert_array_equal(s.load_rgb("transparent", 0, 1, verify=True), rgb)
    assert s.verify_all() == []


# ---------------------------------------------------------------------------------------------
# journal
# ---------------------------------------------------------------------------------------------
def _entry(step: int, **kw) -> JournalEntry:
    rgb, depth = frame_paths("transparent", 0, step)
    return JournalEntry(phase="transparent", arm=0, step=step, angle_deg=0.9 * step, rgb=rgb, depth=depth,
                        sha256={"rgb": "a" * 64, "depth": "b" * 64}, t=1700000000.5 + step, extra=kw)


def test_journal_round_trip(tmp_path):
    assert read_journal(tmp_path) == []
    entries = [_entry(0), _entry(1, gain=2.5, note="x"), _entry(2)]
    for e in entries:
        append_journal(tmp_path, e)
    back = read_journal(tmp_path)
    assert back == entries
    assert back[1].extra == {"gain": 2.5, "note": "x"}
    assert [b.line for b in back] == [1, 2, 3]
    lines = (tmp_path / "journal.jsonl").read_text().splitlines()
    assert len(lines) == 3 and json.loads(lines[1])["gain"] == 2.5
    assert JournalEntry.from_dict(entries[1].to_dict()) == entries[1]


def test_journal_truncated_last_line_ignored(tmp_path, capsys):
    for i in range(2):
        append_journal(tmp_path, _entry(i))
    jp = tmp_path / "journal.jsonl"
    full = json.dumps(_entry(2).to_dict())
    with open(jp, "ab") as f:
        f.write(full[:25].encode())
    before = jp.read_bytes()
    back = read_journal(tmp_path)
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and "journal.jsonl: line 3 is incomplete" in said
    assert [e.step for e in back] == [0, 1]
    assert jp.read_bytes() == before
    # the next append cuts the broken tail off, so the new line stands on its own (already said)
    append_journal(tmp_path, _entry(5))
    assert [e.step for e in read_journal(tmp_path)] == [0, 1, 5]
    assert capsys.readouterr().err == ""


_GOOD = json.dumps(_entry(1).to_dict())


@pytest.mark.parametrize("tail", [
    _GOOD[:30].encode(),                        # torn, no newline (a crash mid-write)
    _GOOD[:30].encode() + b"\n",                # torn, newline-terminated (issue 11, F3)
    _GOOD[:30].encode() + b"\n\n  \n",          # torn, then blank lines
    b"\x00" * 40 + b"\n",                        # a block of zeros a power cut can leave
    _GOOD[:30].encode() + b"\xff\xfe",           # torn inside a multi-byte character
    _GOOD.encode(),                             # complete, newline missing: kept
    _GOOD.encode() + b"\n\n",                    # complete, blank lines after: kept
    b"",                                        # nothing after the good lines
])
def test_journal_reader_and_appender_agree_on_the_last_line(tmp_path, tail):
    """One rule: what read_journal leaves out is exactly what append_journal cuts off."""
    append_journal(tmp_path, _entry(0))
    with open(tmp_path / "journal.jsonl", "ab") as f:
        f.write(tail)
    before = read_journal(tmp_path)
    append_journal(tmp_path, _entry(2))
    after = read_journal(tmp_path)
    assert after == before + [_entry(2)]
    assert [e.line for e in after][-1] == len((tmp_path / "journal.jsonl").read_bytes().rstrip().split(b"\n"))
    assert all(json.loads(ln) for ln in (tmp_path / "journal.jsonl").read_text().split("\n") if ln.strip())


def test_journal_valid_json_last_line_is_no_tear(tmp_path):
    """A last line that is JSON but no entry is an edit, not an interrupted write: an error, before
    and after an append (neither side drops it)."""
    append_journal(tmp_path, _entry(0))
    with open(tmp_path / "journal.jsonl", "ab") as f:
        f.write(b"[1, 2, 3]\n")
    for _ in range(2):
        with pytest.raises(TdofError, match=r"journal\.jsonl: line 2: a journal entry must be a JSON object"):
            read_journal(tmp_path)
        append_journal(tmp_path, _entry(1))


def test_journal_last_line_missing_newline_is_kept(tmp_path):
    append_journal(tmp_path, _entry(0))
    jp = tmp_path / "journal.jsonl"
    with open(jp, "ab") as f:
        f.write(json.dumps(_entry(1).to_dict()).encode())  # complete, no newline
    append_journal(tmp_path, _entry(2))
    assert [e.step for e in read_journal(tmp_path)] == [0, 1, 2]


def test_journal_malformed_middle_line(tmp_path):
    append_journal(tmp_path, _entry(0))
    jp = tmp_path / "journal.jsonl"
    with open(jp, "ab") as f:
        f.write(b"{not json}\n" + json.dumps(_entry(1).to_dict()).encode() + b"\n")  # garbage, then a line
    append_journal(tmp_path, _entry(2))  # only a torn LAST line is cut: this one stays
    assert jp.read_text().splitlines()[1] == "{not json}"
    with pytest.raises(TdofError) as ei:
        read_journal(tmp_path)
    msg = str(ei.value)
    assert "journal.jsonl" in msg and "line 2" in msg and "not valid JSON" in msg


def test_journal_invalid_entry_names_line(tmp_path):
    append_journal(tmp_path, _entry(0))
    d = _entry(1).to_dict()
    del d["sha256"]
    with open(tmp_path / "journal.jsonl", "a") as f:
        f.write(json.dumps(d) + "\n")
    with pytest.raises(TdofError, match=r"journal\.jsonl: line 2: missing field 'sha256'"):
        read_journal(tmp_path)
    d = _entry(1).to_dict()
    d["rgb"] = "../../etc/passwd"
    (tmp_path / "journal.jsonl").write_text(json.dumps(d) + "\n" + json.dumps(_entry(2).to_dict()) + "\n")
    with pytest.raises(TdofError, match="line 1: rgb must be a relative POSIX path"):
        read_journal(tmp_path)


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
def test_atomic_write_keeps_old_file(tmp_path, monkeypatch):
    info = make_info()
    write_session(tmp_path, info)
    p = tmp_path / "session.json"
    before = p.read_bytes()

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    info2 = make_info()
    info2.extra["operator"] = "someone else"
    with pytest.raises(OSError, match="disk full"):
        write_session(tmp_path, info2)
    with pytest.raises(OSError):
        write_json(p, {"x": 1})
    monkeypatch.undo()
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["session.json"]
    # an object that cannot be encoded fails before the file is touched
    with pytest.raises(TypeError):
        write_json(p, {"x": object()})
    assert p.read_bytes() == before
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


def test_atomic_png_write_failure(tmp_path, monkeypatch):
    info = make_info()
    write_session(tmp_path, info)
    rgb, depth = frame_images(0)
    write_frame(tmp_path, info, "transparent", 0, 0, rgb, depth)
    before = snapshot(tmp_path)
    monkeypatch.setattr(os, "replace", lambda a, b: (_ for _ in ()).throw(OSError("io error")))
    rgb2, depth2 = frame_images(1)
    with pytest.raises(OSError):
        write_frame(tmp_path, info, "transparent", 0, 0, rgb2, depth2)
    monkeypatch.undo()
    assert snapshot(tmp_path) == before  # no new journal line, no temp files, old images intact


# ---------------------------------------------------------------------------------------------
# BOP
# ---------------------------------------------------------------------------------------------
def _rect(y0, y1, x0, x1):
    m = np.zeros((H, W), bool)
    m[y0:y1 + 1, x0:x1 + 1] = True
    return m


def tiny_scene():
    """Two overlapping rectangles: B (rows 8..17, cols 10..21) in front of A (rows 4..11, cols 5..14)."""
    a = _rect(4, 11, 5, 14)
    b = _rect(8, 17, 10, 21)
    a_vis = a & ~b
    depth = np.full((H, W), 800, np.uint16)
    depth[4:6, 5:15] = 0  # no depth on the top two rows of A (transparent glass)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[a] = (200, 50, 50)
    rgb[b] = (50, 200, 50)
    poses = [(3, rotation_matrix([0, 0, 1], 0.3), np.array([10.0, -5.0, 600.0])),
             (11, rotation_matrix([1, 0, 0], 1.1), np.array([-20.0, 15.5, 550.25]))]
    return a, b, a_vis, depth, rgb, poses


def test_gt_info_from_masks():
    a, b, a_vis, depth, _, _ = tiny_scene()
    info = gt_info_from_masks(a, a_vis, depth)
    assert info["px_count_all"] == 8 * 10
    assert info["px_count_visib"] == 80 - 4 * 5  # rows 8..11, cols 10..14 hidden by B
    assert info["px_count_valid"] == 80 - 2 * 10  # silhouette pixels with depth > 0
    assert info["visib_fract"] == pytest.approx(60 / 80)
    assert info["bbox_obj"] == [5, 4, 9, 7]  # BOP: w = x_max - x_min, h = y_max - y_min
    assert info["bbox_visib"] == [5, 4, 9, 7]
    empty = np.zeros((H, W), bool)
    e = gt_info_from_masks(a, empty, None)
    assert e["bbox_visib"] == [-1, -1, -1, -1] and e["visib_fract"] == 0.0 and e["px_count_valid"] == 0
    z = gt_info_from_masks(empty, empty, depth)
    assert z["bbox_obj"] == [-1, -1, -1, -1] and z["visib_fract"] == 0.0 and z["px_count_all"] == 0
    with pytest.raises(ValueError, match="outside"):
        gt_info_from_masks(a_vis, a, depth)  # swapped masks
    stray = a_vis.copy()
    stray[20, 30] = True  # one edge pixel a renderer saw as visible but not in the silhouette
    assert gt_info_from_masks(a, stray, depth) == info
    assert bbox_from_mask(_rect(3, 3, 7, 7)) == [7, 3, 0, 0]  # one pixel: w = h = 0, as BOP


def test_bop_round_trip(tmp_path):
    a, b, a_vis, depth, rgb, poses = tiny_scene()
    K = PinholeCamera.from_fov(W, H, 60.0).K
    T_w2c = make_T(rotation_matrix([0, 1, 0], 0.4), [5.0, 0.0, 700.0])
    labels = np.zeros((H, W), np.uint8)
    labels[a_vis] = 1
    labels[b] = 2
    with BopSceneWriter(tmp_path / "000008") as w:
        infos = w.add_frame(0, K, 0.5, poses, [a, b], [a_vis, b], rgb=rgb, depth=depth, T_w2c=T_w2c,
                            extra={"labels": labels})
        w.add_frame(7, K, 0.5, poses[:1], [a], [a], depth=depth)
    assert infos[1]["px_count_visib"] == 10 * 12
    sc = read_scene(tmp_path / "000008")
    assert sc.im_ids() == [0, 7]
    np.testing.assert_allclose(sc.K(0), K)
    assert sc.depth_scale(7) == 0.5
    np.testing.assert_allclose(sc.camera[0]["cam_R_w2c"], T_w2c[:3, :3])
    np.testing.assert_allclose(sc.camera[0]["cam_t_w2c"], T_w2c[:3, 3])
    assert "cam_R_w2c" not in sc.camera[7]
    for gt_id, (obj_id, R, t) in enumerate(poses):
        assert sc.gt[0][gt_id]["obj_id"] == obj_id
        R2, t2 = sc.pose(0, gt_id)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)
    np.testing.assert_array_equal(sc.mask(0, 0), a)
    np.testing.assert_array_equal(sc.mask(0, 0, visib=True), a_vis)
    np.testing.assert_array_equal(sc.mask(0, 1, visib=True), b)
    np.testing.assert_array_equal(sc.rgb(0), rgb)
    np.testing.assert_array_equal(sc.depth(0), depth)
    np.testing.assert_allclose(sc.depth_mm(0), depth * 0.5)
    np.testing.assert_array_equal(sc.image("labels", 0), labels)
    gi = sc.gt_info[0]
    assert gi[0] == gt_info_from_masks(a, a_vis, depth)
    assert gi[0]["bbox_obj"] == [5, 4, 9, 7] and gi[0]["px_count_valid"] == 60
    assert gi[1]["bbox_obj"] == [10, 8, 11, 9] and gi[1]["visib_fract"] == 1.0
    # raw files are BOP-shaped
    gt_raw = json.loads((tmp_path / "000008/scene_gt.json").read_text())
    assert set(gt_raw) == {"0", "7"} and len(gt_raw["0"][0]["cam_R_m2c"]) == 9
    cam_raw = json.loads((tmp_path / "000008/scene_camera.json").read_text())
    assert len(cam_raw["0"]["cam_K"]) == 9 and cam_raw["0"]["depth_scale"] == 0.5
    m = read_png(tmp_path / "000008/mask_visib/000000_000001.png", kind="mask")
    assert m.dtype == np.uint8 and set(np.unique(m).tolist()) == {0, 255}


def test_bop_flush_merges(tmp_path):
    a, b, a_vis, depth, rgb, poses = tiny_scene()
    K = PinholeCamera.from_fov(W, H, 60.0).K
    d = tmp_path / "scene"
    with BopSceneWriter(d) as w:
        for im in (0, 1):
            w.add_frame(im, K, 1.0, poses, [a, b], [a_vis, b])
    with BopSceneWriter(d) as w:  # a resumed writer
        w.add_frame(2, K, 1.0, poses, [a, b], [a_vis, b])
        w.add_frame(1, K, 1.0, poses[1:], [b], [b])  # re-written with fewer instances
    sc = read_scene(d)
    assert sc.im_ids() == [0, 1, 2]
    assert len(sc.gt[0]) == 2 and len(sc.gt[1]) == 1 and sc.gt[1][0]["obj_id"] == 11
    assert len(sc.gt_info[1]) == 1
    assert not (d / "mask/000001_000001.png").exists()  # stale mask of the old frame 1 removed
    np.testing.assert_array_equal(sc.mask(1, 0), b)


def test_bop_read_errors(tmp_path):
    with pytest.raises(TdofError, match="no such scene folder"):
        read_scene(tmp_path / "nope")
    a, b, a_vis, depth, rgb, poses = tiny_scene()
    K = PinholeCamera.from_fov(W, H, 60.0).K
    d = tmp_path / "scene"
    with BopSceneWriter(d) as w:
        w.add_frame(0, K, 1.0, poses, [a, b], [a_vis, b])
    (d / "scene_gt.json").rename(d / "gt.bak")
    with pytest.raises(TdofError, match=r"scene_gt\.json: file not found"):
        read_scene(d)
    assert read_scene(d, require_gt=False).gt == {}
    raw = json.loads((d / "gt.bak").read_text())
    raw["0"][1]["cam_t_m2c"] = [1.0, 2.0]
    (d / "scene_gt.json").write_text(json.dumps(raw))
    with pytest.raises(TdofError, match=r"scene_gt\.json: image 0 instance 1: cam_t_m2c must be 3 numbers, got 2"):
        read_scene(d)
    raw["0"][1]["cam_t_m2c"] = [1.0, 2.0, 3.0]
    raw["0"][0]["cam_R_m2c"] = [1.0] * 9
    (d / "scene_gt.json").write_text(json.dumps(raw))
    with pytest.raises(TdofError, match="not a rotation matrix"):
        read_scene(d)
    (d / "scene_gt.json").write_text(json.dumps(json.loads((d / "gt.bak").read_text())))
    (d / "scene_camera.json").write_text('{"0": {"cam_K": [1, 2, 3')
    with pytest.raises(TdofError, match=r"scene_camera\.json: malformed JSON"):
        read_scene(d)
    (d / "scene_camera.json").write_text('{"zero": {}}')
    with pytest.raises(TdofError, match="not an integer id"):
        read_scene(d)
    (d / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": list(K.reshape(-1)), "depth_scale": 1.0}}))
    sc = read_scene(d)
    (d / "mask/000000_000001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(50))
    with pytest.raises(TdofError, match=r"mask/000000_000001\.png: corrupt PNG"):
        sc.mask(0, 1)
    with pytest.raises(TdofError, match=r"rgb/000000\.png: file not found"):
        sc.rgb(0)
    with pytest.raises(TdofError, match="no ground-truth instance 5"):
        sc.pose(0, 5)


def test_pose_helpers():
    R = rotation_matrix([1, 2, 3], 0.7)
    t = np.array([1.5, -2.0, 700.0])
    d = pose_to_bop(R, t, obj_id=4)
    assert list(d) == ["obj_id", "cam_R_m2c", "cam_t_m2c"]
    assert len(d["cam_R_m2c"]) == 9 and all(isinstance(x, float) for x in d["cam_R_m2c"] + d["cam_t_m2c"])
    assert d["cam_R_m2c"][1] == R[0, 1]  # row-major
    R2, t2 = pose_from_bop(d)
    np.testing.assert_array_equal(R2, R)
    np.testing.assert_array_equal(t2, t)


def test_models_info(tmp_path):
    infos = {
        3: {"diameter": 120.5, "min_x": -30.0, "min_y": -30.0, "min_z": -50.0, "size_x": 60.0, "size_y": 60.0,
            "size_z": 100.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
        11: {"diameter": np.float64(88.0),
             "symmetries_discrete": [make_T(rotation_matrix([0, 0, 1], np.pi), [0, 0, 0]).reshape(-1)]},
    }
    p = write_models_info(tmp_path, infos)
    assert p.name == "models_info.json"
    back = read_models_info(tmp_path)
    assert set(back) == {3, 11}
    assert back[3]["diameter"] == 120.5 and back[3]["symmetries_continuous"][0]["axis"] == [0, 0, 1]
    assert back[11]["diameter"] == 88.0 and len(back[11]["symmetries_discrete"][0]) == 16
    assert read_models_info(p) == back
    raw = json.loads(p.read_text())
    raw["11"]["diameter"] = 0
    p.write_text(json.dumps(raw))
    with pytest.raises(TdofError, match=r"models_info\.json: object 11: diameter must be a number > 0"):
        read_models_info(tmp_path)
    with pytest.raises(TdofError, match="diameter"):
        write_models_info(tmp_path / "x", {1: {"size_x": 3.0}})
    assert not (tmp_path / "x" / "models_info.json").exists()


def test_atomic_writes_get_ordinary_permissions(tmp_path):
    import os
    from tdof20.formats.io import write_json
    p = tmp_path / "a.json"
    write_json(p, {"a": 1})
    mask = os.umask(0)
    os.umask(mask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~mask)


def test_model_mesh_round_trip_and_bad_models(tmp_path):
    from tdof20.formats import model_path, read_model_mesh, write_model_mesh
    from tdof20.objects import get_object

    tm = get_object(5).to_trimesh()
    p = write_model_mesh(model_path(tmp_path, 5), tm.vertices, tm.faces)
    assert p.name == "obj_000005.ply"
    V, F = read_model_mesh(p)
    assert np.allclose(V, tm.vertices, atol=1e-4) and np.array_equal(F, tm.faces)
    with pytest.raises(TdofError, match="not found") as e:
        read_model_mesh(tmp_path / "obj_000006.ply")
    assert "obj_000006.ply" in str(e.value)
    bad = tmp_path / "obj_000007.ply"
    bad.write_bytes(p.read_bytes()[:300])
    with pytest.raises(TdofError, match="obj_000007.ply"):
        read_model_mesh(bad)
    cloud = tmp_path / "obj_000008.ply"
    trimesh.PointCloud(tm.vertices).export(cloud)
    with pytest.raises(TdofError, match="no faces"):
        read_model_mesh(cloud)
    assert read_model_mesh(cloud, need_faces=False)[1].shape == (0, 3)


def test_a_full_disk_names_the_file_and_leaves_the_old_one(tmp_path, monkeypatch):
    """A write that fails inside the open temporary file (ENOSPC) is an OSError naming the target
    (the CLI's and capture's one line say which file), no temporary file is left, and the file
    already there keeps its bytes."""
    import errno

    from tdof20.formats.io import atomic_write_bytes

    target = tmp_path / "scene_gt.json"
    target.write_bytes(b"old")
    real = os.fdopen

    class Full:
        def __init__(self, fd):
            self.f = real(fd, "wb")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fdopen", lambda fd, mode: Full(fd))
    with pytest.raises(OSError) as e:
        atomic_write_bytes(target, b"new")
    assert e.value.filename == str(target) and e.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene_gt.json"] and target.read_bytes() == b"old"


def test_a_corrupt_png_prints_nothing_of_opencv(capfd):
    """OpenCV's own '[ERROR:0@...] grfmt_png.cpp' line would precede the CLI's one-line error."""
    from tdof20.formats.io import decode_png

    with pytest.raises(TdofError, match="corrupt PNG"):
        decode_png(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "x.png")
    out, err = capfd.readouterr()
    assert "grfmt" not in err and "ERROR" not in err
