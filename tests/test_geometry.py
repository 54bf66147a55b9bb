"""tdof20.geometry: camera model, transforms, normals, fitting and sampling."""

from __future__ import annotations

import numpy as np
import pytest

from tdof20.geometry import (
    PinholeCamera,
    compose,
    farthest_point_sampling,
    invert,
    kabsch,
    look_at,
    make_T,
    normals_from_xyz,
    orthonormalize,
    rotation_about_axis,
    rotation_angle,
    rotation_matrix,
    split_T,
    transform_points,
)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return rotation_matrix(rng.normal(size=3), rng.uniform(0.1, np.pi - 0.1))


def random_T(rng: np.random.Generator) -> np.ndarray:
    return make_T(random_rotation(rng), rng.uniform(-500, 500, 3))


@pytest.fixture
def cam() -> PinholeCamera:
    return PinholeCamera.from_fov(64, 48, 60.0, depth_scale=0.25)


# ---------------------------------------------------------------------------------------------
# camera
# ---------------------------------------------------------------------------------------------
def test_from_fov_intrinsics(cam):
    assert cam.fx == pytest.approx(32 / np.tan(np.radians(30)))
    assert (cam.cx, cam.cy) == (31.5, 23.5)
    assert cam.K.shape == (3, 3) and cam.K[2, 2] == 1
    assert PinholeCamera.from_dict(cam.to_dict()).to_dict() == cam.to_dict()
    with pytest.raises(ValueError):
        PinholeCamera(cam.K, 0, 48)
    with pytest.raises(ValueError):
        PinholeCamera(cam.K, 64, 48, depth_scale=0)


def test_backproject_project_round_trip(cam):
    rng = np.random.default_rng(0)
    depth = rng.uniform(300, 1500, (cam.height, cam.width)).astype(np.float32)
    xyz = cam.backproject(depth)
    assert xyz.shape == (48, 64, 3) and xyz.dtype == np.float32
    np.testing.assert_allclose(xyz[..., 2], depth)
    uv, z = cam.project(xyz.reshape(-1, 3))
    vv, uu = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv[:, 0], uu.reshape(-1), atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], vv.reshape(-1), atol=1e-3)
    np.testing.assert_allclose(z, depth.reshape(-1), rtol=1e-6)
    # the principal point's ray is the optical axis
    uv0, _ = cam.project(np.array([[0.0, 0.0, 700.0]]))
    np.testing.assert_allclose(uv0[0], [cam.cx, cam.cy])
    # points behind the camera project to NaN
    uvb, _ = cam.project(np.array([[0.0, 0.0, -5.0], [1.0, 1.0, 0.0]]))
    assert np.isnan(uvb).all()
    with pytest.raises(ValueError):
        cam.backproject(depth[:-1])


def test_to_points_counts_and_indices(cam):
    rng = np.random.default_rng(1)
    depth = rng.uniform(300, 1500, (cam.height, cam.width)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0
    mask = np.zeros(depth.shape, bool)
    mask[10:30, 5:50] = True
    pts, idx = cam.to_points(depth)
    assert len(pts) == np.count_nonzero(depth > 0) and idx.shape == (len(pts), 2)
    pts_m, idx_m = cam.to_points(depth, mask)
    assert len(pts_m) == np.count_nonzero((depth > 0) & mask)
    xyz = cam.backproject(depth)
    np.testing.assert_allclose(pts_m, xyz[idx_m[:, 0], idx_m[:, 1]])
    assert np.all(mask[idx_m[:, 0], idx_m[:, 1]])


def test_visible_with_occlusion(cam):
    pts = np.array([
        [0.0, 0.0, 500.0],      # in front of an occluder at 300 mm -> hidden
        [50.0, 0.0, 500.0],     # surface at 498 mm: within tolerance -> visible
        [-50.0, 0.0, 500.0],    # pixel without depth does not occlude -> visible
        [0.0, 40.0, 500.0],     # surface behind the point -> visible
        [5000.0, 0.0, 500.0],   # outside the image
        [0.0, 0.0, -500.0],     # behind the camera
    ])
    uv, z = cam.project(pts)
    depth = np.full((cam.height, cam.width), 900.0, np.float32)
    px = np.rint(uv[:4]).astype(int)
    depth[px[0, 1], px[0, 0]] = 300.0
    depth[px[1, 1], px[1, 0]] = 498.0
    depth[px[2, 1], px[2, 0]] = 0.0
    vis = cam.visible(uv, z, depth, tol_mm=5.0)
    assert vis.tolist() == [False, True, True, True, False, False]
    assert cam.visible(uv, z).tolist() == [True, True, True, True, False, False]
    assert cam.visible(uv, z, depth, tol_mm=1.0).tolist()[1] is False


@pytest.mark.parametrize("factor", [2.0, 0.5, 1.5])
def test_scaled_camera_keeps_rays(cam, factor):
    w, h = int(cam.width * factor), int(cam.height * factor)
    big = cam.scaled(w, h)
    assert (big.width, big.height, big.depth_scale) == (w, h, cam.depth_scale)
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-200, 200, 50), rng.uniform(-150, 150, 50), rng.uniform(400, 900, 50)])
    uv1, _ = cam.project(pts)
    uv2, _ = big.project(pts)
    # pixel-centre convention: continuous coordinates u + 0.5 scale with the image
    np.testing.assert_allclose(uv2 + 0.5, (uv1 + 0.5) * [w / cam.width, h / cam.height], atol=1e-9)
    # corners of the image stay corners: the same field of view
    np.testing.assert_allclose(big.project(np.array([[(-0.5 - cam.cx) / cam.fx, 0, 1]]))[0][0, 0], -0.5, atol=1e-9)


