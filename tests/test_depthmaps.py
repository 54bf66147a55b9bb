"""Depth maps of the turntable volume and the projective-association ICP (tdof20.annotate.depthmaps):
synthetic geometry with known answers, then two frames of a simulated session against its truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tdof20.annotate import RegistrationConfig, evaluate_against_truth, register_session
from tdof20.annotate.depthmaps import (DepthMap, block_depth, icp_projective, smallest_eigenvectors,
                                       strided_camera)
from tdof20.annotate.evaluate import truth_T_ref_frame
from tdof20.annotate.turntable import T_diff, VolumeCrop
from tdof20.capture import run_capture, sim_config
from tdof20.geometry.camera import PinholeCamera
from tdof20.geometry.transforms import invert, rotation_about_axis

CAM = PinholeCamera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)


def _plane_depth(cam: PinholeCamera, n: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Depth (mm) of the plane through p with normal n seen by ``cam``: z = (n.p) / (n.ray)."""
    rays = cam.pixel_rays().astype(np.float64)
    return ((n @ p) / (rays @ n)).astype(np.float32)


def _sphere_depth(cam: PinholeCamera, c: np.ndarray, r: float) -> np.ndarray:
    """Depth of the near side of a sphere (0 where the ray misses it)."""
    rays = cam.pixel_rays().astype(np.float64)
    a = np.einsum("hwc,hwc->hw", rays, rays)
    b = rays @ c
    disc = b * b - a * (c @ c - r * r)
    t = (b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where(disc > 0, t, 0.0).astype(np.float32)


def _crop(cam: PinholeCamera, radius: float = 1000.0) -> VolumeCrop:
    """A volume that holds everything in front of the camera: axis along the optical axis, table
    far behind, tall and wide."""
    cfg = RegistrationConfig(crop_below_mm=0.0, crop_height_mm=5000.0)
    return VolumeCrop(cam, cfg, np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 5000.0]), radius)


# --- pure pieces --------------------------------------------------------------------------------
def test_block_depth_averages_blocks_and_drops_edges():
    z = np.full((8, 8), 500.0, np.float32)
    z[:, 5:] = 600.0                       # a step edge inside the block of columns 4..5
    z[0, 0] = 0.0                          # one missing pixel: the block still has 3 of 4
    z[6:, 0:2] = 0.0                       # a block without depth
    zb = block_depth(z, [2, 1], 150.0, 2000.0, fx=300.0)
    assert set(zb) == {1, 2} and zb[2].shape == (4, 4)
    assert zb[2][0, 0] == 500.0            # the mean of its valid pixels
    assert np.all(zb[2][:, 2] == 0.0)      # 500 | 600 straddles the edge: dropped, not 550
    assert np.all(zb[2][:, 3] == 600.0)
    assert zb[2][3, 0] == 0.0
    assert np.array_equal(zb[1], np.where((z >= 150) & (z <= 2000), z, 0))
    # a plane seen obliquely (up to 65 deg from the line of sight) is not an edge
    n = np.array([0.0, math.sin(math.radians(60)), -math.cos(math.radians(60))])
    zp = _plane_depth(CAM, n, np.array([0.0, 0.0, 500.0]))
    rays = CAM.pixel_rays().astype(np.float64)
    incidence = np.degrees(np.arccos(np.abs(rays @ n) / np.linalg.norm(rays, axis=-1)))
    seen = (incidence < 65.0).reshape(60, 4, 80, 4).all(axis=(1, 3))
    zb = block_depth(zp, [4], 150.0, 2000.0, fx=CAM.fx)[4]
    assert seen.sum() > 2000 and np.all(zb[seen] > 0)


