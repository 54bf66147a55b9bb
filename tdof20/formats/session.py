"""The raw capture session: what the rig (or the simulator) records, before any annotation.

A session is a folder::

    session.json                              what was planned: scene, objects, camera, arm
                                              positions, hand-eye calibration, turntable, phases
    journal.jsonl                             one JSON line per captured frame, appended
    {phase}/arm{a}/rgb/{k:06d}.png            8-bit colour
    {phase}/arm{a}/depth/{k:06d}.png          uint16, ``depth_scale`` mm per unit, 0 = no depth
    truth/                                    simulated sessions only: a BOP scene (evaluation only)

The journal is the truth: a frame exists once its line is in the journal
(:mod:`tdof20.formats.journal`: its entries, the torn-line rule). This module holds
``session.json``, writing a frame and :class:`RawSession`, the checked reader of the whole
folder; the strict field checks are :mod:`tdof20.formats.checks`. See ``docs/formats.md``.

Every problem in a session found while reading is a one-line :class:`TdofError` naming the file;
reading never modifies anything on disk.
"""

from __future__ import annotations

import copy
import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.checks import Checker, json_type
from tdof20.formats.io import decode_png, dumps_json, read_json, sha256_bytes, write_json, write_png
from tdof20.formats.journal import (JOURNAL_FILE, PHASES, FrameKey, JournalEntry, append_journal, frame_paths,
                                    read_journal)
from tdof20.geometry.camera import PinholeCamera

FORMAT = "tdof20-raw-session"
VERSION = 1
SESSION_FILE = "session.json"
TRUTH_DIR = "truth"
N_JOINTS = 6
#: the most turntable steps per arm position a session may have (0.01 deg steps; the paper's 400 are
#: 0.9 deg): a bound that keeps a typo (1e30 steps) from planning frames until memory runs out
MAX_STEPS = 36000
TURN_DIRECTIONS = ("ccw", "cw")  # turntable.direction: counter-clockwise (default) or clockwise, seen from above
# single/<class name> (single/NN, NN = the object id 01..20, is an alias) or multi/00..multi/19
SCENE_ID_RE = re.compile(r"^(single/([a-z][a-z0-9_]*|0[1-9]|1[0-9]|20)|multi/[01][0-9])$")
OBJ_ID_RANGE = (1, 20)
METRES_THRESHOLD_MM = 5.0  # a T_base_tcp translation shorter than this looks like metres
# a hand-eye translation shorter than this (mm) but not zero looks like metres: a camera on the
# flange sits tens of millimetres away, i.e. well under 1 when written in metres (the capture
# config's hand_eye.T_tcp_cam check uses the same rule)
HAND_EYE_METRES_MM = 1.0
# the valid depths of a tabletop rig's frame lie at arm's length; a median outside this range (mm)
# means camera.depth_scale does not give millimetres
DEPTH_PLAUSIBLE_MM = (100.0, 5000.0)


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def _deep_merge(extra: Any, known: Any) -> Any:
    """``known`` over ``extra``: dicts merge key by key, equal-length lists item by item."""
    if isinstance(extra, dict) and isinstance(known, dict):
        out = {k: _deep_merge(extra.get(k), v) if k in extra else v for k, v in known.items()}
        for k, v in extra.items():
            if k not in out:
                out[k] = copy.deepcopy(v)
        return out
    if isinstance(extra, list) and isinstance(known, list) and len(extra) == len(known):
        return [_deep_merge(e, k) for e, k in zip(extra, known)]
    return known


def _flat(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


# ---------------------------------------------------------------------------------------------
# session.json
# ---------------------------------------------------------------------------------------------
@dataclass(eq=False)
class ArmPosition:
    """One of the arm's capture positions: joint angles ``q`` (6,) in radians and the flange
    (tool centre point) pose ``T_base_tcp`` (4,4) in mm, as the robot reported it."""

    q: np.ndarray
    T_base_tcp: np.ndarray

    def __post_init__(self) -> None:
        self.q = np.asarray(self.q, dtype=np.float64).reshape(N_JOINTS)
        self.T_base_tcp = np.asarray(self.T_base_tcp, dtype=np.float64).reshape(4, 4)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ArmPosition):
            return NotImplemented
        return bool(np.array_equal(self.q, other.q) and np.array_equal(self.T_base_tcp, other.T_base_tcp))


