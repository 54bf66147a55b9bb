"""FFB6D: RandLA neighbour searches, network shapes, MeanShift + least-squares recovery, training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tdof20.methods import ffb6d, ffb6d_pose
from tdof20.methods.base import MethodMeta
from tdof20.methods.data import collate
from tdof20.methods.randla import knn, point_pyramid

pytestmark = pytest.mark.usefixtures("one_torch_thread")

HW = (48, 64)
OBJ = (1, 5)


def rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = math.radians(deg)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def rot_err_deg(Ra, Rb):
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def render_item(obj_id: int, R: np.ndarray, t: np.ndarray, hw=HW, f=70.0, seed=0) -> dict:
    """A dataset item of one catalog object at (R, t mm) in front of a plane 600 mm away, ray cast
    with open3d: rgb coloured by model coordinates (+ noisy background), depth = restored depth."""
    from tdof20.geometry.camera import PinholeCamera
    from tdof20.geometry.raycast import ModelRaycaster
    from tdof20.objects import get_object

    H, W = hw
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    o = get_object(obj_id)
    rc = ModelRaycaster({obj_id: (o.vertices, o.faces)}, PinholeCamera(K, W, H))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    lab = rc.render([(obj_id, T)])
    vis = lab.visible == 0
    depth = np.where(vis, lab.depth, 600.0).astype(np.float32)
    v, u = np.mgrid[:H, :W]
    P = np.stack([(u - K[0, 2]) * depth / f, (v - K[1, 2]) * depth / f, depth], -1)
    Pm = (P - t) @ R
    rng = np.random.default_rng(seed)
    col = np.where(vis[..., None], 0.5 + Pm / o.diameter, 0.2 + 0.1 * rng.random((H, W, 3)))
    rgb = (np.clip(col, 0, 1) * 255).astype(np.uint8).transpose(2, 0, 1)
    return {"rgb": torch.from_numpy(rgb.copy()), "depth": torch.from_numpy(depth),
            "depth_restored": torch.from_numpy(depth), "K": torch.from_numpy(K.astype(np.float32)),
            "scene_id": 1, "im_id": seed, "label": torch.from_numpy(np.where(vis, obj_id, 0).astype(np.int64)),
            "instance": torch.from_numpy(vis.astype(np.int64)), "obj_id": torch.tensor([obj_id]),
            "R": torch.from_numpy(R[None].astype(np.float32)), "t": torch.from_numpy(t[None].astype(np.float32))}


@pytest.fixture(scope="module")
def meta():
    return MethodMeta.from_catalog(OBJ, image_size=HW)


# --------------------------------------------------------------------------------------------
# neighbours


@pytest.mark.parametrize("backend", ["auto", "tree", "block"])
def test_knn_matches_brute_force(backend):
    """Against distances computed here in float64 by brute force, not by either backend's own code."""
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(2, 700, 3, generator=g)
    q = torch.rand(2, 300, 3, generator=g)
    idx = knn(q, ref, 5, block_elements=10_000, backend=backend)     # many small blocks
    assert idx.shape == (2, 300, 5) and idx.dtype == torch.int64
    for b in range(2):
        d = ((q[b].double()[:, None] - ref[b].double()[None]) ** 2).sum(-1).numpy()   # (300,700)
        want = np.argsort(d, axis=1, kind="stable")[:, :5]
        d_got = np.take_along_axis(d, idx[b].numpy(), axis=1)
        d_want = np.take_along_axis(d, want, axis=1)
        assert np.allclose(d_got, d_want, atol=1e-6)                  # the same distances, nearest first
        assert (idx[b].numpy() == want).mean() > 0.99                 # ties may swap
    one = knn(q[0], ref[0], 1, backend=backend)[:, 0]
    assert torch.equal(one, torch.cdist(q[0].double(), ref[0].double()).argmin(1))


def test_knn_refuses_unknown_backend_and_bad_k():
    q, r = torch.zeros(4, 3), torch.zeros(3, 3)
    with pytest.raises(ValueError, match="backend"):
        knn(q, r, 1, backend="gpu")
    with pytest.raises(ValueError, match="1 <= k <= 3"):
        knn(q, r, 4)


