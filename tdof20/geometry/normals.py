"""Surface normals of an organised XYZ map."""

from __future__ import annotations

import numpy as np


def normals_from_xyz(xyz: np.ndarray) -> np.ndarray:
    """Organised XYZ map (H,W,3), 0 where invalid -> unit normals (H,W,3) float32, 0 where undefined.

    Central differences where both neighbours are valid, one-sided otherwise; normals face the
    camera (n . p < 0).
    """
    xyz = np.asarray(xyz, dtype=np.float32)
    valid = xyz[..., 2] > 0
    pad = np.pad(xyz, ((1, 1), (1, 1), (0, 0)))
    vpad = np.pad(valid, 1)

    def diff(a_sl, b_sl, va, vb):
        return np.where((va & vb)[..., None], pad[a_sl] - pad[b_sl], 0.0)

    c = (slice(1, -1), slice(1, -1))
    right, left = (slice(1, -1), slice(2, None)), (slice(1, -1), slice(0, -2))
    down, up = (slice(2, None), slice(1, -1)), (slice(0, -2), slice(1, -1))
    vc, vr, vl, vd, vu = vpad[c], vpad[right], vpad[left], vpad[down], vpad[up]
    du = np.where((vr & vl)[..., None], pad[right] - pad[left], diff(right, c, vr, vc) + diff(c, left, vc, vl))
    dv = np.where((vd & vu)[..., None], pad[down] - pad[up], diff(down, c, vd, vc) + diff(c, up, vc, vu))
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = valid & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12), 0.0)
    flip = np.sum(n * xyz, axis=-1) > 0
    n[flip] *= -1
    return n.astype(np.float32)
