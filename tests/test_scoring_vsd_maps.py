"""VSD of many poses sharing a camera uses full-image ray maps (gathered per pixel) instead of
computing each pose's rays: the values must be the very same, bit for bit, as pose by pose
(:func:`tdof20.scoring.metrics.vsd.ray_maps` is used only from 16 poses of one K on), and both
equal :func:`vsd_from_depths` on full renders up to a grazing pixel or two."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from tdof20.scoring import metrics as M
from tdof20.scoring.metrics import vsd as V

W, H = 160, 120
K = np.array([[190.0, 0.0, 81.3], [0.0, 188.0, 58.9], [0.0, 0.0, 1.0]])


def test_ray_maps_equal_ray_norms_bit_for_bit():
    x, y, nrm = V.ray_maps(K, H, W)
    v, u = np.divmod(np.arange(H * W), W)
    xc, yc, _ = M.ray_norms(K, u + V.RENDER_PIXEL_OFFSET, v + V.RENDER_PIXEL_OFFSET)
    assert np.array_equal(x, xc) and np.array_equal(y, yc)
    assert np.array_equal(nrm, M.ray_norms(K, u, v)[2])


def test_many_poses_equal_pose_by_pose_and_full_renders():
    rng = np.random.default_rng(4)
    mesh = trimesh.creation.box(extents=(40.0, 25.0, 15.0))
    ren = M.DepthRenderer(mesh.vertices, mesh.faces)
    diameter = float(np.linalg.norm(mesh.extents))
    B = 24  # > 16: the ray maps are used
    Rg = Rotation.random(B, random_state=1).as_matrix()
    tg = np.column_stack([rng.uniform(-20, 20, B), rng.uniform(-15, 15, B), rng.uniform(350, 450, B)])
    Re = Rotation.from_rotvec(rng.normal(size=(B, 3)) * 0.08).as_matrix() @ Rg
    te = tg + rng.normal(size=(B, 3)) * 4.0
    depths = []
    for i in range(B):
        d = ren.render(Rg[i], tg[i], K, W, H)
        d = np.where(d > 0, d + rng.normal(0, 3, d.shape).astype(np.float32), 600.0).astype(np.float32)
        d[rng.random(d.shape) < 0.05] = 0.0
        depths.append(d)
    stack = np.stack(depths)
    many = M.vsd_batch(ren, Re, te, Rg, tg, K, stack, np.arange(B), diameter)
    one = np.concatenate([M.vsd_batch(ren, Re[i:i + 1], te[i:i + 1], Rg[i:i + 1], tg[i:i + 1], K, stack[i:i + 1],
                                      np.zeros(1, np.int64), diameter) for i in range(B)])
    assert np.array_equal(many, one)
    assert 0 < (many < 0.3).sum() < many.size  # the thresholds are exercised
    for i in range(0, B, 6):
        ref = M.vsd_from_depths(ren.render(Re[i], te[i], K, W, H), ren.render(Rg[i], tg[i], K, W, H), stack[i], K,
                                diameter)
        assert np.abs(many[i] - ref).max() <= 2e-3
