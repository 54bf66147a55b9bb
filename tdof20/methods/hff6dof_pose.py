"""HFF6DoF's pose recovery (paper section 3.5), used by its ``predict_poses``
(:mod:`tdof20.methods.hff6dof_method`), per image:

1. the network at the run's image size -> segmentation logits and the keypoint vector field;
2. objects: the classes of the segmentation's argmax that cover at least ``min_pixels`` pixels
   (without a segmentation head: the ground-truth visible masks, ``masks = "gt"``);
3. keypoint voting, all objects of a batch at once, in one of two ways (``voting``):

   - ``bearing`` (default): *every* pixel of the object votes, with or without depth. A pixel's
     true 3D point lies on its viewing ray r and its vector v points from that point to the
     keypoint, so the keypoint lies in the plane through the camera centre spanned by r and v,
     whatever the depth: RANSAC over these planes gives each keypoint's bearing (direction from
     the camera), and PnP of the model's keypoints onto the 9 bearings gives R, t. The depth only
     enters through the network's geometry input.
   - ``3d`` (the paper's): the object's pixels *with depth* (the input depth of the run's depth
     mode) are back-projected and vote for 3D keypoints
     (:func:`~tdof20.methods.voting.vote_keypoints_batched`); Kabsch (least squares, weighted by
     each keypoint's inlier count) of the model's keypoints onto them gives R, t.

   On glass most sensor depth is missing or lies behind the surface, which biases ``3d`` voting
   of a run trained with vectors from the true surface points (``vector_origin = "restored"``);
   a run trained with ``vector_origin = "observed"`` (vectors from the input depth's points, none
   where it has no depth) votes from the very points its vectors start at. The comparison is in
   docs/hff6dof.md;
4. score = the mean fraction of the object's voting pixels that are inliers.
"""

from __future__ import annotations

import numpy as np
import torch

from tdof20.errors import TdofError
from tdof20.methods.data import backproject
from tdof20.methods.fitting import kabsch_torch
from tdof20.methods.voting import vote_keypoints_batched

VOTING = ("3d", "bearing")
DEFAULT_VOTING = "bearing"  # the result of the depth comparison in docs/hff6dof.md


def default_min_pixels(image_size) -> int:
    """Smallest segment taken for an object: 0.05 % of the image, at least 10 pixels."""
    return max(10, int(round(5e-4 * image_size[0] * image_size[1])))


def pixel_rays(K: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(H*W,3) unit viewing rays of the pixels of a camera K (3,3)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32, device=K.device),
                          torch.arange(W, dtype=torch.float32, device=K.device), indexing="ij")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    return torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)


