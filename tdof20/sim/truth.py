"""The simulator's exact ground truth of a session, as a BOP scene in ``truth/``.

One image per frame of the transparent phase, ``im_id = arm * steps + step``: poses, full and
visible masks, the noise-free depth, and ``cam_R_w2c``/``cam_t_w2c`` with the turntable frame at
angle 0 as the world. The models go to ``truth/models``; ``truth/rig.json`` holds the rig as it
really was (the true hand-eye and camera poses, the direction and the physical table angle of
every frame of both phases, the clutter). Resumable: frames already written are kept.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats import BopSceneWriter, RawSession, read_json, read_png, read_scene, read_session, write_json
from tdof20.geometry import invert
from tdof20.objects import export_models
from tdof20.progress import progress
from tdof20.sim.lab import TableMotion
from tdof20.sim.render import SimRenderer

RIG_FILE = "rig.json"


def _flat(T) -> list[float]:
    return [float(v) for v in np.asarray(T, float).reshape(-1)]


def write_rig_truth(renderer: SimRenderer, out: Path, steps: int, step_deg: float, table: TableMotion,
                    rig: dict | None = None, phases=("transparent", "opaque")) -> Path:
    """``truth/rig.json``: the rig as it really was. ``table_angle_deg[phase][arm][step]`` is the
    physical angle (counter-clockwise from above) of every frame, ``T_base_cam`` the true camera
    pose per arm position (row-major 16 numbers, mm), ``T_tcp_cam`` the true mount and
    ``T_tcp_cam_recorded`` what session.json says (when the caller knows them)."""
    n_arms = len(renderer.T_base_cams)
    doc = {"direction": table.direction, "step_jitter_deg": table.jitter_deg,
           "table_angle_deg": {ph: [[table.actual(ph, a, k * step_deg) for k in range(steps)] for a in range(n_arms)]
                               for ph in phases},
           "T_base_cam": [_flat(T) for T in renderer.T_base_cams],
           "clutter": list(renderer.clutter)}
    for k, v in (rig or {}).items():
        doc[k] = _flat(v) if isinstance(v, np.ndarray) else v
    path = out / RIG_FILE
    write_json(path, doc, indent=None)
    return path


def write_truth(renderer: SimRenderer, session_dir: str | Path, steps: int, step_deg: float,
                show_progress: bool = True, table: TableMotion | None = None, rig: dict | None = None,
                phases=("transparent", "opaque")) -> Path:
    """Write (or complete) ``truth/`` of a simulated session. ``table``: how the table really
    moved (default: exactly as told, counter-clockwise); ``rig``: more of the true rig for
    rig.json (see :func:`write_rig_truth`)."""
    table = table or TableMotion()
    out = Path(session_dir) / "truth"
    info = read_session(session_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_rig_truth(renderer, out, steps, step_deg, table, rig, phases)
    gt_file = out / "scene_gt.json"
    done = {int(k) for k in read_json(gt_file)} if gt_file.exists() else set()
    obj_ids = sorted({p.obj_id for p in renderer.scene.placements})
    if not (out / "models" / "models_info.json").exists():
        export_models(out / "models", obj_ids)
    n_arms = len(renderer.T_base_cams)
    todo = [(a, k) for a in range(n_arms) for k in range(steps) if a * steps + k not in done]
    cam = info.camera
    with BopSceneWriter(out) as writer, progress(show_progress and bool(todo)) as bar:
        task = bar.add_task("truth", total=len(todo))
        for i, (arm, step) in enumerate(todo):
            angle = table.actual("transparent", arm, step * step_deg)
            f = renderer.truth(arm, angle)
            full = renderer.full_masks(f.poses)
            visib = [f.label == g for g in range(len(f.poses))]
            T_cam_table = invert(renderer.T_base_cams[arm]) @ renderer.layout.T_base_table(angle)
            writer.add_frame(arm * steps + step, cam.K, cam.depth_scale,
                             [(p.obj_id, T[:3, :3], T[:3, 3]) for p, T in zip(renderer.scene.placements, f.poses)],
                             full, visib, depth=cam.mm_to_depth(f.depth_true), T_w2c=T_cam_table)
            bar.advance(task)
            if (i + 1) % 200 == 0:
                writer.flush()
    return out


def oracle_scene(session_dir: str | Path, out_dir: str | Path, show_progress: bool = True) -> Path:
    """An annotated scene made from the simulator's exact truth — the labels a perfect annotator
    would write — in the format ``tdof20 annotate`` writes: a BOP scene with rgb/ and depth/ of
    the transparent phase, depth_opaque/ (the opaque twins' depth as recorded), depth_restored/
    (the exact depth of the scene with the objects opaque), masks, the three JSON files, the
    models in models/, and scene_info.json. It is the reference an annotation is measured against,
    and the way to build datasets before (or without) annotating."""
    session = RawSession.open(session_dir)
    if session.truth_dir is None or not (session.truth_dir / "scene_gt.json").exists():
        raise TdofError("has no truth/ (only simulated sessions do)", session_dir)
    truth = read_scene(session.truth_dir)
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not (out / "scene_info.json").exists():
        raise TdofError("folder is not empty and holds no scene; choose another --out", out)
    steps = session.info.steps
    with progress(show_progress) as bar:
        task = bar.add_task("oracle labels", total=len(truth.im_ids()))
        for im_id in truth.im_ids():
            arm, step = divmod(im_id, steps)
            name = f"{im_id:06d}.png"
            pairs = [(session.path / session.entry("transparent", arm, step).rgb, out / "rgb" / name),
                     (session.path / session.entry("transparent", arm, step).depth, out / "depth" / name),
                     (session.truth_dir / "depth" / name, out / "depth_restored" / name)]
            if session.has_frame("opaque", arm, step):
                pairs.append((session.path / session.entry("opaque", arm, step).depth, out / "depth_opaque" / name))
            for g in range(len(truth.gt[im_id])):
                for kind in ("mask", "mask_visib"):
                    m = f"{im_id:06d}_{g:06d}.png"
                    pairs.append((session.truth_dir / kind / m, out / kind / m))
            for src, dst in pairs:
                if src.parent.parent == session.truth_dir:  # the truth's own PNGs: no checksum guards them
                    read_png(src, "depth" if src.parent.name == "depth" else "mask")
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, dst)
            bar.advance(task)
    for f in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        shutil.copyfile(session.truth_dir / f, out / f)
    if (out / "models").exists():
        shutil.rmtree(out / "models")
    shutil.copytree(session.truth_dir / "models", out / "models")
    write_json(out / "scene_info.json", {
        "scene_id": session.info.scene_id, "n_arms": session.info.n_arms, "steps": steps,
        "step_deg": session.info.step_deg, "labels": "oracle (simulator truth)",
        "source_session": str(Path(session_dir).resolve())})
    return out
