"""Pose-error metrics: tiny pure reference functions, and the fast kernels the scorer uses.

Conventions: lengths in mm, poses map model -> camera (``x = R @ p + t``), ``pts`` (N,3) are the
model points (BOP: the vertices of models_eval/, else of models/), ``K`` (3,3) the intrinsics.

Reference metrics (bop_toolkit ``pose_error.py`` style, batched over poses):

* ``add``    mean_i |(R_e p_i + t_e) - (R_g p_i + t_g)|                    (corresponding points)
* ``adds``   mean_i min_j |(R_g p_i + t_g) - (R_e p_j + t_e)|              (closest point, ADD-S:
  from each ground-truth-posed point to the nearest estimate-posed point; a KD-tree query)
* ``proj2d`` mean_i |pi(K (R_e p_i + t_e)) - pi(K (R_g p_i + t_g))|  pixels (pi = perspective
  division); a point at depth <= 0 in either pose makes the error infinite.

``add`` / ``adds`` / ``proj2d`` take one pose; ``add_batch`` / ``adds_batch`` / ``proj2d_batch``
take (B,3,3) rotations and (B,3) translations of one object and return (B,) errors.

Fast kernels (:class:`ModelPoints` holds what they precompute per object):

* :func:`add_fast_with_error`: ADD as float32 matrix products (|D p + d|^2 is a quadratic form
  in p: 10 monomials of the centred points times 10 coefficients per pose) with a bound of the
  rounding error; poses within it of a threshold are recomputed in float64.
* :func:`proj2d_bounds`: a rigorous interval of the 2D projection error from clusters of model
  points (a Taylor expansion with a bound of the projection's second derivative, and Jensen);
  :func:`proj2d_fast` the exact value (float32, float64 near a threshold).
* ADD-S, where the nearest-neighbour search is the cost, is bounded first and computed exactly
  only where needed. In the estimate's model frame a ground-truth-posed point is q = A p + b
  (:func:`relative_transform`) and its error is dist(q, P). A grid over the model's box (plus a
  margin) holds at each node g the exact dist(g, P) and the nearest point P[idx(g)].
  :func:`adds_cluster_bounds` works per cluster of model points (centroid c, weight w, mean
  distance a and mean squared distance s2 of its points to c): with q_c = A c + b and g its
  nearest node, dist(q_c) <= u = |q_c - P[idx(g)]| and dist(q_c) >= l = max(dist(g) - |q_c - g|,
  distance from q_c to the model's bounding box). dist is 1-Lipschitz, so the cluster's mean
  error is >= l - a; dist^2 = |x|^2 - phi(x) with phi(x) = max_j (2 x.p_j - |p_j|^2) convex, so
  by Jensen its mean squared error is <= dist(q_c)^2 + s2, and its mean error <= sqrt(u^2 + s2).
  :func:`adds_point_bounds` bounds every point: u as above, and (the same convexity on the
  grid: multilinear interpolation over-estimates the convex phi)
  dist(q)^2 >= sum_k w_k dist(g_k)^2 - sum_k w_k |g_k - q|^2 over the 8 corners of q's cell.
  :func:`adds_decide` replaces per-point bounds by exact KD-tree distances, widest first, until
  each pose is on one side of the threshold. The bounds are computed in float32 and widened by
  1e-5 relative + 1e-4 mm.
* :func:`adds_cv_residuals`: exact errors at random points minus a per-point control variate
  whose mean over the model is exactly the cluster estimate; the scorer uses their mean to
  correct the estimates (for AUCs), see :mod:`tdof20.scoring.scoring`.

BOP challenge metrics (BOP19; bop_toolkit ``pose_error.py``, ``eval_calc_errors.py``):

* :func:`symmetry_transformations`: a models_info.json entry's symmetries as BOP discretises them.
* References, one pose: :func:`mssd` (mm), :func:`mspd` (px), :func:`vsd_from_depths` (one error
  per tau, from full-frame depths; :meth:`DepthRenderer.render` renders them by ray casting).
* Fast, many poses of one object: :func:`vsd_batch` casts rays only inside each pose's footprint
  (the projected convex hull, :meth:`DepthRenderer.footprints`) and equals the reference on full
  frames bit for bit (the same rays); :func:`mssd_fast` and :func:`mspd_fast` compute the min over
  symmetries of the max over points by branch and bound over (symmetry, node of a
  :class:`PointTree`), exactly, or (``binof``) only until each error's position among the
  thresholds is certain.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

_CHUNK = 1 << 21  # elements (poses x points) per vectorised chunk: ~50 MB of float64 temporaries


# =============================================================================================
# reference metrics
# =============================================================================================
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
    tree = cKDTree(P) if tree is None else tree
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


# =============================================================================================
# fast kernels
# =============================================================================================
_PAIRS = 1 << 16  # (pose, point) pairs per float32 chunk: arrays of ~256 KB stay in cache
_F32_REL, _F32_ABS = 1e-5, 1e-4  # widening of float32 bounds (relative, mm)


def _widen(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.maximum(lo * (1 - _F32_REL) - _F32_ABS, 0.0), hi * (1 + _F32_REL) + _F32_ABS


@dataclass
class Clusters:
    """A partition of the model points into compact clusters (recursive median splits)."""

    label: np.ndarray  # (N,) cluster of each point
    n: np.ndarray  # (M,) points per cluster
    c: np.ndarray  # (M,3) centroids
    a: np.ndarray  # (M,) mean |p - c|
    s2: np.ndarray  # (M,) mean |p - c|^2
    r: np.ndarray  # (M,) max |p - c|

    @property
    def M(self) -> int:
        return len(self.n)

    @cached_property
    def w(self) -> np.ndarray:
        return self.n / self.n.sum()

    @cached_property
    def cT32(self) -> np.ndarray:
        return np.ascontiguousarray(self.c.T, dtype=np.float32)


def _median_splits(P: np.ndarray, leaf: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Split ``P`` (N,3) level by level, every segment longer than ``leaf`` at the median of its
    longest box side. Returns the point order and the segment bounds of every level (the first
    ``[0, N]``, the last the leaves) into it."""
    N = len(P)
    order = np.arange(N)
    cuts = np.array([0, N])
    history = [cuts]
    while True:
        starts, sizes = cuts[:-1], np.diff(cuts)
        split = sizes > leaf
        if not split.any():
            break
        seg = np.repeat(np.arange(len(sizes)), sizes)
        X = P[order]
        ext = np.maximum.reduceat(X, starts) - np.minimum.reduceat(X, starts)
        key = X[np.arange(N), np.argmax(ext, axis=1)[seg]]
        order = order[np.lexsort((key, seg))]
        cuts = np.sort(np.concatenate([cuts, starts[split] + sizes[split] // 2]))
        history.append(cuts)
    return order, history


def make_clusters(P: np.ndarray, leaf: int) -> Clusters:
    """Split ``P`` (N,3) recursively at the median of its longest box side into clusters of at
    most ``leaf`` points (all segments of a level split at once)."""
    P = _pts(P)
    N = len(P)
    order, history = _median_splits(P, leaf)
    cuts = history[-1]
    M = len(cuts) - 1
    label = np.empty(N, dtype=np.int64)
    label[order] = np.repeat(np.arange(M), np.diff(cuts))
    n = np.bincount(label, minlength=M).astype(np.float64)
    c = np.stack([np.bincount(label, P[:, i], M) for i in range(3)], axis=1) / n[:, None]
    dn = np.sqrt(((P - c[label]) ** 2).sum(1))
    r = np.zeros(M)
    np.maximum.at(r, label, dn)
    return Clusters(label, n, c, np.bincount(label, dn, M) / n, np.bincount(label, dn * dn, M) / n, r)


@dataclass
class DistanceGrid:
    """Exact distance to the point set and its nearest point at the nodes of a regular grid
    (node (i,j,k) at lo + h (i,j,k)); float32 planar copies for the kernels."""

    lo: np.ndarray  # (3,)
    h: float
    shape: np.ndarray  # (3,) int
    node: np.ndarray  # (G,4) float32: the nearest point's x, y, z and the distance

    @property
    def hi(self) -> np.ndarray:
        return self.lo + self.h * (self.shape - 1)

    @cached_property
    def strides(self) -> np.ndarray:
        s = self.shape
        return np.array([s[1] * s[2], s[2], 1], dtype=np.float32)

    @cached_property
    def dist(self) -> np.ndarray:
        return np.ascontiguousarray(self.node[:, 3])

    @cached_property
    def d2(self) -> np.ndarray:
        return self.dist * self.dist


def make_grid(P: np.ndarray, tree: cKDTree, margin: float, max_nodes: int, min_h: float) -> DistanceGrid:
    lo = P.min(0) - margin
    ext = P.max(0) + margin - lo
    h = max(min_h, float(np.cbrt(np.prod(ext) / max_nodes)))
    shape = np.ceil(ext / h).astype(np.int64) + 1
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d, idx = tree.query(G, workers=-1)
    node = np.concatenate([P[idx], d[:, None]], axis=1).astype(np.float32)
    return DistanceGrid(lo, h, shape, node)


@dataclass(eq=False)
class ModelPoints:
    """One object's model points and what the fast kernels precompute from them (built lazily):
    centred float32 monomials for ADD and proj2d, a KD-tree, two cluster levels and a distance
    grid for ADD-S."""

    pts: np.ndarray  # (N,3) mm
    diameter: float
    symmetric: bool = False
    coarse_leaf: int = 0  # 0: automatic, about 96 clusters
    fine_leaf: int = 6
    grid_nodes: int = 40_000
    grid_margin: float = 0.15  # of the diameter (at least 10 mm)
    sym_R: np.ndarray | None = None  # (S,3,3) symmetry transformations (BOP discretisation; MSSD, MSPD)
    sym_t: np.ndarray | None = None  # (S,3); None: the identity only

    def __post_init__(self):
        self.pts = np.ascontiguousarray(_pts(self.pts))

    @cached_property
    def syms(self) -> tuple[np.ndarray, np.ndarray]:
        """(R (S,3,3), t (S,3)) symmetry transformations, the identity alone when none are given."""
        if self.sym_R is None:
            return np.eye(3)[None], np.zeros((1, 3))
        return np.asarray(self.sym_R, np.float64).reshape(-1, 3, 3), np.asarray(self.sym_t, np.float64).reshape(-1, 3)

    @cached_property
    def hull_idx(self) -> np.ndarray:
        """Indices of the points on the convex hull (all points where the hull is degenerate)."""
        from scipy.spatial import ConvexHull, QhullError

        try:
            return np.sort(ConvexHull(self.pts).vertices)
        except (QhullError, ValueError):
            return np.arange(self.n)

    @cached_property
    def hull_tree(self) -> "PointTree":
        """Nested clusters of the hull vertices (MSSD: a convex function peaks on the hull)."""
        return make_point_tree(self.pts[self.hull_idx])

    @cached_property
    def pts_tree(self) -> "PointTree":
        """Nested clusters of all points (MSPD)."""
        return make_point_tree(self.pts)

    @cached_property
    def sym_centre(self) -> tuple[np.ndarray, float]:
        """(centre, radius) of a ball holding the symmetric images R_s m + t_s of :attr:`centre`."""
        R, t = self.syms
        c = np.einsum("sij,j->si", R, self.centre) + t
        m = 0.5 * (c.min(0) + c.max(0))
        return m, float(np.sqrt(((c - m) ** 2).sum(1).max()))

    @property
    def n(self) -> int:
        return len(self.pts)

    @cached_property
    def centre(self) -> np.ndarray:
        return 0.5 * (self.pts.min(0) + self.pts.max(0))

    @cached_property
    def box(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pts.min(0), self.pts.max(0)

    @cached_property
    def radius(self) -> float:
        """Largest distance of a point from ``centre``."""
        return float(np.sqrt(((self.pts - self.centre) ** 2).sum(1).max()))

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.pts, leafsize=32)

    @cached_property
    def quad(self) -> np.ndarray:
        """(10,N) float32 monomials of the centred points: x^2 y^2 z^2 2xy 2xz 2yz 2x 2y 2z 1."""
        x, y, z = (self.pts - self.centre).T
        return np.ascontiguousarray(np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z,
                                              2 * x, 2 * y, 2 * z, np.ones_like(x)]), dtype=np.float32)

    @cached_property
    def hom(self) -> np.ndarray:
        """(4,N) float32 homogeneous centred points."""
        x, y, z = (self.pts - self.centre).T
        return np.ascontiguousarray(np.stack([x, y, z, np.ones_like(x)]), dtype=np.float32)

    @cached_property
    def hom_sample(self) -> np.ndarray:
        """(4,512) a fixed random subset of :attr:`hom` (estimates of 2D projection errors)."""
        if self.n <= 512:
            return self.hom
        idx = np.random.default_rng(0).choice(self.n, 512, replace=False)
        return np.ascontiguousarray(self.hom[:, np.sort(idx)])

    @cached_property
    def coarse(self) -> Clusters:
        return make_clusters(self.pts, self.coarse_leaf or max(8, -(-self.n // 96)))

    @cached_property
    def proj(self) -> Clusters:
        """About 32 clusters (2D projection bounds)."""
        return make_clusters(self.pts, max(8, -(-self.n // 32)))

    @cached_property
    def fine(self) -> Clusters:
        return make_clusters(self.pts, self.fine_leaf)

    @cached_property
    def grid(self) -> DistanceGrid:
        margin = max(10.0, self.grid_margin * self.diameter)
        return make_grid(self.pts, self.tree, margin, self.grid_nodes, self.diameter / 400)

    @cached_property
    def pts32T(self) -> np.ndarray:
        return np.ascontiguousarray(self.pts.T, dtype=np.float32)


@dataclass
class Bounds:
    """Per-pose interval containing the exact error, and an estimate."""

    lo: np.ndarray
    hi: np.ndarray
    est: np.ndarray


def _near_threshold(v: np.ndarray, thr: float | None, tol: float) -> np.ndarray:
    if thr is None:
        return np.zeros(len(v), bool)
    return np.abs(v - thr) <= tol + 1e-4 * thr


def add_fast_with_error(model: ModelPoints, R_est, t_est, R_gt, t_gt,
                        thr: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ADD (B,) as float32 products of monomials, and a bound (B,) of its rounding error: per point
    |sqrt(a) - sqrt(b)| <= sqrt(|a - b|) and |a - b| <= 20 eps32 (|D| r + |d|)^2 for the quadratic
    form of |D p + d|^2 (r: largest centred point norm). Poses within that bound of ``thr`` are
    recomputed in float64 (:func:`add_batch`, error 0), so comparisons with ``thr`` are exact."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    D = Re - Rg
    d = te - tg + D @ model.centre  # the offset for centred points
    G = np.einsum("bki,bkj->bij", D, D)
    v = np.einsum("bki,bk->bi", D, d)
    W = np.stack([G[:, 0, 0], G[:, 1, 1], G[:, 2, 2], G[:, 0, 1], G[:, 0, 2], G[:, 1, 2],
                  v[:, 0], v[:, 1], v[:, 2], (d * d).sum(1)], axis=1).astype(np.float32)  # (B,10)
    F = model.quad
    out = np.empty(len(Re))
    step = max(1, _PAIRS // model.n)
    for s in range(0, len(Re), step):
        S = np.matmul(W[s:s + step, None, :], F)[:, 0]  # (b,N); stacked: no BLAS threading
        np.maximum(S, 0, out=S)
        np.sqrt(S, out=S)
        out[s:s + step] = S.sum(axis=1, dtype=np.float64) / model.n
    scale = np.sqrt((D * D).sum(axis=(1, 2))) * model.radius + np.sqrt((d * d).sum(1))
    err = np.sqrt(20 * np.finfo(np.float32).eps) * scale
    if thr is not None:
        redo = np.abs(out - thr) <= err
        if redo.any():
            out[redo] = add_batch(Re[redo], te[redo], Rg[redo], tg[redo], model.pts)
            err[redo] = 0.0
    return out, err


def add_fast(model: ModelPoints, R_est, t_est, R_gt, t_gt, thr: float | None = None) -> np.ndarray:
    """ADD (B,) with exact comparisons to ``thr`` (see :func:`add_fast_with_error`)."""
    return add_fast_with_error(model, R_est, t_est, R_gt, t_gt, thr)[0]


def proj2d_fast(model: ModelPoints, R_est, t_est, R_gt, t_gt, K, thr: float | None = None,
                sample: bool = False) -> np.ndarray:
    """2D projection error (B,) in float32; poses within 0.01 px of ``thr`` (or with a point
    closer than 50 mm to the camera) are redone in float64 (:func:`proj2d_batch`), so comparisons
    with ``thr`` are exact. ``sample``: the mean over a fixed random subset of 512 model points
    instead (an estimate; no recomputation)."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = _Ks(K, len(Re))
    B = len(Re)

    def homog(R, t):  # (B,3,4): K [R | t + R c0]
        M = np.concatenate([R, (t + R @ model.centre)[:, :, None]], axis=2)
        return np.einsum("bij,bjk->bik", Ks, M)

    W = np.concatenate([homog(Re, te), homog(Rg, tg)], axis=1).astype(np.float32)  # (B,6,4)
    X = model.hom_sample if sample else model.hom
    out = np.empty(B)
    step = max(1, _PAIRS // X.shape[1])
    for s in range(0, B, step):
        b = min(B, s + step) - s
        H = np.matmul(W[s:s + b], X)  # (b,6,N); stacked: no BLAS threading
        ze, zg = H[:, 2], H[:, 5]
        bad = ((ze <= 0) | (zg <= 0)).any(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            du = H[:, 0] / ze - H[:, 3] / zg
            dv = H[:, 1] / ze - H[:, 4] / zg
            du *= du
            dv *= dv
            du += dv
            np.sqrt(du, out=du)
            e = du.mean(axis=1, dtype=np.float64)
        e[bad | ~np.isfinite(e)] = np.inf
        close = np.minimum(ze.min(axis=1), zg.min(axis=1)) < 50.0  # float32 error grows as 1/depth
        e[close & ~bad] = -1.0  # marked for float64
        out[s:s + b] = e
    if sample:
        return np.where(out < 0, np.inf, out) if thr is None else out
    redo = (_near_threshold(out, thr, 0.01) & np.isfinite(out)) | (out < 0)
    if redo.any():
        out[redo] = proj2d_batch(Re[redo], te[redo], Rg[redo], tg[redo], model.pts, Ks[redo])
    return out


def _project_planar(K: np.ndarray, R: np.ndarray, t: np.ndarray, cT: np.ndarray):
    """Pixel position (2 arrays (B,M)), depth (B,M) and the Jacobian d pixel / d model point
    (rows ju (3 arrays), jv (3 arrays)) of cluster centroids cT (3,M) under poses (R, t)."""
    X = np.matmul(R, cT) + t[:, :, None]  # (B,3,M)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    fx, fy, sk = K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 1, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / z
        xz, yz = x * iz, y * iz
        u = fx * xz + sk * yz + K[:, 0, 2, None]
        v = fy * yz + K[:, 1, 2, None]
        a, b, c = fx * iz, sk * iz, -(fx * xz + sk * yz) * iz
        d, e = fy * iz, -fy * yz * iz
    ju = [a * R[:, 0, j, None] + b * R[:, 1, j, None] + c * R[:, 2, j, None] for j in range(3)]
    jv = [d * R[:, 1, j, None] + e * R[:, 2, j, None] for j in range(3)]
    return u, v, X, ju, jv


def proj2d_bounds(model: ModelPoints, R_est, t_est, R_gt, t_gt, K) -> Bounds:
    """Rigorous 2D-projection interval (pixels) per pose from clusters of model points: per
    cluster the offset f(c + d) = f(c) + J d + rem with |rem| <= H |d|^2 / 2, H bounding the
    second derivative of both projections over the cluster's ball (from its smallest depth);
    Jensen gives |f(c)| - H s2/2 <= mean |f| <= sqrt(|f(c)|^2 + |J|_F^2 s2) + H s2/2.
    Infinite where a ball reaches depth <= 1 mm."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    cl = model.proj
    B = len(Re)
    lo = np.empty(B)
    hi = np.empty(B)
    est = np.empty(B)
    step = max(1, _PAIRS // cl.M)
    for s in range(0, B, step):
        sl = slice(s, min(B, s + step))
        Kb = Ks[sl]
        ue, ve, Xe, jue, jve = _project_planar(Kb, Re[sl], te[sl], cl.c.T)
        ug, vg, Xg, jug, jvg = _project_planar(Kb, Rg[sl], tg[sl], cl.c.T)
        H = _proj_curvature(Kb, Xe, cl.r) + _proj_curvature(Kb, Xg, cl.r)
        with np.errstate(invalid="ignore"):
            m2 = (ue - ug) ** 2 + (ve - vg) ** 2
            j2 = sum((p - q) ** 2 for p, q in zip(jue + jve, jug + jvg))
            rem = H * cl.s2 / 2
            lo_k = np.maximum(np.sqrt(m2) - rem, 0.0)
            hi_k = np.sqrt(m2 + j2 * cl.s2) + rem
            est_k = np.sqrt(m2 + 0.5 * j2 * cl.s2)
        bad = ~np.isfinite(hi_k)
        lo_k[bad] = 0.0
        hi[sl] = np.where(bad.any(axis=1), np.inf, np.where(bad, 0.0, hi_k) @ cl.w)
        est[sl] = np.where(bad.any(axis=1), np.inf, np.where(bad, 0.0, est_k) @ cl.w)
        lo[sl] = lo_k @ cl.w
    return Bounds(lo, hi, np.clip(est, lo, hi))


def _proj_curvature(K: np.ndarray, X: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Bound (B,M) of the norm of the second derivative of the pixel position over the ball of
    radius r (M,) around each camera point X (B,3,M); inf where the ball reaches depth <= 1 mm.
    (u = fx x/z + s y/z + cx: Hessian entries 1/z^2 and 2|x|/z^3, norm <= (1 + 2|x/z|) / z^2.)"""
    zmin = X[:, 2] - r
    ok = zmin > 1.0
    zs = np.where(ok, zmin, 1.0)
    ax = (np.abs(X[:, 0]) + r) / zs
    ay = (np.abs(X[:, 1]) + r) / zs
    fx, fy, sk = np.abs(K[:, 0, 0, None]), np.abs(K[:, 1, 1, None]), np.abs(K[:, 0, 1, None])
    hu = (fx * (1 + 2 * ax) + sk * (1 + 2 * ay)) / zs ** 2
    hv = fy * (1 + 2 * ay) / zs ** 2
    return np.where(ok, np.sqrt(hu * hu + hv * hv), np.inf)


def _box_distance(lo: np.ndarray, hi: np.ndarray, Q: np.ndarray, axis: int) -> np.ndarray:
    """Distance from queries to the box [lo, hi] (0 inside); coordinates along ``axis``."""
    sh = [1] * Q.ndim
    sh[axis] = 3
    e = np.maximum(np.maximum(lo.reshape(sh) - Q, Q - hi.reshape(sh)), 0)
    return np.sqrt((e * e).sum(axis=axis))


def _inside_grid(model: ModelPoints, A: np.ndarray, b: np.ndarray, reach: float) -> np.ndarray:
    """(B,) whether every model point, moved by (A, b), stays ``reach`` inside the grid box."""
    g = model.grid
    c = A @ model.centre + b
    r = model.radius + reach
    return np.all((c - r >= g.lo) & (c + r <= g.hi), axis=1)


def _nearest_node(g: DistanceGrid, Q: np.ndarray):
    """Q (b,3,n) float32 -> (flat index (b,n) int32, |Q - node| (b,n))."""
    lo = g.lo.astype(np.float32)[None, :, None]
    U = Q - lo
    U *= np.float32(1.0 / g.h)
    np.rint(U, out=U)
    np.maximum(U, 0, out=U)
    np.minimum(U, (g.shape - 1).astype(np.float32)[None, :, None], out=U)
    flat = U[:, 0] * g.strides[0]
    flat += U[:, 1] * g.strides[1]
    flat += U[:, 2]
    flat = flat.astype(np.int32)
    U *= np.float32(g.h)
    U += lo
    U -= Q
    U *= U
    dq = U[:, 0] + U[:, 1]
    dq += U[:, 2]
    np.sqrt(dq, out=dq)
    return flat, dq


def _node_data(g: DistanceGrid, Q: np.ndarray, flat: np.ndarray):
    """(|Q - nearest point of the node|^2 (an upper bound of dist(Q, P)^2), dist(node)), (b,n) each."""
    N4 = np.take(g.node, flat, axis=0)  # (b,n,4)
    dx = Q[:, 0] - N4[..., 0]
    dy = Q[:, 1] - N4[..., 1]
    dz = Q[:, 2] - N4[..., 2]
    dx *= dx
    dy *= dy
    dz *= dz
    dx += dy
    dx += dz
    return dx, N4[..., 3]


def adds_cluster_bounds(model: ModelPoints, A: np.ndarray, b: np.ndarray, level: str = "fine") -> Bounds:
    """Rigorous ADD-S interval per pose from clusters of model points and the distance grid
    (relative transforms A (B,3,3), b (B,3); see the module docstring). ``level``: 'coarse'
    (about 96 clusters) or 'fine' (6 points each). The estimate sqrt(u^2 + 2/3 s2) per cluster is
    not clipped to the interval (it is the mean of the control variate of
    :func:`adds_cv_residuals`)."""
    cl = model.coarse if level == "coarse" else model.fine
    g = model.grid
    B = len(A)
    lo = np.empty(B)
    hi = np.empty(B)
    est = np.empty(B)
    a32 = cl.a.astype(np.float32)
    s2 = cl.s2.astype(np.float32)
    s2e = (cl.s2 * (2.0 / 3.0)).astype(np.float32)
    A32 = A.astype(np.float32)
    b32 = b.astype(np.float32)[:, :, None]
    inside = _inside_grid(model, A, b, 0.0)
    blo, bhi = (x.astype(np.float32) for x in model.box)
    step = max(1, _PAIRS // cl.M)
    for s in range(0, B, step):
        e = min(B, s + step)
        Q = np.matmul(A32[s:e], cl.cT32)
        Q += b32[s:e]
        flat, dq = _nearest_node(g, Q)
        ub2, dn = _node_data(g, Q, flat)
        lb = dn - dq
        out = ~inside[s:e]
        if out.any():
            lb[out] = np.maximum(lb[out], _box_distance(blo, bhi, Q[out], axis=1))
        lb -= a32
        np.maximum(lb, 0, out=lb)
        lo[s:e] = lb @ cl.w
        hi[s:e] = np.sqrt(ub2 + s2) @ cl.w
        est[s:e] = np.sqrt(ub2 + s2e) @ cl.w
    lo, hi = _widen(lo, hi)
    return Bounds(lo, hi, est)


def _point_bounds(model: ModelPoints, A32: np.ndarray, b32: np.ndarray):
    """Per-point bounds of dist(A p + b, P) for a few poses: (lb, ub, estimate) each (b,N) float32."""
    g = model.grid
    lo3 = g.lo.astype(np.float32)[None, :, None]
    top = (g.shape - 2).astype(np.float32)[None, :, None]
    st = g.strides
    h = np.float32(g.h)
    blo, bhi = (x.astype(np.float32) for x in model.box)
    Q = np.matmul(A32, model.pts32T)
    Q += b32[:, :, None]
    flat, dq = _nearest_node(g, Q)
    ub2, dn = _node_data(g, Q, flat)
    ub = np.sqrt(ub2)
    lb = np.maximum(dn - dq, _box_distance(blo, bhi, Q, axis=1))
    U = (Q - lo3) / h
    I0 = np.floor(U)
    ins = np.all((I0 >= 0) & (I0 <= top), axis=1)
    np.minimum(np.maximum(I0, 0, out=I0), top, out=I0)
    F = np.minimum(np.maximum(U - I0, 0), 1)
    base = (I0[:, 0] * st[0] + I0[:, 1] * st[1] + I0[:, 2]).astype(np.int32)
    fx, fy, fz = F[:, 0], F[:, 1], F[:, 2]
    gx, gy, gz = 1 - fx, 1 - fy, 1 - fz
    d2 = g.d2
    interp = np.zeros_like(fx)
    for i, wx in ((0, gx), (1, fx)):
        for j, wy in ((0, gy), (1, fy)):
            wxy = wx * wy
            o = int(i * st[0] + j * st[1])
            interp += wxy * (gz * np.take(d2, base + o) + fz * np.take(d2, base + (o + 1)))
    S = (fx * gx + fy * gy + fz * gz) * (h * h)
    phi = np.sqrt(np.maximum(interp - S, 0))
    lb = np.where(ins, np.maximum(lb, phi), lb)
    lb = np.minimum(np.maximum(lb, 0), ub)
    est = np.where(ins, np.clip(np.sqrt(interp), lb, ub), ub)
    return lb, ub, est


def adds_point_bounds(model: ModelPoints, A: np.ndarray, b: np.ndarray) -> Bounds:
    """Rigorous ADD-S interval per pose from every point's own bounds on the grid (see the module
    docstring): costlier than :func:`adds_cluster_bounds`, tighter away from the surface."""
    B = len(A)
    lo = np.empty(B)
    hi = np.empty(B)
    est = np.empty(B)
    A32 = A.astype(np.float32)
    b32 = b.astype(np.float32)
    step = max(1, _PAIRS // model.n)
    for s in range(0, B, step):
        lb, ub, e = _point_bounds(model, A32[s:s + step], b32[s:s + step])
        lo[s:s + step] = lb.mean(axis=1, dtype=np.float64)
        hi[s:s + step] = ub.mean(axis=1, dtype=np.float64)
        est[s:s + step] = e.mean(axis=1, dtype=np.float64)
    lo, hi = _widen(lo, hi)
    return Bounds(lo, hi, np.clip(est, lo, hi))


def adds_decide(model: ModelPoints, A: np.ndarray, b: np.ndarray, thr: float,
                rounds: Sequence[float] = (0.04, 0.08, 0.15, 0.25, 0.4, 0.6, 1.0)) -> Bounds:
    """Decide ADD-S < ``thr`` exactly: start from every point's bounds and replace them by exact
    KD-tree distances, widest intervals first (``rounds``: cumulative fractions of the points),
    until each pose's interval lies on one side of ``thr``. Returns the final intervals
    (lo == hi == the exact ADD-S where every point was needed)."""
    B, N = len(A), model.n
    lo = np.empty(B)
    hi = np.empty(B)
    P = model.pts
    step = max(1, (1 << 20) // N)
    for s in range(0, B, step):
        sl = slice(s, min(B, s + step))
        Ab, bb = A[sl], b[sl]
        nb = len(Ab)
        lb32, ub32, _ = _point_bounds(model, Ab.astype(np.float32), bb.astype(np.float32))
        lb = lb32.astype(np.float64) * (1 - _F32_REL) - _F32_ABS
        ub = ub32.astype(np.float64) * (1 + _F32_REL) + _F32_ABS
        order = np.argsort(lb - ub, axis=1)  # widest first
        active = np.arange(nb)
        done = 0
        for frac in rounds:
            k = N if frac >= 1 else max(done + 1, int(np.ceil(frac * N)))
            idx = order[active, done:k]  # (a, k - done) point indices
            rows = np.repeat(active, k - done)
            pts = P[idx.reshape(-1)]
            q = np.einsum("rj,rij->ri", pts, Ab[rows]) + bb[rows]
            d, _ = model.tree.query(q, workers=-1 if len(q) > 4096 else 1)
            lb[rows, idx.reshape(-1)] = d
            ub[rows, idx.reshape(-1)] = d
            done = k
            if done >= N:
                break
            m_lo, m_hi = lb[active].mean(axis=1), ub[active].mean(axis=1)
            active = active[(m_lo < thr) & (m_hi >= thr)]
            if len(active) == 0:
                break
        lo[sl] = np.maximum(lb.mean(axis=1), 0.0)
        hi[sl] = ub.mean(axis=1)
        full = np.isin(np.arange(nb), active) & (done >= N)
        lo[sl][full] = hi[sl][full]  # every point exact
    return Bounds(lo, hi, 0.5 * (lo + hi))


def adds_exact(model: ModelPoints, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact ADD-S (B,) from relative transforms (KD-tree queries, float64)."""
    P = model.pts
    out = np.empty(len(A))
    for s in _chunks(len(A), len(P)):
        Q = np.einsum("nj,bij->bni", P, A[s]) + b[s, None, :]
        d, _ = model.tree.query(Q.reshape(-1, 3), workers=-1)
        out[s] = d.reshape(len(Q), len(P)).mean(axis=1)
    return out


def adds_cv_residuals(model: ModelPoints, A: np.ndarray, b: np.ndarray, level: str, m: int,
                      rng: np.random.Generator) -> np.ndarray:
    """(B, m) residuals exact - control at m random model points per pose. The control of point
    p in cluster k is est_k + n_k . (A (p - c_k)) with est_k the cluster estimate of
    :func:`adds_cluster_bounds` and n_k the unit direction from the nearest point of q_c's node to
    q_c; its mean over all points is that function's estimate, so est + mean residual is an
    unbiased estimate of the exact ADD-S."""
    cl = model.coarse if level == "coarse" else model.fine
    g = model.grid
    B = len(A)
    idx = rng.integers(0, model.n, size=(B, m))
    k = cl.label[idx]  # (B,m)
    p = model.pts[idx]  # (B,m,3)
    c = cl.c[k]
    q = np.einsum("bij,bmj->bmi", A, p) + b[:, None, :]
    qc = np.einsum("bij,bmj->bmi", A, c) + b[:, None, :]
    flat, _ = _nearest_node(g, np.ascontiguousarray(qc.transpose(0, 2, 1), dtype=np.float32))
    near = g.node[flat, :3].astype(np.float64)  # (B,m,3)
    v = qc - near
    u = np.sqrt((v * v).sum(-1))
    est_k = np.sqrt(u * u + cl.s2[k] * (2.0 / 3.0))
    nrm = v / np.where(u > 0, u, 1.0)[..., None]
    control = est_k + (nrm * (q - qc)).sum(-1)
    d, _ = model.tree.query(q.reshape(-1, 3), workers=-1)
    return d.reshape(B, m) - control


__all__ = [
    "add", "adds", "proj2d", "add_batch", "adds_batch", "proj2d_batch", "relative_transform",
    "Clusters", "make_clusters", "DistanceGrid", "make_grid", "ModelPoints", "Bounds",
    "add_fast", "add_fast_with_error", "proj2d_fast", "proj2d_bounds", "adds_cluster_bounds", "adds_point_bounds",
    "adds_decide", "adds_exact",
    "adds_cv_residuals",
]


# =============================================================================================
# BOP challenge metrics (BOP19): VSD, MSSD, MSPD
# =============================================================================================
VSD_DELTA = 15.0  # mm: tolerance of the visibility test
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # misalignment tolerances, fractions of the diameter
VSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # correctness thresholds of the VSD error
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # fractions of the diameter
MSPD_THRESHOLDS = np.arange(5, 51, 5).astype(np.float64)  # pixels at an image width of 640
MSPD_WIDTH = 640.0  # MSPD errors are scaled by MSPD_WIDTH / image width (BOP)
MAX_SYM_DISC_STEP = 0.01  # continuous symmetries: the farthest vertex moves <= 1% of the diameter per step
_BNB_TOL = 1e-6  # absolute slack (mm or px) of the branch-and-bound comparisons (float64 rounding)


def rotation_about(axis, angle: float) -> np.ndarray:
    """(3,3) rotation by ``angle`` radians about ``axis`` (any length; Rodrigues' formula)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    c, s = np.cos(angle), np.sin(angle)
    W = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return c * np.eye(3) + s * W + (1.0 - c) * np.outer(a, a)


def symmetry_transformations(info: dict, max_sym_disc_step: float = MAX_SYM_DISC_STEP
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The symmetry transformations of a models_info.json entry as BOP discretises them:
    (R (S,3,3), t (S,3)), model -> model, the identity first. Discrete symmetries are the 4x4
    matrices of ``symmetries_discrete`` plus the identity; each continuous symmetry (axis through
    ``offset``) becomes n = ceil(pi / max_sym_disc_step) rotations by 2 pi k / n (so the vertex
    farthest from the axis moves at most ``max_sym_disc_step`` of the diameter per step), and with
    continuous symmetries every discrete one is composed with every continuous step (C o D)."""
    disc = [(np.eye(3), np.zeros(3))]
    for sym in info.get("symmetries_discrete") or []:
        T = np.asarray(sym, dtype=np.float64).reshape(4, 4)
        disc.append((T[:3, :3], T[:3, 3]))
    cont = []
    for sym in info.get("symmetries_continuous") or []:
        axis, offset = np.asarray(sym["axis"], float), np.asarray(sym["offset"], float).reshape(3)
        n = int(np.ceil(np.pi / max_sym_disc_step))
        for k in range(n):
            R = rotation_about(axis, k * 2.0 * np.pi / n)
            cont.append((R, offset - R @ offset))
    if cont:
        trans = [(Rc @ Rd, Rc @ td + tc) for Rd, td in disc for Rc, tc in cont]
    else:
        trans = disc
    return np.stack([R for R, _ in trans]), np.stack([t for _, t in trans])


def _syms(syms) -> tuple[np.ndarray, np.ndarray]:
    if syms is None:
        return np.eye(3)[None], np.zeros((1, 3))
    R, t = syms
    return np.asarray(R, np.float64).reshape(-1, 3, 3), np.asarray(t, np.float64).reshape(-1, 3)


def project_points(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,2) pixels of camera points X (N,3); inf where a point has depth <= 0."""
    H = X @ np.asarray(K, np.float64).T
    z = H[:, 2:]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = H[:, :2] / z
    uv[(z[:, 0] <= 0)] = np.inf
    return uv


# --- reference metrics (one pose; what the fast kernels must equal) --------------------------
def mssd(R_est, t_est, R_gt, t_gt, pts, syms=None) -> float:
    """Maximum Symmetry-Aware Surface Distance (mm): min over the symmetries (R_s, t_s) of
    max_i |(R_e p_i + t_e) - (R_g (R_s p_i + t_s) + t_g)|. ``syms``: (R (S,3,3), t (S,3)) from
    :func:`symmetry_transformations` (None: the identity only)."""
    P = _pts(pts)
    Re, te = (np.asarray(x, np.float64) for x in (R_est, t_est))
    Rg, tg = (np.asarray(x, np.float64) for x in (R_gt, t_gt))
    X = P @ Re.T + te.reshape(3)
    best = np.inf
    for Rs, ts in zip(*_syms(syms)):
        Y = P @ (Rg @ Rs).T + (Rg @ ts + tg.reshape(3))
        best = min(best, float(np.sqrt(((X - Y) ** 2).sum(1)).max()))
    return best


def mspd(R_est, t_est, R_gt, t_gt, K, pts, syms=None) -> float:
    """Maximum Symmetry-Aware Projection Distance (px): min over the symmetries of
    max_i |pi(K (R_e p_i + t_e)) - pi(K (R_g (R_s p_i + t_s) + t_g))| (pi: perspective division;
    a point at depth <= 0 makes its term infinite)."""
    P = _pts(pts)
    Re, te = (np.asarray(x, np.float64) for x in (R_est, t_est))
    Rg, tg = (np.asarray(x, np.float64) for x in (R_gt, t_gt))
    ue = project_points(P @ Re.T + te.reshape(3), K)
    best = np.inf
    for Rs, ts in zip(*_syms(syms)):
        ug = project_points(P @ (Rg @ Rs).T + (Rg @ ts + tg.reshape(3)), K)
        with np.errstate(invalid="ignore"):
            d = np.sqrt(((ue - ug) ** 2).sum(1))
        d[~np.isfinite(d)] = np.inf
        best = min(best, float(d.max()))
    return best


def ray_norms(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera rays (x, y, 1) = K^-1 (u, v, 1) through pixel centres (u, v) (float64), and |(x, y, 1)|."""
    K = np.asarray(K, np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return x, y, np.sqrt(x * x + y * y + 1.0)


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth (H,W) along the optical axis -> distance from the camera centre (float64)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return depth.astype(np.float64) * ray_norms(K, u, v)[2]


def vsd_from_depths(depth_est: np.ndarray, depth_gt: np.ndarray, depth_test: np.ndarray, K: np.ndarray,
                    diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS) -> np.ndarray:
    """Visible Surface Discrepancy for each tau (T,), BOP19 form (step cost, normalised by the
    diameter): depths (H,W) in mm, 0 = none; the test depth's missing pixels count as visible.
    V_g = {d_g > 0 and (d_g - d_test <= delta or d_test = 0)}, V_e = {d_e > 0 and (d_e - d_test <=
    delta or d_test = 0 or V_g)} (d: distances from the camera centre); e = (#{V_g & V_e with
    |d_g - d_e| / diameter >= tau} + #(V_g | V_e) - #(V_g & V_e)) / #(V_g | V_e), 1 if the union is empty."""
    dt, dg, de = (distance_image(d, K) for d in (depth_test, depth_gt, depth_est))
    vg = (dg > 0) & (((dg.astype(np.float32) - dt.astype(np.float32)) <= delta) | (dt == 0))
    ve = (de > 0) & (((de.astype(np.float32) - dt.astype(np.float32)) <= delta) | (dt == 0))
    ve |= vg & (de > 0)
    inter, union = vg & ve, vg | ve
    n_union = int(union.sum())
    if n_union == 0:
        return np.ones(len(taus))
    dist = np.abs(dg[inter] - de[inter]) / diameter
    comp = n_union - int(inter.sum())
    return np.array([(int((dist >= tau).sum()) + comp) / n_union for tau in taus])


class DepthRenderer:
    """Depth images of one object model by ray casting (open3d RaycastingScene, built once in
    the model frame; the rays move into the model frame). Pixel centres at integer (u, v); depth
    along the optical axis in mm, 0 where the ray misses."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from tdof20.geometry.raycast import convex_hull_points
        from tdof20.o3d import o3d

        V = np.asarray(vertices, np.float64)
        F = np.asarray(faces, np.int64)
        if len(F) == 0:
            raise ValueError("a triangle mesh is needed to render depth")
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        try:
            self.hull = np.asarray(convex_hull_points(V, F), np.float64)
        except Exception:  # degenerate (flat) meshes: every vertex bounds the silhouette
            self.hull = V
        self._o3d = o3d

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """t of the first hit of rays (model frame, float32 (n,3) each); 0 where none."""
        if len(origins) == 0:
            return np.zeros(0, np.float32)
        rays = np.empty((len(origins), 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        return self.cast_rays(rays)

    def cast_rays(self, rays: np.ndarray) -> np.ndarray:
        """t of the first hit of rays (n,6) float32 (origin, direction; model frame); 0 where none."""
        if len(rays) == 0:
            return np.zeros(0, np.float32)
        t = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32)))
        t = t["t_hit"].numpy()
        t[~np.isfinite(t)] = 0.0
        return t

    def render(self, R, t, K, width: int, height: int) -> np.ndarray:
        """(height, width) float32 depth of the model at pose (R, t): every pixel cast."""
        v, u = np.mgrid[0:height, 0:width].reshape(2, -1).astype(np.float64)
        x, y, _ = ray_norms(K, u, v)
        R = np.asarray(R, np.float64)
        t = np.asarray(t, np.float64).reshape(3)
        d = np.empty((len(x), 3), np.float32)
        for i in range(3):  # R^T (x, y, 1): the rays in the model frame
            d[:, i] = x * R[0, i] + y * R[1, i] + R[2, i]
        o = np.broadcast_to((-R.T @ t).astype(np.float32), d.shape)
        return self.cast(o, d).reshape(height, width)


    def footprints(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int):
        """Where the model at poses (R, t) (B,...) can be seen: (boxes (B,4) int [v0, v1) x [u0, u1)
        clipped to the image (empty when v0 >= v1 or u0 >= u1), polygons: per pose the convex hull
        (k,2) int32 (u, v) of the projected hull vertices, or None for the whole box). A pixel
        whose centre lies more than a pixel outside the polygon cannot be hit; poses whose hull
        reaches depth <= 1 mm get the whole image and no polygon."""
        import cv2

        X = np.einsum("bij,nj->bni", R, self.hull) + t[:, None, :]
        H = np.einsum("bij,bnj->bni", K, X)
        z = X[..., 2]
        near = (z <= 1.0).any(axis=1)  # the projection is unbounded: cast everything
        gone = (z <= 0.0).all(axis=1)  # rays (depth > 0) cannot reach it: nothing to see
        zz = np.where(z > 0, H[..., 2], 1.0)
        u, v = H[..., 0] / zz, H[..., 1] / zz
        out = np.stack([np.floor(v.min(1)) - 2, np.ceil(v.max(1)) + 3,
                        np.floor(u.min(1)) - 2, np.ceil(u.max(1)) + 3], axis=1)
        lim = np.array([height, height, width, width], np.float64)
        out = np.clip(out, 0, lim)
        out[near] = [0, height, 0, width]
        out[gone] = 0
        boxes = out.astype(np.int64)
        big = 1e6  # beyond this the polygon would overflow int32; the box alone is used
        skip = near | (boxes[:, 0] >= boxes[:, 1]) | (boxes[:, 2] >= boxes[:, 3]) | \
            (np.abs(u).max(axis=1) > big) | (np.abs(v).max(axis=1) > big)
        uv = np.rint(np.stack([np.where(skip[:, None], 0, u), np.where(skip[:, None], 0, v)], axis=2)).astype(np.int32)
        polys = [None if skip[b] else cv2.convexHull(uv[b]).reshape(-1, 2) for b in range(len(R))]
        return boxes, polys

    def boxes(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """The boxes of :meth:`footprints`."""
        return self.footprints(R, t, K, width, height)[0]


def _footprint_pixels(poly, box, U0: int, V0: int, W: int):
    """(ys, xs) local to the box origin (U0, V0) of the pixels of ``box`` that the polygon (grown by
    a 3-pixel-wide outline) covers, and their flat index in a W-wide raster at (U0, V0)."""
    import cv2

    v0, v1, u0, u1 = (int(x) for x in box)
    h, w = v1 - v0, u1 - u0
    if poly is None:
        ys, xs = np.divmod(np.arange(h * w), w)
    else:
        m = np.zeros((h, w), np.uint8)
        q = (poly - np.array([u0, v0], np.int32)).reshape(-1, 1, 2)
        cv2.fillConvexPoly(m, q, 1)
        cv2.polylines(m, [q], True, 1, 3)
        ys, xs = np.nonzero(m)
    ys = ys + (v0 - V0)
    xs = xs + (u0 - U0)
    return ys, xs, ys * W + xs


def vsd_batch(renderer: DepthRenderer, R_est, t_est, R_gt, t_gt, K, depth_test: np.ndarray, image: np.ndarray,
              diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS, max_rays: int = 1 << 20) -> np.ndarray:
    """VSD (B,T) of B poses of one object, exactly :func:`vsd_from_depths` on full renders, but
    rendering only where it matters: per pose each render is cast inside the projected convex hull
    of the model (grown by a pixel, :meth:`DepthRenderer.footprints`; no other pixel can be hit),
    and poses whose footprints' boxes do not meet have an empty intersection, so VSD 1 for every
    tau, without rendering. ``depth_test`` (n,H,W) float32 mm test depths, ``image`` (B,) the
    index of each pose's test image."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    taus = np.asarray(taus, np.float64)
    B, T = len(Re), len(taus)
    h, w = depth_test.shape[1:]
    out = np.ones((B, T))
    if B == 0:
        return out
    be, pe = renderer.footprints(Re, te, Ks, w, h)
    bg, pg = renderer.footprints(Rg, tg, Ks, w, h)
    meet = (np.maximum(be[:, 0], bg[:, 0]) < np.minimum(be[:, 1], bg[:, 1])) & \
           (np.maximum(be[:, 2], bg[:, 2]) < np.minimum(be[:, 3], bg[:, 3]))
    todo = np.flatnonzero(meet)
    area = (be[:, 1] - be[:, 0]) * (be[:, 3] - be[:, 2]) + (bg[:, 1] - bg[:, 0]) * (bg[:, 3] - bg[:, 2])
    start = 0
    while start < len(todo):  # chunks of about max_rays rays
        cum = np.cumsum(area[todo[start:]])
        stop = start + max(1, int(np.searchsorted(cum, max_rays, side="right")))
        idx = todo[start:stop]
        start = stop
        out[idx] = _vsd_lists(renderer, Re[idx], te[idx], Rg[idx], tg[idx], Ks[idx], be[idx], bg[idx],
                              [pe[i] for i in idx], [pg[i] for i in idx], depth_test, image[idx], diameter,
                              delta, taus)
    return out


def _vsd_lists(renderer, Re, te, Rg, tg, Ks, be, bg, pe, pg, depth_test, image, diameter, delta, taus):
    n = len(Re)
    V0 = np.minimum(be[:, 0], bg[:, 0])
    U0 = np.minimum(be[:, 2], bg[:, 2])
    W = np.maximum(be[:, 3], bg[:, 3]) - U0
    Hh = np.maximum(be[:, 1], bg[:, 1]) - V0
    off = np.cumsum(W * Hh) - W * Hh  # each pose's raster (its two boxes' union) in one canvas
    lists = {}
    for key, R, t, bx, polys in (("g", Rg, tg, bg, pg), ("e", Re, te, be, pe)):
        px = [_footprint_pixels(polys[j], bx[j], int(U0[j]), int(V0[j]), int(W[j])) for j in range(n)]
        cnt = np.array([len(q[0]) for q in px], np.int64)
        ends = np.cumsum(cnt)
        tot = int(ends[-1]) if n else 0
        rays = np.empty((tot, 6), np.float32)
        nrm = np.empty(tot)
        dt = np.empty(tot)
        cidx = np.empty(tot, np.int64)
        for j, (ys, xs, fl) in enumerate(px):
            a, b = int(ends[j] - cnt[j]), int(ends[j])
            Kj = Ks[j]
            v = ys + V0[j]
            u = xs + U0[j]
            y = (v - Kj[1, 2]) / Kj[1, 1]
            x = (u - Kj[0, 2] - Kj[0, 1] * y) / Kj[0, 0]
            Rj = R[j]
            for i in range(3):  # R^T (x, y, 1): the rays in the model frame
                rays[a:b, 3 + i] = x * Rj[0, i] + y * Rj[1, i] + Rj[2, i]
            rays[a:b, :3] = (-Rj.T @ t[j]).astype(np.float32)
            q = np.sqrt(x * x + y * y + 1.0)
            nrm[a:b] = q
            dt[a:b] = depth_test[image[j]][v, u] * q
            cidx[a:b] = fl + off[j]
        z = renderer.cast_rays(rays) * nrm
        lists[key] = (cidx, z, dt, np.repeat(np.arange(n), cnt))
    cg, dg, dtg, pgi = lists["g"]
    ce, de, dte, pei = lists["e"]
    total = int(off[-1] + W[-1] * Hh[-1])
    vg = (dg > 0) & (((dg.astype(np.float32) - dtg.astype(np.float32)) <= delta) | (dtg == 0))
    vg_c = np.zeros(total, bool)
    vg_c[cg[vg]] = True
    dg_c = np.zeros(total, np.float64)
    dg_c[cg] = dg
    vge = vg_c[ce]
    hit = de > 0
    ve = hit & ((((de.astype(np.float32) - dte.astype(np.float32)) <= delta) | (dte == 0)) | vge)
    inter = ve & vge
    n_vg = np.bincount(pgi[vg], minlength=n)
    n_ve = np.bincount(pei[ve], minlength=n)
    n_inter = np.bincount(pei[inter], minlength=n)
    n_union = n_vg + n_ve - n_inter
    dist = np.abs(dg_c[ce[inter]] - de[inter]) / diameter
    k = np.searchsorted(taus, dist, side="right")  # the taus with dist >= tau: the first k
    T = len(taus)
    hist = np.bincount(pei[inter] * (T + 1) + k, minlength=n * (T + 1)).reshape(n, T + 1)
    cost = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (n,T): #{dist >= tau_i}
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (cost + (n_union - n_inter)[:, None]) / n_union[:, None]
    e[n_union == 0] = 1.0
    return e


# --- exact MSSD / MSPD by branch and bound ----------------------------------------------------
@dataclass
class TreeLevel:
    rep: np.ndarray  # (n,) index (into the tree's points) of each node's representative point
    r: np.ndarray  # (n,) largest distance from the representative to the node's points
    child_start: np.ndarray  # (n,) first child in the next level
    child_count: np.ndarray  # (n,)


@dataclass
class PointTree:
    """Nested clusters of points (recursive median splits along the longest box side): level 0
    has about ``first`` nodes, each next level splits every node into up to ``branching``
    children, the last level holds single points (r = 0). A node's representative is its point
    nearest to the node's centroid."""

    pts: np.ndarray
    levels: list
    screen: np.ndarray = None  # (k,) indices of a few spread-out points (farthest-point order)


def _spread_points(P: np.ndarray, k: int) -> np.ndarray:
    """Indices of k points of P by farthest-point sampling, from the point farthest from the centroid."""
    i = int(np.argmax(((P - P.mean(0)) ** 2).sum(1)))
    out = [i]
    d = ((P - P[i]) ** 2).sum(1)
    for _ in range(min(k, len(P)) - 1):
        i = int(np.argmax(d))
        out.append(i)
        d = np.minimum(d, ((P - P[i]) ** 2).sum(1))
    return np.array(out, np.int64)


def make_point_tree(P: np.ndarray, first: int = 32, branching: int = 2) -> PointTree:
    P = _pts(P)
    order, history = _median_splits(P, 1)
    D = len(history) - 1
    step = max(1, int(round(np.log2(branching))))
    d0 = min(D, max(0, int(np.ceil(np.log2(max(1, first))))))
    depths = list(range(d0, D, step)) + [D]
    X = P[order]
    levels = []
    for li, dep in enumerate(depths):
        c = history[dep]
        starts, sizes = c[:-1], np.diff(c)
        seg = np.repeat(np.arange(len(sizes)), sizes)
        cen = np.add.reduceat(X, starts) / sizes[:, None]
        dc = ((X - cen[seg]) ** 2).sum(1)
        srt = np.lexsort((dc, seg))
        rep = order[srt[starts]]
        r = np.sqrt(np.maximum.reduceat(((X - P[rep][seg]) ** 2).sum(1), starts))
        if li + 1 < len(depths):
            nxt = history[depths[li + 1]]
            cs = np.searchsorted(nxt, starts)
            cc = np.searchsorted(nxt, c[1:]) - cs
        else:
            cs = cc = np.zeros(len(starts), np.int64)
        levels.append(TreeLevel(rep, r, cs, cc))
    return PointTree(P, levels, _spread_points(P, 8))


def _seg_starts(key: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, np.int64)


def _minmax_bnb(tree: PointTree, B: int, screen, prep, items, cutoff: float, chunk: int, binof=None,
                first: int = 3):
    """min over symmetries s of max over the tree's points of a per-point error, per pose, by
    branch and bound. ``screen(b0, b1) -> (lower (b,S), brute (b,))``: per (pose, symmetry) a lower
    bound of its maximum (the error at a few actual points), and the poses left to the caller (nan);
    ``prep(b, s)``: what ``items`` needs per (pose, symmetry) pair; ``items(prep, pair, p, r) ->
    (v, gap)``: for (pair, node) items the error at the node's representative point p and a bound
    of how much more it can be over the node (radius r).

    Per pose an interval [lo, hi] of the error is kept (lo from values at actual points, hi from
    the bounds). Level 0 is first evaluated for the ``first`` symmetries with the smallest screening
    bounds (hi), then for every symmetry whose screening bound does not exceed that hi; a symmetry
    whose lower bound exceeds the pose's hi cannot be the minimum, a node whose upper bound is
    below its symmetry's lower bound cannot hold the maximum; the rest is refined level by level.
    A pose stops when lo >= ``cutoff`` (the interval then only says so), when ``binof`` (a
    function (values, pose indices) -> int bins, e.g. the number of thresholds passed) gives lo
    and hi the same bin, or at the points (lo == hi: exact). Returns (lo (B,), hi (B,))."""
    lo_out = np.full(B, np.nan)
    hi_out = np.full(B, np.nan)
    tol = _BNB_TOL
    L0 = tree.levels[0]
    M0 = len(L0.rep)

    def settled(ids, lo, hi):
        if binof is None:
            return (hi <= lo) | (lo >= cutoff)
        return (binof(lo, ids) == binof(hi, ids)) | (lo >= cutoff)

    def level0(pb, ps):
        """(prep, item values, item upper bounds) of pairs (pb, ps) over every level-0 node."""
        pd = prep(b0 + pb, ps)
        n = len(pb)
        iv, ig = items(pd, np.repeat(np.arange(n), M0), np.tile(L0.rep, n), np.tile(L0.r, n))
        return pd, iv, iv + ig

    for b0 in range(0, B, chunk):
        b1 = min(B, b0 + chunk)
        nb = b1 - b0
        Ls, brute = screen(b0, b1)
        S = Ls.shape[1]
        Plo = Ls.min(axis=1)
        Phi = np.full(nb, np.inf)
        cut_lo = np.where(Ls >= cutoff, Ls, np.inf).min(axis=1)
        done = brute | (Plo >= cutoff)
        # an upper bound from the most promising symmetries
        q = min(first, S)
        top = np.argpartition(Ls, q - 1, axis=1)[:, :q] if q < S else np.broadcast_to(np.arange(S), (nb, S))
        m1 = np.zeros((nb, S), bool)
        m1[np.arange(nb)[:, None], top] = True
        m1 &= (Ls < cutoff) & ~done[:, None]
        pb, ps = np.nonzero(m1)
        if len(pb):
            _, _, ihi = level0(pb, ps)
            np.minimum.at(Phi, pb, ihi.reshape(len(pb), M0).max(axis=1))
        open_ = ~done
        done[open_] = settled(b0 + np.flatnonzero(open_), Plo[open_], Phi[open_])
        # level 0 for every symmetry that can beat it
        pb, ps = np.nonzero((Ls <= Phi[:, None] + tol) & (Ls < cutoff) & ~done[:, None])
        n = len(pb)
        plo = Ls[pb, ps].copy()
        alive = np.ones(n, bool)
        ipair = np.repeat(np.arange(n), M0)
        inode = np.tile(np.arange(M0), n)
        pdata = prep(b0 + pb, ps) if n else None
        for li in range(len(tree.levels)):
            if len(ipair) == 0:
                break
            L = tree.levels[li]
            if li > 0:
                prev = tree.levels[li - 1]
                cs, cc = prev.child_start[inode], prev.child_count[inode]
                ipair = np.repeat(ipair, cc)
                inode = np.repeat(cs - (np.cumsum(cc) - cc), cc) + np.arange(int(cc.sum()))
            iv, ig = items(pdata, ipair, L.rep[inode], L.r[inode])
            ihi = iv + ig
            st = _seg_starts(ipair)
            up = ipair[st]
            plo[up] = np.maximum(plo[up], np.maximum.reduceat(iv, st))
            phi = np.full(n, np.inf)
            phi[up] = np.maximum.reduceat(ihi, st)
            has = np.zeros(n, bool)
            has[up] = True
            alive &= has
            cut = alive & (plo >= cutoff)
            if cut.any():
                np.minimum.at(cut_lo, pb[cut], plo[cut])
            live = np.flatnonzero(alive)
            if len(live):  # per pose: the interval over its live symmetries
                sb = _seg_starts(pb[live])
                pose = pb[live][sb]
                Phi[pose] = np.minimum(Phi[pose], np.minimum.reduceat(phi[live], sb))
                Plo[pose] = np.maximum(Plo[pose], np.minimum(cut_lo[pose], np.minimum.reduceat(plo[live], sb)))
            open_ = ~done
            done[open_] = settled(b0 + np.flatnonzero(open_), Plo[open_], Phi[open_])
            alive &= (plo <= Phi[pb] + tol) & (plo < cutoff) & ~done[pb]
            k = alive[ipair] & (ihi >= plo[ipair] - tol)
            ipair, inode = ipair[k], inode[k]
        # poses still open have been refined to the points: the minimum over live symmetries is exact
        best = np.full(nb, np.inf)
        if alive.any():
            np.minimum.at(best, pb[alive], plo[alive])
        left = ~done
        val = np.minimum(best, cut_lo)
        Plo[left] = val[left]
        Phi[left] = np.where(best[left] <= cut_lo[left], val[left], np.maximum(Phi[left], val[left]))
        lo_out[b0:b1] = np.where(brute, np.nan, Plo)
        hi_out[b0:b1] = np.where(brute, np.nan, np.maximum(Phi, Plo))
    return lo_out, hi_out


def _sym_images(model: "ModelPoints", tree: PointTree) -> np.ndarray:
    """(S,k,3) the symmetric images R_s c + t_s of the tree's screening points (cached per tree)."""
    key = id(tree)
    cache = model.__dict__.setdefault("_sym_img", {})
    if key not in cache:
        R, t = model.syms
        C = tree.pts[tree.screen]
        cache[key] = np.einsum("sij,kj->ski", R, C) + t[:, None, :]
    return cache[key]


def _dense_chunk(S: int, M0: int) -> int:
    return max(1, (1 << 20) // max(1, S * M0))


def mssd_fast(model: "ModelPoints", R_est, t_est, R_gt, t_gt, cutoff: float = np.inf, binof=None) -> Bounds:
    """MSSD of B poses of one object (mm): intervals [lo, hi] (B,) holding :func:`mssd`; exact
    (lo == hi) by default. With ``cutoff`` a pose whose error is >= cutoff stops there (lo >=
    cutoff); with ``binof`` (see :func:`_minmax_bnb`) a pose stops once lo and hi are in one bin
    (decisions against thresholds are then exact at a fraction of the cost). The maximum of the convex
    |D p + d| over the points is attained on their convex hull, so only hull vertices count. In
    the ground truth's frame a point's error is |Q p + c - (R_s p + t_s)| (Q = R_g^T R_e,
    c = R_g^T (t_e - t_g)); over a node of radius r around its representative it exceeds the
    representative's by at most |Q - R_s|_2 r. Branch and bound over (symmetry, node) keeps only
    the symmetries that can be the minimum and the nodes that can hold the maximum."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    B = len(Re)
    if B == 0:
        return Bounds(np.zeros(0), np.zeros(0), np.zeros(0))
    tree = model.hull_tree
    symR, symt = model.syms
    Q = np.einsum("bji,bjk->bik", Rg, Re)
    c = np.einsum("bji,bj->bi", Rg, te - tg)
    C0 = tree.pts[tree.screen]
    Y0 = _sym_images(model, tree)  # (S,k,3)
    yy = (Y0 * Y0).sum(-1)  # (S,k)
    YT = np.ascontiguousarray(Y0.transpose(1, 2, 0))  # (k,3,S)

    def screen(b0, b1):
        a = np.einsum("bij,kj->bki", Q[b0:b1], C0) + c[b0:b1, None, :]  # (b,k,3)
        aa = (a * a).sum(-1)  # (b,k)
        dot = np.matmul(a.transpose(1, 0, 2), YT).transpose(1, 2, 0)  # (b,S,k)
        v2 = aa[:, None, :] + yy[None] - 2 * dot
        slack = 1e-6 * np.sqrt(aa[:, None, :] + yy[None])  # rounding of the expansion
        v = np.maximum(np.sqrt(np.maximum(v2, 0.0)) - slack, 0.0)
        return v.max(axis=2), np.zeros(b1 - b0, bool)

    def prep(b, s):  # per pair: [Q - R_s | c - t_s] and sigma = |Q - R_s|_2
        W = np.concatenate([Q[b] - symR[s], (c[b] - symt[s])[:, :, None]], axis=2)
        tr = np.einsum("nij,nij->n", Q[b], symR[s])
        return W, np.sqrt(np.maximum(3.0 - tr, 0.0)) * (1 + 1e-9) + 1e-7

    def items(pd, ip, p, r):
        W, sig = pd
        X = tree.pts[p]
        E = np.einsum("nij,nj->ni", W[ip][:, :, :3], X) + W[ip][:, :, 3]
        return np.sqrt((E * E).sum(1)), sig[ip] * r

    lo, hi = _minmax_bnb(tree, B, screen, prep, items, cutoff, _dense_chunk(len(symR), 4 * len(C0)), binof)
    return Bounds(lo, hi, np.where(hi > lo, 0.5 * (lo + hi), lo))


def _region_bounds(model: "ModelPoints", Re, te, Rg, tg, K):
    """Per pose: bounds L of |J pi| and H of the derivative of J pi (pixel per mm, per mm^2) over a
    box holding the model in the estimated pose and every symmetric image of it in the ground-truth
    pose, and that box's smallest depth."""
    m = model.centre
    rho = model.radius
    ms, rs = model.sym_centre
    ce = Re @ m + te
    cg = Rg @ ms + tg
    rg = rho + rs
    zmin = np.minimum(ce[:, 2] - rho, cg[:, 2] - rg)
    ax = np.maximum(np.abs(ce[:, 0]) + rho, np.abs(cg[:, 0]) + rg)
    ay = np.maximum(np.abs(ce[:, 1]) + rho, np.abs(cg[:, 1]) + rg)
    fx, fy, sk = np.abs(K[:, 0, 0]), np.abs(K[:, 1, 1]), np.abs(K[:, 0, 1])
    z = np.where(zmin > 1.0, zmin, 1.0)
    a = fx * ax + sk * ay
    b = fy * ay
    f2 = fx * fx + sk * sk + fy * fy
    L = np.sqrt(f2 / z ** 2 + (a * a + b * b) / z ** 4)
    H = np.sqrt(2 * f2 / z ** 4 + 4 * (a * a + b * b) / z ** 6)
    return L * (1 + 1e-9), H * (1 + 1e-9), zmin


def mspd_fast(model: "ModelPoints", R_est, t_est, R_gt, t_gt, K, cutoff: float = np.inf, binof=None) -> Bounds:
    """MSPD of B poses of one object (px): intervals [lo, hi] holding :func:`mspd`, exact by
    default; ``cutoff`` and ``binof`` as in :func:`mssd_fast`. With X = R_e p + t_e and
    Y = R_g (R_s p + t_s) + t_g, the error f(p) = pi(X) - pi(Y) changes over a node of radius r by
    at most r (L s + H (|X - Y| + s r)) at its representative, s = |R_e - R_g R_s|_2, L and H
    bounding the projection's first and second derivatives where the posed model lies
    (:func:`_region_bounds`); branch and bound as in :func:`mssd_fast`. Poses with a point at depth
    <= 0 have error inf; poses whose region reaches within 1 mm of the camera plane are computed
    point by point."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    B = len(Re)
    if B == 0:
        return Bounds(np.zeros(0), np.zeros(0), np.zeros(0))
    tree = model.pts_tree
    symR, symt = model.syms
    Q = np.einsum("bji,bjk->bik", Rg, Re)
    C0 = tree.pts[tree.screen]
    Y0 = _sym_images(model, tree)  # (S,k,3)
    S, k = Y0.shape[:2]
    Yf = np.ascontiguousarray(Y0.reshape(-1, 3).T)  # (3,S*k)
    Lb, Hb, zmin = _region_bounds(model, Re, te, Rg, tg, Ks)
    # an estimate with a model point at depth <= 0 (the minimum depth is at a hull vertex): inf
    ze_min = (np.einsum("bj,nj->bn", Re[:, 2], model.pts[model.hull_idx]) + te[:, 2:3]).min(axis=1)
    behind = ze_min <= 0

    def proj(Hh):  # (b,3,n) homogeneous -> (b,2,n), inf at depth <= 0
        z = Hh[:, 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = Hh[:, :2] / z
        return np.where(z > 0, uv, np.inf)

    def screen(b0, b1):
        sl = slice(b0, b1)
        ue = proj(np.matmul(Ks[sl], np.matmul(Re[sl], C0.T) + te[sl, :, None]))  # (b,2,k)
        ug = proj(np.matmul(np.matmul(Ks[sl], Rg[sl]), Yf) + np.einsum("bij,bj->bi", Ks[sl], tg[sl])[:, :, None])
        ug = ug.reshape(b1 - b0, 2, S, k)
        with np.errstate(invalid="ignore"):
            dv = ue[:, :, None, :] - ug
            v = np.sqrt((dv * dv).sum(1))  # (b,S,k)
        v[~np.isfinite(v)] = np.inf
        lo = np.maximum(v.max(axis=2) * (1 - 1e-9) - 1e-9, 0.0)
        lo[behind[sl]] = np.inf
        brute = (zmin[sl] <= 1.0) & ~behind[sl] & (lo.min(axis=1) < cutoff)
        return lo, brute

    def prep(b, s):  # per pair: rows K[R_e|t_e], K[R'|t'], [R_e - R'|t_e - t'] (R' = R_g R_s, t' = R_g t_s + t_g)
        Rp = np.matmul(Rg[b], symR[s])
        tp = np.einsum("nij,nj->ni", Rg[b], symt[s]) + tg[b]
        Me = np.concatenate([Re[b], te[b, :, None]], axis=2)
        Mg = np.concatenate([Rp, tp[:, :, None]], axis=2)
        W = np.concatenate([np.matmul(Ks[b], Me), np.matmul(Ks[b], Mg), Me - Mg], axis=1)  # (n,9,4)
        tr = np.einsum("nij,nij->n", Q[b], symR[s])
        sig = np.sqrt(np.maximum(3.0 - tr, 0.0)) * (1 + 1e-9) + 1e-7  # |R_e - R_g R_s|_2
        return np.ascontiguousarray(W), sig, Lb[b], Hb[b]

    def items(pd, ip, p, r):
        W, sig, Lp, Hp = pd
        Wi = W[ip]
        E = np.einsum("nij,nj->ni", Wi[:, :, :3], tree.pts[p]) + Wi[:, :, 3]  # (n,9)
        with np.errstate(divide="ignore", invalid="ignore"):
            du = E[:, 0] / E[:, 2] - E[:, 3] / E[:, 5]
            dv = E[:, 1] / E[:, 2] - E[:, 4] / E[:, 5]
            v = np.sqrt(du * du + dv * dv)
        v[(E[:, 2] <= 0) | (E[:, 5] <= 0) | ~np.isfinite(v)] = np.inf
        D = np.sqrt((E[:, 6:] ** 2).sum(1))
        sg = sig[ip]
        return v, r * (Lp[ip] * sg + Hp[ip] * (D + sg * r)) + 1e-9 * np.where(np.isfinite(v), v, 0)

    lo, hi = _minmax_bnb(tree, B, screen, prep, items, cutoff, _dense_chunk(S, 4 * k), binof)
    for b in np.flatnonzero(np.isnan(lo)):  # near the camera plane: point by point
        lo[b] = hi[b] = mspd(Re[b], te[b], Rg[b], tg[b], Ks[b], model.pts, model.syms)
    lo[behind] = hi[behind] = np.inf
    return Bounds(lo, hi, np.where(hi > lo, 0.5 * (lo + hi), lo))


__all__ += [
    "VSD_DELTA", "VSD_TAUS", "VSD_THRESHOLDS", "MSSD_THRESHOLDS", "MSPD_THRESHOLDS", "MSPD_WIDTH",
    "MAX_SYM_DISC_STEP", "rotation_about", "symmetry_transformations", "project_points", "mssd", "mspd",
    "ray_norms", "distance_image", "vsd_from_depths", "DepthRenderer", "vsd_batch", "TreeLevel", "PointTree",
    "make_point_tree", "mssd_fast", "mspd_fast",
]
