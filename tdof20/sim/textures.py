"""Procedural textures: the turntable stickers and the materials of the static room.

A sticker is an RGB image (float32 in [0, 1]) covering the square [-R, R]^2 of the table frame;
the renderer looks it up with ``cv2.remap`` at the rotated table coordinates of each pixel.
Room materials are functions of world points, evaluated once per arm position.
"""

from __future__ import annotations

import cv2
import numpy as np

STICKERS = ("checker", "stripes", "dots", "rings", "marble", "mosaic", "camouflage", "grid")


def _palette(rng: np.random.Generator, n: int) -> np.ndarray:
    """n distinct, moderately saturated colours (float32 RGB in [0,1])."""
    hues = (rng.uniform(0, 1) + np.arange(n) / n + rng.uniform(-0.05, 0.05, n)) % 1.0
    sat = rng.uniform(0.35, 0.8, n)
    val = rng.uniform(0.45, 0.95, n)
    hsv = np.stack([hues * 180, sat * 255, val * 255], axis=1).astype(np.uint8)[None]
    return (cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0] / 255.0).astype(np.float32)


def value_noise(shape: tuple[int, int], rng: np.random.Generator, octaves: int = 4, base: int = 4) -> np.ndarray:
    """Smooth fractal noise in [0, 1] of the given (H, W) shape, float32."""
    h, w = shape
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = base * (2 ** o)
        grid = rng.uniform(0, 1, (cells + 1, cells + 1)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-6)


def make_sticker(name: str, seed: int, radius_mm: float, size_px: int = 1024) -> tuple[np.ndarray, float]:
    """Render sticker ``name`` -> (image (size,size,3) float32 RGB, mm per pixel).

    Pixel (row i, col j) covers table point x = -R + (j + 0.5) * s, y = R - (i + 0.5) * s.
    """
    if name not in STICKERS:
        raise ValueError(f"unknown sticker '{name}' (valid: {', '.join(STICKERS)})")
    rng = np.random.default_rng(seed)
    s = 2 * radius_mm / size_px
    c = (np.arange(size_px) + 0.5) * s - radius_mm
    x, y = np.meshgrid(c, -c)
    pal = _palette(rng, 5)
    if name == "checker":
        sq = rng.uniform(18, 35)
        idx = ((np.floor(x / sq) + np.floor(y / sq)) % 2).astype(int)
        img = pal[idx]
    elif name == "stripes":
        a = rng.uniform(0, np.pi)
        w = rng.uniform(10, 25)
        u = x * np.cos(a) + y * np.sin(a)
        img = pal[(np.floor(u / w) % 3).astype(int)]
    elif name == "dots":
        pitch = rng.uniform(25, 40)
        rad = pitch * rng.uniform(0.2, 0.4)
        gx, gy = (x / pitch) % 1 - 0.5, (y / pitch) % 1 - 0.5
        inside = np.hypot(gx, gy) * pitch < rad
        img = np.where(inside[..., None], pal[1], pal[0])
    elif name == "rings":
        w = rng.uniform(12, 22)
        r = np.hypot(x, y + rng.uniform(-40, 40))
        img = pal[(np.floor(r / w) % 4).astype(int)]
    elif name == "marble":
        n = value_noise(x.shape, rng, octaves=5)
        v = 0.5 + 0.5 * np.sin(x / 15.0 + 8.0 * n)
        img = pal[0] * v[..., None] + pal[1] * (1 - v[..., None])
    elif name == "mosaic":
        from scipy.spatial import cKDTree

        seeds = rng.uniform(-radius_mm, radius_mm, (160, 2))
        small = 256
        cs = (np.arange(small) + 0.5) * (2 * radius_mm / small) - radius_mm
        sx, sy = np.meshgrid(cs, -cs)
        _, lab = cKDTree(seeds).query(np.stack([sx.ravel(), sy.ravel()], 1))
        colours = _palette(rng, 7)[rng.integers(0, 7, len(seeds))]
        img = cv2.resize(colours[lab].reshape(small, small, 3), (size_px, size_px), interpolation=cv2.INTER_NEAREST)
    elif name == "camouflage":
        n = value_noise(x.shape, rng, octaves=4, base=5)
        img = pal[np.clip((n * 4).astype(int), 0, 3)]
    else:  # grid
        pitch = rng.uniform(20, 30)
        line = (np.minimum(x % pitch, y % pitch) < 2.0)
        img = np.where(line[..., None], pal[0] * 0.3, pal[1])
    img = np.asarray(img, np.float32)
    # a little print grain so flat areas are not perfectly flat
    grain = value_noise(x.shape, rng, octaves=2, base=64)[..., None]
    img = np.clip(img * (0.92 + 0.16 * grain), 0, 1).astype(np.float32)
    return img, s


def room_albedo(material: str, points: np.ndarray, rng_seed: int = 7) -> np.ndarray:
    """Albedo (N,3) float32 of a room material at world points (N,3) mm."""
    p = np.asarray(points, np.float64)
    n = len(p)
    if material == "floor":
        tile = 300.0
        gx, gy = p[:, 0] % tile, p[:, 1] % tile
        grout = (np.minimum(gx, gy) < 6) | (np.maximum(gx, gy) > tile - 6)
        checker = ((np.floor(p[:, 0] / tile) + np.floor(p[:, 1] / tile)) % 2)[:, None]
        base = np.where(checker > 0, [0.62, 0.60, 0.57], [0.55, 0.53, 0.50])
        return np.where(grout[:, None], [0.35, 0.35, 0.35], base).astype(np.float32)
    if material == "wall":
        # soft blotches plus a row of posters on the far wall
        w = 0.80 + 0.06 * np.sin(p[:, 1] / 180.0) * np.cos(p[:, 2] / 140.0)
        col = np.stack([w, w * 0.98, w * 0.93], 1)
        poster = (np.abs(p[:, 1] % 700 - 350) < 220) & (p[:, 2] > -350) & (p[:, 2] < 250) & (p[:, 0] > 1900)
        stripes = ((np.floor(p[:, 1] / 45) + np.floor(p[:, 2] / 60)) % 3)
        pc = np.array([[0.85, 0.35, 0.25], [0.25, 0.45, 0.80], [0.95, 0.85, 0.30]])[stripes.astype(int)]
        return np.where(poster[:, None], pc, col).astype(np.float32)
    if material == "wood":
        grain = 0.5 + 0.5 * np.sin(p[:, 0] / 9.0 + 3 * np.sin(p[:, 2] / 70.0))
        return (np.array([0.55, 0.38, 0.22]) * (0.8 + 0.25 * grain)[:, None]).astype(np.float32)
    if material == "dark":
        return np.full((n, 3), 0.18, np.float32)
    if material == "metal":
        return np.full((n, 3), 0.55, np.float32)
    raise ValueError(f"unknown room material '{material}'")
