"""From a capture config to the exact sequence of a session, checked before anything moves.

The sequence: for each phase (transparent, then the opaque twins), for each arm position, move
the arm (moveJ) and confirm it arrived; then for each step turn the table to ``step * step_deg``,
wait until it stopped and settled, grab a synchronised RGB-D pair and journal it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from tdof20.capture.config import CaptureConfig
from tdof20.errors import TdofError
from tdof20.formats import ArmPosition, SessionInfo
from tdof20.geometry import PinholeCamera
from tdof20.sim.rig import DEFAULT_T_TCP_CAM, UR5_HOME, RigLayout, ur5_fk
from tdof20.sim.scenes import get_scene


def hand_eye(cfg: CaptureConfig) -> np.ndarray:
    """T_tcp_cam (4,4) mm: the configured calibration, or the simulated bracket."""
    he = cfg.hand_eye.T_tcp_cam
    return np.asarray(he, float).reshape(4, 4) if he else DEFAULT_T_TCP_CAM.copy()


def lab_record(cfg: CaptureConfig, session: bool = True) -> dict:
    """What session.json records of the simulated lab (under ``sim.lab``): the clutter and the
    sizes of the errors, not the errors themselves (those are in truth/rig.json); {} for a clean
    rig. The direction is not here: it is ``turntable.direction``, or left out. The depth bias
    and the twins' offsets are their own sizes, so session.json leaves them out (annotation must
    find them as on a real rig);
    ``session=False`` gives it too (what ``capture plan`` shows)."""
    s = cfg.sim
    lab = {"clutter": list(s.clutter), "hand_eye_error_mm": s.hand_eye_error_mm,
           "hand_eye_error_deg": s.hand_eye_error_deg, "step_jitter_deg": s.step_jitter_deg}
    if not session:
        if s.depth_bias != 1.0:
            lab["depth_bias"] = s.depth_bias
        lab["twin_offset_mm"], lab["twin_offset_deg"] = s.twin_offset_mm, s.twin_offset_deg
    return {k: v for k, v in lab.items() if v}


def arm_targets(cfg: CaptureConfig) -> list[np.ndarray]:
    """Joint vectors (rad) of the arm positions: the configured ones, or for the simulator the
    UR5 poses that look at the table from evenly spread elevations."""
    if cfg.robot.positions:
        return [np.asarray(q, float) for q in cfg.robot.positions]
    layout = RigLayout(T_tcp_cam=hand_eye(cfg))
    try:
        return [q for q, _ in layout.arm_positions(cfg.sim.n_arms)]
    except ValueError as e:  # ur5_ik: no joint solution for a viewing pose
        raise TdofError(f"hand_eye.T_tcp_cam: the simulated arm cannot place the camera at its viewing positions "
                        f"({e}): is the hand-eye transform in mm, and the camera near the tool flange?",
                        cfg.source or None) from None


@dataclass(frozen=True)
class WorkspaceProblem:
    arm: int
    message: str


def workspace_problems(cfg: CaptureConfig, targets: list[np.ndarray] | None = None) -> list[WorkspaceProblem]:
    """Every arm target outside the joint limits or whose TCP (UR5 forward kinematics) leaves the
    configured box."""
    L = cfg.robot.limits
    out = []
    for a, q in enumerate(targets if targets is not None else arm_targets(cfg)):
        for j, (v, lo, hi) in enumerate(zip(q, L.joint_min, L.joint_max)):
            if not lo <= v <= hi:
                out.append(WorkspaceProblem(a, f"joint {j + 1} = {v:.4f} rad outside [{lo:.4f}, {hi:.4f}]"))
        p = ur5_fk(q)[:3, 3]
        for k, (v, lo, hi) in enumerate(zip(p, L.tcp_min, L.tcp_max)):
            if not lo <= v <= hi:
                out.append(WorkspaceProblem(a, f"TCP {'xyz'[k]} = {v:.1f} mm outside [{lo:.1f}, {hi:.1f}]"))
    return out


def check_workspace(cfg: CaptureConfig) -> list[np.ndarray]:
    """The arm targets, or a TdofError listing every target outside the workspace limits."""
    targets = arm_targets(cfg)
    problems = workspace_problems(cfg, targets)
    if problems:
        listed = "; ".join(f"arm position {p.arm}: {p.message}" for p in problems)
        raise TdofError(f"refused before any motion: {listed}", cfg.source or None)
    return targets


def frame_keys(cfg: CaptureConfig) -> list[tuple[str, int, int]]:
    """Every planned frame (phase, arm, step) in capture order."""
    n_arms = len(arm_targets(cfg))
    return [(ph, a, k) for ph in cfg.session.phases for a in range(n_arms) for k in range(cfg.turntable.steps)]


def estimate_duration(cfg: CaptureConfig, targets: list[np.ndarray] | None = None) -> dict:
    """Seconds per part of the session on the configured hardware (the simulator is faster; the
    operator's swap between phases is not counted)."""
    targets = targets if targets is not None else arm_targets(cfg)
    r, t, c = cfg.robot, cfg.turntable, cfg.camera
    moves = 0.0
    prev = UR5_HOME
    for q in targets:
        d = float(np.abs(np.asarray(q) - prev).max())
        moves += d / r.speed + r.speed / r.acceleration  # cruise + accelerate/decelerate
        prev = q
    per_step = t.step_deg / t.feed_deg_per_s + t.settle_s + 1.0 / c.fps + 0.03
    n_phase = len(cfg.session.phases)
    steps_s = n_phase * len(targets) * t.steps * per_step
    return {"arm_moves_s": n_phase * moves, "frames_s": steps_s, "per_frame_s": per_step,
            "total_s": n_phase * moves + steps_s, "frames": n_phase * len(targets) * t.steps}


def session_info(cfg: CaptureConfig, intrinsics: dict, targets: list[np.ndarray] | None = None) -> SessionInfo:
    """session.json of the capture: the plan, the camera as the device reports it."""
    targets = targets if targets is not None else arm_targets(cfg)
    cam = PinholeCamera.from_dict(intrinsics)
    objs = list(cfg.session.objects) or (get_scene(cfg.session.scene_id).obj_ids if cfg.is_sim else [])
    extra = {"rig": "sim" if cfg.is_sim else "hardware",
             "capture": {k: v for k, v in cfg.to_dict().items() if k in ("robot", "turntable", "camera")}}
    # the direction is recorded once, as turntable.direction (or not at all: sim.record_direction)
    extra["capture"]["turntable"].pop("direction", None)
    turntable = {"step_deg": cfg.turntable.step_deg, "steps": cfg.turntable.steps, "direction": cfg.turntable.direction}
    if cfg.is_sim:
        scene = get_scene(cfg.session.scene_id)
        extra["sim"] = {"seed": cfg.sim.seed, "sticker": scene.sticker}
        lab = lab_record(cfg)
        if lab:
            extra["sim"]["lab"] = lab
        if not cfg.sim.record_direction:
            del turntable["direction"]
    for k in ("K", "width", "height", "depth_scale"):
        intrinsics = {kk: vv for kk, vv in intrinsics.items() if kk != k}
    if intrinsics:
        extra["camera_device"] = intrinsics
    return SessionInfo(
        scene_id=cfg.session.scene_id,
        objects=[{"obj_id": int(o)} for o in objs],
        camera=cam,
        arm_positions=[ArmPosition(q=np.asarray(q, float), T_base_tcp=ur5_fk(q)) for q in targets],
        T_tcp_cam=hand_eye(cfg),
        turntable=turntable,
        phases=tuple(cfg.session.phases),
        extra=extra,
    )


def describe(cfg: CaptureConfig) -> dict:
    """What ``capture plan`` prints: targets, their TCP, limit checks, counts and duration."""
    targets = arm_targets(cfg)
    problems = workspace_problems(cfg, targets)
    return {
        "scene_id": cfg.session.scene_id, "phases": list(cfg.session.phases),
        "backends": {k: getattr(cfg, k).backend for k in ("robot", "turntable", "camera")},
        "arms": [{"arm": a, "q_deg": np.degrees(q).round(2).tolist(), "tcp_mm": ur5_fk(q)[:3, 3].round(1).tolist(),
                  "problems": [p.message for p in problems if p.arm == a]} for a, q in enumerate(targets)],
        "steps": cfg.turntable.steps, "step_deg": cfg.turntable.step_deg, "direction": cfg.turntable.direction,
        "lab": lab_record(cfg, session=False) if cfg.is_sim else {},
        "estimate": estimate_duration(cfg, targets), "ok": not problems,
        "config": dataclasses.asdict(cfg.session),
    }