def vote_bearings_batched(rays: torch.Tensor, vectors: torch.Tensor, valid: torch.Tensor, n_hyp: int = 128,
                          tol: float = 0.02, refine_iters: int = 2, min_sin: float = 1e-2,
                          generator: torch.Generator | None = None, max_elements: int = 1 << 24
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """RANSAC voting of keypoint *bearings* (unit directions from the camera centre), depth-free.

    A pixel's true 3D point lies on its viewing ray r, and its predicted vector v points from that
    point to keypoint k, so the keypoint lies in the plane through the camera centre spanned by r
    and v — whatever the pixel's depth. Each pixel thus constrains the keypoint's bearing b by
    n.b = 0, n = r x v / |r x v|, and b must be a positive combination of r and v. Hypotheses:
    b = n_i x n_j of random pairs; votes: |n.b| < ``tol`` and b between r and v; refinement: the
    smallest eigenvector of sum n n^T over the inliers, ``refine_iters`` times.

    rays (B,N,3) unit; vectors (B,N,K,3) unit; valid (B,N) bool. Returns (bearings (B,K,3),
    n_inliers (B,K) int64); NaN bearings where no hypothesis was acceptable.
    """
    B, N, K, _ = vectors.shape
    dev = rays.device
    dtype = torch.float32
    rays = rays.to(dtype)
    V = torch.nn.functional.normalize(vectors.to(dtype), dim=-1, eps=1e-12).permute(0, 2, 1, 3).contiguous()
    n = torch.cross(rays[:, None].expand_as(V), V, dim=-1)                       # (B,K,N,3)
    norm = n.norm(dim=-1)
    ok_n = valid[:, None] & (norm > 1e-3)
    n = torch.where(ok_n[..., None], n / norm.clamp_min(1e-12)[..., None], torch.zeros_like(n))
    c = (rays[:, None] * V).sum(-1)                                               # (B,K,N) r.v
    rT = rays.transpose(1, 2)[:, None]                                            # (B,1,3,N)
    nT, VT = n.transpose(-1, -2), V.transpose(-1, -2)                             # (B,K,3,N)
    nv = ok_n.sum(-1)                                                             # (B,K)

    def inliers(h: torch.Tensor) -> torch.Tensor:                                 # h (B,K,H,3) -> (B,K,H,N)
        d = torch.matmul(h, nT).abs()
        p = torch.matmul(h, rT)                                                   # b.r
        q = torch.matmul(h, VT)                                                   # b.v
        cc = c[:, :, None]
        return (d < tol) & (p - q * cc > 0) & (q - p * cc > -tol) & ok_n[:, :, None]

    # hypotheses from pairs of valid pixels (per keypoint: pixels whose plane is defined)
    order = torch.argsort((~ok_n).to(torch.int8), dim=-1, stable=True)            # (B,K,N)
    r = torch.rand((B, K, int(n_hyp), 2), generator=generator,
                   device=generator.device if generator is not None else dev).to(dev)
    idx = (r * nv[..., None, None].to(r.dtype)).long().clamp(max=max(N - 1, 0))
    idx = torch.gather(order[:, :, None].expand(B, K, int(n_hyp), N), 3, idx)
    bi = torch.arange(B, device=dev)[:, None, None]
    ki = torch.arange(K, device=dev)[None, :, None]
    h = torch.cross(n[bi, ki, idx[..., 0]], n[bi, ki, idx[..., 1]], dim=-1)     # (B,K,H,3)
    hn = h.norm(dim=-1)
    ok = (hn > min_sin) & (nv[..., None] >= 2)
    h = h / hn.clamp_min(1e-12)[..., None]
    mean_ray = torch.nn.functional.normalize((rays * valid[..., None]).sum(1), dim=-1)
    h = torch.where(((h * mean_ray[:, None, None]).sum(-1) < 0)[..., None], -h, h)
    chunk = max(1, int(max_elements) // max(1, B * K * N))
    score = torch.cat([inliers(h[:, :, i:i + chunk]).sum(-1) for i in range(0, int(n_hyp), chunk)], dim=2)
    score = torch.where(ok, score, torch.full_like(score, -1))
    best = score.argmax(2)
    b = torch.gather(h, 2, best[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
    found = torch.gather(score, 2, best[..., None])[..., 0] > 0
    inl = inliers(b[:, :, None])[:, :, 0]
    for _ in range(max(0, int(refine_iters))):
        w = inl.to(dtype)
        A = torch.einsum("bkn,bkni,bknj->bkij", w, n, n)
        _, evecs = torch.linalg.eigh(A)
        nb = evecs[..., 0]
        nb = torch.where(((nb * b).sum(-1, keepdim=True) < 0), -nb, nb)
        b = torch.where((inl.sum(-1) >= 3)[..., None] & torch.isfinite(nb).all(-1, keepdim=True), nb, b)
        inl = inliers(b[:, :, None])[:, :, 0]
    n_inl = inl.sum(-1)
    b = torch.where(found[..., None], b, torch.full_like(b, float("nan")))
    return b, torch.where(found, n_inl, torch.zeros_like(n_inl))


def pose_from_bearings(model_kp: np.ndarray, bearings: np.ndarray, n_inliers: np.ndarray, n_points: int
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP of model keypoints (K,3) mm onto keypoint bearings (K,3) (OpenCV EPnP, then
    Levenberg-Marquardt); keypoints with few inliers (< max(3, 2 % of the points)) are left out.
    None when fewer than 4 keypoints remain or PnP fails."""
    import cv2

    use = np.isfinite(bearings).all(1) & (bearings[:, 2] > 1e-6) & (n_inliers >= max(3, 0.02 * n_points))
    if use.sum() < 4:
        return None
    obj = np.ascontiguousarray(model_kp[use], dtype=np.float64)
    img = np.ascontiguousarray(bearings[use, :2] / bearings[use, 2:], dtype=np.float64)
    cam = np.eye(3)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, cam, None, flags=cv2.SOLVEPNP_EPNP)
        if ok:
            ok, rvec, tvec = cv2.solvePnP(obj, img, cam, None, rvec, tvec, useExtrinsicGuess=True,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not ok or tvec[2, 0] <= 0:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec[:, 0]


def recover_poses(seg_classes: torch.Tensor, vec: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                  kp_table: torch.Tensor, min_pixels: int, max_points: int = 2000, n_hyp: int = 128,
                  inlier_cos: float = 0.99, generator: torch.Generator | None = None,
                  confidence: torch.Tensor | None = None, voting: str = DEFAULT_VOTING, bearing_tol: float = 0.02
                  ) -> list[list[dict]]:
    """Poses of the objects in a batch of network outputs.

    seg_classes (B,H,W) int64 obj_id per pixel (0 = background); vec (B,3K,H,W) unit vectors;
    depth (B,H,W) mm of the input depth (0 = none); K (B,3,3); kp_table (n_classes,K,3) model
    keypoints in mm; confidence (B,H,W) optional per-pixel class probability.
    voting: '3d' — the object's pixels *with depth* are back-projected and vote for 3D keypoints
    (:func:`~tdof20.methods.voting.vote_keypoints_batched`, inliers within ``inlier_cos``), then
    Kabsch onto the model's keypoints; 'bearing' — *every* pixel of the object votes for the
    keypoints' bearings (:func:`vote_bearings_batched`, depth-free), then PnP.
    Returns per image a list of {"obj_id", "R" (3,3), "t" (3,), "score", "n_points", "confidence"}
    for every object with at least ``min_pixels`` pixels and a successful fit; score = the mean
    fraction of the object's voting pixels that are inliers. At most ``max_points`` random pixels
    of an object vote.
    """
    if voting not in VOTING:
        raise TdofError(f"unknown voting '{voting}' (valid: {', '.join(VOTING)})")
    B, H, W = seg_classes.shape
    dev = vec.device
    nk = vec.shape[1] // 3
    points, vectors, owners = [], [], []
    for b in range(B):
        classes, counts = torch.unique(seg_classes[b], return_counts=True)
        P = None
        for c, cnt in zip(classes.tolist(), counts.tolist()):
            if c <= 0 or c >= kp_table.shape[0] or cnt < min_pixels or not torch.isfinite(kp_table[c]).all():
                continue
            sel = seg_classes[b] == c
            if voting == "3d":
                sel = sel & (depth[b] > 0)
            idx = sel.reshape(-1).nonzero()[:, 0]
            if idx.numel() < 3:
                continue
            if idx.numel() > max_points:
                pick = torch.randperm(idx.numel(), generator=generator, device="cpu" if generator is None
                                      else generator.device)[:max_points].to(idx.device)
                idx = idx[pick]
            if P is None:
                P = backproject(depth[b], K[b]).reshape(-1, 3) if voting == "3d" else pixel_rays(K[b], H, W)
            points.append(P[idx])
            vectors.append(vec[b].reshape(nk, 3, H * W)[:, :, idx].permute(2, 0, 1))
            conf = float(confidence[b].reshape(-1)[idx].mean()) if confidence is not None else 1.0
            owners.append((b, c, int(idx.numel()), conf))
    results: list[list[dict]] = [[] for _ in range(B)]
    if not owners:
        return results
    n = max(p.shape[0] for p in points)
    Pp = torch.zeros(len(points), n, 3, device=dev)
    Vp = torch.zeros(len(points), n, nk, 3, device=dev)
    M = torch.zeros(len(points), n, dtype=torch.bool, device=dev)
    for i, (p, v) in enumerate(zip(points, vectors)):
        Pp[i, :p.shape[0]] = p
        Vp[i, :p.shape[0]] = v.float()
        M[i, :p.shape[0]] = True
    model_kp = kp_table[torch.tensor([o[1] for o in owners], device=kp_table.device)]
    if voting == "3d":
        kps, n_inl = vote_keypoints_batched(Pp, Vp, M, n_hyp=n_hyp, inlier_cos=inlier_cos, generator=generator)
        R, t = kabsch_torch(model_kp.to(dev), kps, weights=n_inl.to(kps.dtype))
        R, t, n_inl = R.cpu().numpy(), t.cpu().numpy(), n_inl.cpu().numpy()
    else:
        bear, n_inl = vote_bearings_batched(Pp, Vp, M, n_hyp=n_hyp, tol=bearing_tol, generator=generator)
        bear, n_inl, mk = bear.cpu().numpy(), n_inl.cpu().numpy(), model_kp.cpu().numpy()
        R = np.full((len(owners), 3, 3), np.nan)
        t = np.full((len(owners), 3), np.nan)
        for i, o in enumerate(owners):
            fit = pose_from_bearings(mk[i], bear[i], n_inl[i], o[2])
            if fit is not None:
                R[i], t[i] = fit
    for i, (b, c, npts, conf) in enumerate(owners):
        if not (np.isfinite(R[i]).all() and np.isfinite(t[i]).all()):
            continue
        results[b].append({"obj_id": int(c), "R": R[i].astype(np.float64), "t": t[i].astype(np.float64),
                           "score": float(n_inl[i].mean() / max(1, npts)), "n_points": npts, "confidence": conf})
    return results