def test_mm_to_depth_rounding_and_overflow():
    c = PinholeCamera.from_fov(4, 1, 60.0, depth_scale=0.5)
    z = np.array([[100.2, 100.3, np.nan, -3.0]])
    np.testing.assert_array_equal(c.mm_to_depth(z), [[200, 201, 0, 0]])
    z = np.array([[32767.5, 32768.0, np.inf, 0.1]])  # 65535 fits; 65536 overflows; 0.1 mm rounds to 0
    out = c.mm_to_depth(z)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [[65535, 0, 0, 0]])
    rng = np.random.default_rng(3)
    zz = rng.uniform(1, 30000, (1, 4))
    assert np.max(np.abs(c.depth_to_mm(c.mm_to_depth(zz)) - zz)) <= 0.25 + 1e-6
    assert c.depth_to_mm(np.array([[0, 2, 4, 6]], np.uint16)).tolist() == [[0, 1, 2, 3]]
    assert int(c.mm_to_depth(100.0)) == 200  # a scalar works too


# ---------------------------------------------------------------------------------------------
# normals
# ---------------------------------------------------------------------------------------------
def test_normals_of_tilted_plane(cam):
    n = np.array([0.3, -0.4, -1.0])
    n /= np.linalg.norm(n)  # faces the camera (n . p < 0 for points in front)
    d = -600.0  # plane n . x = d, about 600 mm away
    rays = cam.pixel_rays().astype(np.float64)
    t = d / (rays @ n)
    xyz = (rays * t[..., None]).astype(np.float32)
    xyz[20:23, 30:34] = 0  # a hole: one-sided differences around it
    normals = normals_from_xyz(xyz)
    valid = xyz[..., 2] > 0
    assert normals.shape == xyz.shape and normals.dtype == np.float32
    np.testing.assert_allclose(normals[valid], np.broadcast_to(n, normals[valid].shape), atol=2e-3)
    assert np.all(np.sum(normals[valid] * xyz[valid], axis=1) < 0)
    assert np.all(normals[~valid] == 0)
    # the flipped plane (same points, opposite normal given) still yields camera-facing normals
    normals2 = normals_from_xyz(xyz[:, ::-1])  # mirroring flips the cross product's sign
    assert np.all(np.sum(normals2[valid[:, ::-1]] * xyz[:, ::-1][valid[:, ::-1]], axis=1) < 0)


