"""PVNet: the network's shapes, the torchvision ResNet18 layout, 2D RANSAC voting + PnP from known
vector fields (clean and with 30 % outlier vectors), and a short CPU training on rendered items."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tdof20.errors import TdofError
from tdof20.geometry.camera import PinholeCamera
from tdof20.geometry.raycast import ModelRaycaster
from tdof20.methods.base import MethodMeta
from tdof20.methods.data import collate
from tdof20.methods.hff6dof import count_macs, count_parameters
from tdof20.methods.pspnet import PSPNet
from tdof20.methods.pvnet import (PVNet, PVNetConfig, PVNetTransform, build, loss, pnp_pose, predict_poses,
                                  project_keypoints, rotation_error_deg, vote_keypoints_2d)
from tdof20.methods.resnet import OUTPUT_STRIDE_8, ResNet18, ResNet34, load_torchvision_state_dict

OBJS = (1, 5)


def torchvision_resnet18_keys() -> list[str]:
    """The state-dict keys of torchvision.models.resnet18(), written out by hand."""
    bn = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
    keys = ["conv1.weight"] + [f"bn1.{k}" for k in bn]
    for layer in (1, 2, 3, 4):
        for block in (0, 1):
            p = f"layer{layer}.{block}"
            keys += [f"{p}.conv1.weight"] + [f"{p}.bn1.{k}" for k in bn]
            keys += [f"{p}.conv2.weight"] + [f"{p}.bn2.{k}" for k in bn]
            if block == 0 and layer > 1:
                keys += [f"{p}.downsample.0.weight"] + [f"{p}.downsample.1.{k}" for k in bn]
    return keys + ["fc.weight", "fc.bias"]


def render_items(obj_ids=OBJS, n=2, H=48, W=64, seed=0):
    """Dataset items (the SceneImages layout) of catalog objects ray-cast at known random poses:
    flat colour per object with depth shading on a dark noisy background."""
    rng = np.random.default_rng(seed)
    f = 0.9 * W
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    from tdof20.objects import get_object
    rc = ModelRaycaster({o: (get_object(o).vertices, get_object(o).faces) for o in obj_ids}, PinholeCamera(K, W, H))
    colours = {o: rng.uniform(0.3, 1.0, 3) for o in obj_ids}
    out = []
    for i in range(n):
        poses, Rs, ts = [], [], []
        for j, o in enumerate(obj_ids):
            ax = rng.normal(size=3)
            R = Rotation.from_rotvec(ax / np.linalg.norm(ax) * rng.uniform(0.3, 1.5)).as_matrix()
            t = np.array([(-1) ** j * 90.0 * (len(obj_ids) > 1) + rng.uniform(-15, 15), rng.uniform(-15, 15),
                          700.0 + rng.uniform(-50, 50)])
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            poses.append((o, T))
            Rs.append(R)
            ts.append(t)
        r = rc.render(poses)
        lab, ins = np.zeros((H, W), np.int64), np.zeros((H, W), np.int64)
        img = rng.uniform(0, 0.3, (H, W, 3))
        shade = np.clip(1.2 - (r.depth - 650) / 200, 0.3, 1.2)[..., None]
        for j, o in enumerate(obj_ids):
            m = r.visible == j
            lab[m], ins[m] = o, j + 1
            img[m] = (colours[o] * shade)[m]
        out.append({"rgb": torch.from_numpy((img * 255).astype(np.uint8).transpose(2, 0, 1).copy()),
                    "depth": torch.from_numpy(r.depth), "depth_restored": torch.from_numpy(r.depth),
                    "K": torch.tensor(K, dtype=torch.float32), "scene_id": 1, "im_id": i,
                    "label": torch.from_numpy(lab), "instance": torch.from_numpy(ins),
                    "obj_id": torch.tensor(obj_ids), "R": torch.tensor(np.array(Rs), dtype=torch.float32),
                    "t": torch.tensor(np.array(ts), dtype=torch.float32)})
    return out


class Oracle(torch.nn.Module):
    """Stands in for the network: returns given segmentation logits and vertex fields."""

    def __init__(self, seg, vertex):
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(1))
        self.seg, self.vertex = seg, vertex

    def forward(self, rgb, classes=None):
        return {"seg": self.seg, "vertex": self.vertex}


# ------------------------------------------------------------------------------------------


def test_resnet18_has_torchvision_names_and_loads():
    r = ResNet18(with_fc=True)
    sd = r.state_dict()
    assert list(sd) == torchvision_resnet18_keys()
    assert count_parameters(r) == 11_689_512  # torchvision resnet18
    assert sd["layer2.0.downsample.0.weight"].shape == (128, 64, 1, 1) and sd["fc.weight"].shape == (1000, 512)
    dil = ResNet18(replace_stride_with_dilation=OUTPUT_STRIDE_8)
    assert {k: v.shape for k, v in dil.state_dict().items()} == {k: v.shape for k, v in sd.items() if "fc" not in k}
    feats = dil(torch.rand(1, 3, 64, 96))
    assert [tuple(f.shape[2:]) for f in feats] == [(32, 48), (16, 24), (8, 12), (8, 12), (8, 12)]
    assert dil.output_stride == 8 and dil.layer4[1].conv1.dilation == (4, 4) and dil.layer3[0].conv1.dilation == (1, 1)
    # a torchvision-layout resnet18 checkpoint initialises PVNet's backbone; resnet34 still loads its own
    net = PVNet(3)
    ignored = net.load_backbone_weights({k: v.clone() for k, v in sd.items()})
    assert ignored == ["fc.bias", "fc.weight"]
    assert torch.equal(net.backbone.layer4[1].conv2.weight, sd["layer4.1.conv2.weight"])
    load_torchvision_state_dict(ResNet34(), ResNet34(with_fc=True).state_dict())
    with pytest.raises(TdofError, match="lacks ResNet34 keys"):
        load_torchvision_state_dict(ResNet34(), sd)


def test_shapes_and_counts():
    meta = MethodMeta.from_catalog(OBJS, (50, 70))
    net = build(PVNetConfig(), meta).eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 50, 70))
        assert out["seg"].shape == (2, 3, 50, 70) and out["vertex"].shape == (2, 18, 50, 70)
        shared = build(PVNetConfig(class_vectors=False), meta).eval()
        assert shared(torch.rand(1, 3, 48, 64))["vertex"].shape == (1, 18, 48, 64)
    # the per-class heads: 2 x 18 outputs, evaluated only at their own class's pixels
    assert net.vertex_head.weight.shape[0] == 36
    # Table 3 figures at 480x640 (21 classes: the released dataset's 20 objects)
    full = PVNet(21)
    assert 12.9e6 < count_parameters(full) < 13.1e6      # clean-pvnet's Resnet18: 12.96 M for 1 object
    assert 60e9 < count_macs(full, (1, 3, 480, 640)) < 85e9
    for backbone, dim in (("resnet18", 32), ("resnet34", 64)):
        psp = PSPNet(backbone, feat_dim=dim).eval()
        with torch.no_grad():
            assert psp(torch.rand(1, 3, 44, 60)).shape == (1, dim, 44, 60)
        assert hasattr(psp.backbone, "layer4") and hasattr(psp, "up_3")


def test_vote_2d_recovers_keypoints_with_outliers():
    g = torch.Generator().manual_seed(0)
    B, N, K = 3, 400, 9
    coords = torch.rand(B, N, 2, generator=g) * 100
    kp = torch.rand(B, K, 2, generator=g) * 200 - 50
    vec = torch.nn.functional.normalize(kp[:, None] - coords[:, :, None], dim=-1) * 3.0  # any length
    x, n = vote_keypoints_2d(coords, vec, generator=g)
    assert (x - kp).norm(dim=-1).max() < 1e-2 and bool((n == N).all())
    bad = torch.rand(B, N, generator=g) < 0.3
    vec = torch.where(bad[..., None, None], torch.randn(B, N, K, 2, generator=g), vec)
    valid = torch.ones(B, N, dtype=torch.bool)
    valid[2, 200:] = False                                      # padding
    x, n = vote_keypoints_2d(coords, vec, valid, generator=g)
    assert (x - kp).norm(dim=-1).max() < 1e-2
    assert bool((n[:2] >= (~bad[:2]).sum(1)[:, None]).all()) and bool((n[2] <= 200).all())
    # clean-pvnet's plain least squares is pulled by the outliers that fall in the cone by chance
    x0, _ = vote_keypoints_2d(coords, vec, valid, robust_iters=0, generator=g)
    assert (x0 - kp).norm(dim=-1).max() > (x - kp).norm(dim=-1).max()
    # an instance with a single pixel gets NaN
    x1, n1 = vote_keypoints_2d(coords[:1, :1], vec[:1, :1])
    assert bool(torch.isnan(x1).all()) and int(n1.sum()) == 0


@pytest.mark.parametrize("outliers", [0.0, 0.3])
def test_pose_from_ground_truth_fields(outliers):
    """The transform's target fields, fed to predict_poses as if the network had predicted them,
    give back the ground-truth poses (EPnP + LM on the voted 2D keypoints)."""
    items = render_items(OBJS, n=2, H=96, W=128, seed=3)
    meta = MethodMeta.from_catalog(OBJS, (96, 128))
    cfg = PVNetConfig()
    batch = collate([PVNetTransform(cfg, meta, train=True)(it) for it in items])
    cls, vert = batch["cls"], batch["vertex"].clone()
    g = torch.Generator().manual_seed(1)
    bad = torch.rand(cls.shape, generator=g) < outliers
    rnd = torch.nn.functional.normalize(torch.randn(vert.shape[0], 9, 2, *cls.shape[1:], generator=g), dim=2)
    vert = torch.where(bad[:, None], rnd.reshape(vert.shape), vert)
    seg = torch.nn.functional.one_hot(cls, meta.n_classes).permute(0, 3, 1, 2).float() * 20
    rows = predict_poses(Oracle(seg, vert), batch, cfg, meta)
    assert sorted((b, o) for b, o, *_ in rows) == [(0, 1), (0, 5), (1, 1), (1, 5)]
    for b, o, score, R, t in rows:
        j = items[b]["obj_id"].tolist().index(o)
        Rg, tg = items[b]["R"][j].double().numpy(), items[b]["t"][j].double().numpy()
        assert rotation_error_deg(R, Rg) < 0.1 and np.linalg.norm(t - tg) < 1.0
        assert 0.5 * (1 - outliers) < score <= 1.0


def test_pnp_and_projection_agree():
    meta = MethodMeta.from_catalog((5,), (96, 128))
    kp = torch.tensor(meta.keypoints[5], dtype=torch.float32)[None]
    R = torch.tensor(Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix(), dtype=torch.float32)[None]
    t = torch.tensor([[10.0, -20.0, 650.0]])
    K = torch.tensor([[110.0, 0, 63.5], [0, 110.0, 47.5], [0, 0, 1]])
    uv = project_keypoints(kp, R, t, K)[0].double().numpy()
    R_, t_ = pnp_pose(meta.keypoints[5], uv, K.double().numpy())
    assert rotation_error_deg(R_, R[0].double().numpy()) < 0.01 and np.linalg.norm(t_ - t[0].numpy()) < 0.05
    assert pnp_pose(meta.keypoints[5], uv, K.numpy(), use=np.arange(9) < 3) is None


def test_transform_targets_and_refusals():
    items = render_items(OBJS, n=1, H=48, W=64)
    meta = MethodMeta.from_catalog((5,), (24, 32))      # obj 1 is not one of this method's objects
    s = PVNetTransform(PVNetConfig(), meta, train=True)(items[0])
    assert s["rgb"].shape == (3, 24, 32) and s["vertex"].shape == (18, 24, 32)
    assert set(s["cls"].unique().tolist()) == {0, 1} and torch.equal(s["mask"], s["cls"] > 0)
    norms = s["vertex"].view(9, 2, 24, 32).norm(dim=1)
    assert torch.allclose(norms[:, s["mask"]], torch.ones(1)) and float(norms[:, ~s["mask"]].abs().max()) == 0
    assert PVNetTransform(PVNetConfig(), meta)(items[0]).keys() == {"rgb", "K", "scene_id", "im_id"}
    bare = {k: v for k, v in items[0].items() if k not in ("label", "instance")}
    with pytest.raises(TdofError, match="need labels"):
        PVNetTransform(PVNetConfig(), meta, train=True)(bare)
    with pytest.raises(TdofError, match="inlier_cos"):
        PVNetConfig(inlier_cos=1.5)


def test_short_training_beats_the_untrained_net(one_torch_thread):
    torch.manual_seed(0)
    items = render_items(OBJS, n=2, H=48, W=64, seed=0)
    meta = MethodMeta.from_catalog(OBJS, (48, 64))
    cfg = PVNetConfig()
    batch = collate([PVNetTransform(cfg, meta, train=True)(it) for it in items])
    net = build(cfg, meta)

    def projection_error() -> float:
        """Mean 2D projection error (px) of the keypoints over the 4 objects; 50 px when missed."""
        rows = {(b, o): (R, t) for b, o, _, R, t in predict_poses(net, batch, cfg, meta)}
        errs = []
        for b, it in enumerate(items):
            for j, o in enumerate(it["obj_id"].tolist()):
                if (b, o) not in rows:
                    errs.append(50.0)
                    continue
                kp = torch.tensor(meta.keypoints[o], dtype=torch.float32)[None]
                R, t = (torch.tensor(np.asarray(a), dtype=torch.float32)[None] for a in rows[(b, o)])
                e = project_keypoints(kp, R, t, batch["K"][b]) - project_keypoints(kp, it["R"][j:j + 1],
                                                                                   it["t"][j:j + 1], batch["K"][b])
                errs.append(min(50.0, float(e.norm(dim=-1).mean())))
        return float(np.mean(errs))

    with torch.no_grad():
        before, _ = loss(net, batch, cfg, meta)
    err_before = projection_error()
    opt = torch.optim.Adam(net.parameters(), 2e-3)
    net.train()
    for _ in range(40):
        opt.zero_grad()
        total, parts = loss(net, batch, cfg, meta)
        total.backward()
        opt.step()
    assert set(parts) == {"loss", "vote", "seg"} and math.isfinite(parts["loss"])
    with torch.no_grad():
        after, _ = loss(net, batch, cfg, meta)
    err_after = projection_error()
    assert float(after) < 0.4 * float(before)
    assert err_after < 5.0 < err_before
