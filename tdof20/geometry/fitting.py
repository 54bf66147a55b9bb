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


def plane_distance(P: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Signed distances of P (N,3) to the plane (4,), elementwise (no BLAS: the same bits on any
    number of threads)."""
    return P[:, 0] * plane[0] + P[:, 1] * plane[1] + P[:, 2] * plane[2] + plane[3]


def least_squares_plane(P: np.ndarray) -> np.ndarray | None:
    """The total-least-squares plane (4,) of P (N,3): through the centroid, normal along the
    smallest eigenvector of the scatter (sums written out: summation order fixed)."""
    c = P.mean(axis=0)
    Q = P - c
    xx, yy, zz = (Q[:, 0] ** 2).sum(), (Q[:, 1] ** 2).sum(), (Q[:, 2] ** 2).sum()
    xy, xz, yz = (Q[:, 0] * Q[:, 1]).sum(), (Q[:, 0] * Q[:, 2]).sum(), (Q[:, 1] * Q[:, 2]).sum()
    w, U = np.linalg.eigh(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))
    n = U[:, 0]
    if not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-12:
        return None
    n = n / np.linalg.norm(n)
    return np.r_[n, -(n @ c)]


def fit_plane(points: np.ndarray, dist_mm: float, iters: int = 1000, seed: int | tuple = 0,
              score_points: int = 20000, refine_iters: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """The dominant plane of ``points`` (N,3) -> (plane (4,) unit normal, d; inlier indices).

    RANSAC: ``iters`` triples drawn by numpy's generator seeded with ``seed`` (an int or a
    tuple of ints), each scored by its inliers (closer than ``dist_mm``) among at most
    ``score_points`` of the points (every k-th); the best (the first of equals) is refined by
    least squares on its inliers among all points, again and again until the inlier set stops
    changing. Deterministic for the same
    points in the same order; the refined plane is the centre of the band the best hypothesis
    found, not the hypothesis. The normal's sign is the caller's to choose. Fewer than 3
    points: a zero plane and no inliers."""
    P = np.asarray(points, np.float64)
    n = len(P)
    if n < 3:
        return np.zeros(4), np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    S = P[:: max(1, n // score_points)]
    idx = rng.integers(0, n, size=(iters, 3))
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    ok = length > 1e-9
    if not ok.any():
        return np.zeros(4), np.zeros(0, np.int64)
    nrm = nrm[ok] / length[ok, None]
    hyp = np.concatenate([nrm, -np.einsum("ij,ij->i", nrm, a[ok])[:, None]], axis=1)
    counts = np.empty(len(hyp), np.int64)
    for k in range(0, len(hyp), 64):
        h = hyp[k:k + 64]
        d = S[:, :1] * h[:, 0] + S[:, 1:2] * h[:, 1] + S[:, 2:3] * h[:, 2] + h[:, 3]
        counts[k:k + 64] = (np.abs(d) < dist_mm).sum(axis=0)
    plane = hyp[int(np.argmax(counts))]
    inl = np.flatnonzero(np.abs(plane_distance(P, plane)) < dist_mm)
    for _ in range(refine_iters):
        if len(inl) < 3:
            break
        refined = least_squares_plane(P[inl])
        if refined is None:
            break
        plane = refined
        new = np.flatnonzero(np.abs(plane_distance(P, plane)) < dist_mm)
        if np.array_equal(new, inl):
            break
        inl = new
    return plane, inl
