"""Surface sampling of triangle meshes and farthest point sampling of point sets."""

from __future__ import annotations

import numpy as np


def farthest_point_sampling(points: np.ndarray, k: int, first: np.ndarray | None = None) -> np.ndarray:
    """Pick ``k`` points spread over ``points`` (N,3) -> (k,3).

    With ``first`` (3,) given (e.g. the object's centre), it is the first returned point and the
    other k-1 are drawn from ``points``, each the farthest from those already chosen. Without it,
    the first pick is the point farthest from the centroid. Deterministic.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if k < 1:
        raise ValueError("k must be >= 1")
    n_from_points = k - 1 if first is not None else k
    if n_from_points > len(pts):
        raise ValueError(f"cannot pick {n_from_points} points from {len(pts)}")
    chosen = []
    if first is not None:
        seed = np.asarray(first, dtype=np.float64).reshape(3)
    else:
        seed = pts.mean(axis=0)
    dist = np.linalg.norm(pts - seed, axis=1)
    if first is not None:
        chosen.append(seed)
    for _ in range(n_from_points):
        i = int(np.argmax(dist))
        chosen.append(pts[i])
        dist = np.minimum(dist, np.linalg.norm(pts - pts[i], axis=1))
    return np.stack(chosen)


def sample_mesh_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Monte-Carlo area-uniform surface samples (n,3) of a triangle mesh, deterministic in seed."""
    V = np.asarray(vertices, dtype=np.float64)
    tri = V[np.asarray(faces)]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    cum = np.cumsum(area)
    rng = np.random.default_rng(seed)
    idx = np.searchsorted(cum, rng.random(int(n)) * cum[-1], side="right")
    idx = np.minimum(idx, len(area) - 1)
    u, v = rng.random((2, int(n)))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    return a[idx] + u[:, None] * (b[idx] - a[idx]) + v[:, None] * (c[idx] - a[idx])
