"""VSD's depth renderer samples pixel centres as bop_toolkit's renderers do: pixel (u, v) (column,
row) sees the ray through (u + 0.5, v + 0.5) in K's image coordinates (its OpenGL projection maps
K's (x, y) to window (x, y) and rasterisation samples window pixel centres), while the distance
image scales pixel (u, v)'s depth by the ray through the integer (u, v) (``depth_im_to_dist_im_fast``).

Checked against an independent z-buffer written here: a numpy rasteriser of the mesh triangles.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from tdof20.scoring import metrics as M

W, H = 160, 120
K = np.array([[600.0, 0.0, 79.3], [0.0, 590.0, 61.7], [0.0, 0.0, 1.0]])


def thin_bar() -> trimesh.Trimesh:
    """A bar 2.5 mm thick (about 3 pixels at 500 mm): a half-pixel shift moves a third of it."""
    return trimesh.creation.box(extents=(2.5, 60.0, 8.0))


def zbuffer(vertices, faces, R, t, Kk, w, h, offset=0.5) -> np.ndarray:
    """Depth (h,w) of the mesh at pose (R, t) by rasterising each triangle: pixel (u, v) is covered
    when its sample point (u + offset, v + offset) lies inside the projected triangle, and its
    depth is where that pixel's ray meets the triangle's plane; the nearest wins; 0 = none."""
    X = vertices @ R.T + t
    uv = (X @ Kk.T)[:, :2] / X[:, 2:3]
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64) + offset
    yr = (vv - Kk[1, 2]) / Kk[1, 1]
    xr = (uu - Kk[0, 2] - Kk[0, 1] * yr) / Kk[0, 0]
    depth = np.full((h, w), np.inf)
    for f in faces:
        a, b, c = uv[f]
        den = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
        if abs(den) < 1e-12:
            continue
        l1 = ((b[1] - c[1]) * (uu - c[0]) + (c[0] - b[0]) * (vv - c[1])) / den
        l2 = ((c[1] - a[1]) * (uu - c[0]) + (a[0] - c[0]) * (vv - c[1])) / den
        inside = (l1 >= 0) & (l2 >= 0) & (1 - l1 - l2 >= 0)
        p0, p1, p2 = X[f]
        n = np.cross(p1 - p0, p2 - p0)
        z = (n @ p0) / (n[0] * xr + n[1] * yr + n[2])  # the ray (x, y, 1) meets the plane at z
        depth = np.where(inside & (z > 0) & (z < depth), z, depth)
    return np.where(np.isfinite(depth), depth, 0.0)


def _pose(angles, t):
    return Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), np.array(t, np.float64)


def test_rendered_depth_matches_a_pixel_centre_zbuffer():
    m = thin_bar()
    ren = M.DepthRenderer(m.vertices, m.faces)
    for angles, t in (([3.0, 7.0, 11.0], [1.3, -2.2, 500.0]), ([40.0, -25.0, 80.0], [-4.1, 3.3, 420.0])):
        R, tt = _pose(angles, t)
        got = ren.render(R, tt, K, W, H).astype(np.float64)
        want = zbuffer(m.vertices, m.faces, R, tt, K, W, H)
        old = zbuffer(m.vertices, m.faces, R, tt, K, W, H, offset=0.0)
        both = (got > 0) & (want > 0)
        assert both.sum() > 100
        # coverage is the same but for a sample grazing an edge (float32 rays)
        assert ((got > 0) != (want > 0)).sum() <= 2
        assert np.abs(got[both] - want[both]).max() < 1e-3  # mm, float32 rays at 500 mm
        # the integer-(u, v) convention is far from it on this thin bar: the test can tell them apart
        assert ((old > 0) != (want > 0)).sum() > 20


def test_vsd_on_the_renderer_equals_vsd_on_the_zbuffer():
    m = thin_bar()
    ren = M.DepthRenderer(m.vertices, m.faces)
    diameter = float(np.linalg.norm(m.extents))
    Rg, tg = _pose([3.0, 7.0, 11.0], [1.3, -2.2, 500.0])
    cases = [_pose([3.0, 7.0, 11.0], [1.3 + dx, -2.2, 500.0 + dz]) for dx, dz in ((0.4, 0.0), (0.9, 2.0), (1.6, 5.0))]
    cases.append(_pose([3.5, 6.0, 12.0], [1.0, -2.0, 503.0]))
    dg = zbuffer(m.vertices, m.faces, Rg, tg, K, W, H)
    dtest = np.where(dg > 0, dg, 900.0).astype(np.float32)
    dtest[:, 70:72] = 0.0  # missing depth
    dtest[30:34, :] = 470.0  # an occluder in front
    Re = np.stack([c[0] for c in cases])
    te = np.stack([c[1] for c in cases])
    want = np.array([M.vsd_from_depths(zbuffer(m.vertices, m.faces, R, t, K, W, H), dg, dtest, K, diameter)
                     for R, t in cases])
    full = np.array([M.vsd_from_depths(ren.render(R, t, K, W, H), ren.render(Rg, tg, K, W, H), dtest, K, diameter)
                     for R, t in cases])
    n = len(cases)
    fast = M.vsd_batch(ren, Re, te, np.repeat(Rg[None], n, 0), np.repeat(tg[None], n, 0), K, dtest[None],
                       np.zeros(n, np.int64), diameter)
    union = max(int((dg > 0).sum()), 1)
    assert np.abs(full - want).max() <= 2.0 / union + 1e-12  # a grazing sample at most
    assert np.array_equal(fast, full)  # the footprint renders are the full renders' rays
    assert 0 < (want < 0.3).sum() < want.size  # the thresholds are exercised


def test_distance_image_scales_by_the_integer_pixel_ray():
    d = np.full((H, W), 500.0, np.float32)
    got = M.distance_image(d, K)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    want = 500.0 * np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    assert np.array_equal(got, want)


def test_a_models_eval_without_its_models_info_is_refused_by_score(tmp_path):
    """A standard BOP dataset whose models_eval/ lacks models_info.json: ``tdof20 benchmark score``
    refuses in one line (as bop_toolkit, which reads models_eval/models_info.json), rather than
    using models/'s diameters, and writes nothing."""
    import subprocess
    import sys

    from tdof20.dataset.results import write_results_csv
    from tests.fixtures.bop_standard import write_bop_dataset

    truth = write_bop_dataset(tmp_path / "bop", obj_ids=(1, 5), splits=("test",), images_per_scene=1)
    root = truth["root"]
    (root / "models_eval" / "models_info.json").unlink()
    tg = truth["targets"][0]
    csv = write_results_csv(tmp_path / "r.csv", [(tg["scene_id"], tg["im_id"], tg["obj_id"], 1.0, np.eye(3),
                                                  np.array([0.0, 0.0, 500.0]), 0.1)])
    out = tmp_path / "score.json"
    p = subprocess.run([sys.executable, "-m", "tdof20", "benchmark", "score", str(csv), "--dataset", str(root),
                        "--json", str(out)], capture_output=True, text=True)
    lines = [ln for ln in (p.stdout + p.stderr).splitlines() if ln.strip()]
    assert p.returncode != 0 and len(lines) == 1, p.stdout + p.stderr
    assert str(root / "models_eval" / "models_info.json") in lines[0] and "models_eval/" in lines[0], lines[0]
    assert not out.exists()
