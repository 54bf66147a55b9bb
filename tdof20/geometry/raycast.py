"""Ray casting of posed object models (open3d RaycastingScene): the exact z-buffer behind the
simulator's truth and the annotation's labels.

Each model's scene is built once in its model frame; per frame the rays move into the model
frame instead of rebuilding anything, and only the pixels inside the projected convex hull of the
model are cast.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from tdof20.errors import TdofError
from tdof20.geometry.camera import PinholeCamera
from tdof20.geometry.transforms import invert, transform_points
from tdof20.o3d import o3d


def convex_hull_points(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Vertices (M,3) of the convex hull of a mesh."""
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).convex_hull.vertices)


def hull_roi(camera: PinholeCamera, poses: list[np.ndarray], hulls: list[np.ndarray],
             margin: int = 2) -> tuple[np.ndarray, tuple | None]:
    """(mask (H,W) bool, box) of the pixels whose rays can meet one of the posed convex hulls:
    their filled projections grown by a pixel, and the bounding box (v0, v1, u0, u1) grown by
    ``margin`` (None when empty). Everything when a hull reaches behind the camera."""
    h, w = camera.height, camera.width
    roi = np.zeros((h, w), np.uint8)
    lo, hi = np.array([np.inf, np.inf]), np.array([-np.inf, -np.inf])
    for T, hull in zip(poses, hulls):
        pc = transform_points(T, hull)
        if np.any(pc[:, 2] <= 1.0):
            return np.ones((h, w), bool), (0, h, 0, w)
        uv, _ = camera.project(pc)
        pts = cv2.convexHull(np.rint(uv).astype(np.int32))
        cv2.fillConvexPoly(roi, pts, 1)
        cv2.polylines(roi, [pts], True, 1, 2)
        lo, hi = np.minimum(lo, pts.reshape(-1, 2).min(0)), np.maximum(hi, pts.reshape(-1, 2).max(0))
    u0, v0 = np.maximum(lo - margin, 0).astype(int) if np.all(np.isfinite(lo)) else (0, 0)
    u1, v1 = np.minimum(hi + margin + 1, [w, h]).astype(int) if np.all(np.isfinite(hi)) else (0, 0)
    box = (int(v0), int(v1), int(u0), int(u1)) if (v1 > v0 and u1 > u0) else None
    return roi.astype(bool), box


@dataclass
class LabelRender:
    """Labels of one frame for instances 0..n-1 (the order of the poses given)."""

    full: list[np.ndarray]      # (H,W) bool per instance: the unoccluded silhouette
    visible: np.ndarray         # (H,W) int16: instance seen at each pixel, -1 = none
    depth: np.ndarray           # (H,W) float32 mm: depth of the nearest model surface, 0 = none

    def visible_mask(self, i: int) -> np.ndarray:
        return self.visible == i


class ModelRaycaster:
    """Renders labels of posed object models for one camera.

    ``models``: {obj_id: (vertices (V,3) mm, faces (F,3))} in each model's frame."""

    def __init__(self, models: dict[int, tuple[np.ndarray, np.ndarray]], camera: PinholeCamera):
        self.camera = camera
        self._rays = camera.pixel_rays().reshape(-1, 3).astype(np.float32)
        self._scenes, self._hulls = {}, {}
        for obj_id, (v, f) in models.items():
            sc = o3d.t.geometry.RaycastingScene()
            sc.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
            self._scenes[int(obj_id)] = sc
            self._hulls[int(obj_id)] = convex_hull_points(v, f)

    def render(self, poses: list[tuple[int, np.ndarray]]) -> LabelRender:
        """poses: [(obj_id, T_cam_obj (4,4) mm)] -> full masks, visible instance labels, model depth."""
        h, w = self.camera.height, self.camera.width
        zbuf = np.full(h * w, np.inf, np.float32)
        vis = np.full(h * w, -1, np.int16)
        full = []
        for i, (obj_id, T) in enumerate(poses):
            if obj_id not in self._scenes:
                raise TdofError(f"no model for object {obj_id}")
            idx = np.flatnonzero(hull_roi(self.camera, [T], [self._hulls[obj_id]])[0])
            T_obj_cam = invert(T)
            rays = np.empty((len(idx), 6), np.float32)
            rays[:, :3] = T_obj_cam[:3, 3]
            rays[:, 3:] = self._rays[idx] @ T_obj_cam[:3, :3].T.astype(np.float32)
            t = self._scenes[obj_id].cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            hit = np.isfinite(t)
            m = np.zeros(h * w, bool)
            m[idx[hit]] = True
            full.append(m.reshape(h, w))
            near = hit & (t < zbuf[idx])
            zbuf[idx[near]] = t[near]  # rays have z = 1: t is the depth along the optical axis
            vis[idx[near]] = i
        depth = np.where(np.isfinite(zbuf), zbuf, 0).astype(np.float32).reshape(h, w)
        return LabelRender(full, vis.reshape(h, w), depth)