def test_point_pyramid_shapes():
    pts = np.random.default_rng(0).random((1024, 3)).astype(np.float32)
    pyr = point_pyramid(pts, 16, (4, 4, 4, 4))
    for i, n in enumerate((1024, 256, 64, 16)):
        assert pyr[f"xyz{i}"].shape == (n, 3)
        assert pyr[f"nei{i}"].shape == (n, 16) and pyr[f"nei{i}"].max() < n
        assert pyr[f"sub{i}"].shape == (n // 4, 16)
        assert pyr[f"interp{i}"].shape == (n, 1) and pyr[f"interp{i}"].max() < n // 4
        assert (pyr[f"nei{i}"][:, 0] == np.arange(n)).all()       # each point is its own nearest


# --------------------------------------------------------------------------------------------
# network


def test_forward_shapes_and_parameter_count(meta):
    cfg = ffb6d.FFB6DConfig(n_points=512)
    net = ffb6d.build(cfg, meta)
    batch = ffb6d.example_batch(cfg, meta, batch_size=2)
    out = net(batch)
    assert out["seg"].shape == (2, meta.n_classes, 512)
    assert out["kp_ofs"].shape == (2, 8, 512, 3)
    assert out["ctr_ofs"].shape == (2, 1, 512, 3)
    n = ffb6d.count_parameters(net)
    assert 33.0e6 < n < 34.5e6                                      # FFB6D's published 33.8 M


def test_bad_sizes_are_one_line_errors(meta):
    from tdof20.errors import TdofError

    with pytest.raises(TdofError, match="divisible by 8"):
        ffb6d.build(ffb6d.FFB6DConfig(), MethodMeta.from_catalog((1,), image_size=(50, 64)))
    with pytest.raises(TdofError, match="n_points"):
        ffb6d.FFB6DConfig(n_points=100)


def test_transform_targets_point_from_points_to_keypoints(meta):
    torch.manual_seed(2)  # the transform samples points from torch's global generator (about 28 of 512 on the object; seed 2: 37)
    R, t = rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])
    item = render_item(1, R, t)
    cfg = ffb6d.FFB6DConfig(n_points=512)
    s = ffb6d.FFB6DTransform(cfg, meta, train=True)(item)
    on = s["labels"] > 0
    assert on.sum() > 20 and set(s["labels"].unique().tolist()) <= {0, 1}
    pts = s["cld_rgb_nrm"][:3].T.double() * 1000
    kp_cam = torch.from_numpy(meta.keypoints[1] @ R.T + t)
    ctr = pts[on] - s["ctr_ofs"][on].double() * 1000
    assert (ctr - kp_cam[0]).norm(dim=1).max() < 1e-2
    kps = pts[on][:, None] - s["kp_ofs"][on].double() * 1000
    assert (kps - kp_cam[1:]).norm(dim=-1).max() < 1e-2
    assert (s["kp_ofs"][~on] == 0).all()
    n = s["cld_rgb_nrm"][6:9]
    assert torch.allclose(n.norm(dim=0)[on], torch.ones(int(on.sum())), atol=1e-4)
    again = ffb6d.FFB6DTransform(cfg, meta, train=False)(item)
    assert torch.equal(again["choose"], ffb6d.FFB6DTransform(cfg, meta, train=False)(item)["choose"])


# --------------------------------------------------------------------------------------------
# pose recovery


def _object_votes(meta, obj_id, R, t, n=400, outliers=0.3, seed=0):
    """Surface points of a catalog model in pose (R, t mm) with ground-truth centre/keypoint offsets
    (point minus keypoint, mm); ``outliers`` of the points get random offsets within +-250 mm."""
    rng = np.random.default_rng(seed)
    mp = meta.model_points[obj_id]
    pts = mp[rng.choice(len(mp), n)] @ R.T + t
    kp = meta.keypoints[obj_id] @ R.T + t
    ofs = pts[:, None] - kp[None]                                     # (n,K,3)
    bad = rng.random(n) < outliers
    ofs[bad] = rng.uniform(-250, 250, (int(bad.sum()), ofs.shape[1], 3))
    return pts, ofs, bad


