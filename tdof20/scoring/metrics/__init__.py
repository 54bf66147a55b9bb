"""Pose-error metrics: tiny pure reference functions, and the fast kernels the scorer uses.

Conventions: lengths in mm, poses map model -> camera (``x = R @ p + t``), ``pts`` (N,3) are the
model points (BOP: the vertices of models_eval/, else of models/), ``K`` (3,3) the intrinsics.

One module per concept (each states its derivations); every public name is re-exported here, so
``from tdof20.scoring import metrics as M; M.add(...)`` reaches all of them:

* :mod:`~tdof20.scoring.metrics.reference`: the paper's errors, one pose or a batch of poses
  (``add``, ``adds``, ``proj2d`` and their ``_batch`` forms, ``relative_transform``).
* :mod:`~tdof20.scoring.metrics.model_points`: :class:`ModelPoints`, one object's points and what
  the fast kernels precompute from them (clusters, a distance grid, point trees), and
  :class:`Bounds`, the per-pose intervals they return.
* :mod:`~tdof20.scoring.metrics.kernels`: fast ADD, 2D projection and ADD-S of many poses, exact
  near the thresholds, with rigorous bounds (and a control variate for ADD-S values).
* :mod:`~tdof20.scoring.metrics.vsd`: BOP19's VSD, from full-frame depths or rendered only inside
  each pose's footprint, and its :class:`DepthRenderer`.
* :mod:`~tdof20.scoring.metrics.mssd_mspd`: BOP19's MSSD and MSPD, the symmetries they minimise
  over, and their exact branch and bound.
"""

from tdof20.scoring.metrics.kernels import (add_fast, add_fast_with_error, adds_cluster_bounds, adds_cv_residuals,
                                            adds_decide, adds_exact, adds_point_bounds, proj2d_bounds, proj2d_fast)
from tdof20.scoring.metrics.model_points import (Bounds, Clusters, DistanceGrid, ModelPoints, PointTree, TreeLevel,
                                                 make_clusters, make_grid, make_point_tree)
from tdof20.scoring.metrics.mssd_mspd import (MAX_SYM_DISC_STEP, MSPD_THRESHOLDS, MSPD_WIDTH, MSSD_THRESHOLDS, mspd,
                                              mspd_fast, mssd, mssd_fast, project_points, rotation_about,
                                              symmetry_transformations)
from tdof20.scoring.metrics.reference import (add, add_batch, adds, adds_batch, proj2d, proj2d_batch,
                                              relative_transform)
from tdof20.scoring.metrics.vsd import (VSD_DELTA, VSD_TAUS, VSD_THRESHOLDS, DepthRenderer, Rasters, VisibleGt,
                                        depth_buffer, distance_image, ray_norms, visible_gt, vsd_batch, vsd_estimates,
                                        vsd_from_depths)

__all__ = [
    "add", "adds", "proj2d", "add_batch", "adds_batch", "proj2d_batch", "relative_transform",
    "Clusters", "make_clusters", "DistanceGrid", "make_grid", "ModelPoints", "Bounds",
    "add_fast", "add_fast_with_error", "proj2d_fast", "proj2d_bounds", "adds_cluster_bounds", "adds_point_bounds",
    "adds_decide", "adds_exact",
    "adds_cv_residuals",
    "VSD_DELTA", "VSD_TAUS", "VSD_THRESHOLDS", "MSSD_THRESHOLDS", "MSPD_THRESHOLDS", "MSPD_WIDTH",
    "MAX_SYM_DISC_STEP", "rotation_about", "symmetry_transformations", "project_points", "mssd", "mspd",
    "ray_norms", "distance_image", "depth_buffer", "vsd_from_depths", "DepthRenderer", "vsd_batch", "Rasters", "VisibleGt", "visible_gt",
    "vsd_estimates", "TreeLevel", "PointTree",
    "make_point_tree", "mssd_fast", "mspd_fast",
]
