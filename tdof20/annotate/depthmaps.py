"""Organised depth maps of the turntable volume and ICP with projective data association.

Every frame of an arm position comes from one still camera, so its depth image is already a
grid of the surface: a point's correspondence in another frame is the target pixel it projects
to (KinectFusion's projective association) instead of a nearest-neighbour search in a 3D tree.

* :class:`DepthMap` — one frame at a stride: the depth block-averaged over ``stride`` x
  ``stride`` pixels (a block that straddles a depth edge is dropped, not averaged across it),
  cropped to the turntable volume, a unit normal per pixel from the principal axes of the points
  in a window about it (moments by box filters, the smallest eigenvector in closed form), and a
  seeded subsample of its points for when it is the ICP source;
* :func:`icp_projective` — point-to-plane Gauss-Newton regularised towards a prior pose (the
  same maths as :func:`tdof20.annotate.icp.icp_prior`), each iteration's correspondences the
  target pixels the moved source points project to.

Why by hand: open3d's ``t.pipelines.odometry`` does projective point-to-plane ICP on RGB-D
images, but without the prior that keeps a rotationally symmetric object's free turn at the
turntable's step angle (docs/annotate.md) and without the turntable-volume crop. Measured on one
arm position of 400 frames at 640x480: the maps take ~5 ms a frame where the voxel pyramid with
open3d's normals took ~75 ms, and an ICP iteration ~0.2 ms where the k-d tree query took ~3 ms.
"""

from __future__ import annotations

import math

import numpy as np

from tdof20.annotate.icp import information_matrix, prior_step, prior_weights
from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.geometry.camera import PinholeCamera


__all__ = ["DepthMap", "MapPyramid", "block_depth", "icp_maps", "icp_projective", "source_points", "map_stride", "smallest_eigenvectors", "strided_camera"]


def map_stride(cam: PinholeCamera, depth_mm: float, pixel_mm: float) -> int:
    """The block size (pixels) that makes a block about ``pixel_mm`` wide at ``depth_mm``."""
    return max(1, int(round(pixel_mm * cam.fx / max(depth_mm, 1.0))))


def block_depth(z: np.ndarray, strides, min_mm: float, max_mm: float, fx: float, edge_mm: float = 4.0,
                edge_slope: float = 3.0) -> dict[int, np.ndarray]:
    """The depth image ``z`` (mm, 0 = none) averaged over blocks of s x s pixels for each stride s
    in ``strides`` (rows and columns beyond a whole block dropped): {s: (H//s, W//s) float32}, the
    mean of a block's valid depths (within [min_mm, max_mm]) where at least half of it is valid
    and its depths span at most ``edge_mm`` or ``edge_slope`` times the block's width at that depth
    (``fx``: the full-resolution focal length; a surface seen up to ~70 deg obliquely passes, a
    block across an object's edge is dropped, not blended); else 0. Sums by OpenCV's area
    resampling, spans by its dilation and erosion (exact for whole blocks)."""
    import cv2

    z = np.asarray(z, np.float32)
    valid = (z >= min_mm) & (z <= max_mm)
    zv = np.where(valid, z, np.float32(0.0))
    zi = None
    out = {}
    for s in sorted({int(v) for v in strides}):
        if s == 1:
            out[s] = zv
            continue
        if zi is None:
            zi = np.where(valid, z, np.float32(1e9))
            vf = valid.astype(np.float32)
        h, w = z.shape[0] // s, z.shape[1] // s
        a, k = s // 2, np.ones((s, s), np.uint8)
        zc, vc, ic = zv[:h * s, :w * s], vf[:h * s, :w * s], zi[:h * s, :w * s]
        mean_all = cv2.resize(zc, (w, h), interpolation=cv2.INTER_AREA)      # sum / s^2
        frac = cv2.resize(vc, (w, h), interpolation=cv2.INTER_AREA)          # count / s^2
        zmax = cv2.dilate(zc, k)[a::s, a::s][:h, :w]
        zmin = cv2.erode(ic, k)[a::s, a::s][:h, :w]
        mean = mean_all / np.maximum(frac, np.float32(1e-6))
        ok = (frac >= 0.5) & (zmax - zmin <= np.maximum(np.float32(edge_mm), np.float32(edge_slope * s / fx) * mean))
        out[s] = np.where(ok, mean, np.float32(0.0)).astype(np.float32)
    return out


