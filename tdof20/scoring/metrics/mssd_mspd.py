"""BOP19's MSSD and MSPD (bop_toolkit ``pose_error.py``, ``eval_calc_errors.py``), and the object
symmetries they minimise over.

* :func:`symmetry_transformations`: a models_info.json entry's symmetries as BOP discretises them.
* References, one pose: :func:`mssd` (mm), :func:`mspd` (px).
* Fast, many poses of one object: :func:`mssd_fast` and :func:`mspd_fast` compute the min over
  symmetries of the max over points by branch and bound over (symmetry, node of a
  :class:`~tdof20.scoring.metrics.model_points.PointTree`), exactly, or (``binof``) only until each
  error's position among the thresholds is certain.
"""

from __future__ import annotations

import numpy as np

from tdof20.scoring.metrics.model_points import Bounds, ModelPoints, PointTree
from tdof20.scoring.metrics.reference import _Ks, _poses, _pts

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


# --- exact MSSD / MSPD by branch and bound ----------------------------------------------------
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


def _sym_images(model: ModelPoints, tree: PointTree) -> np.ndarray:
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


def mssd_fast(model: ModelPoints, R_est, t_est, R_gt, t_gt, cutoff: float = np.inf, binof=None) -> Bounds:
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


def _region_bounds(model: ModelPoints, Re, te, Rg, tg, K):
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


def mspd_fast(model: ModelPoints, R_est, t_est, R_gt, t_gt, K, cutoff: float = np.inf, binof=None) -> Bounds:
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