_TOP_KNOWN = ("format", "version", "scene_id", "objects", "camera", "arm_positions", "hand_eye",
              "turntable", "phases")
_CAMERA_KNOWN = ("K", "width", "height", "depth_scale")


@dataclass(eq=False)
class SessionInfo:
    """The contents of ``session.json``.

    ``extra`` keeps everything the file holds beyond the fields modelled here, with the same
    nesting (e.g. ``{"operator": "ana", "camera": {"serial": "1944"}}``); :meth:`to_dict` merges it
    back, so a read-write round trip keeps the file's content. ``objects`` and ``turntable`` are
    kept whole (their extra keys included).
    """

    scene_id: str
    objects: list[dict]
    camera: PinholeCamera
    arm_positions: list[ArmPosition]
    T_tcp_cam: np.ndarray
    turntable: dict
    phases: tuple = PHASES
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.T_tcp_cam = np.asarray(self.T_tcp_cam, dtype=np.float64).reshape(4, 4)
        self.phases = tuple(self.phases)
        self.arm_positions = [a if isinstance(a, ArmPosition) else ArmPosition(**a) for a in self.arm_positions]

    # --- plan ------------------------------------------------------------------------------
    @property
    def steps(self) -> int:
        return int(self.turntable["steps"])

    @property
    def step_deg(self) -> float:
        return float(self.turntable["step_deg"])

    @property
    def n_arms(self) -> int:
        return len(self.arm_positions)

    @property
    def obj_ids(self) -> list[int]:
        return [int(o["obj_id"]) for o in self.objects]

    def angle_deg(self, step: int) -> float:
        """Turntable angle in degrees at ``step`` (step 0 = 0°)."""
        return float(step) * self.step_deg

    def T_base_cam(self, arm: int) -> np.ndarray:
        """Camera pose in the robot base frame at arm position ``arm``: T_base_tcp @ T_tcp_cam (mm)."""
        return self.arm_positions[arm].T_base_tcp @ self.T_tcp_cam

    def frame_paths(self, phase: str, arm: int, step: int) -> tuple[str, str]:
        """Relative POSIX paths (rgb, depth) of a planned frame."""
        if phase not in self.phases:
            raise ValueError(f"phase {phase!r} is not one of this session's phases {self.phases}")
        if not (0 <= arm < self.n_arms) or not (0 <= step < self.steps):
            raise ValueError(f"frame arm {arm} step {step} is outside the plan ({self.n_arms} arms, {self.steps} steps)")
        return frame_paths(phase, arm, step)

    def planned_frames(self) -> list[FrameKey]:
        """Every planned (phase, arm, step), in capture order."""
        return [(p, a, k) for p in self.phases for a in range(self.n_arms) for k in range(self.steps)]

    # --- (de)serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict:
        known = {
            "format": FORMAT,
            "version": VERSION,
            "scene_id": self.scene_id,
            "objects": copy.deepcopy(list(self.objects)),
            "camera": self.camera.to_dict(),
            "arm_positions": [{"q": _flat(a.q), "T_base_tcp": _flat(a.T_base_tcp)} for a in self.arm_positions],
            "hand_eye": {"T_tcp_cam": _flat(self.T_tcp_cam)},
            "turntable": copy.deepcopy(dict(self.turntable)),
            "phases": list(self.phases),
        }
        # through JSON, so the dict equals what a read-back gives (tuples -> lists, numpy -> float)
        return json.loads(dumps_json(_deep_merge(self.extra, known), indent=None))

    @classmethod
    def from_dict(cls, d: Any, path: str | Path | None = SESSION_FILE) -> "SessionInfo":
        """Validate a parsed ``session.json`` strictly; any problem is a TdofError naming ``path``
        and the field."""
        c = Checker(path)
        if not isinstance(d, dict):
            c.fail(f"must hold a JSON object {{...}}, got {json_type(d)}")
        fmt = c.get(d, "format", "")
        if fmt != FORMAT:
            c.fail(f"is not a tdof20 raw session: format must be '{FORMAT}', got {fmt!r}")
        version = c.integer(c.get(d, "version", ""), "version", lo=1)
        if version > VERSION:
            c.fail(f"version {version} is newer than this tdof20 reads ({VERSION}); upgrade tdof20")

        scene_id = c.string(c.get(d, "scene_id", ""), "scene_id")
        if not SCENE_ID_RE.match(scene_id):
            c.fail(f"scene_id must look like 'single/<class name>', 'single/NN' (NN = object id 01..20) or "
                   f"'multi/NN' (NN in 00..19), got {scene_id!r}")

        objects = c.get(d, "objects", "")
        if not isinstance(objects, list) or not objects:
            c.fail(f"objects must be a non-empty list of objects, got {json_type(objects) if not isinstance(objects, list) else 'an empty list'}")
        for i, o in enumerate(objects):
            c.obj(o, f"objects[{i}]")
            c.integer(c.get(o, "obj_id", f"objects[{i}]"), f"objects[{i}].obj_id", *OBJ_ID_RANGE)
        if scene_id.startswith("single/") and len(objects) != 1:
            c.fail(f"scene {scene_id} is a single-object scene but objects lists {len(objects)}")

        cam = c.obj(c.get(d, "camera", ""), "camera")
        K = c.numbers(c.get(cam, "K", "camera"), 9, "camera.K").reshape(3, 3)
        width = c.integer(c.get(cam, "width", "camera"), "camera.width", lo=1)
        height = c.integer(c.get(cam, "height", "camera"), "camera.height", lo=1)
        depth_scale = c.number(c.get(cam, "depth_scale", "camera"), "camera.depth_scale", gt=0)
        _check_K(c, K, width, height, "camera.K")
        camera = PinholeCamera(K, width, height, depth_scale)

        arms = c.get(d, "arm_positions", "")
        if not isinstance(arms, list) or not arms:
            c.fail(f"arm_positions must be a non-empty list, got {json_type(arms) if not isinstance(arms, list) else 'an empty list'}")
        arm_positions, arm_extra = [], []
        for i, a in enumerate(arms):
            where = f"arm_positions[{i}]"
            c.obj(a, where)
            q = c.numbers(c.get(a, "q", where), N_JOINTS, f"{where}.q", "joint angles (rad)")
            if np.max(np.abs(q)) > 2 * np.pi + 1e-6:
                c.fail(f"{where}.q has a joint angle of {np.max(np.abs(q)):.4g}: looks like degrees, radians expected")
            T = c.rigid(c.get(a, "T_base_tcp", where), f"{where}.T_base_tcp", metres_below=METRES_THRESHOLD_MM)
            arm_positions.append(ArmPosition(q, T))
            arm_extra.append({k: copy.deepcopy(v) for k, v in a.items() if k not in ("q", "T_base_tcp")})

        hand_eye = c.obj(c.get(d, "hand_eye", ""), "hand_eye")
        T_tcp_cam = c.rigid(c.get(hand_eye, "T_tcp_cam", "hand_eye"), "hand_eye.T_tcp_cam",
                            metres_below=HAND_EYE_METRES_MM, zero_ok=True)

        turntable = c.obj(c.get(d, "turntable", ""), "turntable")
        c.number(c.get(turntable, "step_deg", "turntable"), "turntable.step_deg", gt=0)
        c.integer(c.get(turntable, "steps", "turntable"), "turntable.steps", lo=1, hi=MAX_STEPS)
        if "direction" in turntable and turntable["direction"] not in TURN_DIRECTIONS:
            c.fail(f"turntable.direction must be one of {', '.join(TURN_DIRECTIONS)} (seen from above), "
                   f"got {turntable['direction']!r}")

        phases = d.get("phases", list(PHASES))
        if not isinstance(phases, list) or not phases:
            c.fail(f"phases must be a non-empty list of {' / '.join(PHASES)}, got {json_type(phases)}")
        for i, p in enumerate(phases):
            if p not in PHASES:
                c.fail(f"phases[{i}] must be one of {', '.join(PHASES)}, got {p!r}")
        if len(set(phases)) != len(phases):
            c.fail(f"phases lists a phase twice: {phases}")

        extra = {k: copy.deepcopy(v) for k, v in d.items() if k not in _TOP_KNOWN}
        cam_extra = {k: copy.deepcopy(v) for k, v in cam.items() if k not in _CAMERA_KNOWN}
        if cam_extra:
            extra["camera"] = cam_extra
        he_extra = {k: copy.deepcopy(v) for k, v in hand_eye.items() if k != "T_tcp_cam"}
        if he_extra:
            extra["hand_eye"] = he_extra
        if any(arm_extra):
            extra["arm_positions"] = arm_extra

        return cls(scene_id=scene_id, objects=copy.deepcopy(objects), camera=camera,
                   arm_positions=arm_positions, T_tcp_cam=T_tcp_cam,
                   turntable=copy.deepcopy(turntable), phases=tuple(phases), extra=extra)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SessionInfo):
            return NotImplemented
        return self.to_dict() == other.to_dict()


