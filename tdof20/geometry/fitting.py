"""Least-squares rigid (and similarity) fitting of corresponding point sets."""

from __future__ import annotations

import numpy as np


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
           with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Find R (3,3), t (3,), s minimising sum_i w_i |s R src_i + t - dst_i|^2 (Kabsch / Umeyama).

    src, dst: (N,3) corresponding points, N >= 3 not collinear; weights: (N,) >= 0.
    Returns (R, t, s) with det(R) = +1 and s = 1 unless ``with_scale``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"kabsch needs two (N,3) arrays of the same shape, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(w) != len(src) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("kabsch weights must be non-negative, one per point, not all zero")
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    cov = (xd * w[:, None]).T @ xs  # (3,3) = sum w d s^T
    U, S, Vt = np.linalg.svd(cov)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    s = 1.0
    if with_scale:
        var_s = float(w @ np.sum(xs * xs, axis=1))
        s = float(np.trace(np.diag(S) @ D) / var_s)
    t = mu_d - s * R @ mu_s
    return R, t, s
