"""3D keypoint RANSAC voting and batched Kabsch (pose recovery of HFF6DoF)."""

from __future__ import annotations

import math

import pytest
import torch

from tdof20.methods.fitting import kabsch_torch
from tdof20.methods.voting import vote_keypoints, vote_keypoints_batched, vote_keypoints_list


def _rotation(axis, angle_deg):
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float64), dim=0)
    th = math.radians(angle_deg)
    Kx = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


def _object(n=4000, seed=0, K=9):
    """Visible surface points of a ~100 mm ellipsoid in a camera frame (mm), its model keypoints
    (centre + 8 surface points) and the pose."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n * 2, 3, generator=g, dtype=torch.float64), dim=1)
    d = d[d[:, 2] < 0.2][:n]  # roughly the camera-facing half
    axes = torch.tensor([50.0, 35.0, 25.0], dtype=torch.float64)
    model_pts = d * axes
    kd = torch.nn.functional.normalize(torch.randn(K - 1, 3, generator=g, dtype=torch.float64), dim=1)
    model_kp = torch.cat([torch.zeros(1, 3, dtype=torch.float64), kd * axes])
    R = _rotation([0.3, -0.5, 0.8], 37.0 + 10 * seed)
    t = torch.tensor([30.0, -20.0, 650.0], dtype=torch.float64)
    pts = model_pts @ R.T + t
    kp = model_kp @ R.T + t
    vec = torch.nn.functional.normalize(kp[None] - pts[:, None], dim=-1)
    return pts.float(), vec.float(), kp.float(), model_kp.float(), R.float(), t.float()


def _with_outliers(vec, frac, seed=1):
    g = torch.Generator().manual_seed(seed)
    n = vec.shape[0]
    out = torch.rand(n, generator=g) < frac
    rnd = torch.nn.functional.normalize(torch.randn(vec.shape, generator=g), dim=-1)
    return torch.where(out[:, None, None], rnd, vec), out


def test_clean_vectors_recover_keypoints_within_1mm():
    pts, vec, kp, *_ = _object()
    est = vote_keypoints(pts, vec, generator=torch.Generator().manual_seed(0))
    assert est.shape == (9, 3)
    assert (est - kp).norm(dim=1).max() < 1.0


def test_30_percent_outlier_vectors_still_within_1mm():
    pts, vec, kp, *_ = _object(seed=2)
    bad, out = _with_outliers(vec, 0.30)
    assert 0.25 < out.float().mean() < 0.35
    est = vote_keypoints(pts, bad, n_hyp=128, inlier_cos=0.99, generator=torch.Generator().manual_seed(0))
    assert (est - kp).norm(dim=1).max() < 1.0
    # the winning hypothesis' inliers are about the 70% clean rays
    _, n_inl = vote_keypoints_batched(pts[None], bad[None], generator=torch.Generator().manual_seed(0))
    assert (n_inl[0] < 0.8 * len(pts)).all() and (n_inl[0] > 0.6 * len(pts)).all()


def test_voting_is_reproducible_with_a_generator():
    pts, vec, *_ = _object(seed=3)
    bad, _ = _with_outliers(vec, 0.3)
    a = vote_keypoints(pts, bad, generator=torch.Generator().manual_seed(5))
    b = vote_keypoints(pts, bad, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


def test_batched_over_instances_of_different_sizes():
    objs = [_object(n=n, seed=s) for n, s in [(3000, 4), (300, 5), (1500, 6)]]
    pts = [o[0] for o in objs]
    vec = [_with_outliers(o[1], 0.3, seed=i)[0] for i, o in enumerate(objs)]
    kps, n_inl = vote_keypoints_list(pts, vec, generator=torch.Generator().manual_seed(0))
    assert kps.shape == (3, 9, 3) and n_inl.shape == (3, 9)
    for i, o in enumerate(objs):
        assert (kps[i] - o[2]).norm(dim=1).max() < 1.0
        assert (n_inl[i] <= len(pts[i])).all()
    # padded form with invalid (e.g. depth-less) points that carry garbage
    P = torch.zeros(2, 3000, 3)
    V = torch.zeros(2, 3000, 9, 3)
    valid = torch.zeros(2, 3000, dtype=torch.bool)
    P[0], V[0], valid[0] = pts[0], vec[0], True
    P[1, :1500], V[1, :1500], valid[1, :1500] = pts[2], vec[2], True
    P[1, 1500:] = torch.randn(1500, 3) * 1000
    V[1, 1500:] = torch.nn.functional.normalize(torch.randn(1500, 9, 3), dim=-1)
    kps2, _ = vote_keypoints_batched(P, V, valid, generator=torch.Generator().manual_seed(1))
    assert (kps2[0] - objs[0][2]).norm(dim=1).max() < 1.0
    assert (kps2[1] - objs[2][2]).norm(dim=1).max() < 1.0


def test_degenerate_instances_give_nan_not_garbage():
    P = torch.zeros(2, 10, 3)
    V = torch.zeros(2, 10, 2, 3)
    V[..., 2] = 1.0  # all rays parallel: no hypothesis
    P[0, :, 0] = torch.arange(10.0)
    valid = torch.ones(2, 10, dtype=torch.bool)
    valid[1] = False  # empty instance
    kps, n_inl = vote_keypoints_batched(P, V, valid)
    assert torch.isnan(kps).all() and (n_inl == 0).all()


def test_kabsch_recovers_a_known_pose_batched_and_weighted():
    g = torch.Generator().manual_seed(0)
    B, N = 4, 9
    src = torch.randn(B, N, 3, generator=g, dtype=torch.float64) * 50
    Rs = torch.stack([_rotation([1, 2, 3], 10), _rotation([0, 0, 1], 179), _rotation([1, -1, 0], 95),
                      _rotation([0.2, 0.1, -1], 250)])
    ts = torch.tensor([[0, 0, 500], [10, -5, 800], [-40, 30, 600], [1, 2, 3]], dtype=torch.float64)
    dst = src @ Rs.transpose(1, 2) + ts[:, None]
    R, t = kabsch_torch(src.float(), dst.float())
    assert R.shape == (B, 3, 3) and t.shape == (B, 3)
    assert torch.allclose(R.double(), Rs, atol=1e-5)
    assert torch.allclose(t.double(), ts, atol=1e-3)
    assert torch.allclose(torch.linalg.det(R), torch.ones(B), atol=1e-5)
    # unbatched
    R1, t1 = kabsch_torch(src[1], dst[1])
    assert torch.allclose(R1, Rs[1], atol=1e-9) and torch.allclose(t1, ts[1], atol=1e-7)
    # weights: corrupted points with weight 0 do not matter, a NaN keypoint is skipped
    bad = dst.clone()
    bad[:, :3] += 100.0
    w = torch.ones(B, N)
    w[:, :3] = 0
    Rw, tw = kabsch_torch(src, bad, w)
    assert torch.allclose(Rw, Rs, atol=1e-9) and torch.allclose(tw, ts, atol=1e-7)
    Ru, _ = kabsch_torch(src, bad)
    assert not torch.allclose(Ru, Rs, atol=1e-3)
    nan = dst.clone()
    nan[:, 4] = float("nan")
    Rn, tn = kabsch_torch(src, nan)
    assert torch.allclose(Rn, Rs, atol=1e-9) and torch.allclose(tn, ts, atol=1e-7)


def test_kabsch_never_returns_a_reflection():
    g = torch.Generator().manual_seed(1)
    src = torch.randn(1, 6, 3, generator=g)
    dst = src * torch.tensor([1.0, 1.0, -1.0])  # a mirror image: best proper rotation, det +1
    R, _ = kabsch_torch(src, dst)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-5)


def test_pose_recovery_end_to_end_with_outliers():
    pts, vec, kp, model_kp, R_true, t_true = _object(seed=7)
    bad, _ = _with_outliers(vec, 0.3, seed=3)
    est = vote_keypoints(pts, bad, generator=torch.Generator().manual_seed(0))
    R, t = kabsch_torch(model_kp, est)
    ang = torch.rad2deg(torch.arccos(((R.T @ R_true).trace().clamp(-1, 3) - 1) / 2))
    assert ang < 0.5 and (t - t_true).norm() < 1.0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_same_code_on_gpu():
    pts, vec, kp, *_ = _object(seed=8)
    bad, _ = _with_outliers(vec, 0.3)
    est = vote_keypoints(pts.cuda(), bad.cuda(), generator=torch.Generator(device="cuda").manual_seed(0))
    assert est.is_cuda and (est.cpu() - kp).norm(dim=1).max() < 1.0
    R, t = kabsch_torch(torch.randn(2, 5, 3, device="cuda"), torch.randn(2, 5, 3, device="cuda"))
    assert R.is_cuda and t.shape == (2, 3)