def _check_K(c: Checker, K: np.ndarray, width: int, height: int, where: str) -> None:
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        c.fail(f"{where} focal lengths must be > 0 pixels, got fx={K[0, 0]:g} fy={K[1, 1]:g}")
    if np.any(K[2] != [0, 0, 1]) or K[1, 0] != 0:
        c.fail(f"{where} must be an upper-triangular intrinsic matrix with last row 0 0 1, got {_flat(K)}")
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        c.fail(f"{where} principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {width}x{height} image")
    hfov = 2 * math.degrees(math.atan(width / (2 * K[0, 0])))
    vfov = 2 * math.degrees(math.atan(height / (2 * K[1, 1])))
    if not (1.0 <= hfov <= 170.0 and 1.0 <= vfov <= 170.0):
        c.fail(f"{where} gives a field of view of {hfov:.3g}x{vfov:.3g} degrees: "
               f"focal lengths must be in pixels for a {width}x{height} image")


def _session_file(path: str | Path) -> Path:
    p = Path(path)
    if p.is_dir():
        return p / SESSION_FILE
    if p.name == SESSION_FILE or p.exists():
        return p
    raise TdofError("no such session folder", p)


def write_session(dir: str | Path, info: SessionInfo) -> Path:
    """Validate ``info`` and write ``<dir>/session.json`` atomically; returns its path."""
    path = Path(dir) / SESSION_FILE
    d = info.to_dict()
    SessionInfo.from_dict(json.loads(dumps_json(d)), path)  # refuse to write what we could not read
    write_json(path, d, fsync=True)
    return path