def smallest_eigenvectors(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvectors (N,3) of the smallest eigenvalue of symmetric 3x3 matrices (N,3,3), and
    the surface variation lambda_min / trace (N,) — in closed form (the trigonometric solution of
    the characteristic cubic; the eigenvector as the largest cross product of two rows of
    C - lambda I): ~15x faster than numpy's batched eigh."""
    a00, a01, a02 = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2]
    a11, a12, a22 = C[:, 1, 1], C[:, 1, 2], C[:, 2, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt(np.maximum((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0, 1e-300))
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = np.clip(det / (2.0 * p ** 3), -1.0, 1.0)
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * math.pi / 3.0)   # the smallest root
    d0, d1, d2 = a00 - lam, a11 - lam, a22 - lam
    # the cross products of the rows r0 = (d0, a01, a02), r1 = (a01, d1, a12), r2 = (a02, a12, d2)
    c = np.empty((3, 3, len(C)))
    c[0] = (a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - a01 * a01)        # r0 x r1
    c[1] = (a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d0 * a12 - a01 * a02)        # r0 x r2
    c[2] = (d1 * d2 - a12 * a12, a12 * a02 - a01 * d2, a01 * a12 - d1 * a02)        # r1 x r2
    norms = np.einsum("kin,kin->kn", c, c)
    best = np.argmax(norms, axis=0)
    cols = np.arange(len(C))
    v = c[best, :, cols]
    v /= np.sqrt(np.maximum(norms[best, cols], 1e-300))[:, None]
    variation = np.maximum(lam, 0.0) / np.maximum(3.0 * q, 1e-300)
    return v, variation


class DepthMap:
    """One frame's depth inside the turntable volume, at a stride (see the module docstring).

    ``z``: block-averaged depth (h,w) float32, 0 outside the volume or without depth; ``zt``: the
    same where the pixel can be an ICP target (it has a normal), else 0; ``normals``: (h,w,3)
    float16 unit normals towards the camera (0 where none: too few neighbours, or a window that
    straddles an edge; outside the volume they may remain from before a crop); ``cam``: the
    camera of the strided image; ``source``: (m,3) float32 points (a seeded subsample of at most
    ``max_source`` of the volume's points); ``n_points``: how many points the volume holds."""

    def __init__(self, zb: np.ndarray, crop, cfg: RegistrationConfig, window: int, max_source: int,
                 normals_from: "DepthMap | None" = None):
        """``zb``: the frame's depth (mm) block-averaged to this map's stride (:func:`block_depth`);
        ``crop``: the turntable volume (:class:`~tdof20.annotate.turntable.VolumeCrop`) on the
        strided camera (:func:`strided_camera`); ``normals_from``: a map of the same frame and
        volume at a stride a whole multiple r of this one's, whose normals this one takes (pixel
        (v, u) that of (v // r, u // r)) instead of estimating its own — the same window in mm on
        r^2 times fewer pixels (``normal_voxel_mm``); ``window`` is then unused."""
        self.cam = crop.cam
        if zb.shape != (self.cam.height, self.cam.width):
            raise ValueError(f"the crop's camera is {self.cam.width}x{self.cam.height}, the strided depth "
                             f"{zb.shape[1]}x{zb.shape[0]}")
        keep = crop.mask(zb)
        self.z = np.where(keep, zb, np.float32(0.0))
        self.max_source = int(max_source)
        V = self.cam.pixel_rays() * self.z[..., None]
        self._set_source(V, keep)
        if normals_from is None:
            self.normals, has = _normal_map(V, keep, window, cfg.map_max_variation)
        else:
            self.normals, has = _handed_normals(normals_from, self.cam, keep)
        self.zt = np.where(has, self.z, np.float32(0.0))

    def _set_source(self, V: np.ndarray, keep: np.ndarray) -> None:
        v_idx, u_idx = np.nonzero(keep)
        self.n_points = len(v_idx)
        m = self.max_source
        if m and len(v_idx) > m:
            pick = np.sort(np.random.default_rng(len(v_idx)).choice(len(v_idx), m, replace=False))
            v_idx, u_idx = v_idx[pick], u_idx[pick]
        self.source = np.ascontiguousarray(V[v_idx, u_idx], np.float32)

    def cropped(self, crop) -> "DepthMap":
        """A copy holding only the pixels inside ``crop`` (a VolumeCrop on this map's camera), for
        the ICP: its source points drawn again, its ``z`` the target depth ``zt`` (pixels without
        a normal dropped); the normals stay as they were estimated (with the neighbours outside)."""
        out = object.__new__(DepthMap)
        out.cam, out.max_source = self.cam, self.max_source
        keep = crop.mask(self.z) & (self.z > 0)
        out._set_source(self.cam.pixel_rays() * np.where(keep, self.z, np.float32(0.0))[..., None], keep)
        out.zt = np.where(keep, self.zt, np.float32(0.0))
        out.z = out.zt             # (what a cropped map is used for needs the target depth only: half the memory)
        out.normals = self.normals
        return out

    def release(self) -> None:
        """Nothing to drop (the pyramids' k-d trees have no counterpart here)."""

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (N,3), unit normals (N,3)) float32 of the pixels that have a normal."""
        v, u = np.nonzero(self.zt)
        return self.cam.pixel_rays()[v, u] * self.zt[v, u, None], self.normals[v, u].astype(np.float32)

    def nbytes(self) -> int:
        return self.z.nbytes + self.zt.nbytes + self.normals.nbytes + self.source.nbytes

    def __len__(self) -> int:
        return self.n_points


def strided_camera(cam: PinholeCamera, stride: int) -> PinholeCamera:
    """The camera of the image of whole ``stride`` x ``stride`` blocks (:func:`block_depth`;
    pixel-centre convention: block j's centre is full-resolution pixel s*j + (s-1)/2)."""
    s = int(stride)
    K = cam.K.copy()
    K[:2, :2] /= s
    K[:2, 2] = (K[:2, 2] - (s - 1) / 2.0) / s
    return PinholeCamera(K, cam.width // s, cam.height // s, cam.depth_scale)


MIN_COS_VIEW = math.cos(math.radians(80.0))   # a normal more than 80 deg from the line of sight is none


def _handed_normals(coarse: "DepthMap", cam: PinholeCamera, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normals of a coarser map of the same frame handed to the pixels (h,w) of ``keep`` (on
    camera ``cam``): pixel (v, u) takes those of (v // r, u // r), r the stride ratio."""
    h, w = keep.shape
    hc, wc = coarse.zt.shape
    r = int(round(cam.fx / coarse.cam.fx))
    if r < 1 or abs(cam.fx / coarse.cam.fx - r) > 1e-6:
        raise ValueError(f"normals_from: its stride is not a whole multiple of this map's "
                         f"(focal lengths {coarse.cam.fx:g} and {cam.fx:g})")
    vv, uu = np.arange(h) // r, np.arange(w) // r
    rows, cols = np.minimum(vv, hc - 1), np.minimum(uu, wc - 1)
    has = keep & (coarse.zt > 0)[rows][:, cols] & (vv < hc)[:, None] & (uu < wc)[None, :]
    return coarse.normals[rows][:, cols], has


def _normal_map(V: np.ndarray, keep: np.ndarray, window: int, max_variation: float) -> tuple[np.ndarray, np.ndarray]:
    """((h,w,3) float16 unit normals towards the camera, (h,w) bool: which pixels have one) from
    the principal axes of the kept points in a ``window`` x ``window`` box about each kept pixel
    (none where fewer than a third of the box is kept, where the smallest axis holds more than
    ``max_variation`` of the spread, or where the normal grazes the line of sight: an edge)."""
    import cv2

    h, w = keep.shape
    out = np.zeros((h, w, 3), np.float16)
    has = np.zeros((h, w), bool)
    if not keep.any():
        return out, has
    o = V[keep].mean(axis=0).astype(np.float64)          # moments about the frame's mean: no cancellation
    X = V.astype(np.float64) - o
    X[~keep] = 0.0
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    k = (int(window), int(window))

    def box(*channels: np.ndarray) -> np.ndarray:   # OpenCV's fast path takes up to 4 channels at once
        return cv2.boxFilter(np.stack(channels, axis=-1), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    m1 = box(keep.astype(np.float64), x, y, z)
    m2 = box(x * x, x * y, x * z, y * y)
    m3 = box(y * z, z * z)
    ok = keep & (m1[..., 0] >= max(3.0, window * window / 3.0))
    n = m1[..., 0][ok]
    mu = m1[ok][:, 1:] / n[:, None]
    S2 = np.concatenate([m2[ok], m3[ok]], axis=1) / n[:, None]    # xx xy xz yy yz zz
    C = np.empty((len(n), 3, 3))
    for c, (i, j) in enumerate([(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]):
        C[:, i, j] = C[:, j, i] = S2[:, c] - mu[:, i] * mu[:, j]
    nrm, var = smallest_eigenvectors(C)
    P = V[ok].astype(np.float64)
    cos_view = np.einsum("ij,ij->i", nrm, P) / np.linalg.norm(P, axis=1)
    nrm[cos_view > 0] *= -1.0                             # towards the camera (at the origin)
    # an edge: a window of two layers (an object before the table) has its smallest axis across the
    # view, so its "normal" grazes the line of sight; a real surface seen that obliquely is no target either
    good = (var <= max_variation) & (np.abs(cos_view) >= MIN_COS_VIEW)
    v, u = np.nonzero(ok)
    out[v[good], u[good]] = nrm[good].astype(np.float16)
    has[v[good], u[good]] = True
    return out, has


def icp_projective(src: DepthMap, tgt: DepthMap, init: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
                   dist: float, iterations: int, information: bool = True, prior_T: np.ndarray | None = None,
                   tol_scale: float = 1.0, evaluate: bool = True):
    """Point-to-plane ICP (src -> tgt, both maps of one camera at one stride) regularised towards
    ``prior_T`` (default: ``init``, the start) about ``centre`` (:func:`tdof20.annotate.icp.prior_step`), each
    iteration's correspondences the target pixels the moved source points project to, kept within
    ``dist`` mm. Returns (T, fitness, rmse, information (6,6)) like open3d's ICP: fitness = the
    share of source points with a correspondence, RMSE over them. ``tol_scale`` multiplies the
    convergence tolerances (``icp_tol_rad``, ``icp_tol_mm``); ``evaluate=False`` skips the final
    correspondence search (fitness and RMSE nan, information the identity: a coarse level's
    result only starts the next)."""
    T = np.asarray(init, float).copy()
    prior = T if prior_T is None else np.asarray(prior_T, float)
    S = np.asarray(src.source, np.float64)
    if len(S) < 10 or not np.any(tgt.zt):
        return T, 0.0, float("nan"), np.eye(6)
    lam, T0inv, c = prior_weights(prior, centre, cfg)
    cam = tgt.cam
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    h, w = tgt.z.shape
    zt = tgt.zt.reshape(-1)
    nt = tgt.normals.reshape(-1, 3)
    rays = cam.pixel_rays().reshape(-1, 3)
    d2max = dist * dist

    def match(T: np.ndarray):
        X = S @ T[:3, :3].T + T[:3, 3]
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(fx * X[:, 0] / z + cx)
            v = np.rint(fy * X[:, 1] / z + cy)
        idx = np.flatnonzero((z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h))
        f = v[idx].astype(np.int64) * w + u[idx].astype(np.int64)
        zq = zt[f]
        sel = zq > 0
        idx, f, zq = idx[sel], f[sel], zq[sel]
        q = rays[f] * zq[:, None]
        Xo = X[idx]
        dd = Xo - q
        d2 = np.einsum("ij,ij->i", dd, dd)
        near = d2 < d2max
        return Xo[near], q[near].astype(np.float64), nt[f[near]].astype(np.float64), d2[near]

    for _ in range(iterations):
        Xo, q, nn, _ = match(T)
        if len(Xo) < 10:
            break
        T, w_, v_ = prior_step(T, Xo, q, nn, T0inv, c, lam)
        if np.linalg.norm(w_) < tol_scale * cfg.icp_tol_rad and np.linalg.norm(v_) < tol_scale * cfg.icp_tol_mm:
            break
    if not evaluate:
        return T, float("nan"), float("nan"), np.eye(6)
    Xo, q, nn, d2 = match(T)
    fit = len(Xo) / len(S)
    rmse = float(np.sqrt(d2.mean())) if len(d2) else float("nan")
    info = information_matrix(q) if information and len(q) >= 10 else np.eye(6)
    return T, float(fit), rmse, info


class MapPyramid:
    """A frame's :class:`DepthMap` at each ICP scale (``levels[i]`` at ``voxel_sizes_mm[i]``, None
    for a scale a registration pass does not use): what :class:`~tdof20.annotate.icp.Pyramid` is
    for the closest-point ICP."""

    def __init__(self, levels: list, n_fine: int | None = None):
        self.levels = levels
        self.n_fine = len(self.finest()) if n_fine is None else int(n_fine)

    def cropped(self, crops: dict) -> "MapPyramid":
        """The levels in ``crops`` ({level: VolumeCrop on that level's camera}) cropped by them."""
        return MapPyramid([lv.cropped(crops[i]) if lv is not None and i in crops else None
                           for i, lv in enumerate(self.levels)])

    def count_inside(self, crop) -> int:
        """How many pixels of the finest kept level lie inside ``crop`` (a VolumeCrop on its camera)."""
        return int((self.finest().z > 0)[crop.mask(self.finest().z)].sum())

    def finest(self) -> DepthMap:
        return next(lv for lv in reversed(self.levels) if lv is not None)

    def release(self) -> None:
        """Nothing to drop (see :meth:`DepthMap.release`)."""

    def nbytes(self) -> int:
        return sum(lv.nbytes() for lv in self.levels if lv is not None)

    def __len__(self) -> int:
        """The number of points at the finest scale (also when that level is not kept)."""
        return self.n_fine


def icp_maps(src: MapPyramid, tgt: MapPyramid, prior: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
             levels: list[int], information: bool = True):
    """:func:`icp_projective` over ``levels`` (coarse to fine): the correspondence distance
    ``icp_dist_factor`` x the level's scale, its ``icp_iterations``; fitness, RMSE and the
    information matrix of the finest level. A coarser level only brings the pose into the next
    one's reach: it stops at ``COARSE_TOL`` x the tolerances (the projective correspondences
    jitter by a pixel from one iteration to the next, so the fine tolerance would take every
    iteration allowed) and is not evaluated."""
    T = np.asarray(prior, float)
    out = (T, 0.0, float("nan"), np.eye(6))
    for n, i in enumerate(levels):
        it = cfg.icp_iterations[min(i, len(cfg.icp_iterations) - 1)]
        last = n == len(levels) - 1
        out = icp_projective(src.levels[i], tgt.levels[i], T, centre, cfg, cfg.icp_dist_factor * cfg.voxel_sizes_mm[i],
                             it, information=information and last, prior_T=prior,
                             tol_scale=1.0 if last else COARSE_TOL, evaluate=last)
        T = out[0]
    return out


COARSE_TOL = 10.0   # a coarse level stops at this multiple of the convergence tolerances


def source_points(cfg: RegistrationConfig, level: int) -> int:
    """How many points of a map at ``voxel_sizes_mm[level]`` are the ICP's source: ``max_source_points``
    at the finest scale, fewer at the coarser ones (by the ratio of the areas; 1,000 at least), which
    only bring a pose into the finest scale's reach."""
    m = int(cfg.max_source_points)
    ratio = (cfg.voxel_sizes_mm[-1] / cfg.voxel_sizes_mm[level]) ** 2
    return m if level == len(cfg.voxel_sizes_mm) - 1 else max(min(1000, m), int(round(m * ratio)))
