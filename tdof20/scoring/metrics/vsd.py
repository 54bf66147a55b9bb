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
        R = np.asarray(R, np.float64).reshape(-1, 3, 3)
        t = np.asarray(t, np.float64).reshape(-1, 3)
        K = np.asarray(K, np.float64).reshape(-1, 3, 3)
        B, n = len(R), len(self.hull)
        # one matrix product for every pose's hull points (B,3,n), then each camera matrix
        X = (R.reshape(B * 3, 3) @ self.hull.T).reshape(B, 3, n) + t[:, :, None]
        H = np.matmul(K, X)
        z = X[:, 2]
        near = (z <= 1.0).any(axis=1)  # the projection is unbounded: cast everything
        gone = (z <= 0.0).all(axis=1)  # rays (depth > 0) cannot reach it: nothing to see
        zz = np.where(z > 0, H[:, 2], 1.0)
        # pixel indices: pixel (u, v) samples (u, v) + RENDER_PIXEL_OFFSET
        u, v = H[:, 0] / zz - RENDER_PIXEL_OFFSET, H[:, 1] / zz - RENDER_PIXEL_OFFSET
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
        u[skip] = 0
        v[skip] = 0
        uv = np.rint(np.stack([u, v], axis=2)).astype(np.int32)
        polys = [None if skip[b] else cv2.convexHull(uv[b]).reshape(-1, 2) for b in range(B)]
        return boxes, polys

    def boxes(self, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """The boxes of :meth:`footprints`."""
        return self.footprints(R, t, K, width, height)[0]


def _spans(polys, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels each pose's rays are cast through, as row spans: in each pose's box, the pixels
    its polygon (grown by a 3-pixel-wide outline) covers, each row closed from its first to its
    last such pixel (a superset: every pixel a ray can hit, and a few more no ray can). Returns
    (pose, row v, first column, length) of every row with pixels, poses in order."""
    rp, rv, rc, rl = [], [], [], []
    for j, (poly, box) in enumerate(zip(polys, boxes)):
        v0, v1, u0, u1 = (int(x) for x in box)
        h, w = v1 - v0, u1 - u0
        if h <= 0 or w <= 0:
            continue
        if poly is None:
            first = np.zeros(h, np.int64)
            n = np.full(h, w, np.int64)
            rows = np.arange(h)
        else:
            m = np.zeros((h, w), np.uint8)
            q = (poly - np.array([u0, v0], np.int32)).reshape(-1, 1, 2)
            cv2.fillConvexPoly(m, q, 1)
            cv2.polylines(m, [q], True, 1, 3)
            rows = np.flatnonzero(m.any(axis=1))
            m = m[rows]
            first = m.argmax(axis=1)
            n = w - m[:, ::-1].argmax(axis=1) - first
        rp.append(np.full(len(rows), j, np.int64))
        rv.append(rows + v0)
        rc.append(first + u0)
        rl.append(n)
    if not rp:
        z = np.zeros(0, np.int64)
        return z, z, z, z
    return tuple(np.concatenate(a).astype(np.int64) for a in (rp, rv, rc, rl))


def _run_offsets(base: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """base[r] + 0, 1, ..., lengths[r] - 1 for every run r, concatenated (int64)."""
    n = int(lengths.sum())
    start = np.cumsum(lengths) - lengths
    return np.repeat(base - start, lengths) + np.arange(n, dtype=np.int64)


def _render(renderer, R, t, Ks, maps, rp, rv, rc, rl, w_img):
    """Cast the rays of the spans (rp, rv, rc, rl) of poses (R, t, Ks): per pixel its depth as the
    toolkit's depth buffer returns it (float32, 0 = none), that value (int32, DEPTH_BUFFER_MAX =
    none), the norm of its integer (u, v) ray (float64), and each pose's first pixel (n+1,).
    ``maps[j]``: :func:`ray_maps` of pose j's K, or None."""
    n = len(R)
    f = _run_offsets(rv * w_img + rc, rl)
    cnt = np.bincount(rp, weights=rl, minlength=n).astype(np.int64)
    ps = np.concatenate([[0], np.cumsum(cnt)])
    N = len(f)
    rays = np.empty((N, 6), np.float32)
    one = maps[0] if n and all(m is maps[0] for m in maps) else None
    if one is not None:  # one camera matrix: its maps gathered for every pixel at once
        x_all, y_all, nrm = one[0].take(f), one[1].take(f), one[2].take(f)
    else:
        nrm = np.empty(N)
    for j in np.flatnonzero(cnt):
        a, b = int(ps[j]), int(ps[j + 1])
        if one is not None:
            x, y = x_all[a:b], y_all[a:b]
        elif maps[j] is not None:
            fj = f[a:b]
            x, y = maps[j][0].take(fj), maps[j][1].take(fj)
            nrm[a:b] = maps[j][2].take(fj)
        else:
            # the render's rays through (u, v) + RENDER_PIXEL_OFFSET: ray_norms' x, y (the same
            # float64 operations, bit for bit), without the norm it does not need
            v, u = np.divmod(f[a:b], w_img)
            Kj = Ks[j]
            y = (v + RENDER_PIXEL_OFFSET - Kj[1, 2]) / Kj[1, 1]
            x = (u + RENDER_PIXEL_OFFSET - Kj[0, 2] - Kj[0, 1] * y) / Kj[0, 0]
            nrm[a:b] = ray_norms(Kj, u, v)[2]  # distance_image's norm (integer u, v)
        Rj = R[j]
        for i in range(3):  # R^T (x, y, 1): the rays in the model frame
            rays[a:b, 3 + i] = x * Rj[0, i] + y * Rj[1, i] + Rj[2, i]
        rays[a:b, :3] = (-Rj.T @ t[j]).astype(np.float32)  # the camera centre in the model frame
    z = renderer.cast_rays(rays)
    # the toolkit's depth buffer (depth_buffer's operations, with each pose's clip planes)
    near, far = renderer.clip_planes(R, t)
    ca, cb, mult, addi = depth_buffer_coefficients(near, far)
    hit = z > 0
    q = np.repeat(cb, cnt) / np.where(hit, z, np.float32(np.inf))  # float64 (z float32: the cast's t); misses: 0
    np.subtract(np.repeat(ca, cnt), q, out=q)
    np.rint(q, out=q)
    np.clip(q, 0, DEPTH_BUFFER_MAX, out=q)
    qi = q.astype(np.int32)
    qi[~hit] = DEPTH_BUFFER_MAX
    d = np.repeat(mult, cnt) / (_W32.take(qi) + np.repeat(addi, cnt))
    d[qi == DEPTH_BUFFER_MAX] = 0.0
    return d, qi, nrm, ps


def _stored_depths(renderer, R, t, start, qi) -> np.ndarray:
    """The float32 depths of depth-buffer values ``qi`` of poses (R, t) (pose j's: [start[j],
    start[j+1])), as :func:`_render` turns them into depths."""
    near, far = renderer.clip_planes(R, t)
    _, _, mult, addi = depth_buffer_coefficients(near, far)
    cnt = np.diff(start)
    qi = qi.astype(np.int32)
    d = np.repeat(mult, cnt) / (_W32.take(qi) + np.repeat(addi, cnt))
    d[qi == DEPTH_BUFFER_MAX] = 0.0
    return d


class VisibleGt:
    """The ground-truth half of VSD for B poses: what of each pose's render the test image shows,
    V_g = {d_g > 0 and (d_g - d_test <= delta or d_test = 0)} — a function of the dataset alone, so it
    can be kept between scorings. ``boxes`` (B,4) int64: the footprint boxes [v0, v1) x [u0, u1)
    (:meth:`DepthRenderer.footprints`); ``start`` (B+1,): pose j's pixels are [start[j],
    start[j+1]); ``idx`` int64: each V_g pixel's index in its box (row-major); ``depth`` float32:
    the render's depth there (d_g is it times the pixel's ray norm, which the estimate's render of
    the same pixel has); ``qi`` uint16: the depth-buffer value it came from (:meth:`from_stored`)."""

    def __init__(self, boxes, start, idx, depth, qi):
        self.boxes, self.start, self.idx, self.depth, self.qi = boxes, start, idx, depth, qi

    def __len__(self) -> int:
        return len(self.boxes)

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.start)

    def take(self, sel) -> "VisibleGt":
        """The poses ``sel`` (indices, repeats allowed), in that order."""
        sel = np.asarray(sel, np.int64)
        if len(sel) == len(self) and np.array_equal(sel, np.arange(len(self))):
            return self
        cnt = self.counts[sel]
        pix = _run_offsets(self.start[sel], cnt)
        return VisibleGt(self.boxes[sel], np.concatenate([[0], np.cumsum(cnt)]), self.idx.take(pix),
                         None if self.depth is None else self.depth.take(pix), self.qi.take(pix))

    @staticmethod
    def concatenate(parts: list["VisibleGt"]) -> "VisibleGt":
        if not parts:
            z = np.zeros(0, np.int64)
            return VisibleGt(np.zeros((0, 4), np.int64), np.zeros(1, np.int64), z, np.zeros(0, np.float32),
                             np.zeros(0, np.uint16))
        if len(parts) == 1:
            return parts[0]
        cnt = np.concatenate([p.counts for p in parts])
        return VisibleGt(np.concatenate([p.boxes for p in parts]), np.concatenate([[0], np.cumsum(cnt)]),
                         np.concatenate([p.idx for p in parts]), np.concatenate([p.depth for p in parts]),
                         np.concatenate([p.qi for p in parts]))

    @staticmethod
    def from_stored(renderer, R, t, boxes, start, idx, qi) -> "VisibleGt":
        """The VisibleGt of poses (R, t) from its boxes, pixels and depth-buffer values alone (as
        kept on disk): the depths recomputed exactly as when they were cast."""
        R, t = _poses(R, t)
        start = np.asarray(start, np.int64)
        return VisibleGt(np.asarray(boxes, np.int64).reshape(-1, 4), start, np.asarray(idx, np.int64),
                         _stored_depths(renderer, R, t, start, qi), np.asarray(qi, np.uint16))


