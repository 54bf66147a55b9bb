"""Ray casting of posed object models (open3d RaycastingScene): the exact z-buffer behind the
simulator's truth and the annotation's labels.

Each model's scene is built once in its model frame; per frame the rays move into the model
frame instead of rebuilding anything, and only the pixels inside the projected convex hull of the
model are cast. The work of a frame stays inside the box around the objects' projected hulls
(:meth:`ModelRaycaster.render_box`; the label stage works on that box, and
:meth:`ModelRaycaster.render` pastes it into whole images): the same rays, hits and depths as
casting over the whole image, without the passes over all of its pixels.
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


@dataclass
class BoxRender:
    """:class:`LabelRender` of one frame cut to the box ``(v0, v1, u0, u1)`` (rows v0..v1-1,
    columns u0..u1-1) outside which no instance is seen: the arrays are (v1-v0, u1-u0). The box
    keeps a margin of at least 2 pixels that no instance covers on every side that is not the
    image's border (so a 3x3 erosion inside the box equals one over the whole image)."""

    box: tuple[int, int, int, int]
    shape: tuple[int, int]      # (H, W) of the whole image
    full: list[np.ndarray]
    visible: np.ndarray
    depth: np.ndarray

    def whole(self) -> LabelRender:
        """The same labels as whole (H,W) images."""
        h, w = self.shape
        v0, v1, u0, u1 = self.box
        full = []
        for m in self.full:
            f = np.zeros((h, w), bool)
            f[v0:v1, u0:u1] = m
            full.append(f)
        vis = np.full((h, w), -1, np.int16)
        vis[v0:v1, u0:u1] = self.visible
        depth = np.zeros((h, w), np.float32)
        depth[v0:v1, u0:u1] = self.depth
        return LabelRender(full, vis, depth)


def _hull_polygon(camera: PinholeCamera, T: np.ndarray, hull: np.ndarray) -> np.ndarray | None:
    """The projected convex hull (cv2 polygon, integer pixels) of a posed hull; None when the hull
    reaches behind the camera."""
    pc = transform_points(T, hull)
    if np.any(pc[:, 2] <= 1.0):
        return None
    uv, _ = camera.project(pc)
    return cv2.convexHull(np.rint(uv).astype(np.int32))


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
        return self.render_box(poses).whole()

    def render_box(self, poses: list[tuple[int, np.ndarray]], margin: int = 2) -> BoxRender:
        """:meth:`render` inside the box around the posed hulls' projections (grown by ``margin``,
        >= 2, and clipped to the image): per instance, the pixels of its hull's filled projection
        and outline (as :func:`hull_roi` draws them) are cast, the nearest hit wins."""
        h, w = self.camera.height, self.camera.width
        polys = []
        for obj_id, T in poses:
            if obj_id not in self._scenes:
                raise TdofError(f"no model for object {obj_id}")
            polys.append(_hull_polygon(self.camera, T, self._hulls[obj_id]))
        margin = max(2, int(margin))
        if any(p is None for p in polys):
            v0, v1, u0, u1 = 0, h, 0, w          # a hull behind the camera: every pixel
        else:
            pts = np.concatenate([p.reshape(-1, 2) for p in polys]) if polys else np.zeros((0, 2), int)
            if len(pts):
                # the outline is 2 px thick: it reaches 1 px past the polygon; 2 more of margin
                lo, hi = pts.min(0) - 1 - margin, pts.max(0) + 2 + margin
                u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
                u1, v1 = min(int(hi[0]), w), min(int(hi[1]), h)
            if not len(pts) or u1 <= u0 or v1 <= v0:
                v0 = v1 = u0 = u1 = 0
        bh, bw = v1 - v0, u1 - u0
        zbuf = np.full(bh * bw, np.inf, np.float32)
        vis = np.full(bh * bw, -1, np.int16)
        full = []
        if bh and bw:
            rays_box = self._rays.reshape(h, w, 3)[v0:v1, u0:u1].reshape(-1, 3)
        for i, ((obj_id, T), poly) in enumerate(zip(poses, polys)):
            m = np.zeros(bh * bw, bool)
            if bh and bw:
                roi = np.zeros((bh, bw), np.uint8)
                if poly is None:
                    roi[:] = 1
                else:
                    local = poly - np.array([u0, v0], np.int32)
                    cv2.fillConvexPoly(roi, local, 1)
                    cv2.polylines(roi, [local], True, 1, 2)
                idx = np.flatnonzero(roi)
                T_obj_cam = invert(T)
                rays = np.empty((len(idx), 6), np.float32)
                rays[:, :3] = T_obj_cam[:3, 3]
                rays[:, 3:] = rays_box[idx] @ T_obj_cam[:3, :3].T.astype(np.float32)
                t = self._scenes[obj_id].cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
                hit = np.isfinite(t)
                m[idx[hit]] = True
                near = hit & (t < zbuf[idx])
                zbuf[idx[near]] = t[near]  # rays have z = 1: t is the depth along the optical axis
                vis[idx[near]] = i
            full.append(m.reshape(bh, bw))
        depth = np.where(np.isfinite(zbuf), zbuf, 0).astype(np.float32).reshape(bh, bw)
        return BoxRender((v0, v1, u0, u1), (h, w), full, vis.reshape(bh, bw), depth)
