"""Assemble the devices a capture config names: each hardware device from its vendor's line in
:mod:`tdof20.capture.hardware.registry` (the vendor module imported only when used), or the
simulated rig, whose devices share one world."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from tdof20.capture.config import CaptureConfig
from tdof20.capture.hardware.interfaces import RGBDCamera, Robot, Turntable
from tdof20.capture.hardware.registry import DEVICES, vendor
from tdof20.capture.plan import arm_targets, hand_eye
from tdof20.sim.lab import TableMotion, true_hand_eye, twin_offsets
from tdof20.sim.rig import RigLayout, oakd_camera, ur5_fk
from tdof20.sim.scenes import get_scene


@dataclass
class Rig:
    robot: Robot
    turntable: Turntable
    camera: RGBDCamera
    set_phase: Callable[[str], None] | None = None          # the simulator swaps objects itself
    after_capture: Callable[[Path, bool], None] | None = None  # the simulator writes its truth/ (out, progress)
    world: object = field(default=None, repr=False)

    def devices(self) -> list:
        return [self.robot, self.turntable, self.camera]


def build_rig(cfg: CaptureConfig, faults: dict | None = None) -> Rig:
    """The rig of a (checked) config: the simulated one, or each device made by the vendor its
    section's ``backend`` names (nothing connects yet). ``faults``: the simulator's injected failures."""
    if cfg.is_sim:
        return _sim_rig(cfg, faults)
    robot, table, camera = (vendor(d, getattr(cfg, d).backend).make(getattr(cfg, d))
                            for d in DEVICES)
    return Rig(robot, table, camera)


def _sim_rig(cfg: CaptureConfig, faults: dict | None) -> Rig:
    # the renderer imports open3d (tdof20.o3d) at the top: only a simulated rig needs it
    from tdof20.capture.hardware.sim import SimCamera, SimRobot, SimTurntable, SimWorld
    from tdof20.objects import get_object
    from tdof20.sim.render import SimRenderer
    from tdof20.sim.sensor import SensorModel

    s = cfg.sim
    T_tcp_cam = hand_eye(cfg)  # what session.json records, and what the arm targets are planned with
    T_tcp_cam_true = true_hand_eye(T_tcp_cam, s.hand_eye_error_mm, s.hand_eye_error_deg, s.seed)
    layout = RigLayout(T_tcp_cam=T_tcp_cam)
    targets = arm_targets(cfg)
    camera = oakd_camera(cfg.camera.width, cfg.camera.height)
    scene = get_scene(cfg.session.scene_id, layout.table_radius)
    # the opaque twins off their slots (sim.twin_offset_mm/_deg): about each object's centre
    centres = [0.5 * (get_object(p.obj_id).vertices.min(0) + get_object(p.obj_id).vertices.max(0))
               for p in scene.placements]
    offsets = twin_offsets([p.T_table_obj for p in scene.placements], centres, s.twin_offset_mm, s.twin_offset_deg,
                           s.seed)
    renderer = SimRenderer(scene, camera, layout,
                           [ur5_fk(q) @ T_tcp_cam_true for q in targets], sensor=SensorModel(depth_bias=s.depth_bias),
                           seed=s.seed, clutter=s.clutter, twin_offsets=offsets)
    table = TableMotion(cfg.turntable.direction, s.step_jitter_deg, s.seed)
    world = SimWorld(renderer, targets, faults, table)

    def set_phase(phase: str) -> None:
        world.phase = phase

    def after_capture(out: Path, show_progress: bool = True) -> None:
        from tdof20.sim.truth import write_truth   # imports the renderer (open3d)

        write_truth(renderer, out, cfg.turntable.steps, cfg.turntable.step_deg, show_progress, table=table,
                    rig={"T_tcp_cam": T_tcp_cam_true, "T_tcp_cam_recorded": T_tcp_cam, "clutter": list(s.clutter),
                         "hand_eye_error_mm": s.hand_eye_error_mm, "hand_eye_error_deg": s.hand_eye_error_deg,
                         "depth_bias": s.depth_bias, "twin_offset_mm": s.twin_offset_mm,
                         "twin_offset_deg": s.twin_offset_deg,
                         "T_table_twin": [T.reshape(16).tolist() for T in renderer.T_table_twins]},
                    phases=tuple(cfg.session.phases))

    return Rig(SimRobot(world), SimTurntable(world), SimCamera(world), set_phase, after_capture, world)
