"""Render a whole simulated capture session to disk in the raw session format.

The session is what the real rig would record (session.json, journal.jsonl, the RGB-D pairs of
both phases) plus ``truth/``: the simulator's exact ground truth as a BOP scene with the models.
Rerunning on a folder that holds the same session resumes: frames already in the journal are
kept, the others are rendered. Frames are deterministic, so a resumed session equals an
uninterrupted one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats import (ArmPosition, BopSceneWriter, RawSession, SessionInfo, read_session,
                            write_frame, write_session)
from tdof20.geometry import invert
from tdof20.objects import export_models, get_object
from tdof20.progress import progress
from tdof20.sim.render import PHASES, GlassModel, SimRenderer
from tdof20.sim.rig import RigLayout, oakd_camera
from tdof20.sim.scenes import get_scene
from tdof20.sim.sensor import SensorModel


@dataclass(frozen=True)
class SimSessionConfig:
    """Everything that defines a simulated session (all defaults are the real rig's)."""

    scene_id: str = "multi/08"
    steps: int = 400
    step_deg: float = 0.9
    n_arms: int = 4
    width: int = 640
    height: int = 480
    depth_scale: float = 1.0
    seed: int = 0
    phases: tuple = PHASES
    sensor: SensorModel = field(default_factory=SensorModel)
    glass: GlassModel = field(default_factory=GlassModel)
    layout: RigLayout = field(default_factory=RigLayout)

    def validate(self) -> "SimSessionConfig":
        get_scene(self.scene_id)
        if self.steps < 1:
            raise TdofError(f"--steps must be >= 1, got {self.steps}")
        if not 0 < self.step_deg <= 360:
            raise TdofError(f"--step-deg must be in (0, 360], got {self.step_deg}")
        if not 1 <= self.n_arms <= 8:
            raise TdofError(f"--arm-positions must be in 1..8, got {self.n_arms}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise TdofError(f"image size {self.width}x{self.height} out of range (16..4096)")
        if not self.phases or any(p not in PHASES for p in self.phases):
            raise TdofError(f"phases must be taken from {PHASES}, got {self.phases}")
        try:
            self.sensor.validate()
        except ValueError as e:
            raise TdofError(str(e)) from None
        return self


def build_session_info(cfg: SimSessionConfig) -> SessionInfo:
    """The session.json content of a simulated session (pure: no rendering)."""
    scene = get_scene(cfg.scene_id, cfg.layout.table_radius)
    cam = oakd_camera(cfg.width, cfg.height, cfg.depth_scale)
    arms = [ArmPosition(q=q, T_base_tcp=T) for q, T in cfg.layout.arm_positions(cfg.n_arms)]
    objects = [{"obj_id": p.obj_id, "name": get_object(p.obj_id).name, "slot": i}
               for i, p in enumerate(scene.placements)]
    extra = {
        "rig": "sim",
        "sim": {
            "seed": cfg.seed, "sticker": scene.sticker,
            "sensor": dataclasses.asdict(cfg.sensor), "glass": dataclasses.asdict(cfg.glass),
            "table_centre_base_mm": list(cfg.layout.table_centre), "table_radius_mm": cfg.layout.table_radius,
        },
    }
    return SessionInfo(scene_id=cfg.scene_id, objects=objects, camera=cam, arm_positions=arms,
                       T_tcp_cam=cfg.layout.T_tcp_cam, turntable={"step_deg": cfg.step_deg, "steps": cfg.steps,
                                                                  "direction": "ccw"},
                       phases=tuple(cfg.phases), extra=extra)


def make_renderer(cfg: SimSessionConfig, info: SessionInfo) -> SimRenderer:
    scene = get_scene(cfg.scene_id, cfg.layout.table_radius)
    T_base_cams = [info.T_base_cam(a) for a in range(info.n_arms)]
    return SimRenderer(scene, info.camera, cfg.layout, T_base_cams, cfg.sensor, cfg.glass, cfg.seed)


def _same_session(a: SessionInfo, b: SessionInfo) -> bool:
    da, db = a.to_dict(), b.to_dict()
    return da == db


def simulate_session(cfg: SimSessionConfig, out_dir: str | Path, truth: bool = True,
                     show_progress: bool = True) -> Path:
    """Render the session ``cfg`` into ``out_dir`` (resuming a partial one). Returns the folder."""
    cfg.validate()
    out = Path(out_dir)
    info = build_session_info(cfg)
    if (out / "session.json").exists():
        existing = read_session(out)
        if not _same_session(existing, info):
            raise TdofError("holds a different session (other scene or settings); choose another --out",
                            out / "session.json")
    elif out.exists() and any(out.iterdir()):
        raise TdofError("folder is not empty and holds no session.json; choose another --out", out)
    else:
        write_session(out, info)
    session = RawSession.open(out)
    renderer = make_renderer(cfg, info)
    truth_writer = BopSceneWriter(out / "truth") if truth else None
    if truth:
        export_models(out / "truth" / "models", sorted(set(info_obj["obj_id"] for info_obj in info.objects)))
    done_truth = _truth_done(out / "truth") if truth else set()
    n_total = len(cfg.phases) * cfg.n_arms * cfg.steps
    with progress(show_progress) as bar:
        task = bar.add_task(f"simulating {cfg.scene_id}", total=n_total)
        for phase in cfg.phases:
            for arm in range(cfg.n_arms):
                for step in range(cfg.steps):
                    im_id = arm * cfg.steps + step
                    need_frame = not session.has_frame(phase, arm, step)
                    need_truth = truth and phase == "transparent" and im_id not in done_truth
                    if need_frame or need_truth:
                        angle = step * cfg.step_deg
                        frame = renderer.render(arm, step, angle, phase)
                        if need_truth:
                            _add_truth(truth_writer, renderer, frame, info, arm, angle, im_id)
                        if need_frame:
                            write_frame(out, info, phase, arm, step, frame.rgb, frame.depth,
                                        extra={"arm_q": info.arm_positions[arm].q.tolist()})
                    bar.advance(task)
                if truth_writer is not None:
                    truth_writer.flush()
    return out


def _truth_done(truth_dir: Path) -> set[int]:
    f = truth_dir / "scene_gt.json"
    if not f.exists():
        return set()
    from tdof20.formats import read_json

    return {int(k) for k in read_json(f)}


def _add_truth(writer: BopSceneWriter, renderer: SimRenderer, frame, info: SessionInfo, arm: int,
               angle: float, im_id: int) -> None:
    scene = renderer.scene
    poses = frame.poses
    full = renderer.full_masks(poses)
    visib = [frame.label == i for i in range(len(poses))]
    T_cam_table = invert(info.T_base_cam(arm)) @ renderer.layout.T_base_table(angle)
    writer.add_frame(im_id, info.camera.K, info.camera.depth_scale,
                     [(p.obj_id, T[:3, :3], T[:3, 3]) for p, T in zip(scene.placements, poses)],
                     full, visib, depth=info.camera.mm_to_depth(frame.depth_true), T_w2c=T_cam_table)
