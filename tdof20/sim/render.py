"""Ray-cast renderer of the simulated rig (open3d RaycastingScene, CPU).

Three kinds of ray-casting scenes, each built once:
- ``world``: the static room in the robot base frame, with the turntable body and the lab's
  clutter (which does not turn, so it is cached like the room). The turntable is a
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

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from tdof20.geometry import PinholeCamera, invert, transform_points
from tdof20.geometry.raycast import ModelRaycaster, convex_hull_points, hull_roi
from tdof20.o3d import o3d
from tdof20.objects import get_object
from tdof20.sim.lab import clutter_parts
from tdof20.sim.rig import RigLayout
from tdof20.sim.scenes import SceneSpec
from tdof20.sim.sensor import (SensorModel, depth_edges, disparity_slack, smooth_field, stereo_depth,
                               stereo_holes, stereo_occlusion)
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

    ``T_base_cams``: camera pose per arm position (base frame, mm) — the true poses, which a
    session with a hand-eye error records differently. ``clutter``: names of static lab
    presets (:data:`tdof20.sim.lab.CLUTTER`) added to the room. Use :meth:`render`.
    """

    def __init__(self, scene: SceneSpec, camera: PinholeCamera, layout: RigLayout,
                 T_base_cams: list[np.ndarray], sensor: SensorModel | None = None,
                 glass: GlassModel | None = None, seed: int = 0, threads: bool = True,
                 clutter: tuple[str, ...] = (), twin_offsets: list[np.ndarray] | None = None):
        self.scene = scene
        self.clutter = tuple(clutter)
        self.camera = camera
        self.layout = layout
        self.T_base_cams = [np.asarray(T, float) for T in T_base_cams]
        self.sensor = (sensor or SensorModel()).validate()
        self.glass = glass or GlassModel()
        self.seed = int(seed)
        self.objects = [get_object(p.obj_id) for p in scene.placements]
        self._rays_cam = camera.pixel_rays().reshape(-1, 3).astype(np.float32)
        self._dirs_cam = self._rays_cam / np.linalg.norm(self._rays_cam, axis=1, keepdims=True)
        # the opaque twins' poses in the table frame: the transparent objects' own, or each moved by
        # its offset (T_table_twin = offset @ T_table_obj: a twin standing off its object's slot)
        self.T_table_twins = [p.T_table_obj if twin_offsets is None else np.asarray(D, float) @ p.T_table_obj
                              for p, D in zip(scene.placements, twin_offsets or [None] * len(scene.placements))]
        self._build_world()
        self._build_objects()
        self.sticker, self.sticker_mm_px = make_sticker(scene.sticker, scene.sticker_seed, layout.table_radius, 768)
        # the table top is a plane under a directional light: one Lambert factor for all of it
        self._sticker_lit = (self.sticker * (AMBIENT + (1 - AMBIENT) * max(LIGHT_DIR[2], 0.0))).astype(np.float32)
        self._bg_cache: dict[int, dict] = {}
        rng = np.random.default_rng([self.seed, 99])
        h, w = camera.height, camera.width
        self._pad = 32
        self._noise_rgb = rng.standard_normal((h + self._pad, w + self._pad, 3), dtype=np.float32)
        self._noise_depth = rng.standard_normal((h + self._pad, w + self._pad), dtype=np.float32)
        self._uniform = rng.random((h + self._pad, w + self._pad), dtype=np.float32)
        self._twin_albedo = np.stack([_twin_colour(o.obj_id) for o in self.objects])
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-depth") if threads else None

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
        parts += clutter_parts(self.clutter, L)  # the lab's static clutter (sim.lab), after the room
        scene = o3d.t.geometry.RaycastingScene()
        self._world_material = []
        for mesh, mat in parts:
            scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
            self._world_material.append(mat)
        self._world = scene

    def _build_objects(self) -> None:
        self._obj_faces = [np.asarray(obj.faces, np.int32) for obj in self.objects]
        self._face_offset = np.concatenate([[0], np.cumsum([len(f) for f in self._obj_faces])[:-1]]).astype(np.int64)
        vns = [trimesh.Trimesh(o.vertices, o.faces, process=False).vertex_normals for o in self.objects]
        self._phase_objects = {"transparent": self._object_scene([p.T_table_obj for p in self.scene.placements], vns)}
        twins_moved = any(not np.array_equal(T, p.T_table_obj) for T, p in zip(self.T_table_twins, self.scene.placements))
        self._phase_objects["opaque"] = (self._object_scene(self.T_table_twins, vns) if twins_moved
                                         else self._phase_objects["transparent"])
        self._hulls = [convex_hull_points(o.vertices, o.faces) for o in self.objects]
        self._models = ModelRaycaster({o.obj_id: (o.vertices, o.faces) for o in self.objects}, self.camera)

    def _object_scene(self, T_table_objs: list[np.ndarray], vns: list[np.ndarray]) -> tuple:
        """(ray-casting scene, (F, 9) vertex normals of every face, table frame) of the objects at
        the given table-frame poses."""
        scene = o3d.t.geometry.RaycastingScene()
        for T, obj, faces in zip(T_table_objs, self.objects, self._obj_faces):
            v_table = transform_points(T, obj.vertices).astype(np.float32)
            scene.add_triangles(o3d.core.Tensor(v_table), o3d.core.Tensor(faces.astype(np.uint32)))
        face_vn = np.concatenate([(vn @ T[:3, :3].T).astype(np.float32)[f].reshape(-1, 9)
                                  for T, f, vn in zip(T_table_objs, self._obj_faces, vns)])
        return scene, face_vn


    # ------------------------------------------------------------------ helpers
    def _cast(self, scene, origin: np.ndarray, dirs: np.ndarray) -> dict:
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        res = scene.cast_rays(o3d.core.Tensor(rays))
        return {k: v.numpy() for k, v in res.items()}

    def _sticker_maps(self, xy: np.ndarray, on_top: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Table-top points (..., 2) mm, world-aligned, relative to the table centre -> their
        sticker pixel offsets from the sticker centre at angle 0 (two float32 arrays). Points off
        the top get offsets so large that every rotation keeps them outside the sticker."""
        mm = self.sticker_mm_px
        dx = np.where(on_top, xy[..., 0] / mm, 1e7).astype(np.float32)
        dy = np.where(on_top, -xy[..., 1] / mm, 1e7).astype(np.float32)
        return dx, dy

    def _draw_sticker(self, dst: np.ndarray, maps: tuple[np.ndarray, np.ndarray], angle_deg: float) -> np.ndarray:
        """Draw the lit sticker, turned by ``angle_deg`` counter-clockwise, into ``dst`` (float32
        RGB, the same shape as the maps plus a channel axis) where the maps fall on it."""
        dx, dy = maps
        a = np.radians(angle_deg)
        c, s_ = float(np.cos(a)), float(np.sin(a))
        centre = (self._sticker_lit.shape[0] - 1) / 2.0
        # image axes: x right = table x, y down = -table y; rotate back by the angle (Rz(-a))
        mx = cv2.addWeighted(dx, c, dy, -s_, centre)
        my = cv2.addWeighted(dx, s_, dy, c, centre)
        cv2.remap(self._sticker_lit, mx, my, cv2.INTER_LINEAR, dst=dst, borderMode=cv2.BORDER_TRANSPARENT)
        return dst

    def _world_colour(self, points: np.ndarray, normals: np.ndarray, gids: np.ndarray,
                      dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World hits (N) -> (albedo (N,3), Lambert shade (N,), on-sticker (N,) bool); the
        sticker, which turns with the table, is left black (see :meth:`_draw_sticker`)."""
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
            elif callable(mat):  # clutter: its own albedo of base-frame points
                albedo[sel] = mat(points[sel])
            else:
                albedo[sel] = room_albedo(mat, points[sel])
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
        albedo, shade, top = self._world_colour(points, hit["primitive_normals"], hit["geometry_ids"], dirs)
        colour = albedo * shade[:, None]
        h, w = self.camera.height, self.camera.width
        xy = (points[:, :2] - np.asarray(self.layout.table_centre[:2])).astype(np.float32)
        occluded, edges = stereo_holes(z.reshape(h, w), self.camera.fx, self.sensor)
        bg = {"z": z.reshape(h, w), "colour": colour.reshape(h, w, 3).astype(np.float32),
              "sticker_maps": self._sticker_maps(xy.reshape(h, w, 2), top.reshape(h, w)),
              "occluded": occluded, "edges": edges,
              "slack_rmax": np.maximum.accumulate(disparity_slack(z.reshape(h, w), self.camera.fx,
                                                                  self.sensor.baseline_mm)[:, ::-1], axis=1)[:, ::-1]}
        self._bg_cache[arm] = bg
        return bg

    def poses(self, arm: int, angle_deg: float, phase: str = "transparent") -> list[np.ndarray]:
        """T_cam_obj (4,4) of every placement at arm position ``arm`` and table angle ``angle_deg``
        (``phase`` opaque: the twins', which may stand off their objects' slots)."""
        T_cam_table = invert(self.T_base_cams[arm]) @ self.layout.T_base_table(angle_deg)
        if phase == "opaque":
            return [T_cam_table @ T for T in self.T_table_twins]
        return [T_cam_table @ p.T_table_obj for p in self.scene.placements]

    def _roi(self, poses: list[np.ndarray]) -> tuple[np.ndarray, tuple]:
        """(mask, box) of the pixels whose rays can meet an object (see geometry.raycast.hull_roi);
        the box leaves room for the flying-pixel band."""
        return hull_roi(self.camera, poses, self._hulls, margin=max(2, self.sensor.rim_px + 1))

    # ------------------------------------------------------------------ rendering
    def frame_rng(self, phase: str, arm: int, angle_deg: float) -> np.random.Generator:
        """The noise of a frame depends on the seed, the phase, the arm position and the table
        angle (in millidegrees) only: any order of rendering, or a resumed capture, gives the
        same frames."""
        return np.random.default_rng([self.seed, PHASES.index(phase), arm, int(round(angle_deg * 1000)) % 360000])

    def _geometry(self, arm: int, angle_deg: float, phase: str = "transparent") -> dict:
        """The exact geometry of a view: object poses, which object each pixel sees (label) and
        its depth, from one cast of the pixels that can meet an object (``phase`` opaque: the
        twins')."""
        h, w = self.camera.height, self.camera.width
        bg = self._background(arm)
        poses = self.poses(arm, angle_deg, phase)
        objects, face_vn = self._phase_objects[phase]
        T_table_cam = invert(self.layout.T_base_table(angle_deg)) @ self.T_base_cams[arm]
        roi2d, box = self._roi(poses)
        idx = np.flatnonzero(roi2d)
        hit = self._cast(objects, T_table_cam[:3, 3],
                         self._rays_cam[idx] @ T_table_cam[:3, :3].T.astype(np.float32))
        z_obj_roi = hit["t_hit"].astype(np.float32)
        z_bg = bg["z"].reshape(-1)
        vis_roi = np.isfinite(z_obj_roi) & (z_obj_roi < z_bg[idx])
        vi = idx[vis_roi]  # flat indices of the pixels that see an object
        label = np.full(h * w, -1, np.int16)
        label[vi] = hit["geometry_ids"][vis_roi].astype(np.int16)
        z_obj = np.full(h * w, np.inf, np.float32)
        z_obj[vi] = z_obj_roi[vis_roi]
        return {"bg": bg, "poses": poses, "face_vn": face_vn, "T_table_cam": T_table_cam, "roi": roi2d, "box": box, "vi": vi,
                "gid": hit["geometry_ids"][vis_roi], "prim": hit["primitive_ids"][vis_roi],
                "uv": hit["primitive_uvs"][vis_roi], "label": label, "z_obj": z_obj}

    def truth(self, arm: int, angle_deg: float) -> Frame:
        """Ground truth of a view without rendering colour or noise: poses, visible labels and the
        noise-free depth (``rgb`` and ``depth`` are None)."""
        g = self._geometry(arm, angle_deg)
        h, w = self.camera.height, self.camera.width
        z_true = np.minimum(g["z_obj"], g["bg"]["z"].reshape(-1)).reshape(h, w)
        return Frame(None, None, g["label"].reshape(h, w), g["poses"], depth_true=z_true)

    def render(self, arm: int, angle_deg: float, phase: str) -> Frame:
        """Render the RGB-D pair of ``phase`` at arm position ``arm`` and table angle ``angle_deg``.
        Deterministic for (seed, phase, arm, angle)."""
        if phase not in PHASES:
            raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
        cam = self.camera
        h, w = cam.height, cam.width
        rng = self.frame_rng(phase, arm, angle_deg)
        geo = self._geometry(arm, angle_deg, phase)
        label = geo["label"]
        # the frame's truth is the transparent objects' (an opaque twin off its slot is not the label)
        poses = geo["poses"] if phase == "transparent" else self.poses(arm, angle_deg)
        oy, ox = rng.integers(0, self._pad, 2)  # drawn first: the two halves below use rng in a fixed order
        # depth and colour are independent given the geometry: the depth half runs in a second
        # thread (numpy and OpenCV release the GIL), so both cores work on one frame
        if self._pool is None:
            rgb = self._colour_half(phase, arm, angle_deg, geo, oy, ox)
            depth, z_true = self._depth_half(phase, geo, rng, oy, ox)
        else:
            fut = self._pool.submit(self._depth_half, phase, geo, rng, oy, ox)
            rgb = self._colour_half(phase, arm, angle_deg, geo, oy, ox)
            depth, z_true = fut.result()
        return Frame(rgb, depth, label.reshape(h, w), poses, depth_true=z_true)

    def _colour_half(self, phase: str, arm: int, angle_deg: float, geo: dict, oy: int, ox: int) -> np.ndarray:
        """The colour image (H,W,3) uint8 of a view."""
        h, w = self.camera.height, self.camera.width
        bg, vi, z_obj = geo["bg"], geo["vi"], geo["z_obj"]
        T_base_cam = self.T_base_cams[arm]
        R_cam_table = geo["T_table_cam"][:3, :3].T
        # background colour: static room + the sticker at this table angle
        colour = self._draw_sticker(bg["colour"].copy(), bg["sticker_maps"], angle_deg).reshape(-1, 3)
        if len(vi):
            gid = geo["gid"]
            n_table = self._interp_normals(geo["face_vn"], gid, geo["prim"], geo["uv"])
            n_cam = (n_table @ R_cam_table.T.astype(np.float32))
            d_cam = self._dirs_cam[vi]
            n_cam *= np.where(np.einsum("ij,ij->i", n_cam, d_cam) > 0, -1.0, 1.0).astype(np.float32)[:, None]
            L_cam = (T_base_cam[:3, :3].T @ LIGHT_DIR).astype(np.float32)
            if phase == "opaque":
                albedo = self._twin_albedo[gid]
                lam = AMBIENT + (1 - AMBIENT) * np.clip(n_cam @ L_cam, 0, 1)
                hvec = L_cam[None, :] - d_cam
                hvec /= np.linalg.norm(hvec, axis=1, keepdims=True)
                spec = 0.12 * np.clip(np.sum(n_cam * hvec, axis=1), 0, 1) ** 20
                colour[vi] = albedo * lam[:, None] + spec[:, None]
            else:
                colour[vi] = self._glass_colour(vi, z_obj[vi], d_cam, n_cam, L_cam, T_base_cam,
                                                colour.reshape(h, w, 3), bg["z"])
        # sensor noise from the bank, at this frame's offset
        return cv2.addWeighted(colour.reshape(h, w, 3), 255.0, self._noise_rgb[oy:oy + h, ox:ox + w],
                               self.sensor.rgb_sigma, 0.0, dtype=cv2.CV_8U)

    def _depth_half(self, phase: str, geo: dict, rng: np.random.Generator, oy: int, ox: int):
        """(depth (H,W) uint16 as the sensor reports it, noise-free depth (H,W) float32 mm)."""
        cam = self.camera
        h, w = cam.height, cam.width
        bg, box, z_obj = geo["bg"], geo["box"], geo["z_obj"]
        noise = self._noise_depth[oy:oy + h, ox:ox + w]
        uniform = self._uniform[oy:oy + h, ox:ox + w]
        z_true = np.minimum(z_obj, bg["z"].reshape(-1)).reshape(h, w)
        if phase == "opaque":
            z_sensor = stereo_depth(z_true, cam.fx, self.sensor, rng, noise, uniform, self._holes(z_true, bg, box))
        else:
            glass = (geo["label"] >= 0).reshape(h, w)
            z_sensor = self._glass_depth(z_obj.reshape(h, w), bg, glass, box, rng, noise, uniform)
        if self.sensor.depth_bias != 1.0:  # a camera off in scale: every depth it reports, glass too
            z_sensor = z_sensor * np.float32(self.sensor.depth_bias)
        return cam.mm_to_depth(z_sensor), z_true

    def _interp_normals(self, face_vn: np.ndarray, gid: np.ndarray, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Smooth (barycentric) vertex normals at ray hits, table frame, (N,3) unit."""
        g = np.take(face_vn, self._face_offset[gid] + prim, axis=0)  # one gather of 9 floats a hit
        w = np.empty((len(uv), 3), np.float32)
        w[:, 1:] = uv
        w[:, 0] = 1.0 - uv[:, 0] - uv[:, 1]
        n = np.einsum("nk,nkj->nj", w, g.reshape(-1, 3, 3))
        n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-9)[:, None]
        return n

    def _glass_colour(self, vi, z, d_cam, n_cam, L_cam, T_base_cam, background, z_bg):
        """Colour of glass pixels: the background seen along a refracted ray (screen-space: the
        bent ray is followed to the background depth and the background image is sampled
        there), tinted and darkened with path length, plus Fresnel reflection and highlights."""
        g = self.glass
        cam = self.camera
        f32 = np.float32
        cos_i = np.clip(-np.einsum("ij,ij->i", d_cam, n_cam), 1e-3, 1.0)
        eta = f32(1.0 / g.ior)
        k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
        refr = eta * d_cam + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * n_cam
        bent = d_cam + f32(g.refraction) * (refr - d_cam)
        p = self._rays_cam[vi] * z[:, None]
        bz = np.maximum(bent[:, 2], f32(0.05))
        zb = z_bg.reshape(-1)[vi]
        for _ in range(2):  # follow the bent ray to the background depth, twice to settle
            q = p + ((np.maximum(zb - p[:, 2], 0.0) / bz)[:, None]) * bent
            u = q[:, 0] / q[:, 2] * f32(cam.fx) + f32(cam.cx)
            v = q[:, 1] / q[:, 2] * f32(cam.fy) + f32(cam.cy)
            ui = np.clip(np.rint(u), 0, cam.width - 1).astype(np.intp)
            vv = np.clip(np.rint(v), 0, cam.height - 1).astype(np.intp)
            zb = np.minimum(z_bg[vv, ui], f32(1e5))
        n = len(vi)
        cols = 1024
        rows = max(1, -(-n // cols))
        mx = np.zeros(rows * cols, np.float32)
        my = np.zeros(rows * cols, np.float32)
        mx[:n], my[:n] = u, v
        seen = cv2.remap(background, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n]
        F = f32(g.fresnel_f0) + f32(1 - g.fresnel_f0) * (1 - cos_i) ** 5
        refl_z = (d_cam + (2 * cos_i)[:, None] * n_cam) @ T_base_cam[2, :3].astype(np.float32)
        hvec = L_cam[None, :] - d_cam
        n_dot_h = np.einsum("ij,ij->i", n_cam, hvec) / np.sqrt(np.einsum("ij,ij->i", hvec, hvec))
        # Blinn-Phong lobe, written as exp(-shininess (1 - n.h)) ~ (n.h)^shininess, cheaper
        spec = f32(g.specular) * np.exp(f32(-g.shininess) * (1 - np.clip(n_dot_h, 0, 1)))
        add = F * (f32(0.55) + f32(0.4) * np.clip(refl_z, -1, 1)) + spec
        weight = (1 - F) * np.exp(f32(-g.absorption) / cos_i)
        col = seen * (weight[:, None] * np.asarray(g.tint, np.float32)) + add[:, None]
        return np.clip(col, 0, 1)

    def _holes(self, z: np.ndarray, bg: dict, box: tuple | None) -> tuple[np.ndarray, np.ndarray]:
        """Stereo holes of ``z``, which equals the cached background outside ``box`` (v0, v1, u0,
        u1): the occlusions change only on its rows, left of its right end; the edges only
        around it."""
        if box is None:
            return bg["occluded"], bg["edges"]
        v0, v1, u0, u1 = box
        h, w = z.shape
        occluded = bg["occluded"].copy()
        # a pixel is hidden only by pixels to its right: right of the box nothing changes
        tail = bg["slack_rmax"][v0:v1, u1] if u1 < w else None
        occluded[v0:v1, :u1] = stereo_occlusion(z[v0:v1, :u1], self.camera.fx, self.sensor.baseline_mm, tail=tail)
        a0, a1, b0, b1 = max(v0 - 2, 0), min(v1 + 2, h), max(u0 - 2, 0), min(u1 + 2, w)
        c0, c1, d0, d1 = max(v0 - 1, 0), min(v1 + 1, h), max(u0 - 1, 0), min(u1 + 1, w)
        edges = bg["edges"].copy()
        e = depth_edges(z[a0:a1, b0:b1], self.sensor.edge_jump)
        edges[c0:c1, d0:d1] = e[c0 - a0:c1 - a0, d0 - b0:d1 - b0]
        return occluded, edges

    def _glass_depth(self, z_obj, bg, glass, box, rng, noise, uniform):
        """Active stereo on glass: most glass pixels return nothing, some the background behind,
        the rest the glass surface with large noise; flying pixels at the silhouettes.
        All glass lies inside ``box`` (v0, v1, u0, u1); the work is done there."""
        s = self.sensor
        z_bg = bg["z"]
        z = z_bg.copy()
        if box is None:
            return stereo_depth(z, self.camera.fx, s, rng, noise, uniform, self._holes(z, bg, box))
        v0, v1, u0, u1 = box
        g = glass[v0:v1, u0:u1]
        zo, zb = z_obj[v0:v1, u0:u1], z_bg[v0:v1, u0:u1]
        if g.any():
            fv = smooth_field(g.shape, rng)[g]
            q1, q2 = np.quantile(fv, [s.glass_missing, min(1.0, s.glass_missing + s.glass_behind)])
            surface = zo[g] + s.glass_sigma_mm * noise[v0:v1, u0:u1][::-1, ::-1][g]
            z[v0:v1, u0:u1][g] = np.where(fv < q1, 0.0, np.where(fv < q2, zb[g], surface))
        out = stereo_depth(z, self.camera.fx, s, rng, noise, uniform, self._holes(z, bg, box))
        if g.any() and s.rim_px > 0 and s.flying_fraction > 0:
            # flying pixels: a band around the silhouettes (the box holds the hulls grown by 2 px;
            # the band is cut to it)
            g8 = g.astype(np.uint8)
            k = np.ones((2 * s.rim_px + 1, 2 * s.rim_px + 1), np.uint8)
            band = (cv2.dilate(g8, k) > 0) & (cv2.erode(g8, k) == 0)
            u_rand = uniform[v0:v1, u0:u1][::-1, ::-1]
            fly = band & (u_rand < s.flying_fraction)
            zf = cv2.erode(np.where(g, zo, np.float32(1e9)).astype(np.float32), k)
            fly &= (zf < 1e9) & (zb > 0)
            wgt = u_rand[fly] / max(s.flying_fraction, 1e-6)
            out[v0:v1, u0:u1][fly] = wgt * zf[fly] + (1 - wgt) * zb[fly]
        return out

    def full_masks(self, poses: list[np.ndarray]) -> list[np.ndarray]:
        """Unoccluded silhouette (H,W) bool of every object at the given poses."""
        return self._models.render([(p.obj_id, T) for p, T in zip(self.scene.placements, poses)]).full
