"""RANSAC voting of 3D keypoints from per-point unit vectors (paper section 3.5), in plain torch.

Every point p_n of an object (its pixels back-projected to 3D) carries K predicted unit vectors
v_nk pointing towards the K keypoints. For each keypoint, independently and all at once:

1. hypotheses: random pairs of rays (p_i + s v_i, p_j + t v_j); the hypothesis is the midpoint of
   their closest points. Near-parallel pairs (sin of the angle < ``min_sin``) and pairs whose
   closest points lie behind either ray's origin (s <= 0 or t <= 0) are rejected;
2. votes: point n votes for hypothesis h when the direction from p_n to h agrees with v_n,
   cos(v_n, h - p_n) > ``inlier_cos``; the hypothesis with most votes wins;
3. refinement: the point minimising the sum of squared distances to the winner's inlier lines,
   solving sum(I - v v^T) x = sum(I - v v^T) p (3x3), then the inliers are recomputed around the
   new point and the solve repeated ``refine_iters`` times in all.

Everything is batched over keypoints and over instances (B objects, padded to a common N with a
``valid`` mask) and vectorised; the same code runs on CPU and GPU. Work is done in coordinates
centred on each instance's mean point (the float32 vote geometry uses squared distances), and the
vote matrix is evaluated in chunks of hypotheses so that memory stays below ``max_elements``
floats per temporary. Units are whatever the points are in (mm in this project).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


def _rand(shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    gdev = generator.device if generator is not None else device
    return torch.rand(shape, generator=generator, device=gdev).to(device)


def _vote_operands(p: torch.Tensor, v: torch.Tensor, val: torch.Tensor, inlier_cos: float
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-hand operands so that, for hypotheses h (B,K,H,3) and h4 = [h, 1], h5 = [h, |h|^2, 1]:

        num   = h4 @ Vn  = h.v - p.v                       (B,K,H,N)
        -c2d2 = h5 @ Dn  = -c^2 |h - p|^2

    p (B,N,3) centred, v (B,K,N,3), val (B,N). Padding points get |p|^2 = 1e30 so they never vote.
    """
    B, K, N, _ = v.shape
    pv = (v * p[:, None]).sum(-1)                                   # (B,K,N)
    Vn = torch.cat([v, -pv[..., None]], dim=-1).transpose(-1, -2)   # (B,K,4,N)
    pp = torch.where(val, (p * p).sum(-1), torch.full_like(p[..., 0], 1e30))
    c2 = float(inlier_cos) ** 2
    Dn = torch.cat([2.0 * c2 * p, -c2 * torch.ones_like(p[..., :1]), -c2 * pp[..., None]], dim=-1)
    return Vn.contiguous(), Dn.transpose(-1, -2)[:, None].contiguous()  # (B,1,5,N)


def _votes(h: torch.Tensor, Vn: torch.Tensor, Dn: torch.Tensor) -> torch.Tensor:
    """Inlier mask (B,K,H,N): cos(v_n, h - p_n) > c  <=>  num * |num| > c^2 |h - p|^2 (c > 0),
    evaluated with two batched matmuls and two element-wise passes (no (B,K,H,N,3) tensor)."""
    one = torch.ones_like(h[..., :1])
    num = torch.matmul(torch.cat([h, one], dim=-1), Vn)
    negd2 = torch.matmul(torch.cat([h, (h * h).sum(-1, keepdim=True), one], dim=-1), Dn)
    return torch.addcmul(negd2, num, num.abs()) > 0


