"""Ray-cast renderer of the simulated rig (open3d RaycastingScene, CPU).

Three kinds of ray-casting scenes, each built once:
- ``world``: the static room in the robot base frame, with the turntable body. The turntable is a
  disk, so its geometry does not change as it turns; only its sticker does, and the sticker is
  looked up at rotated table coordinates. The world hits of the primary rays are therefore
  cached per arm position.
- ``objects``: the scene's objects posed in the table frame; per frame the rays are moved into the
  table frame instead of rebuilding the scene, and only pixels whose ray can meet an object
  (the projected bounding boxes) are cast.
- one scene per object in its model frame, for the full (unoccluded) truth masks.

Two phases share every pose: ``transparent`` (glass: refraction of the background, Fresnel rims,
specular highlights; depth mostly missing, partly the background's, flying pixels at the rims)
and ``opaque`` (diffuse twins; stereo noise growing with z^2 and holes at discontinuities).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from tdof20.geometry import PinholeCamera, invert, transform_points
from tdof20.o3d import o3d
from tdof20.objects import get_object
from tdof20.sim.rig import RigLayout
from tdof20.sim.scenes import SceneSpec
from tdof20.sim.sensor import (SensorModel, depth_edges, smooth_field, stereo_depth, stereo_holes,
                               stereo_occlusion)
from tdof20.sim.textures import make_sticker, room_albedo

PHASES = ("transparent", "opaque")
LIGHT_DIR = np.array([-0.45, 0.35, 1.0]) / np.linalg.norm([-0.45, 0.35, 1.0])  # towards the light, base frame
AMBIENT = 0.38


@dataclass(frozen=True)
class GlassModel:
    """Look of the transparent phase (options)."""

    ior: float = 1.5            # index of refraction of the glass
    refraction: float = 0.6     # 0 = straight through, 1 = full single-surface refraction bend
    tint: tuple = (0.93, 0.97, 0.95)
    absorption: float = 0.10    # darkening that grows with the path through the glass (1 / cos)
    fresnel_f0: float = 0.04    # Schlick reflectance at normal incidence
    specular: float = 1.6       # Blinn-Phong highlight strength
    shininess: float = 90.0


@dataclass
class Frame:
    """One rendered RGB-D pair and its exact ground truth."""

    rgb: np.ndarray                 # (H,W,3) uint8
    depth: np.ndarray               # (H,W) uint16, camera.depth_scale mm per unit, 0 = no depth
    label: np.ndarray               # (H,W) int16: index of the visible object (placement order), -1 = none
    poses: list[np.ndarray]         # T_cam_obj (4,4) per placement
    depth_true: np.ndarray = field(repr=False, default=None)  # (H,W) float32 mm, noise-free, opaque objects


def _twin_colour(obj_id: int) -> np.ndarray:
    """Matte colour of an object's opaque twin (painted, like a 3D print)."""
    rng = np.random.default_rng(500 + obj_id)
    hsv = np.array([[[rng.uniform(0, 180), rng.uniform(40, 140), rng.uniform(170, 235)]]], np.uint8)
    return (cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255.0).astype(np.float32)


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


