"""Rigid transforms as 4x4 homogeneous matrices (float64, millimetres, radians inside).

A transform ``T_a_b`` maps points from frame b to frame a: ``x_a = T_a_b @ x_b``.
"""

from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3,3) rotation and (3,) translation -> (4,4) transform."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def split_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4,4) transform -> (R (3,3), t (3,))."""
    T = np.asarray(T, dtype=float)
    return T[:3, :3].copy(), T[:3, 3].copy()


def compose(*Ts: np.ndarray) -> np.ndarray:
    """compose(A, B, C) = A @ B @ C (apply C first)."""
    out = np.eye(4)
    for T in Ts:
        out = out @ np.asarray(T, dtype=float)
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4,4) transform, or a stack (..., 4, 4), without a general inverse."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply (4,4) T to (..., 3) points."""
    T = np.asarray(T, dtype=float)
    points = np.asarray(points, dtype=float)
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` radians about the unit direction ``axis`` -> (3,3)."""
    axis = np.asarray(axis, dtype=float).reshape(3)
    n = np.linalg.norm(axis)
    if n == 0:
        raise ValueError("rotation axis has zero length")
    k = axis / n
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * (Kx @ Kx)


def rotation_about_axis(axis: np.ndarray, angle: float, point: np.ndarray | None = None) -> np.ndarray:
    """(4,4) rotation by ``angle`` radians about the line through ``point`` along ``axis``."""
    R = rotation_matrix(axis, angle)
    p = np.zeros(3) if point is None else np.asarray(point, dtype=float).reshape(3)
    return make_T(R, p - R @ p)


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Geodesic angle in radians between two rotations (3,3)."""
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (det +1) to a (3,3) matrix, by SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera pose T_world_cam (OpenCV: x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)
