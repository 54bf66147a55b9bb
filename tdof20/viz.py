"""Pictures a person looks at: depth colouring, mask overlays and contact sheets (uint8 RGB)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_scene


def depth_to_colour(depth_mm: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Depth (H,W) mm -> (H,W,3) uint8 RGB with a perceptual colour map; no depth is black."""
    z = np.asarray(depth_mm, np.float32)
    valid = z > 0
    if vmin is None or vmax is None:
        vals = z[valid]
        lo, hi = (np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0))
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    t = np.clip((z - vmin) / max(vmax - vmin, 1e-6), 0, 1)
    col = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    col[~valid] = 0
    return np.ascontiguousarray(col)


# Kelly's colours of maximum contrast (less the greys), brightest first: neighbours in the list
# differ in hue, so the first few instances of a frame never share a colour family
_PALETTE = np.array([
    (255, 179, 0), (0, 125, 255), (255, 0, 104), (0, 200, 83), (166, 55, 255), (255, 104, 0), (0, 214, 214),
    (206, 162, 98), (255, 122, 92), (129, 112, 102), (193, 0, 32), (246, 118, 142), (0, 83, 138),
    (130, 200, 0), (83, 55, 122), (255, 142, 0), (179, 40, 81), (244, 200, 0), (255, 80, 200), (90, 200, 255),
], np.uint8)


def label_colours(n: int) -> np.ndarray:
    """n distinct bright colours (n,3) uint8 (a fixed palette of 20, then repeated)."""
    return _PALETTE[np.arange(n) % len(_PALETTE)]


def object_colour(obj_id: int) -> np.ndarray:
    """The colour (3,) uint8 of an object id (1..20), the same in every picture."""
    return _PALETTE[(int(obj_id) - 1) % len(_PALETTE)]


def overlay_masks(rgb: np.ndarray, masks: list[np.ndarray], alpha: float = 0.45, contours: bool = True) -> np.ndarray:
    """Tint each boolean mask (H,W) over an RGB image in its own colour, with its contour."""
    out = rgb.astype(np.float32).copy()
    cols = label_colours(max(len(masks), 1))
    for m, c in zip(masks, cols):
        m = np.asarray(m, bool)
        out[m] = (1 - alpha) * out[m] + alpha * c
    out = out.astype(np.uint8)
    if contours:
        for m, c in zip(masks, cols):
            cs, _ = cv2.findContours(np.asarray(m, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(out, cs, -1, tuple(int(x) for x in c), 1)
    return out


def put_label(img: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` in the top-left corner on a dark band (returns a copy)."""
    out = np.ascontiguousarray(img.copy())
    scale = max(0.35, img.shape[1] / 900)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(out, (0, 0), (tw + 6, th + base + 6), (0, 0, 0), -1)
    cv2.putText(out, text, (3, th + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def contact_sheet(tiles: list[np.ndarray], labels: list[str] | None = None, cols: int = 4,
                  tile_width: int = 320, gap: int = 4) -> np.ndarray:
    """Arrange RGB tiles (H,W,3 uint8, any sizes) in a grid, each resized to ``tile_width`` wide."""
    if not tiles:
        raise ValueError("contact_sheet needs at least one tile")
    rs = []
    for i, t in enumerate(tiles):
        t = np.asarray(t)
        if t.ndim == 2:
            t = np.repeat(t[..., None], 3, axis=2)
        h = int(round(t.shape[0] * tile_width / t.shape[1]))
        r = cv2.resize(t, (tile_width, h), interpolation=cv2.INTER_AREA)
        if labels is not None and i < len(labels) and labels[i]:
            r = put_label(r, labels[i])
        rs.append(r)
    th = max(r.shape[0] for r in rs)
    rows = (len(rs) + cols - 1) // cols
    ncols = min(cols, len(rs))
    sheet = np.full((rows * th + (rows + 1) * gap, ncols * tile_width + (ncols + 1) * gap, 3), 24, np.uint8)
    for i, r in enumerate(rs):
        y = gap + (i // cols) * (th + gap)
        x = gap + (i % cols) * (tile_width + gap)
        sheet[y:y + r.shape[0], x:x + tile_width] = r
    return sheet


def session_contact_sheet(session_dir, n_frames: int = 4, tile_width: int = 256) -> np.ndarray:
    """Contact sheet of a raw session: per frame the colour and depth of each phase, and the
    truth's visible masks when the session has truth/ (simulated sessions)."""
    s = RawSession.open(session_dir)
    info = s.info
    keys = [k for k in s.frames("transparent")] or [k for k in s.frames()]
    if not keys:
        raise TdofError("the session has no frames yet", Path(session_dir) / "journal.jsonl")
    pick = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, n_frames).round().astype(int))]
    truth = None
    if s.truth_dir is not None and (s.truth_dir / "scene_gt.json").exists():
        truth = read_scene(s.truth_dir)
    tiles, labels = [], []
    for _, arm, step in pick:
        rgb = None
        for phase in info.phases:
            if s.has_frame(phase, arm, step):
                rgb_p = s.load_rgb(phase, arm, step)
                rgb = rgb if rgb is not None else rgb_p
                tiles += [rgb_p, depth_to_colour(s.load_depth_mm(phase, arm, step), 250, 1500)]
            else:
                blank = np.zeros((info.camera.height, info.camera.width, 3), np.uint8)
                tiles += [blank, blank]
            labels += [f"{phase} arm {arm} step {step}", f"{phase} depth"]
        if truth is not None:
            im_id = arm * info.steps + step
            n = len(truth.gt.get(im_id, []))
            if n:
                masks = [truth.mask(im_id, g, visib=True) for g in range(n)]
                tiles.append(overlay_masks(rgb, masks))
                labels.append("truth visible masks")
    cols = 2 * len(info.phases) + (1 if truth is not None else 0)
    return contact_sheet(tiles, labels, cols=cols, tile_width=tile_width)
