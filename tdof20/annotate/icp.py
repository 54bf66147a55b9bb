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
from typing import TYPE_CHECKING

import numpy as np

from tdof20.annotate.turntable import T_diff, height_radius, turntable_prior
from tdof20.errors import TdofError
from tdof20.geometry.transforms import invert
from tdof20.o3d import o3d

if TYPE_CHECKING:   # the options' type only: registration imports this module
    from tdof20.annotate.registration import RegistrationConfig

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
    """A cloud downsampled at each ICP scale with normals (estimated once, on the ``normal_voxel_mm``
    grid, handed to the finest points and averaged into the coarser ones, oriented towards
    ``viewpoint``), plus a random subsample of each level (at most ``max_source_points``) used
    when the cloud is the ICP source. ``points``: (N,3) raw points, or an open3d cloud already
    downsampled at the finest scale (``voxel_sizes_mm[-1]``)."""

    def __init__(self, points, cfg: RegistrationConfig, viewpoint: np.ndarray | None = None,
                 levels: list | None = None):
        self.cfg = cfg
        if levels is not None:
            self.levels = levels
        else:
            fine = (points if isinstance(points, o3d.geometry.PointCloud)
                    else point_cloud(points).voxel_down_sample(cfg.voxel_sizes_mm[-1]))
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
            self.levels = []
            for v in cfg.voxel_sizes_mm[:-1]:
                if sparse is not fine and v == cfg.normal_voxel_mm:
                    self.levels.append(sparse)  # the same voxel grid, with the normals estimated on it
                    continue
                d = fine.voxel_down_sample(v)
                d.normalize_normals()
                self.levels.append(d)
            self.levels.append(fine)
        self._src: dict[int, "o3d.geometry.PointCloud"] = {}

    def source(self, i: int) -> "o3d.geometry.PointCloud":
        if i not in self._src:
            lv = self.levels[i]
            n = len(lv.points)
            m = self.cfg.max_source_points
            if m and n > m:
                idx = np.random.default_rng(n).choice(n, m, replace=False)
                self._src[i] = lv.select_by_index(np.sort(idx).tolist())
            else:
                self._src[i] = lv
        return self._src[i]

    @classmethod
    def from_cloud(cls, cloud: "o3d.geometry.PointCloud", cfg: RegistrationConfig) -> "Pyramid":
        """From a cloud that has normals (e.g. a fused one): the levels keep (average) them."""
        levels = []
        for v in cfg.voxel_sizes_mm:
            d = cloud.voxel_down_sample(v)
            d.normalize_normals()
            levels.append(d)
        return cls(None, cfg, levels=levels)

    def cropped(self, n: np.ndarray, p: np.ndarray, radius: float) -> "Pyramid":
        """The part inside the turntable volume (same normals)."""
        out = []
        for lv in self.levels:
            h, r = height_radius(np.asarray(lv.points), n, p)
            keep = (h >= -self.cfg.crop_below_mm) & (h <= self.cfg.crop_height_mm) & (r <= radius)
            out.append(lv.select_by_index(np.flatnonzero(keep).tolist()))
        return Pyramid(None, self.cfg, levels=out)

    def tree(self, i: int):
        """(scipy cKDTree, points (N,3), unit normals (N,3)) of level i, built once."""
        if not hasattr(self, "_trees"):
            self._trees = {}
        if i not in self._trees:
            from scipy.spatial import cKDTree
            lv = self.levels[i]
            P = np.asarray(lv.points)
            self._trees[i] = (cKDTree(P), P, np.asarray(lv.normals))
        return self._trees[i]

    def __len__(self) -> int:
        return len(self.levels[-1].points)


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
        s, t = src.source(i), tgt.levels[i]
        if len(s.points) < 10 or len(t.points) < 10:
            continue
        res = REG.registration_icp(s, t, dist, T, est, REG.ICPConvergenceCriteria(1e-6, 1e-6, it))
        T = res.transformation
    dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[n - 1]
    s, t = src.source(n - 1), tgt.levels[n - 1]
    if res is None or (final_dist is not None and final_dist != dist):
        dist = dist if final_dist is None else final_dist
        res = REG.evaluate_registration(s, t, dist, T)
    info = (REG.get_information_matrix_from_point_clouds(s, t, dist, T) if information and len(s.points) >= 10
            else np.eye(6))
    return np.asarray(T), float(res.fitness), float(res.inlier_rmse), np.asarray(info)


