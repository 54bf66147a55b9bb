"""VSD's depth renderer samples pixel centres as bop_toolkit's renderers do: pixel (u, v) (column,
row) sees the ray through (u + 0.5, v + 0.5) in K's image coordinates (its OpenGL projection maps
K's (x, y) to window (x, y) and rasterisation samples window pixel centres), while the distance
image scales pixel (u, v)'s depth by the ray through the integer (u, v) (``depth_im_to_dist_im_fast``).
Its depths are those of the toolkit's vispy renderer: a 16-bit OpenGL depth buffer whose clip planes
are the model's bounding box extremes in eye z, read back with float32 arithmetic.

Checked against an independent z-buffer written here: a numpy rasteriser of the mesh triangles, whose
depths go through a 16-bit depth buffer written here from the toolkit's projection matrix
(``_calc_calib_proj``) and read-back (``_draw_depth``).
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


def depth16(depth, vertices, R, t) -> np.ndarray:
    """Exact depths (0 = none) as bop_toolkit's vispy renderer returns them: clip planes n, f = the
    eye-z extremes of the vertices' bounding box corners; OpenGL's NDC z of eye depth z is
    (q (-z) + qn) / z with q = -(f+n)/(f-n), qn = -2 f n/(f-n) (its projection matrix), window depth
    (ndc + 1) / 2 stored as round(65535 window) in GL_DEPTH_COMPONENT16, read back as float32 and
    turned into depth by n f/(n-f) / (w + f/(n-f)) in float32; w = 1 is background."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    ez = corners @ R[2] + t[2]
    n, f = ez.min(), ez.max()
    q, qn = -(f + n) / (f - n), -2 * f * n / (f - n)
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = (q * -depth + qn) / depth
    stored = np.round(np.clip((ndc + 1) / 2, 0, 1) * 65535)
    w = (stored / 65535).astype(np.float32)
    out = np.float32(n * f / (n - f)) / (w + np.float32(f / (n - f)))
    return np.where((depth > 0) & (stored < 65535), out, np.float32(0))


def _pose(angles, t):
    return Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), np.array(t, np.float64)


def test_rendered_depth_matches_a_pixel_centre_zbuffer():
    m = thin_bar()
    ren = M.DepthRenderer(m.vertices, m.faces)
    for angles, t in (([3.0, 7.0, 11.0], [1.3, -2.2, 500.0]), ([40.0, -25.0, 80.0], [-4.1, 3.3, 420.0])):
        R, tt = _pose(angles, t)
        got = ren.render(R, tt, K, W, H)
        exact = zbuffer(m.vertices, m.faces, R, tt, K, W, H)
        want = depth16(exact, m.vertices, R, tt)
        old = zbuffer(m.vertices, m.faces, R, tt, K, W, H, offset=0.0)
        both = (got > 0) & (want > 0)
        assert both.sum() > 100
        # coverage is the same but for a sample grazing an edge (float32 rays)
        assert ((got > 0) != (want > 0)).sum() <= 2
        # the toolkit's values, bit for bit, but where float32 rays (about 3e-5 mm at 500 mm) round a
        # stored value the other way: one step (twice the largest rounding of the exact depth) apart
        half_step = np.abs(want[both] - exact[both]).max()
        assert (got[both] == want[both]).mean() > 0.8
        assert np.abs(got[both] - want[both]).max() <= 2.01 * half_step < 1e-3
        # the integer-(u, v) convention is far from it on this thin bar: the test can tell them apart
        assert ((old > 0) != (want > 0)).sum() > 20


def test_vsd_on_the_renderer_equals_vsd_on_the_zbuffer():
    m = thin_bar()
    ren = M.DepthRenderer(m.vertices, m.faces)
    diameter = float(np.linalg.norm(m.extents))
    Rg, tg = _pose([3.0, 7.0, 11.0], [1.3, -2.2, 500.0])
    cases = [_pose([3.0, 7.0, 11.0], [1.3 + dx, -2.2, 500.0 + dz]) for dx, dz in ((0.4, 0.0), (0.9, 2.0), (1.6, 5.0))]
    cases.append(_pose([3.5, 6.0, 12.0], [1.0, -2.0, 503.0]))
    dg = depth16(zbuffer(m.vertices, m.faces, Rg, tg, K, W, H), m.vertices, Rg, tg)
    dtest = np.where(dg > 0, dg, 900.0).astype(np.float32)
    dtest[:, 70:72] = 0.0  # missing depth
    dtest[30:34, :] = 470.0  # an occluder in front
    Re = np.stack([c[0] for c in cases])
    te = np.stack([c[1] for c in cases])
    want = np.array([M.vsd_from_depths(depth16(zbuffer(m.vertices, m.faces, R, t, K, W, H), m.vertices, R, t), dg,
                                       dtest, K, diameter) for R, t in cases])
    full = np.array([M.vsd_from_depths(ren.render(R, t, K, W, H), ren.render(Rg, tg, K, W, H), dtest, K, diameter)
                     for R, t in cases])
    n = len(cases)
    fast = M.vsd_batch(ren, Re, te, np.repeat(Rg[None], n, 0), np.repeat(tg[None], n, 0), K, dtest[None],
                       np.zeros(n, np.int64), diameter)
    union = max(int((dg > 0).sum()), 1)
    assert np.abs(full - want).max() <= 2.0 / union + 1e-12  # a grazing sample at most
    assert np.array_equal(fast, full)  # the footprint renders are the full renders' rays
    assert 0 < (want < 0.3).sum() < want.size  # the thresholds are exercised


def test_depth_buffer_holds_65535_steps_between_the_clip_planes():
    """Against :func:`depth16` (the toolkit's projection and read-back); the far plane stores 1,
    the cleared buffer's value: background (0), as the toolkit's ``dep[dep == 1] = 0``."""
    z = np.array([0.0, 500.0, 500.0004, 520.0, 559.9999, 560.0], np.float32)
    got = M.depth_buffer(z, 500.0, 560.0)
    assert got[0] == 0 and got[-2] == 0 and got[-1] == 0  # no hit; within half a step of the far plane
    assert got[1] == got[2] == np.float32(500.0)  # the near plane, to within half a step
    assert abs(got[3] - 520.0) < 60.0 / 65535 * 2 and got[3] != np.float32(520.0)
    assert got.dtype == np.float32
    zz = np.linspace(500.0, 560.0, 20001).astype(np.float32)
    box = np.array([[0.0, 0.0, -30.0], [0.0, 0.0, 30.0]])  # eye z from 500 to 560 at t = (0, 0, 530)
    want = depth16(zz.astype(np.float64), box, np.eye(3), np.array([0.0, 0.0, 530.0]))
    assert (M.depth_buffer(zz, 500.0, 560.0) == want).mean() > 0.999  # but a rounding tie or two
    # near = far (a flat model face on; the toolkit's projection divides by 0): the depth itself
    assert np.array_equal(M.depth_buffer(np.float32([0.0, 500.0]), 500.0, 500.0), np.float32([0.0, 500.0]))


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
