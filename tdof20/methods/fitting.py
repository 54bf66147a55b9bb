"""Batched least-squares rigid fitting in torch (paper section 3.5: keypoints -> pose), and rotations
as unit quaternions (DenseFusion's pose output)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


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


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(...,4) quaternions (w, x, y, z), normalised here -> (...,3,3) rotation matrices (the
    original's ``base`` matrix, lib/loss.py)."""
    q = F.normalize(q, dim=-1, eps=1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (w * y + x * z),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (w * x + y * z), 1 - 2 * (x * x + y * y)], dim=-1).view(*q.shape[:-1], 3, 3)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(...,3,3) -> (...,4) unit quaternions (w >= 0), the numerically stable branch per element."""
    m = R.to(torch.float64)
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack([
        torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                     m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                     1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                     1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)], dim=-2)   # (...,4,4)
    pick = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1).argmax(-1)
    q = torch.gather(cands, -2, pick[..., None, None].expand(*pick.shape, 1, 4))[..., 0, :]
    q = F.normalize(q, dim=-1)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q.to(R.dtype)