def _line_lsq(w: torch.Tensor, p: torch.Tensor, v: torch.Tensor, fallback: torch.Tensor,
              min_eig: float) -> torch.Tensor:
    """Least-squares point of the weighted lines (p_n, v_nk): w (B,K,N) -> (B,K,3).

    A = sum w (I - v v^T), b = sum w (p - v (v.p)); where A is ill-conditioned (fewer than two
    non-parallel lines) the fallback point is kept.
    """
    wsum = w.sum(-1)                                                # (B,K)
    wv = w[..., None] * v                                           # (B,K,N,3)
    S = torch.matmul(wv.transpose(-1, -2), v)                       # (B,K,3,3) sum w v v^T
    eye = torch.eye(3, device=p.device, dtype=p.dtype)
    A = wsum[..., None, None] * eye - S
    wp = torch.bmm(w, p)                                            # (B,K,3) sum w p
    pv = (v * p[:, None]).sum(-1, keepdim=True)                     # (B,K,N,1)
    b = wp - (wv * pv).sum(-2)                                      # (B,K,3)
    evals = torch.linalg.eigvalsh(A)                               # ascending
    good = (wsum >= 2) & (evals[..., 0] > min_eig * wsum.clamp_min(1))
    Areg = torch.where(good[..., None, None], A, eye.expand_as(A))
    x, _ = torch.linalg.solve_ex(Areg, b[..., None])
    x = x[..., 0]
    return torch.where(good[..., None] & torch.isfinite(x).all(-1, keepdim=True), x, fallback)


