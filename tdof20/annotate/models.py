"""Object models in the scene: register a known mesh (a lab's CAD model, or the model an object got
in its single-object scene) into a reconstructed cluster — upright turns about the table normal
(or FPFH global registration) refined by point-to-plane ICP — so one object keeps one model and
one model frame across all scenes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tdof20.config import check_ranges
from tdof20.geometry import rotation_matrix, transform_points
from tdof20.o3d import o3d


@dataclass(frozen=True)
class ModelFitConfig:
    voxel_mm: float = 4.0            # feature scale of the global registration
    icp_mm: tuple = (6.0, 3.0, 1.5)  # multi-scale ICP correspondence distances
    model_samples: int = 20000
    ransac_iters: int = 100000
    seed: int = 0

    def __post_init__(self) -> None:
        check_ranges(self, "fit", positive=("voxel_mm", "icp_mm", "model_samples", "ransac_iters"),
                     non_negative=("seed",))


@dataclass
class ModelFit:
    T_ref_model: np.ndarray          # (4,4): model frame -> reference camera frame, mm
    fitness: float                   # fraction of cluster points with a model point within the last ICP distance
    rmse: float                      # mm, over those
    score: float = 0.0               # mean cluster-to-model distance truncated at 5 mm (lower is better)


def _cloud(points: np.ndarray, voxel: float):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    pc = pc.voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 2.5, max_nn=30))
    return pc


def _icp(model_points: np.ndarray, cluster: np.ndarray, T: np.ndarray, cfg: ModelFitConfig,
         clouds: tuple | None = None) -> ModelFit:
    """Multi-scale point-to-plane ICP from the pose ``T`` (model -> reference). The cluster is
    registered to the model (the cluster is the partial one), then the result inverted.
    ``clouds``: the (model, cluster) clouds of :func:`_cloud` at ``cfg.icp_mm[-1]`` when the
    caller made them already (ICP reads them only: the same fit as with fresh ones)."""
    reg = o3d.pipelines.registration
    src, dst = clouds if clouds is not None else (_cloud(model_points, cfg.icp_mm[-1]), _cloud(cluster, cfg.icp_mm[-1]))
    res = None
    for d in cfg.icp_mm:
        res = reg.registration_icp(dst, src, d, np.linalg.inv(T), reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=60))
        T = np.linalg.inv(res.transformation)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(transform_points(T, model_points)).query(cluster, workers=-1)
    return ModelFit(np.asarray(T), float(res.fitness), float(res.inlier_rmse), float(np.minimum(d, 5.0).mean()))


def _better(a: ModelFit, b: ModelFit | None) -> bool:
    """A truncated mean distance tells the turns of a nearly symmetric body apart: a handle or a
    spout in the wrong place leaves cluster points ~5 mm from the model, where ICP's fitness at
    its finest distance is dominated by the surface noise."""
    return b is None or a.score < b.score


def fit_model(model_points: np.ndarray, cluster: np.ndarray, cfg: ModelFitConfig = ModelFitConfig(),
              up: np.ndarray | None = None, model_z_min: float | None = None,
              table_plane: np.ndarray | None = None, init: np.ndarray | None = None) -> ModelFit:
    """Pose of a model (surface samples (N,3), model frame) in a cluster (M,3) of the scene.

    With ``up`` (the table normal) the object is taken to stand upright on the table, as on the
    rig: the model's z goes along ``up`` and 12 turns about it are each refined by ICP (a handle or a
    spout decides between them; FPFH matching alone confuses the turns of a nearly symmetric
    body). Without it, FPFH + RANSAC global registration gives the start."""
    if init is not None:
        return _icp(model_points, cluster, np.asarray(init, float), cfg)
    if up is not None:
        up = np.asarray(up, float) / np.linalg.norm(up)
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(z, up)
        ang = np.arccos(np.clip(z @ up, -1, 1))
        R_up = rotation_matrix(axis, ang) if np.linalg.norm(axis) > 1e-9 else (np.eye(3) if ang < 1 else np.diag([1, -1, -1.0]))
        c = cluster.mean(axis=0)
        c_h = c - (c @ up) * up  # horizontal part of the cluster centre
        if table_plane is not None and model_z_min is not None:
            base = -table_plane[3] * table_plane[:3] / np.linalg.norm(table_plane[:3]) ** 2  # a point on the plane
            height = (base @ up) - model_z_min
        else:
            height = c @ up
        best = None
        clouds = (_cloud(model_points, cfg.icp_mm[-1]), _cloud(cluster, cfg.icp_mm[-1]))  # one pair for the 12 turns
        for yaw in np.radians(np.arange(0, 360, 30)):
            R = R_up @ rotation_matrix(z, yaw)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = c_h + height * up
            fit = _icp(model_points, cluster, T, cfg, clouds)
            if _better(fit, best):
                best = fit
        return best
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(cfg.seed)
    src = _cloud(model_points, cfg.voxel_mm)
    dst = _cloud(cluster, cfg.voxel_mm)
    feat = o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.voxel_mm * 5, max_nn=100)
    res = reg.registration_ransac_based_on_feature_matching(
        src, dst, reg.compute_fpfh_feature(src, feat), reg.compute_fpfh_feature(dst, feat), True,
        cfg.voxel_mm * 1.5, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(cfg.voxel_mm * 1.5)],
        reg.RANSACConvergenceCriteria(cfg.ransac_iters, 0.999))
    return _icp(model_points, cluster, res.transformation, cfg)


def place_in_frames(T_ref_model: np.ndarray, T_ref_frames: dict) -> dict:
    """T_frame_model for every frame from the model's pose in the reference frame."""
    return {k: np.linalg.inv(T) @ T_ref_model for k, T in T_ref_frames.items()}