def test_meanshift_recovers_a_known_pose_with_30_percent_outliers(meta):
    poses = [(rotation([0.3, -0.5, 0.8], 37), np.array([30.0, -20.0, 650.0])),
             (rotation([1, 0.2, 0], 120), np.array([-60.0, 15.0, 800.0]))]
    P, O, C = [], [], []
    for b, (obj, (R, t)) in enumerate(zip(OBJ, poses)):
        pts, ofs, bad = _object_votes(meta, obj, R, t, seed=b)
        assert 0.25 < bad.mean() < 0.35
        P.append(pts)
        O.append(ofs)
        C.append(np.full(len(pts), meta.class_of(obj)))
    P, O, C = (torch.from_numpy(np.stack(a)) for a in (P, O, C))
    kps = torch.from_numpy(meta.keypoint_array())
    rows = ffb6d_pose.recover_poses(P.float(), C, O[:, :, 0].float(), O[:, :, 1:].permute(0, 2, 1, 3).float(),
                               kps.float(), bandwidth=40.0, generator=torch.Generator().manual_seed(0))
    assert [(b, c) for b, c, *_ in rows] == [(0, 1), (1, 2)]
    for (b, c, score, R, t), (R_gt, t_gt) in zip(rows, poses):
        assert np.linalg.norm(t - t_gt) < 1.0
        assert rot_err_deg(R, R_gt) < 0.1
        assert 0.6 < score <= 1.0                                    # about the 70 % clean points


def test_meanshift_mode_and_inliers():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(300, 3, generator=g) * 3 + torch.tensor([100.0, 0, 0])
    b = torch.randn(100, 3, generator=g) * 3 - torch.tensor([100.0, 0, 0])
    pts = torch.cat([a, b])[None]
    valid = torch.ones(1, 400, dtype=torch.bool)
    valid[0, :10] = False
    mode, inl = ffb6d_pose.meanshift(pts, valid, bandwidth=20.0)
    assert (mode[0] - a[10:].mean(0)).norm() < 1.0
    assert inl[0, 10:300].all() and not inl[0, 300:].any() and not inl[0, :10].any()
    empty, _ = ffb6d_pose.meanshift(pts, torch.zeros_like(valid), bandwidth=20.0)
    assert torch.isnan(empty).all()


def test_meanshift_with_fewer_votes_than_seeds_and_mixed_groups():
    """Groups of 3 valid votes among 600 (fewer than the 32 seeds and 512 seed votes: repeats are
    dropped), none, and 600 — in one batch, float64 in, far from the origin."""
    g = torch.Generator().manual_seed(1)
    pts = (torch.randn(3, 600, 3, generator=g) * 2 + torch.tensor([10.0, 20.0, 900.0])).double()
    valid = torch.zeros(3, 600, dtype=torch.bool)
    valid[0, [5, 100, 599]] = True
    valid[2] = True
    stats: dict = {}
    mode, inl = ffb6d_pose.meanshift(pts, valid, bandwidth=40.0, stats=stats)
    assert torch.allclose(mode[0].double(), pts[0, [5, 100, 599]].median(0).values, atol=1e-3)
    assert torch.isnan(mode[1]).all() and not inl[1].any()
    assert (mode[2].double() - pts[2].mean(0)).norm() < 0.5 and inl[2].all() and inl[0].sum() == 3
    assert stats["seeds"] == 32 and stats["seed_votes"] == 512 and stats["votes"] == 600