def vote_keypoints_batched(points: torch.Tensor, vectors: torch.Tensor, valid: torch.Tensor | None = None,
                           n_hyp: int = 128, inlier_cos: float = 0.99, refine_iters: int = 2,
                           min_sin: float = 1e-2, generator: torch.Generator | None = None,
                           max_elements: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    """RANSAC keypoint voting for B instances at once.

    points (B,N,3); vectors (B,N,K,3) unit (re-normalised here); valid (B,N) bool (padding and
    points without depth False; None = all valid).
    Returns (keypoints (B,K,3), n_inliers (B,K) int64). An instance with fewer than two valid points,
    or a keypoint without any acceptable hypothesis, gets NaN coordinates and 0 inliers.
    """
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be (B,N,3), got {tuple(points.shape)}")
    if vectors.dim() != 4 or vectors.shape[:2] != points.shape[:2] or vectors.shape[-1] != 3:
        raise ValueError(f"vectors must be (B,N,K,3) matching points {tuple(points.shape)}, got {tuple(vectors.shape)}")
    if not 0.0 < float(inlier_cos) < 1.0:
        raise ValueError(f"inlier_cos must lie in (0, 1), got {inlier_cos}")
    B, N, K, _ = vectors.shape
    dev = points.device
    dtype = points.dtype if points.dtype in (torch.float32, torch.float64) else torch.float32
    if valid is None:
        valid = torch.ones(B, N, dtype=torch.bool, device=dev)
    valid = valid.to(dev, torch.bool) & torch.isfinite(points).all(-1) & torch.isfinite(vectors).all(-1).all(-1)
    nv = valid.sum(1)                                               # (B,)
    if N == 0:
        return (torch.full((B, K, 3), float("nan"), device=dev, dtype=dtype),
                torch.zeros(B, K, dtype=torch.long, device=dev))

    # valid points first, centred on their mean
    order = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)
    bidx = torch.arange(B, device=dev)[:, None]
    p = points.to(dtype)[bidx, order]                               # (B,N,3)
    v = torch.nn.functional.normalize(vectors.to(dtype)[bidx, order], dim=-1, eps=1e-12)
    val = valid[bidx, order]
    p = torch.where(val[..., None], p, torch.zeros_like(p))
    v = torch.where(val[..., None, None], v, torch.zeros_like(v))
    centre = p.sum(1, keepdim=True) / nv.clamp_min(1)[:, None, None].to(dtype)
    p = torch.where(val[..., None], p - centre, torch.zeros_like(p))
    v = v.permute(0, 2, 1, 3).contiguous()                          # (B,K,N,3)
    Vn, Dn = _vote_operands(p, v, val, inlier_cos)

    # hypotheses from random pairs of valid rays
    H = int(n_hyp)
    r = _rand((B, K, H, 2), generator, dev)
    idx = (r * nv[:, None, None, None].to(r.dtype)).long().clamp(max=N - 1)
    idx = torch.minimum(idx, (nv - 1).clamp_min(0)[:, None, None, None])
    bi = torch.arange(B, device=dev)[:, None, None]
    ki = torch.arange(K, device=dev)[None, :, None]
    pi, pj = p[bi, idx[..., 0]], p[bi, idx[..., 1]]                 # (B,K,H,3)
    vi, vj = v[bi, ki, idx[..., 0]], v[bi, ki, idx[..., 1]]
    w0 = pi - pj
    b_ = (vi * vj).sum(-1)
    d_ = (vi * w0).sum(-1)
    e_ = (vj * w0).sum(-1)
    a_ = (vi * vi).sum(-1)
    c_ = (vj * vj).sum(-1)
    denom = a_ * c_ - b_ * b_
    ok = (denom > min_sin * min_sin) & (idx[..., 0] != idx[..., 1]) & (nv[:, None, None] >= 2)
    safe = torch.where(ok, denom, torch.ones_like(denom))
    s = (b_ * e_ - c_ * d_) / safe
    t = (a_ * e_ - b_ * d_) / safe
    ok = ok & (s > 0) & (t > 0)
    hyp = 0.5 * (pi + s[..., None] * vi + pj + t[..., None] * vj)
    hyp = torch.where(ok[..., None], hyp, torch.zeros_like(hyp))

    # votes, in chunks of hypotheses
    chunk = max(1, int(max_elements) // max(1, B * K * N))
    scores = []
    for h0 in range(0, H, chunk):
        scores.append(_votes(hyp[:, :, h0:h0 + chunk], Vn, Dn).sum(-1))
    score = torch.cat(scores, dim=2)                                # (B,K,H)
    score = torch.where(ok, score, torch.full_like(score, -1))
    best = score.argmax(dim=2)                                      # (B,K)
    x = torch.gather(hyp, 2, best[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]  # (B,K,3)
    found = torch.gather(score, 2, best[..., None])[..., 0] > 0

    # refinement on the inliers
    inl = _votes(x[:, :, None], Vn, Dn)[:, :, 0]  # (B,K,N)
    for _ in range(max(0, int(refine_iters))):
        x = _line_lsq(inl.to(dtype), p, v, x, 1e-6)
        inl = _votes(x[:, :, None], Vn, Dn)[:, :, 0]
    n_inl = inl.sum(-1)
    x = x + centre
    x = torch.where(found[..., None], x, torch.full_like(x, float("nan")))
    return x, torch.where(found, n_inl, torch.zeros_like(n_inl))


def vote_keypoints(points: torch.Tensor, vectors: torch.Tensor, n_hyp: int = 128, inlier_cos: float = 0.99,
                   generator: torch.Generator | None = None, refine_iters: int = 2,
                   min_sin: float = 1e-2) -> torch.Tensor:
    """RANSAC voting for one instance: points (N,3), vectors (N,K,3) unit -> keypoints (K,3).

    See the module docstring for the algorithm; keypoints without a hypothesis are NaN.
    """
    kp, _ = vote_keypoints_batched(points[None], vectors[None], None, n_hyp=n_hyp, inlier_cos=inlier_cos,
                                   refine_iters=refine_iters, min_sin=min_sin, generator=generator)
    return kp[0]


def pad_instances(points: Sequence[torch.Tensor], vectors: Sequence[torch.Tensor]
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pad a list of instances (points (N_i,3), vectors (N_i,K,3)) into (B,N,3), (B,N,K,3), valid (B,N)."""
    if len(points) != len(vectors) or not points:
        raise ValueError("pad_instances needs equally long, non-empty lists of points and vectors")
    B = len(points)
    N = max(int(p.shape[0]) for p in points)
    K = int(vectors[0].shape[1])
    ref = points[0]
    P = ref.new_zeros(B, N, 3)
    V = ref.new_zeros(B, N, K, 3)
    M = torch.zeros(B, N, dtype=torch.bool, device=ref.device)
    for b, (p, v) in enumerate(zip(points, vectors)):
        n = int(p.shape[0])
        P[b, :n] = p
        V[b, :n] = v
        M[b, :n] = True
    return P, V, M


def vote_keypoints_list(points: Sequence[torch.Tensor], vectors: Sequence[torch.Tensor], **kwargs
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Voting for a list of instances of different sizes -> (keypoints (B,K,3), n_inliers (B,K)).
    Keyword arguments as :func:`vote_keypoints_batched`."""
    P, V, M = pad_instances(points, vectors)
    return vote_keypoints_batched(P, V, M, **kwargs)
