"""BOP19's Visible Surface Discrepancy (VSD; bop_toolkit ``pose_error.py``, ``eval_calc_errors.py``)
and the depth renderer it needs.

* Reference, one pose: :func:`vsd_from_depths` (one error per tau, from full-frame depths;
  :meth:`DepthRenderer.render` renders them by ray casting).
* Fast, many poses of one object: :func:`vsd_batch` casts rays only inside each pose's footprint
  (the projected convex hull, :meth:`DepthRenderer.footprints`) and equals the reference on full
  frames bit for bit (the same rays).
"""

from __future__ import annotations

import cv2
import numpy as np

from tdof20.scoring.metrics.reference import _Ks, _poses

VSD_DELTA = 15.0  # mm: tolerance of the visibility test
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # misalignment tolerances, fractions of the diameter
VSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # correctness thresholds of the VSD error


# Where the renderer samples pixel (u, v) (column, row): at (u + 0.5, v + 0.5) in K's image
# coordinates, as bop_toolkit's OpenGL renderers do (rasterisation samples window pixel centres, and
# its projection maps K's (x, y) to window (x, y)). The distance image, as the toolkit's
# ``depth_im_to_dist_im_fast``, scales depth at pixel (u, v) by the ray through the integer (u, v).
RENDER_PIXEL_OFFSET = 0.5

# bop_toolkit's vispy renderer (the one eval_bop19_pose.py uses) reads its depth from a 16-bit
# depth buffer (vispy's default GL_DEPTH_COMPONENT16) whose near and far planes are the eye-z
# extremes of the model's bounding box at that pose: its depths lie on a grid of 65,535 steps
# between them (about 1e-3 mm for a 60 mm object at 700 mm), each step converted back with float32
# arithmetic. Ray-cast depths pushed through the same buffer (:func:`depth_buffer`) equal its values
# (96% of them bit for bit; the others a step apart, where the GPU's interpolation rounds the other
# way) instead of differing by up to half a step: a pixel whose |d_gt - d_est| or d - d_test lies
# within a step of tau * diameter or delta decides as in the toolkit. (Ties bunch: a flat face of an
# estimate a small shift away has the same |d_gt - d_est| at every pixel.)
DEPTH_BUFFER_MAX = 65535  # 2^16 - 1: the unsigned normalised depth buffer's largest value (the far plane)