def test_recovery_of_a_480x640_vote_set_does_bounded_work():
    """12,800 points, 3 objects, 30 % outlier votes: every pose within 1 mm / 0.1 deg, and MeanShift's
    work bounded by seeds x seed votes x seed iterations + the winner's iterations over all votes (the
    old all-votes-as-seeds MeanShift computed 4,000^2 kernel entries per cluster and iteration)."""
    meta3 = MethodMeta.from_catalog((1, 2, 3), image_size=(480, 640))
    v = ffb6d_pose.example_votes(meta3, 12800, object_share=0.6, outliers=0.3, seed=3)
    assert v["points"].shape == (1, 12800, 3) and v["kp_ofs"].shape == (1, 8, 12800, 3)
    cfg = ffb6d.FFB6DConfig()
    stats: dict = {}
    rows = ffb6d_pose.recover_poses(v["points"], v["classes"], v["ctr_ofs"], v["kp_ofs"], v["model_kps"],
                               cfg.bandwidth_mm, cfg.meanshift_iters, cfg.max_votes, cfg.min_points,
                               torch.Generator().manual_seed(0), stats=stats)
    assert sorted(c for _, c, *_ in rows) == [1, 2, 3]
    for _, c, score, R, t in rows:
        R_gt, t_gt = v["poses"][c]
        assert np.linalg.norm(t - t_gt) < 1.0 and rot_err_deg(R, R_gt) < 0.1
        assert 0.6 < score <= 1.0
    n_votes = 12800 * 6 // 10 // 3                                   # 2,560 points per object
    for part, groups in (("ctr", 3), ("kp", 3 * 8)):
        st = stats[part]
        assert st["groups"] == groups and st["votes"] == n_votes
        assert st["seeds"] == cfg.meanshift_seeds == 32 and st["seed_votes"] == cfg.meanshift_seed_votes == 512
        assert 1 <= st["seed_iters"] <= cfg.meanshift_seed_iters and 1 <= st["refine_iters"] <= 10
        bound = groups * (32 * 512 * cfg.meanshift_seed_iters + 32 * n_votes + n_votes * st["refine_iters"])
        assert st["kernel_evals"] <= bound
    total = stats["ctr"]["kernel_evals"] + stats["kp"]["kernel_evals"]
    assert total < 12_000_000 < 27 * n_votes ** 2                    # < one iteration of the old MeanShift


# --------------------------------------------------------------------------------------------
# training


def _pose_error(rows, R_gt, t_gt, obj_id):
    """Translation error (mm) of the row of ``obj_id``, 1000 when there is none."""
    hits = [r for r in rows if r[1] == obj_id]
    return float(np.linalg.norm(hits[0][4] - t_gt)) if hits else 1000.0


def test_short_training_beats_the_untrained_network(meta):
    torch.manual_seed(0)
    poses = [(rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])),
             (rotation([0, 1, 0.2], -30), np.array([-15.0, 8.0, 420.0]))]
    items = [render_item(1, R, t, seed=i) for i, (R, t) in enumerate(poses)]
    cfg = ffb6d.FFB6DConfig(n_points=512, min_points=5, max_votes=200)
    net = ffb6d.build(cfg, meta)
    train_tf = ffb6d.FFB6DTransform(cfg, meta, train=True)
    eval_tf = ffb6d.FFB6DTransform(cfg, meta, train=False)
    fixed = collate([train_tf(it) for it in items])
    test_batch = collate([eval_tf(it) for it in items])

    def evaluate():
        """Loss and mean translation error (batch statistics, as a 15-step BN has no running ones yet)."""
        with torch.no_grad():
            l0, parts = ffb6d.loss(net, fixed, cfg, meta)
            rows = ffb6d.predict_poses(net, test_batch, cfg, meta)
        err = np.mean([_pose_error([r for r in rows if r[0] == b], R, t, 1) for b, (R, t) in enumerate(poses)])
        return float(l0), parts, err

    loss0, parts0, err0 = evaluate()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for step in range(15):
        batch = collate([train_tf(it) for it in items])
        total, _ = ffb6d.loss(net, batch, cfg, meta)
        opt.zero_grad()
        total.backward()
        opt.step()
    loss1, parts1, err1 = evaluate()
    assert loss1 < 0.25 * loss0, (loss0, loss1)
    assert parts1["ctr_ofs"] < 0.5 * parts0["ctr_ofs"] and parts1["seg_acc"] > 0.9, (parts0, parts1)
    assert err1 < 0.5 * err0 and err1 < 100.0, (err0, err1)