def _camera_maps(Ks: np.ndarray, h: int, w: int) -> list:
    """Per pose the ray maps of its camera matrix (:func:`_maps_for`: those used by many poses)."""
    n = len(Ks)
    if n == 0:
        return []
    uniq, inv, counts = np.unique(Ks.reshape(n, 9), axis=0, return_inverse=True, return_counts=True)
    maps = [_maps_for(uniq[k].reshape(3, 3), h, w, int(counts[k])) for k in range(len(uniq))]
    return [maps[k] for k in inv.reshape(-1)]


def _chunks(area: np.ndarray, max_rays: int):
    """Consecutive index ranges whose areas add up to about max_rays (at least one index each)."""
    start = 0
    cum = np.cumsum(area)
    while start < len(area):
        base = cum[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(cum, base + max_rays, side="right")))
        yield start, stop
        start = stop


def _empty(box: np.ndarray) -> np.ndarray:
    return (box[:, 0] >= box[:, 1]) | (box[:, 2] >= box[:, 3])


class Rasters:
    """n poses' rasters laid end to end in one flat canvas: pose j's covers [v0, v0 + h) x
    [u0, u0 + w) of its image (the union of the boxes it is given; an empty box adds nothing) at
    canvas[off[j]:off[j] + h*w], row-major. ``depth``: the test depth on the canvas (:meth:`crop`)."""

    def __init__(self, *boxes: np.ndarray, dtype=np.float32):
        self.dtype = dtype
        bs = [np.asarray(b, np.int64).reshape(-1, 4) for b in boxes]
        lo_v = np.min([np.where(_empty(b), np.iinfo(np.int64).max, b[:, 0]) for b in bs], axis=0)
        hi_v = np.max([np.where(_empty(b), np.iinfo(np.int64).min, b[:, 1]) for b in bs], axis=0)
        lo_u = np.min([np.where(_empty(b), np.iinfo(np.int64).max, b[:, 2]) for b in bs], axis=0)
        hi_u = np.max([np.where(_empty(b), np.iinfo(np.int64).min, b[:, 3]) for b in bs], axis=0)
        none = lo_v > hi_v
        self.v0 = np.where(none, 0, lo_v)
        self.u0 = np.where(none, 0, lo_u)
        self.h = np.where(none, 0, hi_v - lo_v)
        self.w = np.where(none, 0, hi_u - lo_u)
        area = self.h * self.w
        self.off = np.cumsum(area) - area
        self.total = int(area.sum())
        self.depth = None

    def __len__(self) -> int:
        return len(self.off)

    def crop(self, j: int, image: np.ndarray) -> None:
        """Copy pose j's part of its test depth image into ``depth`` (of the rasters' dtype, float32
        by default: uint16 and float32 images' values exactly; allocated at the first call)."""
        if self.depth is None:
            self.depth = np.zeros(self.total, self.dtype)
        a, h, w = int(self.off[j]), int(self.h[j]), int(self.w[j])
        v0, u0 = int(self.v0[j]), int(self.u0[j])
        self.depth[a:a + h * w].reshape(h, w)[...] = image[v0:v0 + h, u0:u0 + w]

    def index(self, rp, rv, rc, rl) -> np.ndarray:
        """The canvas index of every pixel of the spans (rp, rv, rc, rl)."""
        return _run_offsets(self.off[rp] + (rv - self.v0[rp]) * self.w[rp] + (rc - self.u0[rp]), rl)


