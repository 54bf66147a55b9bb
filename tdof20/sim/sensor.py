"""Sensor models of the simulated OAK-D: active stereo depth on opaque and on glass surfaces.

All functions are vectorised over whole images; depth is float32 millimetres with 0 = no depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """Noise levels of the simulated camera (all options; defaults resemble an OAK-D at 640x480)."""

    baseline_mm: float = 75.0          # stereo baseline
    disparity_sigma_px: float = 0.08   # sub-pixel disparity noise: sigma_z = z^2 * sigma_d / (f * b)
    min_depth_mm: float = 200.0
    max_depth_mm: float = 3500.0
    edge_jump: float = 0.03            # relative depth jump that marks a discontinuity
    edge_dropout: float = 0.6          # probability that a discontinuity pixel has no depth
    glass_missing: float = 0.65        # fraction of glass pixels without depth
    glass_behind: float = 0.25         # fraction of glass pixels that see what lies behind
    glass_sigma_mm: float = 6.0        # noise of glass pixels that do return the glass surface
    rim_px: int = 3                    # width of the band of flying pixels at glass silhouettes
    flying_fraction: float = 0.5       # fraction of rim pixels that fly between glass and background
    rgb_sigma: float = 2.0             # colour noise, 8-bit levels
    depth_bias: float = 1.0            # reported / true depth: a camera whose depth reads 2 % long is 1.02

    def validate(self) -> "SensorModel":
        for name in ("glass_missing", "glass_behind", "edge_dropout", "flying_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"sensor.{name} must be in [0, 1], got {v}")
        if self.glass_missing + self.glass_behind > 1.0:
            raise ValueError("sensor.glass_missing + sensor.glass_behind must not exceed 1")
        for name in ("baseline_mm", "min_depth_mm", "max_depth_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"sensor.{name} must be > 0")
        if not 0.8 <= self.depth_bias <= 1.25:
            raise ValueError(f"sensor.depth_bias must be in [0.8, 1.25] (reported / true depth), got {self.depth_bias}")
        for name in ("disparity_sigma_px", "glass_sigma_mm", "rgb_sigma"):
            if getattr(self, name) < 0:
                raise ValueError(f"sensor.{name} must be >= 0")
        return self

    def depth_sigma(self, z_mm: np.ndarray, f_px: float) -> np.ndarray:
        """Standard deviation of stereo depth (mm) at depth z (mm)."""
        return np.square(z_mm) * (self.disparity_sigma_px / (f_px * self.baseline_mm))


def smooth_field(shape: tuple[int, int], rng: np.random.Generator, cell_px: int = 12) -> np.ndarray:
    """Spatially correlated noise (H, W) float32: random values on a grid of ``cell_px`` cells,
    bicubically interpolated. Threshold it at quantiles to pick blobs covering given fractions."""
    h, w = shape
    gh, gw = max(2, h // cell_px + 2), max(2, w // cell_px + 2)
    grid = rng.random((gh, gw), dtype=np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def disparity_slack(z: np.ndarray, f_px: float, baseline_mm: float) -> np.ndarray:
    """g(x) = d(x) - x per row, with disparity d = f b / z; -inf where there is no depth."""
    valid = z > 0
    d = np.where(valid, f_px * baseline_mm / np.where(valid, z, 1.0), -np.inf).astype(np.float32)
    return d - np.arange(z.shape[1], dtype=np.float32)[None, :]


def stereo_occlusion(z: np.ndarray, f_px: float, baseline_mm: float, tol_px: float = 0.5,
                     tail: np.ndarray | None = None) -> np.ndarray:
    """Pixels that the second stereo camera cannot see (bool (H,W)).

    With disparity d(x) = f b / z, pixel x is hidden if some pixel x' > x on its row has
    d(x') - d(x) > x' - x: a row-wise reverse running maximum of g(x) = d(x) - x.
    ``tail`` (H,) is the maximum of g right of the last column when ``z`` holds only the left
    part of the rows (default: nothing there).
    """
    g = disparity_slack(z, f_px, baseline_mm)
    rmax = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]
    ahead = np.empty_like(g)
    ahead[:, :-1] = rmax[:, 1:]
    ahead[:, -1] = -np.inf if tail is None else tail
    return (z > 0) & (ahead > g + tol_px)


def depth_edges(z: np.ndarray, rel_jump: float) -> np.ndarray:
    """Pixels next to a depth discontinuity (relative jump > rel_jump to a 4-neighbour), bool (H,W)."""
    zf = z.astype(np.float32)
    big = np.float32(1e9)
    zz = np.where(zf > 0, zf, big)
    mx = cv2.dilate(zz, np.ones((3, 3), np.uint8))
    mn = cv2.erode(zz, np.ones((3, 3), np.uint8))
    return (zf > 0) & (mx < big) & ((mx - mn) > rel_jump * zf)


def stereo_holes(z: np.ndarray, f_px: float, model: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """(occluded, edges): the two geometric causes of stereo holes, bool (H,W) each."""
    return stereo_occlusion(z, f_px, model.baseline_mm), depth_edges(z, model.edge_jump)


def stereo_depth(z_true: np.ndarray, f_px: float, model: SensorModel, rng: np.random.Generator,
                 noise: np.ndarray | None = None, uniform: np.ndarray | None = None,
                 holes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """True depth (H,W) mm -> what an active stereo camera reports: noise growing with z^2,
    holes where the second camera is occluded and at discontinuities, range limits.
    ``noise`` (standard normal) and ``uniform`` ([0,1)) images may be passed in to save drawing
    them; ``holes`` = :func:`stereo_holes` of ``z_true`` when the caller has it already."""
    z = np.asarray(z_true, np.float32)
    if noise is None:
        noise = rng.standard_normal(z.shape, dtype=np.float32)
    if uniform is None:
        uniform = rng.random(z.shape, dtype=np.float32)
    occluded, edges = holes if holes is not None else stereo_holes(z, f_px, model)
    out = z + model.depth_sigma(z, f_px).astype(np.float32) * noise
    drop = occluded | (edges & (uniform < model.edge_dropout))
    drop |= (z < model.min_depth_mm) | (z > model.max_depth_mm)
    out[drop] = 0.0
    return out
