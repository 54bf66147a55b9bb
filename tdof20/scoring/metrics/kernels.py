"""Fast kernels of the ADD family: many poses of one object at once, with rigorous error bounds,
on what :class:`~tdof20.scoring.metrics.model_points.ModelPoints` precomputes per object; each
equals (or bounds) its reference in :mod:`tdof20.scoring.metrics.reference`.

* :func:`add_fast_with_error`: ADD as float32 matrix products (|D p + d|^2 is a quadratic form
  in p: 10 monomials of the centred points times 10 coefficients per pose) with a bound of the
  rounding error; poses within it of a threshold are recomputed in float64.
* :func:`proj2d_bounds`: a rigorous interval of the 2D projection error from clusters of model
  points (a Taylor expansion with a bound of the projection's second derivative, and Jensen);
  :func:`proj2d_fast` the exact value (float32, float64 near a threshold).
* ADD-S, where the nearest-neighbour search is the cost, is bounded first and computed exactly
  only where needed. In the estimate's model frame a ground-truth-posed point is q = A p + b
  (:func:`~tdof20.scoring.metrics.reference.relative_transform`) and its error is dist(q, P). A
  grid over the model's box (plus a margin) holds at each node g the exact dist(g, P) and the
  nearest point P[idx(g)].
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
  correct the estimates (for AUCs), see :mod:`tdof20.scoring.scorer`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tdof20.scoring.metrics.model_points import Bounds, DistanceGrid, ModelPoints
from tdof20.scoring.metrics.reference import _Ks, _chunks, _poses, add_batch, proj2d_batch

_PAIRS = 1 << 16  # (pose, point) pairs per float32 chunk: arrays of ~256 KB stay in cache
_F32_REL, _F32_ABS = 1e-5, 1e-4  # widening of float32 bounds (relative, mm)


def _widen(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.maximum(lo * (1 - _F32_REL) - _F32_ABS, 0.0), hi * (1 + _F32_REL) + _F32_ABS


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
