"""Pinhole camera: intrinsics, depth units, back-projection and projection.

Pixel (u, v) has its centre at integer coordinates; u along the width, v along the height.
Depth images hold ``z`` (along the optical axis) in units of ``depth_scale`` mm; 0 = no depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """K (3,3) in pixels, image size, and ``depth_scale`` millimetres per depth unit."""

    K: np.ndarray
    width: int
    height: int
    depth_scale: float = 1.0
    _grid: dict = field(default_factory=dict, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=float).reshape(3, 3)
        object.__setattr__(self, "K", K)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.depth_scale > 0):
            raise ValueError(f"depth_scale must be > 0 mm per unit, got {self.depth_scale}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1:
            raise ValueError("K must have positive focal lengths and K[2,2] == 1")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PinholeCamera):
            return NotImplemented
        return (self.width, self.height, self.depth_scale) == (other.width, other.height, other.depth_scale) \
            and bool(np.array_equal(self.K, other.K))

    def __hash__(self) -> int:
        return hash((self.width, self.height, self.depth_scale, tuple(np.round(self.K.reshape(-1), 9))))

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, depth_scale: float = 1.0) -> "PinholeCamera":
        f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
        return cls(K, width, height, depth_scale)

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same camera resampled to another image size (pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return PinholeCamera(K, width, height, self.depth_scale)

    def to_dict(self) -> dict:
        return {"K": [float(x) for x in self.K.reshape(-1)], "width": int(self.width),
                "height": int(self.height), "depth_scale": float(self.depth_scale)}

    @classmethod
    def from_dict(cls, d: dict) -> "PinholeCamera":
        return cls(np.asarray(d["K"], dtype=float).reshape(3, 3), int(d["width"]), int(d["height"]),
                   float(d.get("depth_scale", 1.0)))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    # --- depth units ----------------------------------------------------------------------
    def depth_to_mm(self, depth: np.ndarray) -> np.ndarray:
        """Raw depth image (H,W) in units -> float32 millimetres (0 stays 0)."""
        return np.asarray(depth, dtype=np.float32) * np.float32(self.depth_scale)

    def mm_to_depth(self, z_mm: np.ndarray) -> np.ndarray:
        """Millimetres (H,W) -> uint16 depth units, rounded; NaN, <= 0 and overflow become 0."""
        units = np.asarray(np.rint(np.asarray(z_mm, dtype=np.float32) * np.float32(1.0 / self.depth_scale)))
        bad = ~((units > 0) & (units <= 65535))  # also catches NaN
        units[bad] = 0
        return units.astype(np.uint16)

    # --- rays and back-projection ---------------------------------------------------------
    def pixel_rays(self) -> np.ndarray:
        """(H,W,3) float32 rays with z = 1 through every pixel centre, in the camera frame."""
        key = "rays"
        if key not in self._grid:
            u = (np.arange(self.width, dtype=np.float64) - self.cx) / self.fx
            v = (np.arange(self.height, dtype=np.float64) - self.cy) / self.fy
            rays = np.empty((self.height, self.width, 3), dtype=np.float32)
            rays[..., 0] = u[None, :]
            rays[..., 1] = v[:, None]
            rays[..., 2] = 1.0
            rays.setflags(write=False)
            self._grid[key] = rays
        return self._grid[key]

    def backproject(self, depth_mm: np.ndarray) -> np.ndarray:
        """Depth in mm (H,W) -> organised XYZ map (H,W,3) float32 in the camera frame; 0 where no depth."""
        z = np.asarray(depth_mm, dtype=np.float32)
        if z.shape != (self.height, self.width):
            raise ValueError(f"depth is {z.shape}, camera is {(self.height, self.width)}")
        return self.pixel_rays() * z[..., None]

    def to_points(self, depth_mm: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth in mm (H,W) -> (points (N,3), pixel indices (N,2) as (v, u)) of valid pixels."""
        z = np.asarray(depth_mm, dtype=np.float32)
        valid = z > 0
        if mask is not None:
            valid &= np.asarray(mask, dtype=bool)
        v, u = np.nonzero(valid)
        pts = self.pixel_rays()[v, u] * z[v, u, None]
        return pts, np.stack([v, u], axis=1)

    # --- projection -----------------------------------------------------------------------
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (N,3) -> (uv (N,2) float pixels, z (N,) mm). Points with z<=0 give NaN uv."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p[:, :2] / z[:, None]) * [self.fx, self.fy] + [self.cx, self.cy]
        uv[z <= 0] = np.nan
        return uv, z

    def visible(self, uv: np.ndarray, z: np.ndarray, depth_mm: np.ndarray | None = None,
                tol_mm: float = 5.0) -> np.ndarray:
        """Which projected points (uv (N,2), z (N,)) are visible: in front, inside the image and,
        when a depth image (mm) is given, not behind its surface by more than ``tol_mm``
        (pixels without depth do not occlude)."""
        uv = np.asarray(uv, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ui = np.rint(uv[:, 0])
            vi = np.rint(uv[:, 1])
            ok = (z > 0) & (ui >= 0) & (ui < self.width) & (vi >= 0) & (vi < self.height)
        if depth_mm is not None and ok.any():
            d = np.asarray(depth_mm, dtype=np.float32)[vi[ok].astype(int), ui[ok].astype(int)]
            ok[np.flatnonzero(ok)] = (d <= 0) | (z[ok] <= d + tol_mm)
        return ok