def visible_gt(renderer: "DepthRenderer", R_gt, t_gt, K, boxes, polys, rasters: Rasters, sel, width: int,
               height: int, delta: float = VSD_DELTA, max_rays: int = 1 << 18) -> VisibleGt:
    """:class:`VisibleGt` of B ground-truth poses of one object with footprints (``boxes``,
    ``polys``: :meth:`DepthRenderer.footprints`), each cast inside its footprint, against the test
    depth of raster ``sel[j]`` of ``rasters`` (which covers its box)."""
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Rg)))
    sel = np.asarray(sel, np.int64)
    if len(Rg) == 0:
        return VisibleGt.concatenate([])
    boxes = np.asarray(boxes, np.int64).reshape(-1, 4)
    maps = _camera_maps(Ks, height, width)
    bw = np.maximum(boxes[:, 3] - boxes[:, 2], 0)
    area = np.maximum(boxes[:, 1] - boxes[:, 0], 0) * bw
    parts = []
    for a, b in _chunks(area, max_rays):
        rp, rv, rc, rl = _spans(polys[a:b], boxes[a:b])
        d, qi, nrm, ps = _render(renderer, Rg[a:b], tg[a:b], Ks[a:b], maps[a:b], rp, rv, rc, rl, width)
        bx = boxes[a:b]
        local = _run_offsets((rv - bx[rp, 0]) * bw[a:b][rp] + (rc - bx[rp, 2]), rl)
        dtg = rasters.depth.take(rasters.index(sel[a:b][rp], rv, rc, rl)) * nrm
        dg = d * nrm
        vg = (dg > 0) & (((dg.astype(np.float32) - dtg.astype(np.float32)) <= delta) | (dtg == 0))
        pose = np.repeat(np.arange(b - a), np.diff(ps))
        cnt = np.bincount(pose[vg], minlength=b - a)
        parts.append(VisibleGt(bx, np.concatenate([[0], np.cumsum(cnt)]), local[vg], d[vg],
                               qi[vg].astype(np.uint16)))
    return VisibleGt.concatenate(parts)


