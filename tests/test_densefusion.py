"""DenseFusion: shapes, quaternions, crops, most-confident-point recovery + refinement, ADD-S loss, training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tdof20.methods import densefusion as dfm
from tdof20.methods.base import MethodMeta
from tdof20.methods.data import collate
from tdof20.methods.fitting import matrix_to_quaternion, quaternion_to_matrix
from tests.test_ffb6d import render_item, rot_err_deg, rotation

pytestmark = pytest.mark.usefixtures("one_torch_thread")

HW = (48, 64)
OBJ = (1, 5)
SMALL = dict(n_points=64, n_model_points=60, crop_size=32, min_points=10)


@pytest.fixture(scope="module")
def meta():
    return MethodMeta.from_catalog(OBJ, image_size=HW)


@pytest.fixture(scope="module")
def net(meta):
    torch.manual_seed(0)
    return dfm.build(dfm.DenseFusionConfig(**SMALL), meta)


def test_quaternion_round_trip():
    g = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(200, 4, generator=g, dtype=torch.float64), dim=1)
    R = quaternion_to_matrix(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(200, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(200, dtype=torch.float64))
    assert torch.allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-10)
    Rz = torch.from_numpy(rotation([0, 0, 1], 90))
    assert torch.allclose(matrix_to_quaternion(Rz), torch.tensor([0.5 ** 0.5, 0, 0, 0.5 ** 0.5], dtype=torch.float64))


def test_forward_shapes_and_parameter_counts(meta, net):
    cfg = dfm.DenseFusionConfig(**SMALL)
    out = net(dfm.example_batch(cfg, meta, batch_size=2))
    assert out["seg"].shape == (2, meta.n_classes, *HW)
    assert out["quat"].shape == (2, 64, 4) and out["trans"].shape == (2, 64, 3) and out["conf"].shape == (2, 64)
    assert ((out["conf"] > 0) & (out["conf"] < 1)).all()
    assert out["refine_quat"].shape == (2, 4) and out["refine_trans"].shape == (2, 3)
    n = {k: sum(p.numel() for p in getattr(net, k).parameters()) for k in ("seg", "estimator", "refiner")}
    assert 20e6 < n["estimator"] < 23e6 and 1.8e6 < n["refiner"] < 2.1e6


def test_crop_box_follows_the_border_list():
    m = np.zeros((480, 640), bool)
    m[100:150, 200:290] = True                                       # 50 x 90 -> 80 x 120
    r0, r1, c0, c1 = dfm.crop_box(m, (480, 640))
    assert (r1 - r0, c1 - c0) == (80, 120) and r0 <= 100 and r1 >= 150 and c0 <= 200 and c1 >= 290
    m[:] = False
    m[470:480, 630:640] = True                                       # at the corner: shifted inside
    assert dfm.crop_box(m, (480, 640)) == (440, 480, 600, 640)


def _per_point_predictions(meta, obj_id, R, t_mm, n=200, outliers=0.3, seed=0):
    """Cloud (1,n,3) m on the model in pose (R, t) and per-point predictions: the true quaternion and
    translation offset with confidence 0.5-0.9, ``outliers`` of the points random with confidence < 0.3."""
    rng = np.random.default_rng(seed)
    mp = meta.model_points[obj_id][rng.choice(len(meta.model_points[obj_id]), n)]
    cloud = (mp @ R.T + t_mm) / 1000.0
    q = matrix_to_quaternion(torch.from_numpy(R))
    quat = q.expand(n, 4).clone()
    trans = torch.from_numpy(t_mm / 1000.0 - cloud)
    conf = torch.from_numpy(rng.uniform(0.5, 0.9, n))
    bad = torch.from_numpy(rng.random(n) < outliers)
    quat[bad] = torch.nn.functional.normalize(torch.randn(int(bad.sum()), 4, dtype=torch.float64), dim=1)
    trans[bad] = torch.from_numpy(rng.uniform(-0.2, 0.2, (int(bad.sum()), 3)))
    conf[bad] = torch.from_numpy(rng.uniform(0.0, 0.3, int(bad.sum())))
    return cloud, quat, trans, conf, bad


def test_most_confident_point_recovers_a_known_pose_with_30_percent_outliers(meta):
    R_gt, t_gt = rotation([0.3, -0.5, 0.8], 37), np.array([30.0, -20.0, 650.0])
    cloud, quat, trans, conf, bad = _per_point_predictions(meta, 1, R_gt, t_gt)
    assert 0.25 < bad.float().mean() < 0.35
    R, t, score = dfm.best_pose(quat[None], trans[None], conf[None], torch.from_numpy(cloud)[None])
    assert np.linalg.norm(t[0].numpy() * 1000 - t_gt) < 1.0
    assert rot_err_deg(R[0].numpy(), R_gt) < 0.1
    assert float(score[0]) == float(conf.max()) and float(score[0]) >= 0.5


def test_refinement_composes_the_corrections(meta, net):
    """refine_pose applies T <- T @ T_corr per iteration (eval_ycb.py): a refiner that returns the
    exact correction (Kabsch of the model points onto the points in the current frame) takes a
    perturbed start onto the truth, and a second iteration keeps it there."""
    from tdof20.methods.fitting import kabsch_torch

    R_gt, t_gt = torch.from_numpy(rotation([1, 0, 0.3], 25)), torch.tensor([0.02, 0.01, 0.6], dtype=torch.float64)
    model = torch.from_numpy(meta.model_points[1][:100] / 1000.0)
    cloud = (model @ R_gt.T + t_gt)[None]
    R0 = torch.from_numpy(rotation([0, 1, 0], 8)) @ R_gt
    t0 = t_gt + torch.tensor([0.01, -0.005, 0.02], dtype=torch.float64)

    class Exact(torch.nn.Module):
        calls = 0

        def forward(self, x, emb, cls):
            self.calls += 1
            Rc, tc = kabsch_torch(model[None], x)
            return matrix_to_quaternion(Rc), tc

    real = net.refiner
    try:
        net.refiner = Exact()
        R, t = dfm.refine_pose(net, R0[None], t0[None], cloud, None, torch.zeros(1, dtype=torch.long), 2)
        calls = net.refiner.calls
    finally:
        net.refiner = real
    assert calls == 2
    assert rot_err_deg(R[0].numpy(), R_gt.numpy()) < 1e-5
    assert (t[0] - t_gt).norm() < 1e-9


def test_symmetric_loss_takes_the_closest_point(meta):
    g = torch.Generator().manual_seed(0)
    target = torch.randn(1, 50, 3, generator=g)
    perm = target[:, torch.randperm(50, generator=g)]                # same set, other order
    sym = dfm.point_distances(perm[:, None], target, torch.tensor([True]))
    add = dfm.point_distances(perm[:, None], target, torch.tensor([False]))
    assert float(sym) < 1e-6 < float(add)


def test_transform_crops_the_object(meta):
    R, t = rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])
    item = render_item(1, R, t)
    cfg = dfm.DenseFusionConfig(**SMALL, noise_trans_mm=0.0)
    s = dfm.DenseFusionTransform(cfg, meta, train=True)(item)
    assert bool(s["has_crop"]) and int(s["cls"]) == 1 and bool(s["symmetric"]) == meta.symmetric[1]
    assert s["crop"].shape == (3, 32, 32) and s["cloud"].shape == (64, 3) and s["choose"].max() < 32 * 32
    # the cloud is on the object: within its diameter of the true centre
    ctr = (meta.keypoints[1][0] @ R.T + t) / 1000
    assert np.linalg.norm(s["cloud"].numpy() - ctr, axis=1).max() < meta.diameters[1] / 1000
    assert torch.allclose(s["target"], s["model_points"] @ torch.from_numpy(R).float().T
                          + torch.from_numpy(t).float() / 1000, atol=1e-6)
    assert set(s["seg"].unique().tolist()) == {0, 1}


def test_prediction_from_a_given_segmentation(meta, net):
    """predict_poses: segmentation -> crops -> estimator -> refiner, rows per predicted object."""
    R, t = rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])
    item = render_item(5, R, t)
    cfg = dfm.DenseFusionConfig(**SMALL)
    batch = collate([dfm.DenseFusionTransform(cfg, meta, train=False)(item)])
    real = net.seg

    class Oracle(torch.nn.Module):
        def forward(self, rgb):
            return torch.nn.functional.one_hot(batch["seg"], meta.n_classes).permute(0, 3, 1, 2).float()

    net.eval()
    try:
        net.seg = Oracle()
        rows = dfm.predict_poses(net, batch, cfg, meta)
    finally:
        net.seg = real
        net.train()
    assert [(b, o) for b, o, *_ in rows] == [(0, 5)]
    b, o, score, Rp, tp = rows[0]
    assert Rp.shape == (3, 3) and tp.shape == (3,) and 0 < score < 1
    assert np.allclose(Rp @ Rp.T, np.eye(3), atol=1e-5)


def test_short_training_beats_the_untrained_network(meta):
    torch.manual_seed(0)
    poses = [(rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])),
             (rotation([0, 1, 0.2], -30), np.array([-15.0, 8.0, 420.0]))]
    items = [render_item(5, R, t, seed=i) for i, (R, t) in enumerate(poses)]
    cfg = dfm.DenseFusionConfig(**SMALL, stage="pose", noise_trans_mm=0.0)
    net = dfm.build(cfg, meta)
    tf = dfm.DenseFusionTransform(cfg, meta, train=True)
    fixed = collate([tf(it) for it in items])

    def evaluate():
        with torch.no_grad():
            return dfm.loss(net, fixed, cfg, meta)[1]

    before = evaluate()
    opt = torch.optim.Adam(net.estimator.parameters(), lr=1e-3)
    for _ in range(15):
        total, _ = dfm.loss(net, collate([tf(it) for it in items]), cfg, meta)
        opt.zero_grad()
        total.backward()
        opt.step()
    after = evaluate()
    assert after["pose"] < 0.5 * before["pose"], (before, after)
    assert after["dis_mm"] < 0.5 * before["dis_mm"], (before, after)   # ADD-S of the most confident pose


def test_stages_train_what_they_say(meta, net):
    R, t = rotation([1, 2, 0.5], 40), np.array([10.0, -5.0, 400.0])
    batch = collate([dfm.DenseFusionTransform(dfm.DenseFusionConfig(**SMALL), meta, train=True)(render_item(1, R, t))])
    for stage, trained, frozen in (("seg", "seg", "estimator"), ("pose", "estimator", "refiner"),
                                   ("refine", "refiner", "estimator")):
        net.zero_grad(set_to_none=True)
        total, parts = dfm.loss(net, batch, dfm.DenseFusionConfig(**SMALL, stage=stage), meta)
        total.backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in getattr(net, trained).parameters()), stage
        assert all(p.grad is None for p in getattr(net, frozen).parameters()), stage
    net.zero_grad(set_to_none=True)
    total, parts = dfm.loss(net, batch, dfm.DenseFusionConfig(**SMALL, stage="joint"), meta)
    assert {"seg", "pose", "refine", "dis_mm", "dis_refined_mm", "loss"} <= set(parts)
    from tdof20.errors import TdofError

    with pytest.raises(TdofError, match="stage"):
        dfm.DenseFusionConfig(stage="everything")