# ---------------------------------------------------------------------------------------------
# transforms
# ---------------------------------------------------------------------------------------------
def test_compose_invert_round_trip():
    rng = np.random.default_rng(4)
    A, B, C = (random_T(rng) for _ in range(3))
    np.testing.assert_allclose(compose(A, invert(A)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(compose(invert(A), A), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(compose(A, B, C), A @ B @ C)
    np.testing.assert_allclose(invert(compose(A, B)), compose(invert(B), invert(A)), atol=1e-12)
    np.testing.assert_allclose(invert(A), np.linalg.inv(A), atol=1e-12)
    stack = np.stack([A, B, C])
    np.testing.assert_allclose(invert(stack)[1], invert(B))
    pts = rng.normal(size=(10, 3)) * 100
    np.testing.assert_allclose(transform_points(invert(A), transform_points(A, pts)), pts, atol=1e-9)
    np.testing.assert_allclose(transform_points(compose(A, B), pts), transform_points(A, transform_points(B, pts)))
    R, t = split_T(A)
    np.testing.assert_array_equal(make_T(R, t), A)


def test_rotation_about_axis():
    axis = np.array([1.0, 2.0, 2.0])
    point = np.array([100.0, -50.0, 30.0])
    angle = np.radians(37.0)
    T = rotation_about_axis(axis, angle, point)
    on_axis = point + np.outer([-2.0, 0.0, 1.5, 10.0], axis)
    np.testing.assert_allclose(transform_points(T, on_axis), on_axis, atol=1e-9)
    p = np.array([250.0, 80.0, -40.0])
    q = transform_points(T, p)
    u = axis / np.linalg.norm(axis)
    rp = (p - point) - u * ((p - point) @ u)  # components perpendicular to the axis
    rq = (q - point) - u * ((q - point) @ u)
    assert np.linalg.norm(rp) == pytest.approx(np.linalg.norm(rq))
    assert (q - point) @ u == pytest.approx((p - point) @ u)
    cosang = rp @ rq / (np.linalg.norm(rp) * np.linalg.norm(rq))
    assert np.arccos(np.clip(cosang, -1, 1)) == pytest.approx(angle)
    assert np.cross(rp, rq) @ u > 0  # right-handed about the axis
    assert rotation_angle(np.eye(3), T[:3, :3]) == pytest.approx(angle)
    with pytest.raises(ValueError):
        rotation_matrix([0, 0, 0], 1.0)


def test_look_at_puts_target_on_axis(cam):
    eye = np.array([400.0, -300.0, 500.0])
    target = np.array([10.0, 20.0, 80.0])
    T_w_c = look_at(eye, target)
    R = T_w_c[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    p_cam = transform_points(invert(T_w_c), target)
    np.testing.assert_allclose(p_cam[:2], 0, atol=1e-9)
    assert p_cam[2] == pytest.approx(np.linalg.norm(target - eye))
    uv, _ = cam.project(p_cam[None])
    np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)
    assert R[:, 1] @ np.array([0, 0, 1.0]) < 0  # image y points down in the world
    with pytest.raises(ValueError):
        look_at([0, 0, 500.0], [0, 0, 0])


def test_orthonormalize():
    rng = np.random.default_rng(5)
    R = random_rotation(rng)
    noisy = R + rng.normal(scale=1e-3, size=(3, 3))
    Q = orthonormalize(noisy)
    np.testing.assert_allclose(Q.T @ Q, np.eye(3), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)
    assert rotation_angle(Q, R) < np.radians(0.3)
    np.testing.assert_allclose(orthonormalize(R), R, atol=1e-12)
    assert np.linalg.det(orthonormalize(np.diag([1.0, 1.0, -1.0]))) == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------
# fitting
# ---------------------------------------------------------------------------------------------
def test_kabsch_exact():
    rng = np.random.default_rng(6)
    R = random_rotation(rng)
    t = rng.uniform(-300, 300, 3)
    src = rng.uniform(-80, 80, (50, 3))
    dst = src @ R.T + t
    R2, t2, s = kabsch(src, dst)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-8)
    assert s == 1.0


def test_kabsch_noise():
    rng = np.random.default_rng(7)
    R = random_rotation(rng)
    t = rng.uniform(-300, 300, 3)
    src = rng.uniform(-100, 100, (200, 3))
    dst = src @ R.T + t + rng.normal(scale=0.5, size=src.shape)
    R2, t2, _ = kabsch(src, dst)
    assert np.degrees(rotation_angle(R, R2)) < 0.5
    assert np.linalg.norm(t2 - t) < 1.0


def test_kabsch_weights_ignore_outliers():
    rng = np.random.default_rng(8)
    R = random_rotation(rng)
    t = rng.uniform(-300, 300, 3)
    src = rng.uniform(-80, 80, (60, 3))
    dst = src @ R.T + t
    dst[:15] += rng.uniform(-500, 500, (15, 3))  # outliers
    w = np.ones(60)
    w[:15] = 0
    R2, t2, _ = kabsch(src, dst, weights=w)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-7)
    R3, _, _ = kabsch(src, dst)  # unweighted is pulled away
    assert rotation_angle(R3, R) > 1e-3
    with pytest.raises(ValueError):
        kabsch(src, dst, weights=np.zeros(60))


def test_kabsch_with_scale_and_no_reflection():
    rng = np.random.default_rng(9)
    R = random_rotation(rng)
    t = rng.uniform(-300, 300, 3)
    src = rng.uniform(-80, 80, (40, 3))
    dst = 0.001 * src @ R.T + t  # e.g. a model in mm fitted to points in metres
    R2, t2, s = kabsch(src, dst, with_scale=True)
    assert s == pytest.approx(0.001)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    mirrored = src * [1, 1, -1]  # best orthogonal fit would be a reflection
    Rm, _, _ = kabsch(src, mirrored)
    assert np.linalg.det(Rm) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        kabsch(src, dst[:-1])


# ---------------------------------------------------------------------------------------------
# sampling
# ---------------------------------------------------------------------------------------------
def test_farthest_point_sampling():
    rng = np.random.default_rng(10)
    pts = rng.normal(size=(500, 3)) * [100, 50, 20]
    first = np.zeros(3)
    kp = farthest_point_sampling(pts, 8, first=first)
    assert kp.shape == (8, 3)
    np.testing.assert_array_equal(kp[0], first)
    np.testing.assert_array_equal(kp[1], pts[np.argmax(np.linalg.norm(pts - first, axis=1))])
    # each further pick is the point farthest from those already chosen
    for i in range(2, 8):
        d = np.min(np.linalg.norm(pts[:, None] - kp[None, :i], axis=2), axis=1)
        np.testing.assert_array_equal(kp[i], pts[np.argmax(d)])
    kp2 = farthest_point_sampling(pts, 8)
    np.testing.assert_array_equal(kp2[0], pts[np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1))])
    np.testing.assert_array_equal(farthest_point_sampling(pts, 8), kp2)  # deterministic
    assert len({tuple(p) for p in kp2}) == 8
    with pytest.raises(ValueError):
        farthest_point_sampling(pts[:3], 5)