def read_session(path: str | Path) -> SessionInfo:
    """Read and validate a session's ``session.json`` (give the folder or the file)."""
    f = _session_file(path)
    return SessionInfo.from_dict(read_json(f), f)


# writing a frame
# ---------------------------------------------------------------------------------------------
def write_frame(dir: str | Path, info: SessionInfo, phase: str, arm: int, step: int, rgb: np.ndarray,
                depth: np.ndarray, t: float | None = None, extra: dict | None = None) -> JournalEntry:
    """Write one RGB-D frame: both PNGs atomically, then its journal line (fsync'ed).

    rgb: (H,W,3) uint8 RGB; depth: (H,W) uint16 in ``info.camera.depth_scale`` mm per unit.
    Returns the journal entry. Re-writing a frame appends a new line; the last one wins.
    """
    dir = Path(dir)
    rgb_rel, depth_rel = info.frame_paths(phase, arm, step)
    cam = info.camera
    rgb = np.asarray(rgb)
    depth = np.asarray(depth)
    if rgb.shape != (cam.height, cam.width, 3) or rgb.dtype != np.uint8:
        raise TdofError(f"colour frame is {rgb.shape} {rgb.dtype}, session camera needs "
                        f"({cam.height}, {cam.width}, 3) uint8", dir / rgb_rel)
    if depth.shape != (cam.height, cam.width) or depth.dtype != np.uint16:
        raise TdofError(f"depth frame is {depth.shape} {depth.dtype}, session camera needs "
                        f"({cam.height}, {cam.width}) uint16", dir / depth_rel)
    rgb_bytes = write_png(dir / rgb_rel, rgb)
    depth_bytes = write_png(dir / depth_rel, depth)
    entry = JournalEntry(phase=phase, arm=int(arm), step=int(step), angle_deg=info.angle_deg(step),
                         rgb=rgb_rel, depth=depth_rel,
                         sha256={"rgb": sha256_bytes(rgb_bytes), "depth": sha256_bytes(depth_bytes)},
                         t=time.time() if t is None else float(t), extra=dict(extra or {}))
    append_journal(dir, entry)
    return entry


