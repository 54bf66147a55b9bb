"""Batched least-squares rigid fitting in torch (paper section 3.5: keypoints -> pose)."""

from __future__ import annotations

import torch


def kabsch_torch(src: torch.Tensor, dst: torch.Tensor, weights: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """R, t minimising sum_n w_n |R src_n + t - dst_n|^2, batched; det(R) = +1.

    src, dst: (B,N,3) (or (N,3), then R (3,3), t (3,) come back); weights: (B,N) or (N,) >= 0.
    With src = the model's keypoints and dst = the voted keypoints in the camera frame this is the
    pose model -> camera. Rows where src or dst is not finite (e.g. a keypoint that got no vote)
    get weight 0. Solved in float64 (SVD of the 3x3 cross-covariance), returned in dst's dtype.
    A batch element whose weights are all zero gets NaN R and t, so that a failed fit cannot pass
    for a pose. Fewer than three non-collinear points leave the rotation undetermined.
    """
    single = src.dim() == 2
    if single:
        src, dst = src[None], dst[None]
        weights = None if weights is None else weights[None]
    if src.shape != dst.shape or src.dim() != 3 or src.shape[-1] != 3:
        raise ValueError("kabsch_torch needs (B,N,3) src and dst of one shape, "
                         f"got {tuple(src.shape)} and {tuple(dst.shape)}")
    out_dtype = dst.dtype if dst.is_floating_point() else torch.float32
    s = src.to(torch.float64)
    d = dst.to(torch.float64)
    w = torch.ones(s.shape[:2], dtype=torch.float64, device=s.device) if weights is None \
        else weights.to(device=s.device, dtype=torch.float64).expand(s.shape[:2]).clone()
    finite = torch.isfinite(s).all(-1) & torch.isfinite(d).all(-1) & torch.isfinite(w)
    w = torch.where(finite, w.clamp_min(0), torch.zeros_like(w))
    s = torch.where(finite[..., None], s, torch.zeros_like(s))
    d = torch.where(finite[..., None], d, torch.zeros_like(d))
    wsum = w.sum(1, keepdim=True)                                   # (B,1)
    ok = wsum[:, 0] > 0
    wn = w / wsum.clamp_min(1e-300)
    mu_s = (wn[..., None] * s).sum(1)                               # (B,3)
    mu_d = (wn[..., None] * d).sum(1)
    xs = s - mu_s[:, None]
    xd = d - mu_d[:, None]
    cov = torch.matmul((xd * wn[..., None]).transpose(1, 2), xs)    # (B,3,3) sum w d s^T
    U, _, Vh = torch.linalg.svd(cov)
    sign = torch.sign(torch.linalg.det(torch.matmul(U, Vh)))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    D = torch.diag_embed(torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], dim=-1))
    R = U @ D @ Vh
    t = mu_d - torch.matmul(R, mu_s[..., None])[..., 0]
    R = torch.where(ok[:, None, None], R, torch.full_like(R, float("nan")))
    t = torch.where(ok[:, None], t, torch.full_like(t, float("nan")))
    R, t = R.to(out_dtype), t.to(out_dtype)
    return (R[0], t[0]) if single else (R, t)