def vsd_batch(renderer: DepthRenderer, R_est, t_est, R_gt, t_gt, K, depth_test: np.ndarray, image: np.ndarray,
              diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS, max_rays: int = 1 << 18) -> np.ndarray:
    """VSD (B,T) of B poses of one object, exactly :func:`vsd_from_depths` on full renders, but
    rendering only where it matters: per pose each render is cast inside the projected convex hull
    of the model (grown by a pixel, :meth:`DepthRenderer.footprints`; no other pixel can be hit),
    and poses whose footprints' boxes do not meet have an empty intersection, so VSD 1 for every
    tau, without rendering. ``depth_test`` (n,H,W) float32 mm test depths, ``image`` (B,) the
    index of each pose's test image (``depth_test`` may be a list of (H,W) images)."""
    Re, te = _poses(R_est, t_est)
    Rg, tg = _poses(R_gt, t_gt)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    B = len(Re)
    out = np.ones((B, len(np.asarray(taus))))
    if B == 0:
        return out
    h, w = depth_test[0].shape
    image = np.asarray(image, np.int64)
    be, pe = renderer.footprints(Re, te, Ks, w, h)
    bg, pg = renderer.footprints(Rg, tg, Ks, w, h)
    ras = Rasters(be, bg, dtype=np.result_type(np.float32, depth_test[0].dtype))
    ras.depth = np.zeros(ras.total, ras.dtype)
    for j in range(B):
        ras.crop(j, depth_test[image[j]])
    gt = visible_gt(renderer, Rg, tg, Ks, bg, pg, ras, np.arange(B), w, h, delta, max_rays)
    return vsd_estimates(renderer, Re, te, Ks, be, pe, gt, ras, np.arange(B), w, h, diameter, delta, taus, max_rays)


