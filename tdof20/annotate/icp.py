"""Point clouds and ICP for the registration: multi-scale clouds, point-to-plane ICP (plain and
regularised towards a prior), and the pose-graph pass over one arm position's frames.

* :class:`Pyramid` — a cloud downsampled at each ICP scale with normals, its ICP-source
  subsamples, nearest-neighbour trees, and its part inside the turntable volume;
* :func:`icp` — open3d's multi-scale point-to-plane ICP; :func:`icp_prior` — Gauss-Newton
  point-to-plane with a Gaussian prior on the deviation from a given pose (the turntable's or the
  robot's), so directions the geometry leaves free stay at the prior;
* :func:`edge_pairs` and :func:`pose_graph_pass` — pairwise ICP between frames a step and given
  angles apart, edges that disagree with the turntable prior dropped, open3d's global
  optimisation over the frames connected to the first.

Options: :class:`~tdof20.annotate.registration.RegistrationConfig`; mm throughout.
"""

from __future__ import annotations

import math

import numpy as np

from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.annotate.turntable import T_diff, height_radius, turntable_prior
from tdof20.errors import TdofError
from tdof20.geometry.transforms import invert
from tdof20.o3d import o3d


__all__ = ["REG", "Pyramid", "edge_pairs", "icp", "icp_prior", "point_cloud", "pose_graph_pass", "voxel_cells"]

REG = o3d.pipelines.registration


# ---------------------------------------------------------------------------------------------
# multi-scale clouds and ICP
# ---------------------------------------------------------------------------------------------
def point_cloud(points: np.ndarray) -> "o3d.geometry.PointCloud":
    """An open3d cloud of (N,3) points (mm)."""
    p = o3d.geometry.PointCloud()
    p.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return p


