"""The capture session config: typed, loaded from TOML, every option with a default that works on
the simulator. Any mistake is one line naming the file and the option (before anything moves).

    [session]    scene_id, objects, phases, retries
    [hand_eye]   T_tcp_cam
    [robot]      backend ("sim" | "ur_rtde"), host, speed, acceleration, timeouts, stop_deceleration, positions
    [robot.limits] joint_min, joint_max, tcp_min, tcp_max
    [turntable]  backend ("sim" | "grbl"), port, baudrate, axis, units_per_degree, feed, step_deg, steps, settle_s, ...
    [camera]     backend ("sim" | "oakd"), width, height, fps, device_id, timeout_s
    [sim]        seed

See docs/capture.md for every option and ``examples/real_rig.toml`` for the real rig.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tdof20.capture.hardware.registry import DEVICES, backends
from tdof20.config import config_from_data, fail as _fail, load_config_file
from tdof20.dataset.naming import VALID_FORMS, normalize_scene_id
from tdof20.errors import TdofError
from tdof20.formats.session import MAX_STEPS
from tdof20.sim.lab import DIRECTIONS, clutter_names

TWO_PI = 2 * math.pi
PHASES = ("transparent", "opaque")


@dataclass(frozen=True)
class Limits:
    """Workspace limits every arm target is checked against before anything moves."""

    joint_min: tuple[float, ...] = (-TWO_PI,) * 6      # rad
    joint_max: tuple[float, ...] = (TWO_PI,) * 6       # rad
    tcp_min: tuple[float, ...] = (-850.0, -850.0, -150.0)  # mm, base frame box for the TCP
    tcp_max: tuple[float, ...] = (850.0, 850.0, 900.0)


@dataclass(frozen=True)
class RobotConfig:
    backend: str = "sim"                  # "sim" | "ur_rtde"
    host: str = "192.168.1.10"
    speed: float = 0.5                    # moveJ joint speed, rad/s
    acceleration: float = 0.5             # moveJ joint acceleration, rad/s^2
    connect_timeout_s: float = 5.0
    move_timeout_s: float = 60.0
    joint_tolerance_rad: float = 0.002    # arrival check after each move
    stop_deceleration: float = 2.0        # stopJ deceleration when a move is stopped (timeout, Ctrl-C), rad/s^2
    positions: tuple[tuple[float, ...], ...] = ()  # arm positions as joint vectors (rad); sim: computed if empty
    limits: Limits = field(default_factory=Limits)


@dataclass(frozen=True)
class TurntableConfig:
    backend: str = "sim"                  # "sim" | "grbl"
    port: str = "/dev/ttyUSB0"
    baudrate: int = 115200
    axis: str = "X"
    units_per_degree: float = 1.0         # GRBL axis units per table degree
    feed_deg_per_s: float = 30.0
    step_deg: float = 0.9
    steps: int = 400
    settle_s: float = 0.0                 # wait after the table stopped, before grabbing
    timeout_s: float = 30.0
    home: bool = True                     # home the table before the first frame
    direction: str = "ccw"                # which way positive angles turn the table, seen from above: "ccw" | "cw"


@dataclass(frozen=True)
class CameraConfig:
    backend: str = "sim"                  # "sim" | "oakd"
    width: int = 640
    height: int = 480
    fps: float = 10.0
    device_id: str = ""
    timeout_s: float = 3.0


@dataclass(frozen=True)
class SessionConfig:
    scene_id: str = "multi/08"
    objects: tuple[int, ...] = ()         # object ids on the table; sim: the scene's own if empty
    phases: tuple[str, ...] = PHASES
    retries: int = 2                      # retries of a failed device call before the run stops


@dataclass(frozen=True)
class HandEyeConfig:
    T_tcp_cam: tuple[float, ...] = ()     # 16 numbers, row-major, mm; sim: the simulated bracket if empty


@dataclass(frozen=True)
class SimConfig:
    seed: int = 0
    n_arms: int = 4                       # arm positions computed for the sim when robot.positions is empty
    # the lab (tdof20.sim.lab): what a real lab adds to a clean turntable; the defaults are the clean rig
    clutter: tuple[str, ...] = ()         # static presets beside the table: cabinet, monitor, box, wall
    record_direction: bool = True         # false: leave turntable.direction out of session.json
    hand_eye_error_mm: float = 0.0        # the camera really sits this far from the recorded hand-eye
    hand_eye_error_deg: float = 0.0       # ... and turned by this much (direction seeded by sim.seed)
    step_jitter_deg: float = 0.0          # the table stands at nominal + U[-jitter, jitter] per frame
    depth_bias: float = 1.0               # the camera's depth reads this multiple of the true depth (1.02: 2 % long)
    twin_offset_mm: float = 0.0           # each opaque twin stands this far off its object's slot (direction seeded)
    twin_offset_deg: float = 0.0          # ... and turned by this much about the table axis (sign seeded)


@dataclass(frozen=True)
class CaptureConfig:
    session: SessionConfig = field(default_factory=SessionConfig)
    hand_eye: HandEyeConfig = field(default_factory=HandEyeConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    turntable: TurntableConfig = field(default_factory=TurntableConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    source: str = ""                      # the file it was read from ("" = built in code)

    @property
    def is_sim(self) -> bool:
        return "sim" in (self.robot.backend, self.turntable.backend, self.camera.backend)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("source")
        return d


#: the backends each device may name: "sim" and its vendors' (tdof20.capture.hardware.registry)
BACKENDS = {device: backends(device) for device in DEVICES}


# ------------------------------------------------------------------------------------ loading
def config_from_dict(data: dict, source: str = "") -> CaptureConfig:
    """A checked :class:`CaptureConfig` from a parsed TOML document (strict; one-line errors)."""
    return validate(config_from_data(CaptureConfig, data, source))


def load_config(path: str | Path) -> CaptureConfig:
    """Read and check a TOML capture config; any problem is a one-line TdofError naming the file."""
    return validate(load_config_file(CaptureConfig, path))


# ------------------------------------------------------------------------------------ checks
def validate(cfg: CaptureConfig) -> CaptureConfig:
    """Everything that can be checked without hardware (workspace limits: see plan.check_workspace)."""
    src = cfg.source
    s = cfg.session
    try:
        scene_name = normalize_scene_id(s.scene_id)
    except TdofError:
        _fail(src, "session.scene_id", f"'{s.scene_id}' is not a scene name ({VALID_FORMS})")
    if scene_name != s.scene_id:  # the alias single/NN -> single/<class name>
        s = dataclasses.replace(s, scene_id=scene_name)
        cfg = dataclasses.replace(cfg, session=s)
    if not s.phases or any(p not in PHASES for p in s.phases) or len(set(s.phases)) != len(s.phases):
        _fail(src, "session.phases", f"must be distinct phases from {list(PHASES)}, got {list(s.phases)}")
    for i, o in enumerate(s.objects):
        if not 1 <= o <= 20:
            _fail(src, f"session.objects[{i}]", f"unknown object id {o} (valid: 1-20)")
        if o in s.objects[:i]:
            _fail(src, f"session.objects[{i}]", f"object {o} is listed twice (each object once per scene)")
    if s.retries < 0:
        _fail(src, "session.retries", "must be >= 0")
    for name, allowed in BACKENDS.items():
        b = getattr(cfg, name).backend
        if b not in allowed:
            _fail(src, f"{name}.backend", f"unknown backend '{b}' (valid: {', '.join(allowed)})")
    backends = {cfg.robot.backend, cfg.turntable.backend, cfg.camera.backend}
    if cfg.is_sim and backends != {"sim"}:
        _fail(src, "", "robot, turntable and camera must all be 'sim' or all be hardware (mixing is not supported)")
    if not cfg.is_sim and not s.objects:
        _fail(src, "session.objects", "list the object ids on the table (a real rig cannot guess them)")
    r = cfg.robot
    for k in ("speed", "acceleration", "connect_timeout_s", "move_timeout_s", "joint_tolerance_rad"):
        if not getattr(r, k) > 0:
            _fail(src, f"robot.{k}", f"must be > 0, got {getattr(r, k)}")
    if not 0 < r.stop_deceleration <= 40:
        _fail(src, "robot.stop_deceleration", f"must be in (0, 40] rad/s^2 (the UR5's joint acceleration limit), "
                                              f"got {r.stop_deceleration}")
    if r.speed > 3.2:
        _fail(src, "robot.speed", f"{r.speed} rad/s exceeds the UR5's joint speed limit (3.14 rad/s); degrees?")
    if not r.positions and r.backend != "sim":
        _fail(src, "robot.positions", "list the arm positions as joint vectors (rad)")
    for i, q in enumerate(r.positions):
        if len(q) != 6:
            _fail(src, f"robot.positions[{i}]", f"must be 6 joint angles (rad), got {len(q)}")
        if max(abs(v) for v in q) > TWO_PI:
            _fail(src, f"robot.positions[{i}]", "has a joint beyond 2*pi: looks like degrees, radians expected")
    L = r.limits
    for k, n in (("joint_min", 6), ("joint_max", 6), ("tcp_min", 3), ("tcp_max", 3)):
        if len(getattr(L, k)) != n:
            _fail(src, f"robot.limits.{k}", f"must be {n} numbers, got {len(getattr(L, k))}")
    if any(a >= b for a, b in zip(L.joint_min, L.joint_max)) or any(a >= b for a, b in zip(L.tcp_min, L.tcp_max)):
        _fail(src, "robot.limits", "every minimum must be below its maximum")
    t = cfg.turntable
    if not 0 < t.step_deg <= 360:
        _fail(src, "turntable.step_deg", f"must be in (0, 360], got {t.step_deg}")
    if not 1 <= t.steps <= MAX_STEPS:
        _fail(src, "turntable.steps", f"must be in 1..{MAX_STEPS}, got {t.steps}")
    for k in ("units_per_degree", "feed_deg_per_s", "timeout_s", "baudrate"):
        if not getattr(t, k) > 0:
            _fail(src, f"turntable.{k}", f"must be > 0, got {getattr(t, k)}")
    if t.settle_s < 0:
        _fail(src, "turntable.settle_s", "must be >= 0")
    c = cfg.camera
    if not (16 <= c.width <= 4096 and 16 <= c.height <= 4096):
        _fail(src, "camera.width/height", f"{c.width}x{c.height} out of range (16..4096)")
    if not c.fps > 0 or not c.timeout_s > 0:
        _fail(src, "camera", "fps and timeout_s must be > 0")
    he = cfg.hand_eye.T_tcp_cam
    if he:
        if len(he) != 16:
            _fail(src, "hand_eye.T_tcp_cam", f"must be 16 numbers (row-major 4x4), got {len(he)}")
        T = np.asarray(he, float).reshape(4, 4)
        R = T[:3, :3]
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0 and np.allclose(T[3], [0, 0, 0, 1])):
            _fail(src, "hand_eye.T_tcp_cam", "is not a rigid transform (rotation must be orthonormal, last row 0 0 0 1)")
        if 0 < np.linalg.norm(T[:3, 3]) < 1.0:
            _fail(src, "hand_eye.T_tcp_cam", "translation looks like metres; millimetres expected")
    elif not cfg.is_sim:
        _fail(src, "hand_eye.T_tcp_cam", "give the hand-eye calibration (16 numbers, mm)")
    if cfg.sim.seed < 0:
        _fail(src, "sim.seed", f"must be >= 0, got {cfg.sim.seed}")
    if cfg.sim.n_arms < 1 or cfg.sim.n_arms > 8:
        _fail(src, "sim.n_arms", "must be in 1..8")
    if t.direction not in DIRECTIONS:
        _fail(src, "turntable.direction", f"must be one of {', '.join(DIRECTIONS)} (seen from above), got '{t.direction}'")
    sm = cfg.sim
    bad = [c for c in sm.clutter if c not in clutter_names()]
    if bad:
        _fail(src, "sim.clutter", f"unknown preset {', '.join(repr(b) for b in bad)} (known: {', '.join(clutter_names())})")
    if len(set(sm.clutter)) != len(sm.clutter):
        _fail(src, "sim.clutter", f"names a preset twice: {list(sm.clutter)}")
    if not 0 <= sm.hand_eye_error_mm <= 50:
        _fail(src, "sim.hand_eye_error_mm", f"must be in [0, 50] mm, got {sm.hand_eye_error_mm}")
    if not 0 <= sm.hand_eye_error_deg <= 10:
        _fail(src, "sim.hand_eye_error_deg", f"must be in [0, 10] degrees, got {sm.hand_eye_error_deg}")
    if not 0 <= sm.step_jitter_deg < t.step_deg / 2:
        _fail(src, "sim.step_jitter_deg", f"must be in [0, step_deg / 2 = {t.step_deg / 2:g}) degrees, got {sm.step_jitter_deg}")
    if not 0.9 <= sm.depth_bias <= 1.1:
        _fail(src, "sim.depth_bias", f"must be in [0.9, 1.1] (reported / true depth; 1.02 reads 2 % long), "
                                     f"got {sm.depth_bias}")
    if not 0 <= sm.twin_offset_mm <= 20:
        _fail(src, "sim.twin_offset_mm", f"must be in [0, 20] mm, got {sm.twin_offset_mm}")
    if not 0 <= sm.twin_offset_deg <= 20:
        _fail(src, "sim.twin_offset_deg", f"must be in [0, 20] degrees, got {sm.twin_offset_deg}")
    return cfg


def sim_config(scene_id: str = "multi/08", steps: int = 400, step_deg: float = 0.9, n_arms: int = 4,
               width: int = 640, height: int = 480, seed: int = 0, phases=PHASES, clutter=(),
               direction: str = "ccw", record_direction: bool = True, hand_eye_error_mm: float = 0.0,
               hand_eye_error_deg: float = 0.0, step_jitter_deg: float = 0.0,
               depth_bias: float = 1.0, twin_offset_mm: float = 0.0, twin_offset_deg: float = 0.0) -> CaptureConfig:
    """The config of a capture on the simulated rig (what ``capture run --sim`` builds); the
    lab options (clutter ... twin_offset_deg) are those of :class:`SimConfig` and
    ``TurntableConfig.direction``."""
    cfg = CaptureConfig(session=SessionConfig(scene_id=scene_id, phases=tuple(phases)),
                        turntable=TurntableConfig(step_deg=step_deg, steps=steps, direction=direction),
                        camera=CameraConfig(width=width, height=height),
                        sim=SimConfig(seed=seed, n_arms=n_arms, clutter=tuple(clutter),
                                      record_direction=record_direction,
                                      hand_eye_error_mm=float(hand_eye_error_mm),
                                      hand_eye_error_deg=float(hand_eye_error_deg),
                                      step_jitter_deg=float(step_jitter_deg), depth_bias=float(depth_bias),
                                      twin_offset_mm=float(twin_offset_mm), twin_offset_deg=float(twin_offset_deg)))
    return validate(cfg)