def test_strided_camera_puts_blocks_at_their_pixel_centres():
    """Back-projecting a block's mean depth through the strided camera gives the mean of the
    block's points (a fronto-parallel plane: exact)."""
    z = np.full((CAM.height, CAM.width), 480.0, np.float32)
    for s in (2, 3, 4):
        sc = strided_camera(CAM, s)
        zb = block_depth(z, [s], 150.0, 2000.0, fx=CAM.fx)[s]
        assert zb.shape == (CAM.height // s, CAM.width // s) == (sc.height, sc.width)
        P = CAM.backproject(z)
        Pb = sc.backproject(zb)
        for v, u in [(0, 0), (5, 7), (sc.height - 1, sc.width - 1)]:
            mean = P[v * s:(v + 1) * s, u * s:(u + 1) * s].reshape(-1, 3).mean(axis=0)
            assert np.allclose(Pb[v, u], mean, atol=1e-3)


def test_smallest_eigenvectors_match_numpy():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(500, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    C[:50] = np.diag([4.0, 1.0, 0.01])                      # a flat patch: one tiny axis
    v, var = smallest_eigenvectors(C)
    w, V = np.linalg.eigh(C)
    assert np.allclose(np.abs(np.einsum("ni,ni->n", v, V[:, :, 0])), 1.0, atol=1e-9)
    assert np.allclose(var, w[:, 0] / w.sum(axis=1), atol=1e-12)
    assert np.allclose(np.abs(v[:50, 2]), 1.0)


def test_normals_of_a_tilted_plane_and_a_sphere_and_none_across_its_silhouette():
    n = np.array([0.0, math.sin(math.radians(35)), -math.cos(math.radians(35))])   # towards the camera
    p = np.array([0.0, 0.0, 600.0])
    c, r = np.array([10.0, -5.0, 450.0]), 60.0
    zp, zs = _plane_depth(CAM, n, p), _sphere_depth(CAM, c, r)
    z = np.where((zs > 0) & (zs < zp), zs, zp)
    cfg = RegistrationConfig()
    m = DepthMap(z, _crop(CAM), cfg, window=7, max_source=500)
    assert len(m.source) == 500 and len(m) == np.count_nonzero(z)
    has = m.zt > 0
    N = m.normals.astype(np.float64)
    V = CAM.backproject(z).astype(np.float64)
    sphere = (zs > 0) & (zs < zp)
    inner_sphere = sphere & (np.linalg.norm(V - c, axis=-1) < r + 0.5)
    true_sphere = (V - c) / r
    ang = np.degrees(np.arccos(np.clip(np.einsum("hwc,hwc->hw", N, true_sphere), -1, 1)))
    # well inside the sphere's disc (away from its silhouette) the normals are the sphere's
    (u0, v0), = CAM.project(c[None])[0]
    disc = np.hypot(np.arange(CAM.width)[None, :] - u0, np.arange(CAM.height)[:, None] - v0)   # px from its centre
    inside = inner_sphere & has & (disc < 0.6 * CAM.fx * r / c[2])
    assert inside.sum() > 500 and np.median(ang[inside]) < 2.0 and np.percentile(ang[inside], 95) < 5.0
    # on the plane far from the sphere: the plane's normal
    far = ~sphere & has & (disc > 2.0 * CAM.fx * r / c[2])
    ang_p = np.degrees(np.arccos(np.clip(N[far] @ n, -1, 1)))
    assert far.sum() > 5000 and ang_p.max() < 0.5
    # the silhouette: the sphere's edge pixels (their window holds the plane 100+ mm behind) get none
    edge = sphere & ~np.roll(sphere, 2, axis=1)
    assert edge.sum() > 20 and not has[edge].any()


def test_projective_icp_recovers_a_known_motion_of_a_synthetic_scene():
    """Two views of a plane with a sphere on it, the scene turned 3 deg about an axis: started 0.5
    deg / 3 mm off, the ICP ends on the true motion; the prior holds what the data leaves free."""
    n = np.array([0.0, math.sin(math.radians(40)), -math.cos(math.radians(40))])
    p = np.array([0.0, 0.0, 550.0])
    axis_n = -n
    balls = [(np.array([40.0, 10.0, 520.0]), 25.0), (np.array([-30.0, -20.0, 500.0]), 18.0)]

    def depth(T):   # the scene moved by T (model -> camera)
        R, t = T[:3, :3], T[:3, 3]
        z = _plane_depth(CAM, R @ n, R @ p + t)
        for c, r in balls:
            zs = _sphere_depth(CAM, R @ c + t, r)
            z = np.where((zs > 0) & (zs < z), zs, z)
        return z
    M = rotation_about_axis(axis_n, math.radians(3.0), p)           # the turn of the scene
    cfg = RegistrationConfig()
    a = DepthMap(depth(np.eye(4)), _crop(CAM), cfg, window=9, max_source=4000)
    b = DepthMap(depth(M), _crop(CAM), cfg, window=9, max_source=4000)
    # points of view a, moved by M, are points of view b: register a (source) onto b (target)
    start = rotation_about_axis(np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]), math.radians(0.5), p) @ M
    start[:3, 3] += [2.0, -2.0, 1.0]
    T, fit, rmse, info = icp_projective(a, b, start, p, RegistrationConfig(prior_sigma_deg=5.0, prior_sigma_mm=50.0),
                                        dist=10.0, iterations=30)
    rd, _ = T_diff(T, M)
    rd0, _ = T_diff(start, M)
    # (measured: 0.039 deg / 0.25 mm from 0.50 deg / 3.5 mm; the residue is the pixel grid's: a
    # projective correspondence is the surface at the pixel centre, ~1 mm beside the true point)
    assert rd0 > 0.45 and rd < 0.08 and np.linalg.norm((T - M)[:3, :3] @ p + (T - M)[:3, 3]) < 0.5
    assert fit > 0.8 and rmse < 1.5 and info.shape == (6, 6)