def ray_norms(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera rays (x, y, 1) = K^-1 (u, v, 1) through image points (u, v) (float64), and |(x, y, 1)|.
    The distance image uses integer (u, v); the renderer's rays use (u, v) + RENDER_PIXEL_OFFSET."""
    K = np.asarray(K, np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return x, y, np.sqrt(x * x + y * y + 1.0)


_MAP_MIN_POSES = 16  # poses of one chunk sharing a K before its full-image ray maps pay off
_MAPS: dict = {}  # (K, h, w) -> ray maps; a few kept (datasets mostly have one K per camera)


def ray_maps(K: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat (h*w,) float64 maps of camera K: x and y of the render's rays through the pixel
    centres (u, v) + RENDER_PIXEL_OFFSET, and the norm of the ray through the integer (u, v)
    (:func:`distance_image`'s); element for element the values :func:`ray_norms` computes."""
    key = (np.asarray(K, np.float64).tobytes(), int(h), int(w))
    if key not in _MAPS:
        v, u = np.mgrid[0:h, 0:w].reshape(2, -1).astype(np.float64)
        x, y, _ = ray_norms(K, u + RENDER_PIXEL_OFFSET, v + RENDER_PIXEL_OFFSET)
        nrm = ray_norms(K, u, v)[2]
        if len(_MAPS) >= 4:
            _MAPS.pop(next(iter(_MAPS)))
        _MAPS[key] = (x, y, nrm)
    return _MAPS[key]


_SEEN: dict = {}  # (K, h, w) -> poses seen so far (bounded: a few keys kept, as _MAPS)


def _maps_for(K: np.ndarray, h: int, w: int, poses: int):
    """:func:`ray_maps` of camera K once _MAP_MIN_POSES poses have used it (in this call or the
    ones before: a batch of a few poses per image chunk gets the maps the earlier ones paid for),
    else None (the poses compute their rays)."""
    key = (np.asarray(K, np.float64).tobytes(), int(h), int(w))
    if key not in _MAPS:
        if len(_SEEN) >= 64:
            _SEEN.clear()
        _SEEN[key] = _SEEN.get(key, 0) + poses
        if _SEEN[key] < _MAP_MIN_POSES:
            return None
    return ray_maps(K, h, w)


def distance_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth (H,W) along the optical axis -> distance from the camera centre (float64); pixel
    (u, v)'s ray through the integer (u, v), as bop_toolkit's ``depth_im_to_dist_im_fast``."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return depth.astype(np.float64) * ray_norms(K, u, v)[2]


_W32 = (np.arange(DEPTH_BUFFER_MAX + 1) / DEPTH_BUFFER_MAX).astype(np.float32)  # stored value -> float32 read back


def depth_buffer_coefficients(near, far) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per clip planes (near, far) (scalars or arrays): a, b with the stored value round(a - b / z)
    of eye depth z (OpenGL's window depth f/(f-n) - f n/((f-n) z), scaled to 0..65535), and the
    toolkit's float32 ``mult`` = n f/(n-f), ``addi`` = f/(n-f) that turn it back into depth. Where
    n = f (a flat model seen face on: the toolkit's projection divides by 0, its output is undefined)
    every depth is n: a = b = 0, mult = n, addi = 1 give exactly that."""
    near = np.asarray(near, np.float64)
    far = np.asarray(far, np.float64)
    flat = ~(far > near)
    span = np.where(flat, 1.0, far - near)
    a = np.where(flat, 0.0, far / span * DEPTH_BUFFER_MAX)
    b = np.where(flat, 0.0, far * near / span * DEPTH_BUFFER_MAX)
    mult = np.where(flat, near, near * far / -span).astype(np.float32)
    addi = np.where(flat, 1.0, far / -span).astype(np.float32)
    return a, b, mult, addi


def depth_buffer(z: np.ndarray, near, far, coefficients=None) -> np.ndarray:
    """Depths z (mm, 0 = none) as bop_toolkit's vispy renderer returns them (float32): stored in a
    16-bit depth buffer with clip planes ``near`` and ``far`` (scalars) and read back by its
    ``_draw_depth``: OpenGL's window depth rounded to 1/65535 (unsigned normalised), read as
    float32 w, turned into n f/(n-f) / (w + f/(n-f)) in float32 (numpy < 2 computes a float32
    array with a float64 scalar in float32), and 0 where w = 1: the far plane counts as background,
    so a surface touching the far corner of the model's box loses the pixels that round to it, as
    in the toolkit. ``coefficients``: instead of near and far, a function of the indices of the
    hits (z > 0) giving their :func:`depth_buffer_coefficients` (per-pixel clip planes)."""
    z = np.asarray(z)
    hit = np.flatnonzero(z.reshape(-1) > 0)  # only hits are converted (half the rays miss)
    a, b, mult, addi = depth_buffer_coefficients(near, far) if coefficients is None else coefficients(hit)
    q = b / z.reshape(-1).take(hit)  # float64 (z float32: the cast's t)
    np.subtract(a, q, out=q)
    np.rint(q, out=q)
    np.clip(q, 0, DEPTH_BUFFER_MAX, out=q)
    qi = q.astype(np.int32)
    d = mult / (_W32.take(qi) + addi)
    d[qi == DEPTH_BUFFER_MAX] = 0.0
    out = np.zeros(z.shape, np.float32)
    out.reshape(-1)[hit] = d
    return out


def vsd_from_depths(depth_est: np.ndarray, depth_gt: np.ndarray, depth_test: np.ndarray, K: np.ndarray,
                    diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS) -> np.ndarray:
    """Visible Surface Discrepancy for each tau (T,), BOP19 form (step cost, normalised by the
    diameter): depths (H,W) in mm, 0 = none; the test depth's missing pixels count as visible.
    V_g = {d_g > 0 and (d_g - d_test <= delta or d_test = 0)}, V_e = {d_e > 0 and (d_e - d_test <=
    delta or d_test = 0 or V_g)} (d: distances from the camera centre); e = (#{V_g & V_e with
    |d_g - d_e| / diameter >= tau} + #(V_g | V_e) - #(V_g & V_e)) / #(V_g | V_e), 1 if the union is empty."""
    dt, dg, de = (distance_image(d, K) for d in (depth_test, depth_gt, depth_est))
    vg = (dg > 0) & (((dg.astype(np.float32) - dt.astype(np.float32)) <= delta) | (dt == 0))
    ve = (de > 0) & (((de.astype(np.float32) - dt.astype(np.float32)) <= delta) | (dt == 0))
    ve |= vg & (de > 0)
    inter, union = vg & ve, vg | ve
    n_union = int(union.sum())
    if n_union == 0:
        return np.ones(len(taus))
    dist = np.abs(dg[inter] - de[inter]) / diameter
    comp = n_union - int(inter.sum())
    return np.array([(int((dist >= tau).sum()) + comp) / n_union for tau in taus])


class DepthRenderer:
    """Depth images of one object model by ray casting (open3d RaycastingScene, built once in
    the model frame; the rays move into the model frame). Pixel (u, v) samples the ray through
    (u + 0.5, v + 0.5), bop_toolkit's renderers' pixel centres; depth along the optical axis in
    mm, 0 where the ray misses, through the toolkit's 16-bit depth buffer (:func:`depth_buffer`;
    near and far planes from the model's bounding box, :meth:`clip_planes`)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        # lazy: open3d (and tdof20.geometry.raycast, which imports it at top level)
        from tdof20.geometry.raycast import convex_hull_points
        from tdof20.o3d import o3d

        V = np.asarray(vertices, np.float64)
        F = np.asarray(faces, np.int64)
        if len(F) == 0:
            raise ValueError("a triangle mesh is needed to render depth")
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        lo, size = V.min(axis=0), V.max(axis=0) - V.min(axis=0)  # the toolkit's calc_3d_bbox corners
        self.box_corners = np.array([[lo[0] + a * size[0], lo[1] + b * size[1], lo[2] + c * size[2], 1.0]
                                     for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        try:
            self.hull = np.asarray(convex_hull_points(V, F), np.float64)
        except Exception:  # degenerate (flat) meshes: every vertex bounds the silhouette
            self.hull = V
        self._o3d = o3d

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """t of the first hit of rays (model frame, float32 (n,3) each); 0 where none."""
        if len(origins) == 0:
            return np.zeros(0, np.float32)
        rays = np.empty((len(origins), 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        return self.cast_rays(rays)

    def cast_rays(self, rays: np.ndarray) -> np.ndarray:
        """t of the first hit of rays (n,6) float32 (origin, direction; model frame); 0 where none."""
        if len(rays) == 0:
            return np.zeros(0, np.float32)
        t = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32)))
        t = t["t_hit"].numpy()
        t[~np.isfinite(t)] = 0.0
        return t

    def clip_planes(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(near, far) (B,) of poses (B,3,3), (B,3): the eye-z extremes of the model's bounding box
        corners, as the toolkit's ``render_object`` computes them (its view matrix is float32)."""
        R = np.asarray(R, np.float64).reshape(-1, 3, 3)
        t = np.asarray(t, np.float64).reshape(-1, 3)
        row = np.concatenate([R[:, 2, :], t[:, 2:3]], axis=1).astype(np.float32).astype(np.float64)
        z = row @ self.box_corners.T  # (B, 8)
        return z.min(axis=1), z.max(axis=1)

    def render(self, R, t, K, width: int, height: int) -> np.ndarray:
        """(height, width) float32 depth of the model at pose (R, t): every pixel cast, stored
        as the toolkit's depth buffer stores it (:func:`depth_buffer`)."""
        v, u = np.mgrid[0:height, 0:width].reshape(2, -1).astype(np.float64) + RENDER_PIXEL_OFFSET
        x, y, _ = ray_norms(K, u, v)
        R = np.asarray(R, np.float64)
        t = np.asarray(t, np.float64).reshape(3)
        d = np.empty((len(x), 3), np.float32)
        for i in range(3):  # R^T (x, y, 1): the rays in the model frame
            d[:, i] = x * R[0, i] + y * R[1, i] + R[2, i]
        o = np.broadcast_to((-R.T @ t).astype(np.float32), d.shape)
        near, far = self.clip_planes(R, t)
        return depth_buffer(self.cast(o, d), near[0], far[0]).reshape(height, width)


    def footprints(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int):
        """Where the model at poses (R, t) (B,...) can be seen: (boxes (B,4) int [v0, v1) x [u0, u1)
        clipped to the image (empty when v0 >= v1 or u0 >= u1), polygons: per pose the convex hull
        (k,2) int32 (u, v) of the projected hull vertices, or None for the whole box). A pixel
        whose centre lies more than a pixel outside the polygon cannot be hit; poses whose hull
        reaches depth <= 1 mm get the whole image and no polygon."""
        X = np.einsum("bij,nj->bni", R, self.hull) + t[:, None, :]
        H = np.einsum("bij,bnj->bni", K, X)
        z = X[..., 2]
        near = (z <= 1.0).any(axis=1)  # the projection is unbounded: cast everything
        gone = (z <= 0.0).all(axis=1)  # rays (depth > 0) cannot reach it: nothing to see
        zz = np.where(z > 0, H[..., 2], 1.0)
        # pixel indices: pixel (u, v) samples (u, v) + RENDER_PIXEL_OFFSET
        u, v = H[..., 0] / zz - RENDER_PIXEL_OFFSET, H[..., 1] / zz - RENDER_PIXEL_OFFSET
        out = np.stack([np.floor(v.min(1)) - 2, np.ceil(v.max(1)) + 3,
                        np.floor(u.min(1)) - 2, np.ceil(u.max(1)) + 3], axis=1)
        lim = np.array([height, height, width, width], np.float64)
        out = np.clip(out, 0, lim)
        out[near] = [0, height, 0, width]
        out[gone] = 0
        boxes = out.astype(np.int64)
        big = 1e6  # beyond this the polygon would overflow int32; the box alone is used
        skip = near | (boxes[:, 0] >= boxes[:, 1]) | (boxes[:, 2] >= boxes[:, 3]) | \
            (np.abs(u).max(axis=1) > big) | (np.abs(v).max(axis=1) > big)
        uv = np.rint(np.stack([np.where(skip[:, None], 0, u), np.where(skip[:, None], 0, v)], axis=2)).astype(np.int32)
        polys = [None if skip[b] else cv2.convexHull(uv[b]).reshape(-1, 2) for b in range(len(R))]
        return boxes, polys

    def boxes(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """The boxes of :meth:`footprints`."""
        return self.footprints(R, t, K, width, height)[0]


def _footprint_pixels(poly, box, U0: int, V0: int, W: int):
    """(ys, xs) local to the box origin (U0, V0) of the pixels of ``box`` that the polygon (grown by
    a 3-pixel-wide outline) covers, and their flat index in a W-wide raster at (U0, V0)."""
    v0, v1, u0, u1 = (int(x) for x in box)
    h, w = v1 - v0, u1 - u0
    if poly is None:
        ys, xs = np.divmod(np.arange(h * w), w)
    else:
        m = np.zeros((h, w), np.uint8)
        q = (poly - np.array([u0, v0], np.int32)).reshape(-1, 1, 2)
        cv2.fillConvexPoly(m, q, 1)
        cv2.polylines(m, [q], True, 1, 3)
        ys, xs = np.nonzero(m)
    ys = ys + (v0 - V0)
    xs = xs + (u0 - U0)
    return ys, xs, ys * W + xs


def vsd_batch(renderer: DepthRenderer, R_est, t_est, R_gt, t_gt, K, depth_test: np.ndarray, image: np.ndarray,
              diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS, max_rays: int = 1 << 20) -> np.ndarray:
    """VSD (B,T) of B poses of one object, exactly :func:`vsd_from_depths` on full renders, but
    rendering only where it matters: per pose each render is cast inside the projected convex hull
    of the model (grown by a pixel, :meth:`DepthRenderer.footprints`; no other pixel can be hit),
    and poses whose footprints' boxes do not meet have an empty intersection, so VSD 1 for every
    tau, without rendering. ``depth_test`` (n,H,W) float32 mm test depths, ``image`` (B,) the
    index of each pose's test image (``depth_test`` may be a list of (H,W) images)."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    taus = np.asarray(taus, np.float64)
    B, T = len(Re), len(taus)
    h, w = depth_test[0].shape if len(depth_test) else (0, 0)
    out = np.ones((B, T))
    if B == 0:
        return out
    be, pe = renderer.footprints(Re, te, Ks, w, h)
    bg, pg = renderer.footprints(Rg, tg, Ks, w, h)
    meet = (np.maximum(be[:, 0], bg[:, 0]) < np.minimum(be[:, 1], bg[:, 1])) & \
           (np.maximum(be[:, 2], bg[:, 2]) < np.minimum(be[:, 3], bg[:, 3]))
    todo = np.flatnonzero(meet)
    area = (be[:, 1] - be[:, 0]) * (be[:, 3] - be[:, 2]) + (bg[:, 1] - bg[:, 0]) * (bg[:, 3] - bg[:, 2])
    start = 0
    while start < len(todo):  # chunks of about max_rays rays
        cum = np.cumsum(area[todo[start:]])
        stop = start + max(1, int(np.searchsorted(cum, max_rays, side="right")))
        idx = todo[start:stop]
        start = stop
        out[idx] = _vsd_lists(renderer, Re[idx], te[idx], Rg[idx], tg[idx], Ks[idx], be[idx], bg[idx],
                              [pe[i] for i in idx], [pg[i] for i in idx], depth_test, image[idx], diameter,
                              delta, taus)
    return out


def _per_hit(coef: tuple, pose_of_hit: np.ndarray) -> tuple:
    """Per-pose depth-buffer coefficients gathered for each hit."""
    return tuple(c.take(pose_of_hit) for c in coef)


def _vsd_lists(renderer, Re, te, Rg, tg, Ks, be, bg, pe, pg, depth_test, image, diameter, delta, taus):
    n = len(Re)
    V0 = np.minimum(be[:, 0], bg[:, 0])
    U0 = np.minimum(be[:, 2], bg[:, 2])
    W = np.maximum(be[:, 3], bg[:, 3]) - U0
    Hh = np.maximum(be[:, 1], bg[:, 1]) - V0
    off = np.cumsum(W * Hh) - W * Hh  # each pose's raster (its two boxes' union) in one canvas
    h_img, w_img = depth_test[0].shape
    # per camera matrix used by many poses: its ray maps, gathered per pixel (8x cheaper than
    # computing them pose by pose); the other poses compute theirs
    uniq, inv, counts = np.unique(Ks.reshape(n, 9), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    maps = [_maps_for(uniq[k].reshape(3, 3), h_img, w_img, int(counts[k])) for k in range(len(uniq))]
    lists = {}
    for key, R, t, bx, polys in (("g", Rg, tg, bg, pg), ("e", Re, te, be, pe)):
        near, far = renderer.clip_planes(R, t)
        px = [_footprint_pixels(polys[j], bx[j], int(U0[j]), int(V0[j]), int(W[j])) for j in range(n)]
        cnt = np.array([len(q[0]) for q in px], np.int64)
        ends = np.cumsum(cnt)
        tot = int(ends[-1]) if n else 0
        rays = np.empty((tot, 6), np.float32)
        nrm = np.empty(tot)
        dt = np.empty(tot)
        cidx = np.empty(tot, np.int64)
        org = np.empty((n, 3), np.float32)  # each pose's ray origin (the camera centre in the model frame)
        # pose by pose: each pose's pixels stay in cache through the dozen operations on them
        # (one pass over every pixel of the chunk per operation is several times slower)
        for j, (ys, xs, fl) in enumerate(px):
            a, b = int(ends[j] - cnt[j]), int(ends[j])
            Kj = Ks[j]
            v = ys + V0[j]
            u = xs + U0[j]
            mp = maps[inv[j]]
            if mp is not None:
                f = v * w_img + u
                x, y, q = mp[0].take(f), mp[1].take(f), mp[2].take(f)
            else:
                # the render's rays through (u, v) + RENDER_PIXEL_OFFSET: ray_norms' x, y (the
                # same float64 operations, bit for bit), without the norm it does not need
                y = (v + RENDER_PIXEL_OFFSET - Kj[1, 2]) / Kj[1, 1]
                x = (u + RENDER_PIXEL_OFFSET - Kj[0, 2] - Kj[0, 1] * y) / Kj[0, 0]
                q = ray_norms(Kj, u, v)[2]  # distance_image's norm (integer u, v)
            Rj = R[j]
            for i in range(3):  # R^T (x, y, 1): the rays in the model frame
                rays[a:b, 3 + i] = x * Rj[0, i] + y * Rj[1, i] + Rj[2, i]
            org[j] = (-Rj.T @ t[j]).astype(np.float32)
            nrm[a:b] = q
            img = depth_test[image[j]]
            dt[a:b] = img.ravel().take(v * img.shape[1] + u) * q
            cidx[a:b] = fl + off[j]
        pose = np.repeat(np.arange(n), cnt)
        rays[:, :3] = org.take(pose, axis=0)
        coef = depth_buffer_coefficients(near, far)  # per pose; per hit below
        z = depth_buffer(renderer.cast_rays(rays), None, None, lambda hit: _per_hit(coef, pose.take(hit))) * nrm
        lists[key] = (cidx, z, dt, pose)
    cg, dg, dtg, pgi = lists["g"]
    ce, de, dte, pei = lists["e"]
    total = int(off[-1] + W[-1] * Hh[-1])
    vg = (dg > 0) & (((dg.astype(np.float32) - dtg.astype(np.float32)) <= delta) | (dtg == 0))
    vg_c = np.zeros(total, bool)
    vg_c[cg[vg]] = True
    dg_c = np.zeros(total, np.float64)
    dg_c[cg] = dg
    vge = vg_c[ce]
    hit = de > 0
    ve = hit & ((((de.astype(np.float32) - dte.astype(np.float32)) <= delta) | (dte == 0)) | vge)
    inter = ve & vge
    n_vg = np.bincount(pgi[vg], minlength=n)
    n_ve = np.bincount(pei[ve], minlength=n)
    n_inter = np.bincount(pei[inter], minlength=n)
    n_union = n_vg + n_ve - n_inter
    dist = np.abs(dg_c[ce[inter]] - de[inter]) / diameter
    k = np.searchsorted(taus, dist, side="right")  # the taus with dist >= tau: the first k
    T = len(taus)
    hist = np.bincount(pei[inter] * (T + 1) + k, minlength=n * (T + 1)).reshape(n, T + 1)
    cost = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (n,T): #{dist >= tau_i}
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (cost + (n_union - n_inter)[:, None]) / n_union[:, None]
    e[n_union == 0] = 1.0
    return e
