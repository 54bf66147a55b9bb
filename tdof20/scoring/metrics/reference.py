"""Reference pose errors: tiny pure functions (bop_toolkit ``pose_error.py`` style, batched over poses).

Conventions: lengths in mm, poses map model -> camera (``x = R @ p + t``), ``pts`` (N,3) are the
model points (BOP: the vertices of models_eval/, else of models/), ``K`` (3,3) the intrinsics.

* ``add``    mean_i |(R_e p_i + t_e) - (R_g p_i + t_g)|                    (corresponding points)
* ``adds``   mean_i min_j |(R_g p_i + t_g) - (R_e p_j + t_e)|              (closest point, ADD-S:
  from each ground-truth-posed point to the nearest estimate-posed point; a KD-tree query)
* ``proj2d`` mean_i |pi(K (R_e p_i + t_e)) - pi(K (R_g p_i + t_g))|  pixels (pi = perspective
  division); a point at depth <= 0 in either pose makes the error infinite.

``add`` / ``adds`` / ``proj2d`` take one pose; ``add_batch`` / ``adds_batch`` / ``proj2d_batch``
take (B,3,3) rotations and (B,3) translations of one object and return (B,) errors.

The input checks (``_poses``, ``_pts``, ``_Ks``) and the chunking of (pose, point) work
(``_chunks``) are shared by the package's other modules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy.spatial is imported on first use: importing the scorer (as the CLI does) stays light
    from scipy.spatial import cKDTree

_CHUNK = 1 << 21  # elements (poses x points) per vectorised chunk: ~50 MB of float64 temporaries


def _poses(R, t) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.ndim == 2:
        R = R[None]
    if t.ndim == 1:
        t = t[None]
    if R.shape[1:] != (3, 3) or t.shape[1:] != (3,) or len(R) != len(t):
        raise ValueError(f"poses must be (B,3,3) rotations and (B,3) translations, got {R.shape} and {t.shape}")
    return R, t


def _pts(pts) -> np.ndarray:
    P = np.asarray(pts, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise ValueError(f"model points must be a non-empty (N,3) array, got {P.shape}")
    return P


def _chunks(n_poses: int, n_pts: int):
    step = max(1, _CHUNK // max(1, n_pts))
    for s in range(0, n_poses, step):
        yield slice(s, min(n_poses, s + step))


def add_batch(R_est, t_est, R_gt, t_gt, pts) -> np.ndarray:
    """ADD of B poses of one object: (B,) mean distance of corresponding model points (mm)."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    P = _pts(pts)
    D, dt = Re - Rg, te - tg
    out = np.empty(len(Re))
    for s in _chunks(len(Re), len(P)):
        X = np.einsum("nj,bij->bni", P, D[s]) + dt[s, None, :]
        out[s] = np.sqrt(np.einsum("bni,bni->bn", X, X)).mean(axis=1)
    return out


def add(R_est, t_est, R_gt, t_gt, pts) -> float:
    """ADD of one pose (mm)."""
    return float(add_batch(R_est, t_est, R_gt, t_gt, pts)[0])


def relative_transform(R_est, t_est, R_gt, t_gt) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with A = R_e^T R_g, b = R_e^T (t_g - t_e): a ground-truth-posed model point, seen in
    the estimate's model frame, is A p + b (so ADD-S = mean_i dist(A p_i + b, pts))."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    A = np.einsum("bji,bjk->bik", Re, Rg)
    b = np.einsum("bji,bj->bi", Re, tg - te)
    return A, b


def adds_batch(R_est, t_est, R_gt, t_gt, pts, tree: cKDTree | None = None) -> np.ndarray:
    """ADD-S of B poses of one object: (B,) mean distance from each ground-truth-posed point to
    the nearest estimate-posed point (mm), by exact KD-tree queries (``tree`` on ``pts``)."""
    P = _pts(pts)
    A, b = relative_transform(R_est, t_est, R_gt, t_gt)
    if tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(P)
    out = np.empty(len(A))
    for s in _chunks(len(A), len(P)):
        Q = np.einsum("nj,bij->bni", P, A[s]) + b[s, None, :]
        d, _ = tree.query(Q.reshape(-1, 3), workers=-1)
        out[s] = d.reshape(len(Q), len(P)).mean(axis=1)
    return out


def adds(R_est, t_est, R_gt, t_gt, pts, tree: cKDTree | None = None) -> float:
    """ADD-S of one pose (mm)."""
    return float(adds_batch(R_est, t_est, R_gt, t_gt, pts, tree)[0])


def _Ks(K, n: int) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (n, 3, 3))
    if K.shape != (n, 3, 3):
        raise ValueError(f"K must be (3,3) or ({n},3,3), got {K.shape}")
    return K


def proj2d_batch(R_est, t_est, R_gt, t_gt, pts, K) -> np.ndarray:
    """2D projection error of B poses: (B,) mean pixel distance between the model points
    projected with the estimated and the ground-truth pose (inf if a point has depth <= 0)."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    P = _pts(pts)
    Ks = _Ks(K, len(Re))
    out = np.empty(len(Re))
    for s in _chunks(len(Re), len(P)):
        uv = []
        for R, t in ((Re[s], te[s]), (Rg[s], tg[s])):
            Mr = np.einsum("bij,bjk->bik", Ks[s], R)
            X = np.einsum("nj,bij->bni", P, Mr) + np.einsum("bij,bj->bi", Ks[s], t)[:, None, :]
            z = X[..., 2]
            bad = z <= 0
            z = np.where(bad, 1.0, z)
            u = X[..., :2] / z[..., None]
            u[bad] = np.inf
            uv.append(u)
        with np.errstate(invalid="ignore"):
            d = np.sqrt(((uv[0] - uv[1]) ** 2).sum(-1))
        d[~np.isfinite(d)] = np.inf
        out[s] = d.mean(axis=1)
    return out


def proj2d(R_est, t_est, R_gt, t_gt, pts, K) -> float:
    """2D projection error of one pose (pixels)."""
    return float(proj2d_batch(R_est, t_est, R_gt, t_gt, pts, K)[0])