class Pyramid:
    """A cloud at each ICP scale: per level (points (N,3), unit normals (N,3)) as float32 arrays
    (the depth's own precision; half the memory of open3d's float64 clouds), or None for a level
    a registration pass does not use. Normals are estimated once, on the ``normal_voxel_mm`` grid,
    handed to the finest points and averaged into the coarser ones, oriented towards ``viewpoint``.
    A random subsample of each level (at most ``max_source_points``) is used when the cloud is the
    ICP source; a level's nearest-neighbour tree is built when the cloud is first a target and
    kept until :meth:`release` (one arm's 400 trees would hold ~1 GB).
    ``n_fine``: the number of points of the finest level, also when that level is not kept."""

    def __init__(self, levels: list, cfg: RegistrationConfig, n_fine: int | None = None):
        self.cfg = cfg
        self.levels = levels
        self.n_fine = int(len(levels[-1][0]) if n_fine is None else n_fine)
        self._src: dict[int, np.ndarray] = {}
        self._trees: dict[int, tuple] = {}

    @classmethod
    def from_fine(cls, fine: "o3d.geometry.PointCloud", cfg: RegistrationConfig,
                  viewpoint: np.ndarray | None = None, keep: set[int] | None = None) -> "Pyramid":
        """From an open3d cloud downsampled at the finest scale (``voxel_sizes_mm[-1]``, no normals
        yet): the levels in ``keep`` (default all) with normals."""
        n_lv = len(cfg.voxel_sizes_mm)
        keep = set(range(n_lv)) if keep is None else set(keep)
        if cfg.normal_voxel_mm:
            # each fine point takes the normal of its cell of the sparser grid (4x fewer points
            # and neighbours for the normal estimation)
            centres, cell = voxel_cells(np.asarray(fine.points), cfg.normal_voxel_mm)
            sparse = point_cloud(centres)
        else:
            sparse, cell = fine, None
        sparse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_mm,
                                                                     max_nn=cfg.normal_max_nn))
        if viewpoint is not None:
            sparse.orient_normals_towards_camera_location(viewpoint)
        if cell is not None:
            fine.normals = o3d.utility.Vector3dVector(np.asarray(sparse.normals)[cell])
        levels: list = []
        for i, v in enumerate(cfg.voxel_sizes_mm[:-1]):
            if i not in keep:
                levels.append(None)
            elif sparse is not fine and v == cfg.normal_voxel_mm:
                levels.append(_arrays(sparse))  # the same voxel grid, with the normals estimated on it
            else:
                d = fine.voxel_down_sample(v)
                d.normalize_normals()
                levels.append(_arrays(d))
        levels.append(_arrays(fine) if n_lv - 1 in keep else None)
        return cls(levels, cfg, n_fine=len(fine.points))

    @classmethod
    def from_cloud(cls, cloud: "o3d.geometry.PointCloud", cfg: RegistrationConfig) -> "Pyramid":
        """From a cloud that has normals (e.g. a fused one): the levels keep (average) them."""
        levels = []
        for v in cfg.voxel_sizes_mm:
            d = cloud.voxel_down_sample(v)
            d.normalize_normals()
            levels.append(_arrays(d))
        return cls(levels, cfg)

    def points(self, i: int) -> np.ndarray:
        return self.levels[i][0]

    def source(self, i: int) -> np.ndarray:
        """The ICP-source points of level i (a seeded subsample of at most ``max_source_points``)."""
        if i not in self._src:
            P = self.levels[i][0]
            n, m = len(P), self.cfg.max_source_points
            if m and n > m:
                self._src[i] = P[np.sort(np.random.default_rng(n).choice(n, m, replace=False))]
            else:
                self._src[i] = P
        return self._src[i]

    def cloud(self, i: int, source: bool = False) -> "o3d.geometry.PointCloud":
        """Level i as an open3d cloud (with normals; ``source``: the ICP-source subsample, points only)."""
        if source:
            return point_cloud(self.source(i))
        P, N = self.levels[i]
        pc = point_cloud(P)
        pc.normals = o3d.utility.Vector3dVector(np.asarray(N, np.float64))
        return pc

    def cropped(self, n: np.ndarray, p: np.ndarray, radius: float, levels: list[int] | None = None) -> "Pyramid":
        """The part inside the turntable volume (same normals), of the kept ``levels`` (default all
        kept); the count of the finest level's points inside is kept even when that level is not."""
        cfg = self.cfg
        n64, p64 = np.asarray(n, np.float64), np.asarray(p, np.float64)

        def inside(P: np.ndarray) -> np.ndarray:
            h, r = height_radius(P, n64, p64)
            return (h >= -cfg.crop_below_mm) & (h <= cfg.crop_height_mm) & (r <= radius)
        want = set(range(len(self.levels))) if levels is None else set(levels)
        out = []
        for i, lv in enumerate(self.levels):
            if lv is None or i not in want:
                out.append(None)
            else:
                m = inside(lv[0])
                out.append((lv[0][m], lv[1][m]))
        fine = out[-1]
        if fine is not None:
            n_fine = len(fine[0])
        elif self.levels[-1] is not None:
            n_fine = int(inside(self.levels[-1][0]).sum())
        else:
            n_fine = self.n_fine
        return Pyramid(out, cfg, n_fine=n_fine)

    def tree(self, i: int):
        """(scipy cKDTree, points (N,3), unit normals (N,3)) of level i, built once (until :meth:`release`)."""
        if i not in self._trees:
            from scipy.spatial import cKDTree
            P, N = self.levels[i]
            # unbalanced, uncompacted: half the build time, the same (exact) nearest neighbours
            self._trees[i] = (cKDTree(P, balanced_tree=False, compact_nodes=False), P, N)
        return self._trees[i]

    def release(self) -> None:
        """Drop the nearest-neighbour trees (rebuilt when needed again)."""
        self._trees.clear()

    def nbytes(self) -> int:
        return sum(a.nbytes for lv in self.levels if lv is not None for a in lv)

    def __len__(self) -> int:
        return self.n_fine


def _arrays(pc: "o3d.geometry.PointCloud") -> tuple[np.ndarray, np.ndarray]:
    """(points, normals) of an open3d cloud as float32 arrays."""
    return np.asarray(pc.points, np.float32), np.asarray(pc.normals, np.float32)


