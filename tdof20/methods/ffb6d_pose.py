"""FFB6D's pose recovery (PVN3D's, as FFB6D's original code does it): per object, MeanShift
clustering of the points' centre votes and keypoint votes, then least squares (Kabsch) of the
model's keypoints onto the voted ones; and a synthetic vote set to measure it without a network.

    rows = recover_poses(points, classes, ctr_ofs, kp_ofs, model_kps, bandwidth=40.0)
    votes = example_votes(meta)            # {"points", "classes", "ctr_ofs", "kp_ofs", "model_kps", "poses"}
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tdof20.methods.base import MethodMeta
from tdof20.methods.fitting import kabsch_torch


def gaussian_weights(d: torch.Tensor, bandwidth: float) -> torch.Tensor:
    return torch.exp(-0.5 * (d / bandwidth) ** 2)


def _even_picks(valid: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``k`` evenly spaced indices among the valid entries of each row of ``valid`` (G,N) ->
    (idx (G,k), ok (G,k)); ok is False for repeats (a row with fewer than k valid entries) and for
    rows without a valid entry."""
    G, N = valid.shape
    n = valid.sum(1)
    ranks = valid.long().cumsum(1)                                         # (G,N) sorted per row
    want = torch.arange(k, device=valid.device)[None] * n[:, None] // k + 1  # (G,k) 1-based ranks
    idx = torch.searchsorted(ranks, want).clamp_max(N - 1)
    ok = (n > 0)[:, None].expand(G, k).clone()
    ok[:, 1:] &= idx[:, 1:] != idx[:, :-1]
    return idx, ok


def _shift(C: torch.Tensor, A: torch.Tensor, m: torch.Tensor, bw2: float) -> torch.Tensor:
    """One Gaussian mean-shift step of the seeds C (g,S,3) over the votes A (g,M,3) weighted by m (g,M)."""
    d2 = (C.square().sum(-1)[:, :, None] + A.square().sum(-1)[:, None, :]
          - 2.0 * torch.bmm(C, A.transpose(1, 2))).clamp_min_(0.0)
    w = torch.exp_(d2.mul_(-0.5 / bw2)).mul_(m[:, None, :])
    ws = w.sum(2, keepdim=True)
    new = torch.bmm(w, A) / ws.clamp_min(1e-30)
    return torch.where(ws > 0, new, C)                                    # a seed with no vote in reach stays


