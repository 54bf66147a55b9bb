"""Pictures made by the simulator: the object catalog, and a few frames of a scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats import write_png
from tdof20.geometry import transform_points
from tdof20.objects import all_objects
from tdof20.sim.render import SimRenderer
from tdof20.sim.rig import RigLayout, oakd_camera
from tdof20.sim.scenes import SceneSpec, _place
from tdof20.viz import contact_sheet, depth_to_colour, overlay_masks


def _crop_square(img: np.ndarray, uv: np.ndarray, margin: float = 0.12) -> np.ndarray:
    lo, hi = uv.min(0), uv.max(0)
    c = (lo + hi) / 2
    half = max(hi - lo) * (0.5 + margin)
    h, w = img.shape[:2]
    x0, y0 = int(max(c[0] - half, 0)), int(max(c[1] - half, 0))
    x1, y1 = int(min(c[0] + half, w)), int(min(c[1] + half, h))
    return img[y0:y1, x0:x1]


def catalog_picture(tile: int = 240) -> np.ndarray:
    """All 20 objects, each as glass (on a checker sticker) and as its opaque twin; handles to
    the right, spouts to the left."""
    layout = RigLayout()
    cam = oakd_camera(960, 720)
    T_cam = layout.camera_target(30.0)
    tiles, labels = [], []
    for obj in all_objects():
        scene = SceneSpec(f"single/{obj.name}", (_place(obj.obj_id, (0.0, 0.0), np.radians(90)),),
                          "checker", 11)
        r = SimRenderer(scene, cam, layout, [T_cam])
        pose = r.poses(0, 0.0)[0]
        uv, _ = cam.project(transform_points(pose, obj.vertices))
        for phase in ("transparent", "opaque"):
            f = r.render(0, 0.0, phase)
            tiles.append(_crop_square(f.rgb, uv))
            labels.append(f"{obj.obj_id} {obj.name}" if phase == "transparent" else "opaque twin")
    return contact_sheet(tiles, labels, cols=8, tile_width=tile)


def render_frames(renderer: SimRenderer, out_dir: str | Path, arm: int, angles: list[float]) -> Path:
    """Render both phases at the given table angles into ``out_dir`` (PNGs + contact_sheet.png)."""
    r = renderer
    if not 0 <= arm < len(r.T_base_cams):
        raise TdofError(f"--arm must be in 0..{len(r.T_base_cams) - 1}, got {arm}")
    out = Path(out_dir)
    tiles, labels = [], []
    for a in angles:
        for phase in ("transparent", "opaque"):
            f = r.render(arm, a, phase)
            stem = f"arm{arm}_{a:07.2f}deg_{phase}"
            write_png(out / f"{stem}_rgb.png", f.rgb)
            write_png(out / f"{stem}_depth.png", f.depth)
            z = r.camera.depth_to_mm(f.depth)
            tiles += [f.rgb, depth_to_colour(z, 250, 1500)]
            labels += [f"{phase} {a:g} deg", f"{phase} depth"]
        masks = [f.label == i for i in range(len(f.poses))]
        tiles.append(overlay_masks(f.rgb, masks))
        labels.append("visible masks")
    sheet_path = out / "contact_sheet.png"
    write_png(sheet_path, contact_sheet(tiles, labels, cols=5, tile_width=256))
    return sheet_path