# ---------------------------------------------------------------------------------------------
# checks of the frames against session.json
# ---------------------------------------------------------------------------------------------
_KIND_WORDS = {"rgb": "colour image", "depth": "depth image"}


def frame_size_problem(image: np.ndarray | tuple[int, int], camera: PinholeCamera, kind: str = "image") -> str | None:
    """None when a frame — a decoded ``image`` ((H,W) or (H,W,C)), or its (H, W) read from a PNG
    header — has the size of session.json's camera, else the problem in words (the caller names
    the file). ``kind``: 'rgb', 'depth'."""
    h, w = (tuple(image) if isinstance(image, tuple) else np.shape(image))[:2]
    if (h, w) == (camera.height, camera.width):
        return None
    return (f"{_KIND_WORDS.get(kind, kind)} is {w}x{h} pixels but session.json's camera is "
            f"{camera.width}x{camera.height} (camera.width x camera.height)")


def depth_units_problem(info: SessionInfo, depth_mm: np.ndarray) -> str | None:
    """None when the valid depths (> 0) of ``depth_mm`` (any shape: one decoded opaque frame, or
    several stacked, in mm through ``info.camera.depth_scale``) are plausible for a tabletop rig,
    i.e. their median lies in ``DEPTH_PLAUSIBLE_MM``; else the problem in words, with the
    ``camera.depth_scale`` that would fix it (the caller names the file). No valid depth at all
    is a problem too."""
    z = np.asarray(depth_mm, dtype=np.float64).reshape(-1)
    z = z[np.isfinite(z) & (z > 0)]
    scale = info.camera.depth_scale
    if z.size == 0:
        return "holds no depth at all (every pixel is 0): the camera delivered no depth"
    med = float(np.median(z))
    lo, hi = DEPTH_PLAUSIBLE_MM
    if lo <= med <= hi:
        return None
    factor = 10.0 ** round(math.log10(math.sqrt(lo * hi) / med))
    return (f"the valid depths have a median of {med:.3g} mm, implausible for a tabletop rig "
            f"({lo:g}..{hi:g} mm): camera.depth_scale in session.json is {scale:g} mm per unit; "
            f"depth_scale = {scale * factor:g} would give {med * factor:.4g} mm")


