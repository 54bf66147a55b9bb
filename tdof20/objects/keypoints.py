"""The one keypoint definition of the project (torch-free): K = 9 points of an object model.

    kp = surface_keypoints(vertices, faces)      # (9,3) mm: bbox centre, then 8 FPS surface points

The paper's and PVNet's choice: the centre of the model's bounding box first, then K-1 points of
the surface picked by farthest point sampling from ``KEYPOINT_SAMPLES`` area-uniform Monte-Carlo
samples (seed ``KEYPOINT_SEED``). The catalog, the model builder of the annotation and every method
use this function, so the keypoints written beside a model are the ones any loader recomputes
from its PLY. A dataset that brings its own keypoints (the released TDoF20's farthest/ files)
overrides them.
"""

from __future__ import annotations

import numpy as np

from tdof20.geometry.sampling import farthest_point_sampling, sample_mesh_surface

N_KEYPOINTS = 9
KEYPOINT_SAMPLES = 10000
KEYPOINT_SEED = 0


def surface_keypoints(vertices: np.ndarray, faces: np.ndarray, k: int = N_KEYPOINTS,
                      n_samples: int = KEYPOINT_SAMPLES, seed: int = KEYPOINT_SEED) -> np.ndarray:
    """(k,3): the centre of the bounding box of ``vertices``, then k-1 farthest-point samples of
    ``n_samples`` area-uniform samples of the mesh surface. Deterministic in ``seed``."""
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if k < 1:
        raise ValueError("k must be >= 1")
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
    if k == 1:
        return centre[None].copy()
    samples = sample_mesh_surface(V, np.asarray(faces), max(int(n_samples), k), seed)
    return farthest_point_sampling(samples, k, first=centre)