# --- a simulated session ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small(tmp_path_factory):
    out = tmp_path_factory.mktemp("dm") / "single"
    run_capture(sim_config("multi/08", steps=12, step_deg=30.0, n_arms=1, phases=("opaque",), width=320, height=240),
                out, yes=True, show_progress=False)
    return out


def test_both_associations_register_a_session_against_its_truth(small):
    """The default (projective) and the k-d tree (closest) associations both register every frame
    well within the targets; the projective one at least as accurately here."""
    errs = {}
    for assoc in ("projective", "closest"):
        res = register_session(small, RegistrationConfig(association=assoc), progress=False)
        ev = evaluate_against_truth(res, small)
        assert res.flagged_frames() == [] and ev["n_frames"] == 12, assoc
        assert ev["consecutive"]["rot_deg"]["median"] < 0.1 and ev["consecutive"]["trans_mm"]["median"] < 1.0, assoc
        errs[assoc] = ev["pairs"]["rot_deg"]["median"]
    assert errs["projective"] < 0.1 and errs["closest"] < 0.1
    assert errs["projective"] <= 1.5 * errs["closest"], errs


def test_maps_of_a_simulated_frame_pair_give_the_true_turn(small):
    from tdof20.formats.session import RawSession

    s = RawSession.open(small)
    truth = truth_T_ref_frame(small)
    T01 = invert(truth[0, 0]) @ truth[0, 1]            # cam(0,1) -> cam(0,0)
    cfg = RegistrationConfig()
    crop = _crop(s.info.camera)

    def depth_map(k):
        return DepthMap(block_depth(s.load_depth_mm("opaque", 0, k), [1], 150, 2000, s.info.camera.fx)[1], crop, cfg,
                        7, 4000)
    m0, m1 = depth_map(0), depth_map(1)
    centre = np.array([0.0, 0.0, 450.0])    # roughly the table's middle
    start = T01.copy()
    start[:3, 3] += [1.5, 0.0, -1.0]
    T, fit, _, _ = icp_projective(m1, m0, start, centre, RegistrationConfig(prior_sigma_deg=2.0, prior_sigma_mm=20.0),
                                  dist=8.0, iterations=30)
    rd, _ = T_diff(T, T01)
    err0 = np.linalg.norm((start - T01)[:3, :3] @ centre + (start - T01)[:3, 3])
    err = np.linalg.norm((T - T01)[:3, :3] @ centre + (T - T01)[:3, 3])
    assert rd < 0.1 and err < 0.5 < err0 and fit > 0.5