def voxel_cells(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,3) on a grid of ``voxel`` mm cells anchored at the origin: (the centroids of the
    occupied cells (M,3), in the order of their cell index; each point's cell (N,))."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    k = np.floor(P / voxel).astype(np.int64)
    k -= k.min(axis=0)
    dims = k.max(axis=0) + 1
    _, cell, count = np.unique((k[:, 0] * dims[1] + k[:, 1]) * dims[2] + k[:, 2], return_inverse=True,
                               return_counts=True)
    cell = cell.reshape(-1)
    centres = np.stack([np.bincount(cell, P[:, i], minlength=len(count)) for i in range(3)], axis=1)
    return centres / count[:, None], cell


def icp(src: Pyramid, tgt: Pyramid, init: np.ndarray, cfg: RegistrationConfig,
        final_dist: float | None = None, levels: list[int] | None = None, information: bool = True):
    """Multi-scale point-to-plane ICP (src -> tgt) over ``levels`` (default all, coarse to fine).
    Returns (T, fitness, rmse, information (6,6)) — fitness/RMSE at the finest level used."""
    T = np.asarray(init, float)
    est = REG.TransformationEstimationPointToPlane()
    res = None
    levels = list(range(len(cfg.voxel_sizes_mm))) if levels is None else list(levels)
    n = levels[-1] + 1
    for i in levels:
        v = cfg.voxel_sizes_mm[i]
        it = cfg.icp_iterations[min(i, len(cfg.icp_iterations) - 1)]
        dist = cfg.icp_dist_factor * v
        if len(src.source(i)) < 10 or len(tgt.points(i)) < 10:
            continue
        res = REG.registration_icp(src.cloud(i, source=True), tgt.cloud(i), dist, T, est,
                                   REG.ICPConvergenceCriteria(1e-6, 1e-6, it))
        T = res.transformation
    dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[n - 1]
    s, t = src.cloud(n - 1, source=True), tgt.cloud(n - 1)
    if res is None or (final_dist is not None and final_dist != dist):
        dist = dist if final_dist is None else final_dist
        res = REG.evaluate_registration(s, t, dist, T)
    info = (REG.get_information_matrix_from_point_clouds(s, t, dist, T) if information and len(s.points) >= 10
            else np.eye(6))
    return np.asarray(T), float(res.fitness), float(res.inlier_rmse), np.asarray(info)


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues; the series near 0)."""
    th2 = float(w @ w)
    K = _skew(w)
    if th2 < 1e-12:
        return np.eye(3) + K + 0.5 * (K @ K)
    th = math.sqrt(th2)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * (K @ K)


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector of the rotation matrix ``R`` (angles below pi - 0.1: the prior's deviations)."""
    s = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])   # sin(th) * axis
    sn = float(np.linalg.norm(s))
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    th = math.atan2(sn, c)
    if th > math.pi - 0.1:   # near a half turn the skew part loses the axis
        from scipy.spatial.transform import Rotation
        return Rotation.from_matrix(R).as_rotvec()
    return s * (th / sn if sn > 1e-12 else 1.0)


def prior_weights(prior: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
                  sigma_deg: float | None = None, sigma_mm: float | None = None):
    """The Gaussian prior of :func:`icp_prior`: (the diagonal weights (6,) of the deviation
    (rotation vector, displacement of ``centre``) relative to one point-to-plane residual,
    inv(prior), the centre)."""
    sigma_deg = cfg.prior_sigma_deg if sigma_deg is None else sigma_deg
    sigma_mm = cfg.prior_sigma_mm if sigma_mm is None else sigma_mm
    lam = np.r_[np.full(3, (cfg.prior_sigma_r_mm / math.radians(sigma_deg)) ** 2),
                np.full(3, (cfg.prior_sigma_r_mm / sigma_mm) ** 2)]
    return lam, invert(prior), np.asarray(centre, float)