def vsd_estimates(renderer: DepthRenderer, R_est, t_est, K, boxes, polys, gt: VisibleGt, rasters: Rasters, sel,
                  width: int, height: int, diameter: float, delta: float = VSD_DELTA, taus=VSD_TAUS,
                  max_rays: int = 1 << 18) -> np.ndarray:
    """VSD (B,T) of B estimates of one object with footprints (``boxes``, ``polys``) against
    their ground truths' V_g (``gt``, one per estimate), with the test depth of raster ``sel[j]``
    of ``rasters`` (which covers both boxes). Estimates whose box does not meet their ground
    truth's have VSD 1 for every tau (no pixel of theirs can be in V_g), without rendering."""
    Re, te = _poses(R_est, t_est)
    Ks = np.ascontiguousarray(_Ks(K, len(Re)))
    taus = np.asarray(taus, np.float64)
    sel = np.asarray(sel, np.int64)
    B, T = len(Re), len(taus)
    out = np.ones((B, T))
    be, bg = np.asarray(boxes, np.int64).reshape(-1, 4), gt.boxes
    meet = (np.maximum(be[:, 0], bg[:, 0]) < np.minimum(be[:, 1], bg[:, 1])) & \
           (np.maximum(be[:, 2], bg[:, 2]) < np.minimum(be[:, 3], bg[:, 3]))
    todo = np.flatnonzero(meet)
    if not len(todo):
        return out
    maps = _camera_maps(Ks[todo], height, width)
    area = (be[todo, 1] - be[todo, 0]) * (be[todo, 3] - be[todo, 2]) + \
        (bg[todo, 1] - bg[todo, 0]) * (bg[todo, 3] - bg[todo, 2])
    for a, b in _chunks(area, max_rays):
        idx = todo[a:b]
        out[idx] = _vsd_est(renderer, Re[idx], te[idx], Ks[idx], maps[a:b], be[idx], [polys[i] for i in idx],
                            gt.take(idx), rasters, sel[idx], width, diameter, delta, taus)
    return out


def _vsd_est(renderer, Re, te, Ks, maps, be, pe, gt: VisibleGt, rasters: Rasters, sel, w_img, diameter, delta, taus):
    """VSD (n,T) of n estimates against their ground truths' V_g (``gt``, one per estimate)."""
    n = len(Re)
    bg = gt.boxes
    # V_g and its depths on the ground truths' box rasters
    gr = Rasters(bg)
    cg = gt.counts
    gi = np.repeat(gr.off, cg) + gt.idx
    vg_c = np.zeros(gr.total, bool)
    vg_c[gi] = True
    dg_c = np.zeros(gr.total, np.float32)
    dg_c[gi] = gt.depth
    # the estimates' renders
    rp, rv, rc, rl = _spans(pe, be)
    d, _, nrm, ps = _render(renderer, Re, te, Ks, maps, rp, rv, rc, rl, w_img)
    de = d * nrm
    dte = rasters.depth.take(rasters.index(sel[rp], rv, rc, rl)) * nrm
    # each span's part inside its ground truth's box: there V_g and d_g are looked up
    rs = np.cumsum(rl) - rl
    gb = bg[rp]
    c0 = np.maximum(rc, gb[:, 2])
    c1 = np.minimum(rc + rl, gb[:, 3])
    ln = np.where((rv >= gb[:, 0]) & (rv < gb[:, 1]), np.maximum(c1 - c0, 0), 0)
    at = _run_offsets(rs + c0 - rc, ln)  # pixels of the estimate's render
    src = _run_offsets(gr.off[rp] + (rv - gb[:, 0]) * gr.w[rp] + (c0 - gb[:, 2]), ln)  # on the rasters
    vge = np.zeros(len(d), bool)
    vge[at] = vg_c.take(src)
    pei = np.repeat(np.arange(n), np.diff(ps))
    hit = de > 0
    ve = hit & ((((de.astype(np.float32) - dte.astype(np.float32)) <= delta) | (dte == 0)) | vge)
    inter = ve & vge
    n_ve = np.bincount(pei[ve], minlength=n)
    n_inter = np.bincount(pei[inter], minlength=n)
    n_union = cg + n_ve - n_inter
    dg = np.zeros(len(d), np.float32)
    dg[at] = dg_c.take(src)
    ii = np.flatnonzero(inter)
    nr = nrm.take(ii)
    dist = np.abs(dg.take(ii) * nr - de.take(ii)) / diameter  # d_g = its depth times the same ray's norm
    k = np.searchsorted(taus, dist, side="right")  # the taus with dist >= tau: the first k
    T = len(taus)
    hist = np.bincount(pei.take(ii) * (T + 1) + k, minlength=n * (T + 1)).reshape(n, T + 1)
    cost = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (n,T): #{dist >= tau_i}
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (cost + (n_union - n_inter)[:, None]) / n_union[:, None]
    e[n_union == 0] = 1.0
    return e
