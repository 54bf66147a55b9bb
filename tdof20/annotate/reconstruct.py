"""Reconstruction: fuse the opaque frames into one scene, remove the table, split the objects.

Input: the opaque-phase depth of every frame and its pose ``T_ref_frame`` (camera of the frame
-> camera of arm 0, step 0, from registration). Output: the fused scene (a TSDF volume integrated
with open3d, extracted as a point cloud and a mesh) in the reference frame, the table plane, and
one point cluster per object standing on it, with the TSDF's normals of its points.

Two details of the fusion keep the surface where the depth puts it (measured on the simulated
jar single/13, whose wall is 3 mm thick, against the true model; true poses, 240x180 images):

* open3d's integration reads the depth pixel ``floor(u)`` of a voxel projected to ``u``, while
  pixel ``i`` samples the ray through ``u = i`` (the convention of
  :class:`tdof20.geometry.PinholeCamera`). :func:`fuse` hands open3d the principal point moved
  by half a pixel, so that every voxel reads its nearest pixel: without it the views disagree
  by half a pixel and the outer wall came out 0.36 mm too far out (sdf_trunc 4 mm).
* ``sdf_trunc_mm`` must stay below the thickness of the thinnest wall: the voxels just outside
  one side of a thin wall lie less than the truncation behind the other side for the views
  that see that side, and are pulled inside. With 8 mm the jar's outer wall came out 0.5 mm
  and its inner wall 2.6 mm off the truth (the model 2.7 mm too wide); with 4 mm (two voxels;
  3x the depth noise of a 240x180 frame at 0.5 m) -0.03 and +0.46 mm.

Repeatable: the same frames give the same plane, clusters and files run to run, bit for bit.
Two things of open3d are not: the TSDF's blocks sit in a hash map that several threads fill, so
the extracted points and the mesh come out in another order each run (their values do not
change: each voxel is integrated by one thread), and ``segment_plane`` draws its samples from one
generator shared by its OpenMP threads (with a stop that depends on how far the others got), so
even a seeded run differs with more than one thread. Hence: the extracted points (with their
normals) and the mesh are put in a canonical order (lexicographic by coordinates, duplicated mesh
vertices merged) before anything reads them; the table plane is found by :func:`tdof20.geometry.fitting.fit_plane`, a
RANSAC seeded by ``seed`` on numpy, refined by least squares on its inliers until the inlier set
no longer changes (so the plane is the centre of the table's band, not one of the random planes
within it); clusters are ordered by size, then centroid, each with its points in that canonical
order. Measured over 5 processes on the same frames of single/12 with a cabinet beside the table
(640x480, 4 arms x 24 steps, true poses): before (segment_plane on the hash map's order) the
plane moved up to 0.006 mm over the turntable and the points, clusters and mesh came out in
other orders (a clean session's clusters also lost or gained a border point in DBSCAN); now all
five are identical, bit for bit — so are the built model and the labels after them
(``benchmarks/annotate_accuracy.py --repeat``; ``tests/test_repeatable.py`` runs the stage twice
in two processes). The TSDF integration itself needs no bound: its values were the same in
every run, only their order was not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from tdof20.config import check_ranges
from tdof20.geometry import PinholeCamera, invert
from tdof20.geometry.fitting import fit_plane, plane_distance
from tdof20.o3d import o3d


@dataclass(frozen=True)
class ReconstructionConfig:
    voxel_mm: float = 2.0             # TSDF voxel
    sdf_trunc_mm: float = 4.0         # below the thinnest wall (module docstring), >= ~3x the depth noise
    depth_max_mm: float = 1200.0      # ignore the far room
    plane_dist_mm: float = 3.0        # RANSAC inlier distance of the table plane
    above_table_mm: float = 4.0       # points closer to the table than this belong to it
    crop_radius_mm: float = 240.0     # keep points within this distance of the turntable axis
    cluster_eps_mm: float = 8.0       # DBSCAN neighbourhood
    cluster_min_points: int = 60
    min_weight: float = 2.0           # a surface voxel must be seen by this many frames
    block_count: int = 2000           # initial hash-map capacity of the TSDF grid (open3d grows it
                                      # when more blocks are touched; each slot is allocated up front:
                                      # 40,000 took 9 s and 3.3 GB)
    min_cluster_points: int = 300     # smaller clusters are noise
    floating_mm: float = 15.0         # a cluster whose lowest point is higher above the table than
                                      # this is a piece of an object (objects stand on the table) ...
    floating_join_mm: float = 60.0    # ... and joins the standing cluster nearest to it across the
                                      # table, if one is within this (horizontal distance)
    static_max_agree: float = 0.3     # a point above the table whose fused position the frames' depth
                                      # agrees with in at most this share of the frames that decide
                                      # (agree, or see through it) does not turn with the table: static
                                      # clutter smeared round the axis, never an object (0 = keep all)
    static_frames: int = 48           # frames kept (evenly over the run) for that test
    plane_iters: int = 1000           # RANSAC hypotheses per plane
    seed: int = 0                     # of the RANSAC samples (the least-squares refinement all but
                                      # removes their effect)

    def __post_init__(self) -> None:
        check_ranges(self, "reconstruct", positive=("voxel_mm", "sdf_trunc_mm", "depth_max_mm", "plane_dist_mm",
                                                    "crop_radius_mm", "cluster_eps_mm", "cluster_min_points",
                                                    "min_weight", "block_count", "min_cluster_points",
                                                    "plane_iters", "floating_mm"),
                     non_negative=("above_table_mm", "seed", "floating_join_mm", "static_max_agree",
                                   "static_frames"))


@dataclass
class Reconstruction:
    points: np.ndarray                # (N,3) fused scene surface points, reference frame, mm
    plane: np.ndarray                 # (4,) table plane a x + b y + c z + d = 0, normal towards the objects
    clusters: list[np.ndarray] = field(default_factory=list)  # (Ni,3) object points, largest first (then by centroid)
    mesh: object = None               # open3d TriangleMesh of the fused scene
    cluster_normals: list[np.ndarray] = field(default_factory=list)  # (Ni,3) unit normals of the clusters
    dropped: list[int] = field(default_factory=list)  # the point counts of the DBSCAN clusters under
    # min_cluster_points (largest first, at most 8): what to look at when an object is missing
    # (the TSDF's gradient: oriented towards the free space the cameras saw, each wall of a thin
    # vessel its own way — what :func:`tdof20.annotate.modelbuild.build_model_from_cluster` needs)


def fuse(frames: list[tuple[np.ndarray, np.ndarray]], camera: PinholeCamera,
         cfg: ReconstructionConfig = ReconstructionConfig()):
    """TSDF-integrate (depth_mm (H,W), T_ref_frame (4,4)) pairs -> open3d VoxelBlockGrid (metres).

    The tensor VoxelBlockGrid is used: the legacy ScalableTSDFVolume of open3d 0.20 extracts
    nothing here. The grid holds the TSDF and its weight only (a dummy colour channel, once
    thought needed for the extraction, cost a sixth of the integration and changed nothing
    but the mesh file's constant grey). Its hash map starts at ``cfg.block_count`` blocks and
    grows when a frame touches more (the full 3,200-frame scene touches ~480).
    The integration gets the principal point moved by +0.5 px: open3d truncates a voxel's
    projection to a pixel index, and that makes it the nearest pixel (module docstring)."""
    import open3d.core as o3c

    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)), voxel_size=cfg.voxel_mm / 1000.0, block_resolution=16,
        block_count=cfg.block_count, device=o3c.Device("CPU:0"))
    K = o3c.Tensor(camera.K, o3c.float64)
    K_nearest = np.array(camera.K, np.float64)
    K_nearest[:2, 2] += 0.5
    K_int = o3c.Tensor(K_nearest, o3c.float64)
    trunc_voxels = cfg.sdf_trunc_mm / cfg.voxel_mm
    for depth_mm, T_ref_frame in frames:
        d = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth_mm, np.float32) / 1000.0))
        T = np.asarray(T_ref_frame, float).copy()
        T[:3, 3] /= 1000.0
        ext = o3c.Tensor(invert(T))  # open3d wants the world -> camera extrinsic
        coords = vbg.compute_unique_block_coordinates(d, K, ext, 1.0, cfg.depth_max_mm / 1000.0, trunc_voxels)
        vbg.integrate(coords, d, K_int, ext, 1.0, cfg.depth_max_mm / 1000.0, trunc_voxels)
    return vbg


def _canonical_order(P: np.ndarray, N: np.ndarray | None = None) -> np.ndarray:
    """Indices putting points (and their normals, to break ties) in lexicographic order."""
    keys = [P[:, 2], P[:, 1], P[:, 0]]
    if N is not None:
        keys = [N[:, 2], N[:, 1], N[:, 0]] + keys
    return np.lexsort(keys)


def _canonical_mesh(mesh):
    """The legacy mesh with duplicated vertices merged, vertices in lexicographic order, each
    triangle starting at its smallest index (winding kept), triangles sorted."""
    mesh.remove_duplicated_vertices()
    V = np.asarray(mesh.vertices)
    if len(V) == 0:
        return mesh
    order = _canonical_order(V, np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    T = rank[np.asarray(mesh.triangles, np.int64)]
    if len(T):
        T = _roll_min_first(T)
        T = T[np.lexsort((T[:, 2], T[:, 1], T[:, 0]))]
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V[order]),
                                    o3d.utility.Vector3iVector(T.astype(np.int32)))
    if mesh.has_vertex_normals():
        out.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals)[order])
    if mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[order])
    return out


def _roll_min_first(T: np.ndarray) -> np.ndarray:
    """(M,3) triangles cyclically turned so that each starts at its smallest index."""
    k = np.argmin(T, axis=1)
    cols = (k[:, None] + np.arange(3)[None, :]) % 3
    return np.take_along_axis(T, cols, axis=1)


def reconstruct(frames: list[tuple[np.ndarray, np.ndarray]], camera: PinholeCamera, axis_point: np.ndarray,
                axis_dir: np.ndarray, cfg: ReconstructionConfig = ReconstructionConfig()) -> Reconstruction:
    """Fuse the frames, find the turntable top, keep what stands on it, cluster it.

    ``axis_point``, ``axis_dir``: the turntable axis in the reference frame (registration finds
    it). The fused points are first cropped to a cylinder around the axis (the bench around the
    turntable, a larger parallel plane, falls outside it); the table top is then the largest plane
    perpendicular to the axis (planes are peeled off by RANSAC one by one)."""
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    vol = fuse(_keep_sample(frames, kept, cfg.static_frames), camera, cfg)
    if vol.hashmap().size() == 0:  # nothing integrated (no frame, or every depth empty): open3d cannot extract
        return Reconstruction(np.zeros((0, 3)), np.r_[np.asarray(axis_dir, float), 0.0], [], None)
    try:
        pc = vol.extract_point_cloud(weight_threshold=cfg.min_weight)
    except RuntimeError as e:
        # no surface seen by cfg.min_weight frames (a 1-arm x 2-step session whose two views share
        # little): open3d fails on the empty point cloud's colours (SetPointColors)
        if "SetPointColors" not in str(e):
            raise
        return Reconstruction(np.zeros((0, 3)), np.r_[np.asarray(axis_dir, float), 0.0], [], None)
    pts = pc.point.positions.numpy().astype(np.float64) * 1000.0
    nrm = pc.point.normals.numpy().astype(np.float64) if "normals" in pc.point else np.zeros_like(pts)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    order = _canonical_order(pts, nrm)  # the hash map's order changes run to run (module docstring)
    pts, nrm = pts[order], nrm[order]
    mesh = vol.extract_triangle_mesh(weight_threshold=cfg.min_weight).to_legacy()
    mesh.scale(1000.0, center=(0, 0, 0))
    mesh = _canonical_mesh(mesh)
    a = np.asarray(axis_dir, float) / np.linalg.norm(axis_dir)
    p0 = np.asarray(axis_point, float)
    if a @ (np.zeros(3) - p0) < 0:  # "up": from the table towards the reference camera
        a = -a
    rel = pts - p0
    radial = np.linalg.norm(rel - np.outer(rel @ a, a), axis=1)
    in_cyl = radial < cfg.crop_radius_mm
    cyl, cyl_n = pts[in_cyl], nrm[in_cyl]
    plane = None
    rest = cyl
    for k in range(4):
        if len(rest) < 100:
            break
        cand, inl = fit_plane(rest, cfg.plane_dist_mm, cfg.plane_iters, seed=(cfg.seed, k))
        if not len(inl):
            break
        if cand[:3] @ a < 0:
            cand = -cand
        if cand[:3] @ a > 0.995 and (plane is None or len(inl) > plane[1]):
            plane = (cand, len(inl))
        rest = np.delete(rest, inl, axis=0)
    if plane is None:
        return Reconstruction(pts, np.r_[a, -a @ p0], [], mesh)
    plane = plane[0]
    dist = plane_distance(cyl, plane)
    above = dist > cfg.above_table_mm
    cand, cand_n = cyl[above], cyl_n[above]
    if len(cand) and kept and cfg.static_max_agree > 0:
        turns = turning_points(cand, kept, camera, cfg)
        cand, cand_n = cand[turns], cand_n[turns]
    clusters, dropped = [], []
    if len(cand):
        c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cand))
        labels = np.asarray(c.cluster_dbscan(cfg.cluster_eps_mm, cfg.cluster_min_points))
        for lab in range(labels.max() + 1 if len(labels) else 0):
            sel = labels == lab
            if sel.sum() >= cfg.min_cluster_points:
                clusters.append((cand[sel], cand_n[sel]))  # (in the canonical order of cand)
            else:
                dropped.append(int(sel.sum()))
        clusters = join_floating(clusters, plane, cfg)
        clusters.sort(key=lambda cn: (-len(cn[0]), *cn[0].mean(axis=0).tolist()))
    return Reconstruction(pts, plane, [c for c, _ in clusters], mesh, [n for _, n in clusters],
                          sorted(dropped, reverse=True)[:8])


def join_floating(clusters: list[tuple[np.ndarray, np.ndarray]], plane: np.ndarray,
                  cfg: ReconstructionConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Join the pieces of one object that the fusion left apart.

    Objects stand on the turntable apart from each other, so their footprints on the table do not
    overlap. A reconstruction from few turntable steps can cut one object into pieces farther
    apart than ``cluster_eps_mm``: the near outer wall of a cup, its far inner wall seen over the
    rim, its inner bottom; or a goblet's bowl above a stem the fusion lost. Left alone, a piece is
    matched to the object as if it were the whole object and the fit slides along the object's
    axis. Two rules, largest cluster first:

    * a cluster whose centre, seen from above, lies inside the footprint of a larger cluster (a
      circle fitted to that cluster's points seen from above, when they bend round enough to fix
      one: radius at most 0.6 of their extent) joins it;
    * a cluster whose lowest point lies more than ``floating_mm`` above the table joins the
      standing cluster nearest to it across the table, if within ``floating_join_mm``.

    (points, normals) pairs in, the same out (joined ones concatenated, in the input order)."""
    from scipy.spatial import cKDTree

    if len(clusters) < 2:
        return clusters
    n = plane[:3] / np.linalg.norm(plane[:3])
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    flat = [np.stack([c @ e1, c @ e2], axis=1) for c, _ in clusters]   # seen from above, (N,2) mm
    low = [float(plane_distance(c, plane).min()) for c, _ in clusters]
    parent = list(range(len(clusters)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    circles = [_footprint_circle(f) for f in flat]
    rank = sorted(range(len(clusters)), key=lambda k: (-len(clusters[k][0]), k))  # largest first (DBSCAN's
    for r, i in enumerate(rank):                                                   # labels are in no size order)
        ci = flat[i].mean(axis=0)
        for j in rank[:r]:
            if circles[j] is not None and np.linalg.norm(ci - circles[j][0]) < circles[j][1]:
                parent[root(i)] = root(j)
                break
    standing = [i for i, h in enumerate(low) if h <= cfg.floating_mm]
    trees = {i: cKDTree(flat[i]) for i in standing}
    for i, h in enumerate(low):
        if h <= cfg.floating_mm or not standing or root(i) != i:
            continue
        dist = {j: float(trees[j].query(flat[i], k=1)[0].min()) for j in standing}
        j = min(dist, key=lambda k: (dist[k], k))
        if dist[j] <= cfg.floating_join_mm:
            parent[root(i)] = root(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(clusters)):
        groups.setdefault(root(i), []).append(i)
    return [(np.concatenate([clusters[k][0] for k in ks]), np.concatenate([clusters[k][1] for k in ks]))
            for ks in groups.values()]


def _footprint_circle(xy: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(centre (2,), radius) of a least-squares circle through points seen from above, or None
    when they do not bend round enough to fix one (radius > 0.6 of their extent)."""
    if len(xy) < 10:
        return None
    m = xy.mean(axis=0)
    q = xy - m
    A = np.c_[2 * q, np.ones(len(q))]
    sol, *_ = np.linalg.lstsq(A, (q ** 2).sum(axis=1), rcond=None)
    r2 = sol[2] + sol[0] ** 2 + sol[1] ** 2
    if not np.isfinite(r2) or r2 <= 0:
        return None
    r = float(np.sqrt(r2))
    extent = float(np.ptp(q @ np.linalg.svd(q, full_matrices=False)[2][0]))   # along the main direction
    return (m + sol[:2], r) if r <= 0.6 * extent else None


def _keep_sample(frames, kept: list, n: int):
    """Pass the frames through, keeping at most ~``n`` of them, evenly spread over the run, in
    ``kept`` (every s-th; when the list grows to 2n every other is dropped and s doubles)."""
    stride, i = 1, 0
    for depth_mm, T in frames:
        if n > 0 and i % stride == 0:
            kept.append((depth_mm, np.asarray(T, float)))
            if len(kept) >= 2 * n:
                del kept[1::2]
                stride *= 2
        i += 1
        yield depth_mm, T


def turning_points(points: np.ndarray, frames: list[tuple[np.ndarray, np.ndarray]], camera: PinholeCamera,
                   cfg: ReconstructionConfig = ReconstructionConfig()) -> np.ndarray:
    """(N,) bool: the fused points (reference frame, the table's turning frame) that turn with the
    turntable. Each frame's depth is asked about each point: the depth there agrees (within
    max(6 mm, 3 voxels)), lies beyond it (the camera sees through where the point would be), or
    before it (hidden: no say); no depth there (cut off by the crop, beyond the cylinder) counts as
    seen through. Something fixed in the lab (a cabinet) is fused into an arc smeared
    round the axis, which each frame's depth agrees with only where it was seen: a point the
    deciding frames agree with in at most ``cfg.static_max_agree`` of them is static. The votes are
    pooled over each point's neighbours within ``cfg.cluster_eps_mm`` (a surface turns or stands
    as a whole): one point's votes are noisy where few frames decide (a small object on an 8-frame
    session lost 6 % of its points to them and fell under ``min_cluster_points``). A point whose
    neighbourhood fewer than two frames decide on is kept."""
    tol = max(6.0, 3.0 * cfg.voxel_mm)
    agree = np.zeros(len(points), np.int32)
    decide = np.zeros(len(points), np.int32)
    P = np.c_[points, np.ones(len(points))]
    K = camera.K
    for depth_mm, T_ref_frame in frames:
        X = P @ invert(T_ref_frame).T
        z = X[:, 2]
        ok = z > 1.0
        u = np.full(len(z), -1, np.int64)
        v = np.full(len(z), -1, np.int64)
        u[ok] = np.rint(K[0, 0] * X[ok, 0] / z[ok] + K[0, 2]).astype(np.int64)
        v[ok] = np.rint(K[1, 1] * X[ok, 1] / z[ok] + K[1, 2]).astype(np.int64)
        h, w = depth_mm.shape
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        zo = np.zeros(len(z))
        zo[ok] = depth_mm[v[ok], u[ok]]
        # no depth at a point inside the crop: the camera saw past it (to what the crop cut off)
        a = ok & (zo > 0) & (np.abs(zo - z) <= tol)
        agree += a
        decide += a | (ok & ((zo > z + tol) | (zo == 0)))
    agree, decide = _pool(points, cfg.cluster_eps_mm, agree, decide)
    return (decide < 2) | (agree > cfg.static_max_agree * decide)


def _pool(points: np.ndarray, radius: float, *values: np.ndarray) -> list[np.ndarray]:
    """Each (N,) array of ``values``: every point's value summed with those of the points within
    ``radius`` of it (the neighbour pairs found once for all of them)."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    i, j, n = pairs[:, 0], pairs[:, 1], len(points)
    return [v + np.bincount(i, weights=v[j], minlength=n) + np.bincount(j, weights=v[i], minlength=n)
            for v in values]