class SimRenderer:
    """Renders frames of one scene as seen from the arm positions of a session.

    ``T_base_cams``: camera pose per arm position (base frame, mm). Use :meth:`render`.
    """

    def __init__(self, scene: SceneSpec, camera: PinholeCamera, layout: RigLayout,
                 T_base_cams: list[np.ndarray], sensor: SensorModel | None = None,
                 glass: GlassModel | None = None, seed: int = 0):
        self.scene = scene
        self.camera = camera
        self.layout = layout
        self.T_base_cams = [np.asarray(T, float) for T in T_base_cams]
        self.sensor = (sensor or SensorModel()).validate()
        self.glass = glass or GlassModel()
        self.seed = int(seed)
        self.objects = [get_object(p.obj_id) for p in scene.placements]
        self._rays_cam = camera.pixel_rays().reshape(-1, 3).astype(np.float32)
        self._build_world()
        self._build_objects()
        sticker, self.sticker_mm_px = make_sticker(scene.sticker, scene.sticker_seed, layout.table_radius, 768)
        self.sticker = np.clip(sticker * 255 + 0.5, 0, 255).astype(np.uint8)
        self._bg_cache: dict[int, dict] = {}
        rng = np.random.default_rng([self.seed, 99])
        h, w = camera.height, camera.width
        self._pad = 32
        self._noise_rgb = rng.standard_normal((h + self._pad, w + self._pad, 3), dtype=np.float32)
        self._noise_depth = rng.standard_normal((h + self._pad, w + self._pad), dtype=np.float32)
        self._uniform = rng.random((h + self._pad, w + self._pad), dtype=np.float32)

    # ------------------------------------------------------------------ scene building
    def _build_world(self) -> None:
        L = self.layout
        cx, cy, cz = L.table_centre
        R, th = L.table_radius, L.table_thickness
        parts: list[tuple[trimesh.Trimesh, str]] = []
        top = trimesh.creation.cylinder(radius=R, height=th, sections=160)
        top.apply_translation([cx, cy, cz - th / 2])
        parts.append((top, "turntable"))
        bench_z = cz - th
        parts.append((_box([cx - 550, cy - 700, bench_z - 30], [cx + 650, cy + 700, bench_z]), "wood"))
        parts.append((_box([cx - 500, cy - 650, -900], [cx + 600, cy + 650, bench_z - 30]), "dark"))
        room_lo, room_hi = np.array([-1500.0, -1800.0, -900.0]), np.array([2100.0, 1800.0, 1500.0])
        room = _box(room_lo, room_hi)
        parts.append((trimesh.Trimesh(room.vertices, room.faces[:, ::-1]), "room"))
        parts.append((_box([1700, -1150, -900], [2080, -420, 300]), "wood"))
        parts.append((_box([1750, 500, -900], [2080, 1300, -150]), "metal"))
        scene = o3d.t.geometry.RaycastingScene()
        self._world_material = []
        for mesh, mat in parts:
            scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
            self._world_material.append(mat)
        self._world = scene

    def _build_objects(self) -> None:
        self._objects = o3d.t.geometry.RaycastingScene()
        self._obj_faces, self._obj_vnormals = [], []
        self._model_scenes = []
        for p, obj in zip(self.scene.placements, self.objects):
            v_table = transform_points(p.T_table_obj, obj.vertices).astype(np.float32)
            faces = np.asarray(obj.faces, np.int32)
            self._objects.add_triangles(o3d.core.Tensor(v_table), o3d.core.Tensor(faces.astype(np.uint32)))
            vn = trimesh.Trimesh(obj.vertices, obj.faces, process=False).vertex_normals
            self._obj_faces.append(faces)
            self._obj_vnormals.append((vn @ p.T_table_obj[:3, :3].T).astype(np.float32))
            ms = o3d.t.geometry.RaycastingScene()
            ms.add_triangles(o3d.core.Tensor(obj.vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
            self._model_scenes.append(ms)
        sizes_v = [len(v) for v in self._obj_vnormals]
        v_off = np.concatenate([[0], np.cumsum(sizes_v)[:-1]]).astype(np.int64)
        self._faces_all = np.concatenate([f.astype(np.int64) + o for f, o in zip(self._obj_faces, v_off)])
        self._face_offset = np.concatenate([[0], np.cumsum([len(f) for f in self._obj_faces])[:-1]]).astype(np.int64)
        self._vnormals_all = np.concatenate(self._obj_vnormals)
        self._hulls = [np.asarray(trimesh.Trimesh(o.vertices, o.faces, process=False).convex_hull.vertices)
                       for o in self.objects]


    # ------------------------------------------------------------------ helpers
    def _cast(self, scene, origin: np.ndarray, dirs: np.ndarray) -> dict:
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        res = scene.cast_rays(o3d.core.Tensor(rays))
        return {k: v.numpy() for k, v in res.items()}

    def _sticker_maps(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Table-top points (N,2) mm, world-aligned, relative to the table centre -> their sticker
        pixel coordinates relative to the sticker centre at angle 0, as two (rows, 1024) arrays
        (cv2.remap needs maps shorter than 32767 in each dimension), and N."""
        mm = self.sticker_mm_px
        n = len(xy)
        cols = 1024
        rows = max(1, -(-n // cols))
        dx = np.zeros(rows * cols, np.float32)
        dy = np.zeros(rows * cols, np.float32)
        dx[:n] = xy[:, 0] / mm
        dy[:n] = -xy[:, 1] / mm
        return dx.reshape(rows, cols), dy.reshape(rows, cols), n

    def _sample_sticker(self, xy: np.ndarray | None, angle_deg: float, maps=None) -> np.ndarray:
        """Sticker albedo (N,3) float32 at table-top points (N,2) once the table has turned by
        ``angle_deg`` counter-clockwise: the points are rotated back by the angle into the sticker."""
        dx, dy, n = maps if maps is not None else self._sticker_maps(xy)
        a = np.radians(angle_deg)
        c, s_ = np.float32(np.cos(a)), np.float32(np.sin(a))
        centre = np.float32((self.sticker.shape[0] - 1) / 2.0)
        # image axes: x right = table x, y down = -table y; Rz(-a) in those axes
        mx = c * dx - s_ * dy + centre
        my = s_ * dx + c * dy + centre
        out = cv2.remap(self.sticker, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return out.reshape(-1, 3)[:n].astype(np.float32) * np.float32(1 / 255)

    def _world_colour(self, points: np.ndarray, normals: np.ndarray, gids: np.ndarray, dirs: np.ndarray,
                      angle_deg: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World hits (N) -> (albedo (N,3), Lambert shade (N,), on-sticker (N,) bool).
        The sticker albedo is looked up only when ``angle_deg`` is given (else left black)."""
        n = np.where((np.sum(normals * dirs, axis=1) > 0)[:, None], -normals, normals)
        shade = (AMBIENT + (1 - AMBIENT) * np.clip(n @ LIGHT_DIR, 0, 1)).astype(np.float32)
        albedo = np.zeros((len(points), 3), np.float32)
        cz = self.layout.table_centre[2]
        is_top = np.zeros(len(points), bool)
        for gid, mat in enumerate(self._world_material):
            sel = gids == gid
            if not sel.any():
                continue
            if mat == "turntable":
                top = sel & (np.abs(points[:, 2] - cz) < 0.5)
                albedo[sel & ~top] = 0.12
                is_top |= top
            elif mat == "room":
                albedo[sel] = self._room_surface(points[sel])
            else:
                albedo[sel] = room_albedo(mat, points[sel])
        if angle_deg is not None and is_top.any():
            xy = points[is_top, :2] - np.asarray(self.layout.table_centre[:2])
            albedo[is_top] = self._sample_sticker(xy, angle_deg)
        return albedo, shade, is_top

    def _room_surface(self, p: np.ndarray) -> np.ndarray:
        floor = p[:, 2] < -899.0
        out = room_albedo("wall", p)
        if floor.any():
            out[floor] = room_albedo("floor", p[floor])
        return out

    def _background(self, arm: int) -> dict:
        """World hits of the primary rays of one arm position (cached)."""
        if arm in self._bg_cache:
            return self._bg_cache[arm]
        T = self.T_base_cams[arm]
        dirs = (self._rays_cam @ T[:3, :3].T).astype(np.float32)
        hit = self._cast(self._world, T[:3, 3], dirs)
        z = hit["t_hit"].astype(np.float32)
        points = T[:3, 3] + dirs * z[:, None]
        albedo, shade, top = self._world_colour(points, hit["primitive_normals"], hit["geometry_ids"], dirs, None)
        colour = albedo * shade[:, None]
        h, w = self.camera.height, self.camera.width
        xy = (points[:, :2] - np.asarray(self.layout.table_centre[:2])).astype(np.float32)
        top_idx = np.flatnonzero(top)
        occluded, edges = stereo_holes(z.reshape(h, w), self.camera.fx, self.sensor)
        bg = {"z": z.reshape(h, w), "colour": colour.reshape(h, w, 3).astype(np.float32),
              "top_idx": top_idx, "top_shade": shade[top_idx, None], "top_maps": self._sticker_maps(xy[top_idx]),
              "occluded": occluded, "edges": edges}
        self._bg_cache[arm] = bg
        return bg

    def poses(self, arm: int, angle_deg: float) -> list[np.ndarray]:
        """T_cam_obj (4,4) of every placement at arm position ``arm`` and table angle ``angle_deg``."""
        T_cam_table = invert(self.T_base_cams[arm]) @ self.layout.T_base_table(angle_deg)
        return [T_cam_table @ p.T_table_obj for p in self.scene.placements]

    def _roi(self, poses: list[np.ndarray], hulls: list[np.ndarray] | None = None) -> np.ndarray:
        """Pixel mask (H,W) where a ray can meet one of the objects: the filled projections of
        their convex hulls, grown by a pixel. Everything when an object reaches behind the camera."""
        roi = np.zeros((self.camera.height, self.camera.width), np.uint8)
        for T, hull in zip(poses, hulls if hulls is not None else self._hulls):
            pc = transform_points(T, hull)
            if np.any(pc[:, 2] <= 1.0):
                return np.ones(roi.shape, bool)
            uv, _ = self.camera.project(pc)
            pts = cv2.convexHull(np.rint(uv).astype(np.int32))
            cv2.fillConvexPoly(roi, pts, 1)
            cv2.polylines(roi, [pts], True, 1, 2)
        return roi.astype(bool)

    # ------------------------------------------------------------------ rendering
    def frame_rng(self, phase: str, arm: int, step: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, PHASES.index(phase), arm, step])

    def render(self, arm: int, step: int, angle_deg: float, phase: str) -> Frame:
        """Render the RGB-D pair of ``phase`` at arm position ``arm``, table step ``step`` (seeds the
        noise) and table angle ``angle_deg``. Deterministic for (seed, phase, arm, step)."""
        if phase not in PHASES:
            raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
        cam = self.camera
        h, w = cam.height, cam.width
        rng = self.frame_rng(phase, arm, step)
        bg = self._background(arm)
        poses = self.poses(arm, angle_deg)
        T_base_cam = self.T_base_cams[arm]
        T_table_cam = invert(self.layout.T_base_table(angle_deg)) @ T_base_cam
        R_cam_table = T_table_cam[:3, :3].T

        roi2d = self._roi(poses)
        idx = np.flatnonzero(roi2d)
        rays_cam = self._rays_cam[idx]
        hit = self._cast(self._objects, T_table_cam[:3, 3], rays_cam @ T_table_cam[:3, :3].T.astype(np.float32))
        z_obj_roi = hit["t_hit"].astype(np.float32)
        z_bg = bg["z"].reshape(-1)
        vis_roi = np.isfinite(z_obj_roi) & (z_obj_roi < z_bg[idx])
        label = np.full(h * w, -1, np.int16)
        label[idx[vis_roi]] = hit["geometry_ids"][vis_roi].astype(np.int16)
        z_obj = np.full(h * w, np.inf, np.float32)
        z_obj[idx[vis_roi]] = z_obj_roi[vis_roi]

        # background colour: static room + the sticker at this table angle
        colour = bg["colour"].copy().reshape(-1, 3)
        if len(bg["top_idx"]):
            colour[bg["top_idx"]] = self._sample_sticker(None, angle_deg, bg["top_maps"]) * bg["top_shade"]

        vi = idx[vis_roi]  # flat pixel indices of visible object pixels
        if len(vi):
            gid = hit["geometry_ids"][vis_roi]
            n_table = self._interp_normals(gid, hit["primitive_ids"][vis_roi], hit["primitive_uvs"][vis_roi])
            n_cam = n_table @ R_cam_table.T
            d_cam = rays_cam[vis_roi] / np.linalg.norm(rays_cam[vis_roi], axis=1, keepdims=True)
            n_cam = np.where((np.sum(n_cam * d_cam, axis=1) > 0)[:, None], -n_cam, n_cam)
            L_cam = T_base_cam[:3, :3].T @ LIGHT_DIR
            if phase == "opaque":
                albedo = np.stack([_twin_colour(self.objects[g].obj_id) for g in range(len(self.objects))])[gid]
                lam = AMBIENT + (1 - AMBIENT) * np.clip(n_cam @ L_cam, 0, 1)
                hvec = L_cam[None, :] - d_cam
                hvec /= np.linalg.norm(hvec, axis=1, keepdims=True)
                spec = 0.12 * np.clip(np.sum(n_cam * hvec, axis=1), 0, 1) ** 20
                colour[vi] = albedo * lam[:, None] + spec[:, None]
            else:
                colour[vi] = self._glass_colour(vi, z_obj[vi], d_cam, n_cam, L_cam, T_base_cam,
                                                colour.reshape(h, w, 3).copy(), bg["z"])

        # RGB with sensor noise
        oy, ox = rng.integers(0, self._pad, 2)
        rgb = cv2.addWeighted(colour.reshape(h, w, 3), 255.0, self._noise_rgb[oy:oy + h, ox:ox + w],
                              self.sensor.rgb_sigma, 0.0, dtype=cv2.CV_8U)
        noise = self._noise_depth[oy:oy + h, ox:ox + w]
        uniform = self._uniform[oy:oy + h, ox:ox + w]

        # depth
        z_true = np.minimum(z_obj, z_bg).reshape(h, w)
        z_obj_img = z_obj.reshape(h, w)
        glass = (label >= 0).reshape(h, w)
        if phase == "opaque":
            z_sensor = stereo_depth(z_true, cam.fx, self.sensor, rng, noise, uniform,
                                    self._holes(z_true, bg, roi2d))
        else:
            z_sensor = self._glass_depth(z_obj_img, bg, glass, roi2d, rng, noise, uniform)
        depth = cam.mm_to_depth(z_sensor)
        return Frame(rgb, depth, label.reshape(h, w), poses, depth_true=z_true)

    def _interp_normals(self, gid: np.ndarray, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Smooth (barycentric) vertex normals at ray hits, table frame, (N,3) unit."""
        f = self._faces_all[self._face_offset[gid] + prim]  # (N,3) global vertex ids
        vn = self._vnormals_all
        u, v = uv[:, 0:1], uv[:, 1:2]
        n = (1 - u - v) * vn[f[:, 0]] + u * vn[f[:, 1]] + v * vn[f[:, 2]]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
        return n

    def _glass_colour(self, vi, z, d_cam, n_cam, L_cam, T_base_cam, background, z_bg):
        """Colour of glass pixels: the background seen along a refracted ray (screen-space: the
        bent ray is followed to the background depth and the background image is sampled
        there), tinted and darkened with path length, plus Fresnel reflection and highlights."""
        g = self.glass
        cam = self.camera
        cos_i = np.clip(-np.sum(d_cam * n_cam, axis=1), 1e-3, 1.0)
        eta = 1.0 / g.ior
        k = 1.0 - eta ** 2 * (1.0 - cos_i ** 2)
        refr = eta * d_cam + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * n_cam
        bent = d_cam + g.refraction * (refr - d_cam)
        p = self._rays_cam[vi] * z[:, None]
        bz = np.maximum(bent[:, 2], 0.05)
        zb = z_bg.reshape(-1)[vi]
        for _ in range(2):  # follow the bent ray to the background depth, twice to settle
            q = p + ((np.maximum(zb - p[:, 2], 0.0) / bz)[:, None]) * bent
            u = q[:, 0] / q[:, 2] * cam.fx + cam.cx
            v = q[:, 1] / q[:, 2] * cam.fy + cam.cy
            ui = np.clip(np.rint(u), 0, cam.width - 1).astype(np.int64)
            vv = np.clip(np.rint(v), 0, cam.height - 1).astype(np.int64)
            zb = np.minimum(z_bg[vv, ui], 1e5)
        n = len(vi)
        cols = 1024
        rows = max(1, -(-n // cols))
        mx = np.zeros(rows * cols, np.float32)
        my = np.zeros(rows * cols, np.float32)
        mx[:n], my[:n] = u, v
        seen = cv2.remap(background, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n]
        trans = np.exp(-g.absorption / cos_i)[:, None] * np.asarray(g.tint, np.float32)
        F = g.fresnel_f0 + (1 - g.fresnel_f0) * (1 - cos_i) ** 5
        refl_dir_z = (d_cam + 2 * cos_i[:, None] * n_cam) @ T_base_cam[2, :3]
        env = 0.55 + 0.4 * np.clip(refl_dir_z, -1, 1)
        hvec = L_cam[None, :] - d_cam
        hvec /= np.linalg.norm(hvec, axis=1, keepdims=True)
        spec = g.specular * np.clip(np.sum(n_cam * hvec, axis=1), 0, 1) ** g.shininess
        col = (1 - F)[:, None] * seen * trans + (F * env)[:, None] + spec[:, None]
        return np.clip(col, 0, 1)

    def _holes(self, z: np.ndarray, bg: dict, roi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stereo holes of ``z``, which equals the cached background outside ``roi``: the
        occlusions change only on the rows of the ROI, the edges only around its bounding box."""
        rows = np.flatnonzero(roi.any(axis=1))
        if not len(rows):
            return bg["occluded"], bg["edges"]
        colsnz = np.flatnonzero(roi.any(axis=0))
        h, w = z.shape
        v0, v1 = rows[0], rows[-1] + 1
        occluded = bg["occluded"].copy()
        occluded[v0:v1] = stereo_occlusion(z[v0:v1], self.camera.fx, self.sensor.baseline_mm)
        a0, a1 = max(v0 - 2, 0), min(v1 + 2, h)
        b0, b1 = max(colsnz[0] - 2, 0), min(colsnz[-1] + 3, w)
        edges = bg["edges"].copy()
        e = depth_edges(z[a0:a1, b0:b1], self.sensor.edge_jump)
        c0, c1 = max(v0 - 1, 0), min(v1 + 1, h)
        d0, d1 = max(colsnz[0] - 1, 0), min(colsnz[-1] + 2, w)
        edges[c0:c1, d0:d1] = e[c0 - a0:c1 - a0, d0 - b0:d1 - b0]
        return occluded, edges

    def _glass_depth(self, z_obj, bg, glass, roi, rng, noise, uniform):
        """Active stereo on glass: most glass pixels return nothing, some the background behind,
        the rest the glass surface with large noise; flying pixels at the silhouettes."""
        s = self.sensor
        z_bg = bg["z"]
        z = z_bg.copy()
        if glass.any():
            field_ = smooth_field(glass.shape, rng)
            fv = field_[glass]
            q1, q2 = np.quantile(fv, [s.glass_missing, min(1.0, s.glass_missing + s.glass_behind)])
            surface = z_obj[glass] + s.glass_sigma_mm * noise[glass][::-1]
            z[glass] = np.where(fv < q1, 0.0, np.where(fv < q2, z_bg[glass], surface))
        out = stereo_depth(z, self.camera.fx, s, rng, noise, uniform, self._holes(z, bg, roi))
        if glass.any() and s.rim_px > 0 and s.flying_fraction > 0:
            # work in the bounding box of the glass pixels grown by the rim width
            vs, us = np.nonzero(glass)
            m = s.rim_px + 1
            v0, v1 = max(vs.min() - m, 0), min(vs.max() + m + 1, glass.shape[0])
            u0, u1 = max(us.min() - m, 0), min(us.max() + m + 1, glass.shape[1])
            g8 = glass[v0:v1, u0:u1].astype(np.uint8)
            k = np.ones((2 * s.rim_px + 1, 2 * s.rim_px + 1), np.uint8)
            band = (cv2.dilate(g8, k) > 0) & (cv2.erode(g8, k) == 0)
            u_rand = uniform[v0:v1, u0:u1][::-1, ::-1]
            fly = band & (u_rand < s.flying_fraction)
            zf = cv2.erode(np.where(g8 > 0, z_obj[v0:v1, u0:u1], np.float32(1e9)).astype(np.float32), k)
            zb = z_bg[v0:v1, u0:u1]
            fly &= (zf < 1e9) & (zb > 0)
            wgt = u_rand[fly] / max(s.flying_fraction, 1e-6)
            sub = out[v0:v1, u0:u1]
            sub[fly] = wgt * zf[fly] + (1 - wgt) * zb[fly]
        return out

    def full_masks(self, poses: list[np.ndarray]) -> list[np.ndarray]:
        """Unoccluded silhouette (H,W) bool of every object at the given poses."""
        h, w = self.camera.height, self.camera.width
        out = []
        for T, hull, ms in zip(poses, self._hulls, self._model_scenes):
            idx = np.flatnonzero(self._roi([T], [hull]))
            T_obj_cam = invert(T)
            hit = self._cast(ms, T_obj_cam[:3, 3], self._rays_cam[idx] @ T_obj_cam[:3, :3].T.astype(np.float32))
            m = np.zeros(h * w, bool)
            m[idx[np.isfinite(hit["t_hit"])]] = True
            out.append(m.reshape(h, w))
        return out