def _iterate(C: torch.Tensor, A: torch.Tensor, m: torch.Tensor, bw: float, tol: float, max_iter: int,
             max_elements: int) -> tuple[torch.Tensor, int, int]:
    """Mean-shift the seeds C (G,S,3) over the fixed votes A (G,M,3) (weights m (G,M)) until no seed
    of a group moves ``tol`` or more (or ``max_iter``); groups that have converged drop out, the
    others go in chunks of at most ``max_elements`` kernel entries. -> (C, iterations, kernel entries)."""
    G, S, _ = C.shape
    M = A.shape[1]
    step = max(1, int(max_elements) // max(1, S * M))
    active = torch.ones(G, dtype=torch.bool, device=C.device)
    it = work = 0
    for it in range(1, int(max_iter) + 1):
        run = torch.nonzero(active, as_tuple=False)[:, 0]
        if run.numel() == 0:
            it -= 1
            break
        for r0 in range(0, run.numel(), step):
            r = run[r0:r0 + step]
            cr = C[r]
            new = _shift(cr, A[r], m[r], bw * bw)
            active[r] = ((new - cr).norm(dim=-1) >= tol).any(1)
            C[r] = new
        work += int(run.numel()) * S * M
    return C, it, work


def meanshift(points: torch.Tensor, valid: torch.Tensor | None = None, bandwidth: float = 40.0,
              max_iter: int = 300, n_seeds: int = 32, seed_votes: int = 512, seed_iters: int = 20,
              tol: float = 1e-3, max_elements: int = 2 ** 22, stats: dict | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched MeanShift (Gaussian kernel) over groups of votes, with bounded work.

    1. ``n_seeds`` seeds, evenly spaced among each group's valid votes, mean-shift over (at most)
       ``seed_votes`` evenly spaced votes for at most ``seed_iters`` iterations (a group stops when
       no seed moves bandwidth/100);
    2. the winner is the seed with the most votes within one bandwidth (all votes), as PVN3D/FFB6D's
       ``MeanShiftTorch.fit`` picks its biggest cluster;
    3. the winner alone mean-shifts over all the votes until it moves less than ``tol`` x bandwidth
       (the original's stop threshold, 1e-3) or ``max_iter`` (the original's 300).

    The inliers are the votes within one bandwidth of that mode (the original's labels); the mode
    returned is the coordinate-wise median of the inliers (the kernel-weighted mean is pulled by the
    outliers that happen to lie within a bandwidth or two of the cluster). The original runs a
    blurring MeanShift with every vote as a seed: N^2 kernel entries per iteration for up to 300
    iterations; here the work is at most G x (S x seed_votes x seed_iters + S x N + N x max_iter).

    points (G,N,3), valid (G,N) bool -> (mode (G,3), inliers (G,N) bool). Groups without a valid
    vote get NaN. Work is chunked over groups to stay under ``max_elements`` kernel entries.
    ``stats`` (a dict), when given, is updated: groups, seeds, seed_votes, votes (this call's sizes),
    seed_iters / refine_iters (the most iterations used), kernel_evals (kernel entries computed, summed).
    """
    G, N, _ = points.shape
    dev = points.device
    if valid is None:
        valid = torch.ones(G, N, dtype=torch.bool, device=dev)
    A = points.to(torch.float32)
    valid = valid & torch.isfinite(A).all(-1)
    gi = torch.arange(G, device=dev)
    has = valid.any(1)
    if G == 0 or N == 0:
        return A.new_full((G, 3), float("nan")), valid
    # centred on a vote of the group: float32 distances in mm stay exact far from the camera
    ref = A[gi, valid.to(torch.uint8).argmax(1)]
    ref = torch.where(has[:, None], ref, torch.zeros_like(ref))
    A = torch.where(valid[..., None], A - ref[:, None], torch.zeros_like(A))
    wv = valid.to(A.dtype)
    bw = float(bandwidth)
    # 1. seeds over a subset of the votes
    S = max(1, min(int(n_seeds), N))
    si, sok = _even_picks(valid, S)
    C = A[gi[:, None], si]
    if N > int(seed_votes):
        vi, vok = _even_picks(valid, int(seed_votes))
        As, ms = A[gi[:, None], vi], vok.to(A.dtype)
    else:
        As, ms = A, wv
    C, it1, work1 = _iterate(C, As, ms, bw, bw * 1e-2, min(int(max_iter), int(seed_iters)), max_elements)
    # 2. the seed with the most votes within one bandwidth
    count = torch.empty(G, S, dtype=torch.long, device=dev)
    step = max(1, int(max_elements) // max(1, S * N))
    for g0 in range(0, G, step):
        c, a = C[g0:g0 + step], A[g0:g0 + step]
        d2 = c.square().sum(-1)[:, :, None] + a.square().sum(-1)[:, None, :] \
            - 2.0 * torch.bmm(c, a.transpose(1, 2))
        count[g0:g0 + step] = ((d2 < bw * bw) & valid[g0:g0 + step, None, :]).sum(2)
    count = count.masked_fill(~sok, -1)
    best = C[gi, count.argmax(1)][:, None]                                 # (G,1,3)
    # 3. the winner over all votes
    best, it2, work2 = _iterate(best, A, wv, bw, bw * float(tol), int(max_iter), max_elements)
    inl = ((A - best).norm(dim=-1) < bw) & valid
    inl = inl | (valid & ~inl.any(1, keepdim=True))
    mode = torch.where(inl[..., None], A, torch.full_like(A, float("nan"))).nanmedian(dim=1).values + ref
    mode = torch.where(has[:, None], mode, torch.full_like(mode, float("nan")))
    if stats is not None:
        stats.update(groups=G, seeds=S, seed_votes=int(As.shape[1]), votes=N,
                     seed_iters=max(it1, int(stats.get("seed_iters", 0))),
                     refine_iters=max(it2, int(stats.get("refine_iters", 0))),
                     kernel_evals=int(stats.get("kernel_evals", 0)) + work1 + work2 + G * S * N)
    return mode, inl


def _subset(mask: torch.Tensor, cap: int, gen: torch.Generator | None) -> torch.Tensor:
    """Indices (n,) of the True entries of mask (N,), a random subset of ``cap`` when more."""
    idx = torch.nonzero(mask, as_tuple=False)[:, 0]
    if idx.numel() > cap:
        perm = torch.randperm(idx.numel(), generator=gen, device="cpu")[:cap].to(idx.device)
        idx = idx[perm]
    return idx


def recover_poses(points: torch.Tensor, classes: torch.Tensor, ctr_ofs: torch.Tensor, kp_ofs: torch.Tensor,
                  model_kps: torch.Tensor, bandwidth: float = 40.0, max_iter: int = 300, max_votes: int = 4000,
                  min_points: int = 10, generator: torch.Generator | None = None, scores: torch.Tensor | None = None,
                  n_seeds: int = 32, seed_votes: int = 512, seed_iters: int = 20, tol: float = 1e-3,
                  stats: dict | None = None) -> list[tuple[int, int, float, np.ndarray, np.ndarray]]:
    """PVN3D's voting + least squares for a batch, in mm.

    points (B,N,3) mm; classes (B,N) class index per point (0 = background); ctr_ofs (B,N,3) and
    kp_ofs (B,K-1,N,3) in mm (point minus keypoint); model_kps (C,K,3) mm by class, centre first;
    scores (B,N) optional per-point class confidence. Returns rows (b, class index, score, R, t mm):
    one per (image, class) with at least ``min_points`` points; score = the share of the class's
    points that the centre MeanShift keeps (times their mean confidence when ``scores`` is given).
    n_seeds, seed_votes, seed_iters, tol: :func:`meanshift`'s; ``stats`` (a dict), when given, gets
    the work of both MeanShift calls (centres, then keypoints) under "ctr" and "kp".
    """
    B, N, _ = points.shape
    Km1 = kp_ofs.shape[1]
    groups = []                                                            # (b, c, idx)
    for b in range(B):
        for c in torch.unique(classes[b]).tolist():
            if c == 0:
                continue
            m = classes[b] == c
            if int(m.sum()) >= int(min_points):
                groups.append((b, int(c), _subset(m, int(max_votes), generator)))
    if not groups:
        return []
    G = len(groups)
    M = max(int(g[2].numel()) for g in groups)
    P = points.new_zeros(G, M, 3)
    V = torch.zeros(G, M, dtype=torch.bool, device=points.device)
    KV = points.new_zeros(G, Km1, M, 3)
    for g, (b, c, idx) in enumerate(groups):
        n = idx.numel()
        P[g, :n] = points[b, idx] - ctr_ofs[b, idx]
        KV[g, :, :n] = points[b, idx][None] - kp_ofs[b][:, idx]
        V[g, :n] = True
    ms = dict(bandwidth=bandwidth, max_iter=max_iter, n_seeds=n_seeds, seed_votes=seed_votes,
              seed_iters=seed_iters, tol=tol)
    st = {} if stats is None else stats
    st.setdefault("ctr", {})
    st.setdefault("kp", {})
    ctr, inl = meanshift(P.float(), V, stats=st["ctr"], **ms)
    inl = torch.where(inl.any(1, keepdim=True), inl, V)                    # no inlier: keep all
    kps, _ = meanshift(KV.reshape(G * Km1, M, 3).float(), inl[:, None].expand(G, Km1, M).reshape(G * Km1, M),
                       stats=st["kp"], **ms)
    voted = torch.cat([ctr[:, None], kps.view(G, Km1, 3)], dim=1)          # (G,K,3) centre first
    src = torch.stack([model_kps[c] for _, c, _ in groups]).to(voted)
    R, t = kabsch_torch(src.double(), voted.double())
    rows = []
    for g, (b, c, idx) in enumerate(groups):
        if not (torch.isfinite(R[g]).all() and torch.isfinite(t[g]).all()):
            continue
        n = idx.numel()
        score = float(inl[g].sum()) / max(1, n)
        if scores is not None:
            score *= float(scores[b, idx].float().mean())
        rows.append((b, c, score, R[g].cpu().numpy(), t[g].cpu().numpy()))
    return rows


def example_votes(meta: MethodMeta, n_points: int = 12800, object_share: float = 0.6, outliers: float = 0.3,
                  noise_mm: float = 2.0, seed: int = 0) -> dict:
    """A vote set of one image for :func:`recover_poses` (profiling and tests, no network): the
    ``n_points`` sampled points, ``object_share`` of them split evenly over ``meta``'s objects
    (surface points in a random pose 500-900 mm away; the rest background, class 0); their centre
    and keypoint offsets (mm, point minus keypoint) with Gaussian noise ``noise_mm``, and
    ``outliers`` of them random within +-250 mm.

    -> {"points" (1,N,3), "classes" (1,N), "ctr_ofs" (1,N,3), "kp_ofs" (1,K-1,N,3), "model_kps"
    (C,K,3), "poses": {class index: (R, t mm)}} (float32 tensors, mm)."""

    rng = np.random.default_rng(seed)
    n = int(n_points)
    n_obj = len(meta.obj_ids)
    per = int(n * float(object_share)) // max(1, n_obj)
    K = len(next(iter(meta.keypoints.values())))
    pts = rng.uniform([-300, -250, 600], [300, 250, 1000], (n, 3))
    ofs = rng.uniform(-250, 250, (n, K, 3))
    cls = np.zeros(n, np.int64)
    poses = {}
    for i, obj in enumerate(meta.obj_ids):
        R = Rotation.random(random_state=int(rng.integers(2 ** 31))).as_matrix()
        t = np.array([-200.0 + 400.0 * i / max(1, n_obj - 1) if n_obj > 1 else 0.0, rng.uniform(-100, 100),
                      rng.uniform(500, 900)])
        sl = slice(i * per, (i + 1) * per)
        mp = meta.model_points[obj]
        p = mp[rng.choice(len(mp), per)] @ R.T + t
        kp = meta.keypoints[obj] @ R.T + t
        o = p[:, None] - kp[None] + rng.normal(0, float(noise_mm), (per, K, 3))
        bad = rng.random(per) < float(outliers)
        o[bad] = rng.uniform(-250, 250, (int(bad.sum()), K, 3))
        pts[sl], ofs[sl], cls[sl] = p, o, meta.class_of(obj)
        poses[meta.class_of(obj)] = (R, t)
    perm = rng.permutation(n)
    pts, ofs, cls = pts[perm], ofs[perm], cls[perm]
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return {"points": f32(pts[None]), "classes": torch.from_numpy(cls[None]), "ctr_ofs": f32(ofs[None, :, 0]),
            "kp_ofs": f32(ofs[None, :, 1:].transpose(0, 2, 1, 3)), "model_kps": f32(meta.keypoint_array()),
            "poses": poses}


__all__ = ["example_votes", "gaussian_weights", "meanshift", "recover_poses"]