def icp_prior(src: Pyramid, tgt: Pyramid, prior: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
              levels: list[int] | None = None, information: bool = True,
              sigma_deg: float | None = None, sigma_mm: float | None = None):
    """Multi-scale point-to-plane ICP (src -> tgt) regularised towards the turntable prior.

    Gauss-Newton on sum r_i^2 / sigma_r^2 + |w|^2 / sigma_w^2 + |v|^2 / sigma_v^2, where (w, v)
    is the deviation from ``prior`` (rotation vector, and displacement of ``centre``, the table
    centre): directions the geometry pins (most of them) follow the data, directions it leaves
    free (a rotationally symmetric object turning about itself) stay at the prior instead of
    drifting. Returns (T, fitness, rmse, information (6,6)) like open3d's ICP."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(prior, float).copy()
    T0inv = invert(prior)
    c = np.asarray(centre, float)
    sigma_deg = cfg.prior_sigma_deg if sigma_deg is None else sigma_deg
    sigma_mm = cfg.prior_sigma_mm if sigma_mm is None else sigma_mm
    lam = np.r_[np.full(3, (cfg.prior_sigma_r_mm / math.radians(sigma_deg)) ** 2),
                np.full(3, (cfg.prior_sigma_r_mm / sigma_mm) ** 2)]
    levels = list(range(len(cfg.voxel_sizes_mm))) if levels is None else list(levels)
    for i in levels:
        dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[i]
        S = np.asarray(src.source(i).points)
        tree, Q, N = tgt.tree(i)
        if len(S) < 10 or len(Q) < 10:
            continue
        it = cfg.icp_iterations[min(i, len(cfg.icp_iterations) - 1)]
        for _ in range(it):
            X = S @ T[:3, :3].T + T[:3, 3]
            d, idx = tree.query(X, distance_upper_bound=dist)  # <= max_source_points: threads cost more
            ok = np.isfinite(d)
            if ok.sum() < 10:
                break
            Xo, q, nn = X[ok], Q[idx[ok]], N[idx[ok]]
            r = np.einsum("ij,ij->i", Xo - q, nn)
            J = np.concatenate([np.cross(Xo - c, nn), nn], axis=1)
            D = T @ T0inv                                   # deviation from the prior (target frame)
            dev = np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, :3] @ c + D[:3, 3] - c]
            H = J.T @ J + np.diag(lam)
            g = J.T @ r + lam * dev
            xi = -np.linalg.solve(H, g)
            w, v = xi[:3], xi[3:]
            Rw = Rotation.from_rotvec(w).as_matrix()
            step = np.eye(4)
            step[:3, :3] = Rw
            step[:3, 3] = c - Rw @ c + v
            T = step @ T
            if np.linalg.norm(w) < cfg.icp_tol_rad and np.linalg.norm(v) < cfg.icp_tol_mm:
                break
    n = levels[-1]
    dist = cfg.icp_dist_factor * cfg.voxel_sizes_mm[n]
    S = np.asarray(src.source(n).points)
    tree, Q, N = tgt.tree(n)
    X = S @ T[:3, :3].T + T[:3, 3]
    d, idx = tree.query(X, distance_upper_bound=dist)
    ok = np.isfinite(d)
    fit = float(ok.mean()) if len(S) else 0.0
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("nan")
    info = _information(Q[idx[ok]]) if information and len(S) >= 10 else np.eye(6)
    return T, fit, rmse, info


def _information(q: np.ndarray) -> np.ndarray:
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
                    max_mm: float, angles: tuple[float, ...], levels: list[int], prog, task
                    ) -> tuple[dict[int, np.ndarray], dict[int, list[tuple[float, float, bool]]]]:
    """Pairwise ICP + pose graph over the usable frames of arm position ``arm`` (``pyr``: step ->
    its cloud, cropped to the turntable volume of ``radius`` about the axis ``axis_dir`` through
    ``axis_point``), each edge started from the turntable prior and dropped when it ends further
    than ``max_deg`` / ``max_mm`` from it.
    Returns (step -> T_arm_frame, step -> [(fitness, rmse, kept) of each of its edges])."""
    steps = sorted(pyr)
    prior = {k: turntable_prior(axis_dir, axis_point, k * step_deg, sign) for k in steps}
    pairs = edge_pairs(steps, step_deg, angles)
    stats: dict[int, list[tuple[float, float, bool]]] = {k: [] for k in steps}
    c = np.append(axis_point, 1.0)
    edges = []
    for i, j in pairs:
        init = invert(prior[i]) @ prior[j]            # cam(j) -> cam(i)
        if cfg.prior_weighted_icp:
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