def prior_step(T: np.ndarray, X: np.ndarray, q: np.ndarray, nn: np.ndarray, T0inv: np.ndarray, c: np.ndarray,
               lam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton step of point-to-plane ICP with the prior (:func:`prior_weights`): moved
    source points X (M,3) against target points q with unit normals nn. Returns (the updated T,
    the step's rotation vector w, its displacement v of the centre)."""
    r = np.einsum("ij,ij->i", X - q, nn)
    J = np.empty((len(r), 6))
    a = X - c
    J[:, 0] = a[:, 1] * nn[:, 2] - a[:, 2] * nn[:, 1]   # (X - c) x n
    J[:, 1] = a[:, 2] * nn[:, 0] - a[:, 0] * nn[:, 2]
    J[:, 2] = a[:, 0] * nn[:, 1] - a[:, 1] * nn[:, 0]
    J[:, 3:] = nn
    D = T @ T0inv                                   # deviation from the prior (target frame)
    dev = np.r_[_log_so3(D[:3, :3]), D[:3, :3] @ c + D[:3, 3] - c]
    xi = -np.linalg.solve(J.T @ J + np.diag(lam), J.T @ r + lam * dev)
    w, v = xi[:3], xi[3:]
    Rw = _exp_so3(w)
    step = np.eye(4)
    step[:3, :3] = Rw
    step[:3, 3] = c - Rw @ c + v
    return step @ T, w, v


def icp_prior(src: Pyramid, tgt: Pyramid, prior: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
              levels: list[int] | None = None, information: bool = True,
              sigma_deg: float | None = None, sigma_mm: float | None = None):
    """Multi-scale point-to-plane ICP (src -> tgt) regularised towards the turntable prior.

    Gauss-Newton on sum r_i^2 / sigma_r^2 + |w|^2 / sigma_w^2 + |v|^2 / sigma_v^2, where (w, v)
    is the deviation from ``prior`` (rotation vector, and displacement of ``centre``, the table
    centre): directions the geometry pins (most of them) follow the data, directions it leaves
    free (a rotationally symmetric object turning about itself) stay at the prior instead of
    drifting. Returns (T, fitness, rmse, information (6,6)) like open3d's ICP.

    Closed-form maths in the loop (Rodrigues' formula for the step, the deviation's rotation
    vector from the skew part) instead of scipy's Rotation objects."""
    T = np.asarray(prior, float).copy()
    lam, T0inv, c = prior_weights(prior, centre, cfg, sigma_deg, sigma_mm)
    levels = list(range(len(cfg.voxel_sizes_mm))) if levels is None else list(levels)
    for i in levels:
        dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[i]
        S = src.source(i)
        if len(S) < 10 or len(tgt.points(i)) < 10:
            continue
        tree, Q, N = tgt.tree(i)
        it = cfg.icp_iterations[min(i, len(cfg.icp_iterations) - 1)]
        for _ in range(it):
            X = S @ T[:3, :3].T + T[:3, 3]
            d, idx = tree.query(X, distance_upper_bound=dist)  # <= max_source_points: threads cost more
            ok = d < np.inf
            if np.count_nonzero(ok) < 10:
                break
            j = idx[ok]
            T, w, v = prior_step(T, X[ok], Q[j], N[j], T0inv, c, lam)
            if np.linalg.norm(w) < cfg.icp_tol_rad and np.linalg.norm(v) < cfg.icp_tol_mm:
                break
    n = levels[-1]
    dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[n]
    S = src.source(n)
    tree, Q, N = tgt.tree(n)
    X = S @ T[:3, :3].T + T[:3, 3]
    d, idx = tree.query(X, distance_upper_bound=dist)
    ok = np.isfinite(d)
    fit = float(ok.mean()) if len(S) else 0.0
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("nan")
    info = information_matrix(Q[idx[ok]].astype(np.float64)) if information and len(S) >= 10 else np.eye(6)
    return T, fit, rmse, info


def information_matrix(q: np.ndarray) -> np.ndarray:
    """(6,6) information matrix of a registration from the target points (M,3) of its inlier
    correspondences — open3d's GetInformationMatrixFromPointClouds, from the correspondences the
    ICP already found instead of a second nearest-neighbour search (measured: 19 of 155 s per arm)."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    zero, one = np.zeros_like(x), np.ones_like(x)
    G = np.concatenate([np.stack([zero, z, -y, one, zero, zero], 1), np.stack([-z, zero, x, zero, one, zero], 1),
                        np.stack([y, -x, zero, zero, zero, one], 1)])
    return G.T @ G


# ---------------------------------------------------------------------------------------------
# the pose graph of one arm position
# ---------------------------------------------------------------------------------------------
def edge_pairs(steps: list[int], step_deg: float, angles: tuple[float, ...]) -> list[tuple[int, int]]:
    """Pairs (i, j) of frames about 1 step / the given angles apart (the loop wraps)."""
    ang = np.array(steps, float) * step_deg
    pairs = set()
    for a in angles:
        a = max(float(a), step_deg)
        for ii, i in enumerate(steps):
            diff = ((ang - ang[ii] - a + 180.0) % 360.0) - 180.0
            diff[ii] = np.inf
            jj = int(np.argmin(np.abs(diff)))
            if abs(diff[jj]) <= max(step_deg / 2.0, 1e-6) + 1e-9:
                j = steps[jj]
                if j != i:
                    pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def pose_graph_pass(pyr: dict[int, Pyramid], cfg: RegistrationConfig, arm: int, axis_dir: np.ndarray,
                    axis_point: np.ndarray, radius: float, step_deg: float, sign: float, max_deg: float,
                    max_mm: float, angles: tuple[float, ...], levels: list[int], prog, task, pair_icp=None
                    ) -> tuple[dict[int, np.ndarray], dict[int, list[tuple[float, float, bool]]]]:
    """Pairwise ICP + pose graph over the usable frames of arm position ``arm`` (``pyr``: step ->
    its cloud, cropped to the turntable volume of ``radius`` about the axis ``axis_dir`` through
    ``axis_point``), each edge started from the turntable prior and dropped when it ends further
    than ``max_deg`` / ``max_mm`` from it. ``pair_icp(src, tgt, init, centre, cfg, levels)`` registers
    a pair (default: :func:`icp_prior`, or :func:`icp` without ``prior_weighted_icp``).
    Returns (step -> T_arm_frame, step -> [(fitness, rmse, kept) of each of its edges])."""
    steps = sorted(pyr)
    prior = {k: turntable_prior(axis_dir, axis_point, k * step_deg, sign) for k in steps}
    pairs = edge_pairs(steps, step_deg, angles)
    stats: dict[int, list[tuple[float, float, bool]]] = {k: [] for k in steps}
    c = np.append(axis_point, 1.0)
    edges = []
    target = None
    for i, j in pairs:                                # sorted: each target's edges come together
        if target is not None and target != i:
            pyr[target].release()                     # its trees are not needed again
        target = i
        init = invert(prior[i]) @ prior[j]            # cam(j) -> cam(i)
        if pair_icp is not None:
            T, fit, rmse, info = pair_icp(pyr[j], pyr[i], init, axis_point, cfg, levels)
        elif cfg.prior_weighted_icp:
            T, fit, rmse, info = icp_prior(pyr[j], pyr[i], init, axis_point, cfg, levels=levels)
        else:
            T, fit, rmse, info = icp(pyr[j], pyr[i], init, cfg, levels=levels)
        prog.advance(task)
        rdeg, _ = T_diff(init, T)
        rmm = float(np.linalg.norm((T @ c - init @ c)[:3]))
        ok = not (fit < cfg.edge_min_fitness or rdeg > max_deg or rmm > max_mm)
        stats[i].append((fit, rmse, ok))
        stats[j].append((fit, rmse, ok))
        if ok:
            edges.append((i, j, T, info))
    if target is not None:
        pyr[target].release()
    # the pose graph over the frames connected to the first one (open3d refuses a disconnected graph)
    if not steps:
        raise TdofError(f"arm {arm}: no frame keeps enough depth points inside the turntable volume "
                        f"(crop radius {radius:.0f} mm about the axis)")
    k0 = steps[0]
    connected = _connected(steps, [(i, j) for i, j, _, _ in edges])[k0]
    nodes = [k for k in steps if k in connected]
    idx = {k: n for n, k in enumerate(nodes)}
    pg = REG.PoseGraph()
    for k in nodes:
        pg.nodes.append(REG.PoseGraphNode(prior[k]))
    for i, j, T, info in edges:
        if i in idx and j in idx:
            # source j, target i: pose_j = pose_i @ T
            pg.edges.append(REG.PoseGraphEdge(idx[j], idx[i], T, info, uncertain=abs(j - i) != 1))
    if len(pg.edges):
        opt = REG.GlobalOptimizationOption(max_correspondence_distance=cfg.icp_dist_factor * cfg.voxel_sizes_mm[levels[-1]],
                                           edge_prune_threshold=0.25, reference_node=0)
        REG.global_optimization(pg, REG.GlobalOptimizationLevenbergMarquardt(),
                                REG.GlobalOptimizationConvergenceCriteria(), opt)
    poses = {k: np.asarray(pg.nodes[idx[k]].pose) for k in nodes}
    # express relative to step 0 (or the first usable step, through its prior)
    fix = prior[k0] @ invert(poses[k0])
    return {k: (fix @ poses[k] if k in connected else prior[k]) for k in steps}, \
        {k: v if k in connected else [(f, r, False) for f, r, _ in v] for k, v in stats.items()}


def _connected(nodes: list[int], edges: list[tuple[int, int]]) -> dict[int, set[int]]:
    parent = {n: n for n in nodes}

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x
    for a, b in edges:
        parent[find(a)] = find(b)
    groups: dict[int, set[int]] = {}
    for n in nodes:
        groups.setdefault(find(n), set()).add(n)
    return {n: groups[find(n)] for n in nodes}