# ---------------------------------------------------------------------------------------------
# reading a session
# ---------------------------------------------------------------------------------------------
class RawSession:
    """A raw session opened for reading: ``session.json`` plus the journal. Reads only."""

    def __init__(self, path: Path, info: SessionInfo, entries: list[JournalEntry]):
        self.path = Path(path)
        self.info = info
        self.entries = entries
        self._index: dict[FrameKey, JournalEntry] = {}
        jpath = self.path / JOURNAL_FILE
        for e in entries:
            self._index[e.key] = e  # the last line for a frame wins
        for n, e in enumerate(entries):
            if e.phase not in info.phases or not (0 <= e.arm < info.n_arms) or not (0 <= e.step < info.steps):
                where = f"line {e.line}" if e.line is not None else f"entry {n + 1}"
                raise TdofError(f"{where}: frame {e.phase} arm {e.arm} step {e.step} is outside the plan in "
                                f"session.json (phases {list(info.phases)}, {info.n_arms} arms, {info.steps} steps)",
                                jpath)

    @classmethod
    def open(cls, path: str | Path) -> "RawSession":
        """Open a session folder (or its session.json)."""
        f = _session_file(path)
        info = SessionInfo.from_dict(read_json(f), f)
        return cls(f.parent, info, read_journal(f.parent))

    def with_depth_factor(self, factor: float) -> "RawSession":
        """The same session read with its camera's ``depth_scale`` multiplied by ``factor`` (a depth
        correction found by annotation: every depth it loads, in mm, is ``factor`` times the
        file's reading). ``factor`` 1 gives this session itself."""
        if factor == 1.0:
            return self
        cam = self.info.camera
        info = copy.copy(self.info)
        info.camera = PinholeCamera(cam.K, cam.width, cam.height, cam.depth_scale * float(factor))
        out = copy.copy(self)
        out.info = info
        return out

    # --- what is there ---------------------------------------------------------------------------
    def frames(self, phase: str | None = None) -> list[FrameKey]:
        """Captured frames (phase, arm, step), in plan order (phase, then arm, then step)."""
        order = {p: i for i, p in enumerate(self.info.phases)}
        keys = [k for k in self._index if phase is None or k[0] == phase]
        return sorted(keys, key=lambda k: (order[k[0]], k[1], k[2]))

    def has_frame(self, phase: str, arm: int, step: int) -> bool:
        return (phase, arm, step) in self._index

    def entry(self, phase: str, arm: int, step: int) -> JournalEntry:
        """The journal entry of a frame; TdofError if the journal does not list it."""
        e = self._index.get((phase, arm, step))
        if e is None:
            try:
                rel = frame_paths(phase, arm, step)[0]
            except ValueError:
                rel = f"{phase}/arm{arm}"
            raise TdofError(f"missing frame: {phase} arm {arm} step {step} is not in {JOURNAL_FILE} "
                            f"(never captured)", self.path / rel)
        return e

    def missing_frames(self) -> list[FrameKey]:
        """Planned (phase, arm, step) triples that the journal does not list, in plan order."""
        return [k for k in self.info.planned_frames() if k not in self._index]

    def require_frames(self, phase: str) -> list[FrameKey]:
        """The captured frames of ``phase`` (plan order), or a TdofError naming journal.jsonl (or
        session.json) that says what is missing: no such phase in the plan, no frame of the phase
        at all, or arm positions without any. The same answer on every call, for every caller."""
        if phase not in self.info.phases:
            raise TdofError(f"phases {list(self.info.phases)} do not include '{phase}': this session "
                            f"has no {phase} frames", self.path / SESSION_FILE)
        jpath = self.path / JOURNAL_FILE
        frames = self.frames(phase)
        if not frames:
            if not self.entries:
                why = ("the journal is empty" if jpath.exists() else "there is no journal") + ": was the capture run?"
            else:
                by_phase = {p: len(self.frames(p)) for p in self.info.phases if self.frames(p)}
                listed = ", ".join(f"{n} {p}" for p, n in by_phase.items())
                why = f"the journal lists {listed} frames only: was the {phase} phase captured?"
            raise TdofError(f"no {phase} frames ({why})", jpath)
        have = {a for _, a, _ in frames}
        lacking = [a for a in range(self.info.n_arms) if a not in have]
        if lacking:
            arms = ", ".join(str(a) for a in lacking)
            raise TdofError(f"no {phase} frames for arm position{'s' if len(lacking) > 1 else ''} {arms} "
                            f"(of {self.info.n_arms} in session.json): was the capture stopped early?", jpath)
        return frames

    @property
    def truth_dir(self) -> Path | None:
        d = self.path / TRUTH_DIR
        return d if d.is_dir() else None

    # --- loading ---------------------------------------------------------------------------------
    def _load(self, phase: str, arm: int, step: int, kind: str, verify: bool) -> np.ndarray:
        e = self.entry(phase, arm, step)
        rel = e.rgb if kind == "rgb" else e.depth
        p = self.path / rel
        try:
            data = p.read_bytes()
        except FileNotFoundError:
            raise TdofError(f"missing frame {phase} arm {arm} step {step}: the journal lists it "
                            f"but the {kind} file is not there", p) from None
        except (IsADirectoryError, PermissionError) as ex:
            raise TdofError(f"cannot read ({type(ex).__name__})", p) from None
        if verify and sha256_bytes(data) != e.sha256.get(kind):
            raise TdofError(f"checksum mismatch: the file differs from what the journal recorded "
                            f"for {phase} arm {arm} step {step}", p)
        img = decode_png(data, p, kind)
        problem = frame_size_problem(img, self.info.camera, kind)
        if problem:
            raise TdofError(problem, p)
        return img

    def load_rgb(self, phase: str, arm: int, step: int, verify: bool = False) -> np.ndarray:
        """(H,W,3) uint8 RGB of a captured frame."""
        return self._load(phase, arm, step, "rgb", verify)

    def load_depth(self, phase: str, arm: int, step: int, verify: bool = False) -> np.ndarray:
        """(H,W) uint16 depth (``depth_scale`` mm per unit, 0 = no depth) of a captured frame."""
        return self._load(phase, arm, step, "depth", verify)

    def load_depth_mm(self, phase: str, arm: int, step: int, verify: bool = False) -> np.ndarray:
        """(H,W) float32 depth in millimetres (0 = no depth)."""
        return self.info.camera.depth_to_mm(self.load_depth(phase, arm, step, verify))

    # --- checking --------------------------------------------------------------------------------
    def verify_file(self, entry: JournalEntry, decode: bool = True) -> list[str]:
        """Problems with a frame's files: missing, checksum mismatch, undecodable, wrong size
        (the last two only with ``decode``; a matching checksum already proves the bytes are the
        ones written). Each problem is one line naming the file; [] when all is well."""
        problems = []
        cam = self.info.camera
        for kind in ("rgb", "depth"):
            p = self.path / (entry.rgb if kind == "rgb" else entry.depth)
            try:
                data = p.read_bytes()
            except FileNotFoundError:
                problems.append(f"{p}: missing file ({entry.phase} arm {entry.arm} step {entry.step} is in the journal)")
                continue
            except OSError as ex:
                problems.append(f"{p}: cannot read ({type(ex).__name__})")
                continue
            if sha256_bytes(data) != entry.sha256.get(kind):
                problems.append(f"{p}: checksum mismatch (the file differs from what the journal recorded)")
            if not decode:
                continue
            try:
                img = decode_png(data, p, kind)
            except TdofError as ex:
                problems.append(str(ex))
                continue
            problem = frame_size_problem(img, cam, kind)
            if problem:
                problems.append(f"{p}: {problem}")
        return problems

    def verify_all(self) -> list[str]:
        """:meth:`verify_file` over every captured frame (the entry that counts for each)."""
        out = []
        for k in self.frames():
            out.extend(self.verify_file(self._index[k]))
        return out

    def __iter__(self) -> Iterator[FrameKey]:
        return iter(self.frames())

    def __len__(self) -> int:
        return len(self._index)

    def __repr__(self) -> str:
        return (f"RawSession({str(self.path)!r}, scene {self.info.scene_id}, "
                f"{len(self)}/{len(self.info.planned_frames())} frames)")


__all__ = [
    "FORMAT", "VERSION", "SESSION_FILE", "JOURNAL_FILE", "TRUTH_DIR", "PHASES", "SCENE_ID_RE",
    "ArmPosition", "SessionInfo", "JournalEntry", "RawSession", "frame_paths", "write_session",
    "read_session", "append_journal", "read_journal", "write_frame", "frame_size_problem",
    "depth_units_problem", "DEPTH_PLAUSIBLE_MM",
]
