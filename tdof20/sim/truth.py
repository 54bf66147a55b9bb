"""The simulator's exact ground truth of a session, as a BOP scene in ``truth/``.

One image per frame of the transparent phase, ``im_id = arm * steps + step``: poses, full and
visible masks, the noise-free depth, and ``cam_R_w2c``/``cam_t_w2c`` with the turntable frame at
angle 0 as the world. The models go to ``truth/models``. Resumable: frames already written are kept.
"""

from __future__ import annotations

from pathlib import Path

from tdof20.formats import BopSceneWriter, read_json, read_session
from tdof20.geometry import invert
from tdof20.objects import export_models
from tdof20.progress import progress
from tdof20.sim.render import SimRenderer


def write_truth(renderer: SimRenderer, session_dir: str | Path, steps: int, step_deg: float,
                show_progress: bool = True) -> Path:
    out = Path(session_dir) / "truth"
    info = read_session(session_dir)
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
            angle = step * step_deg
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
