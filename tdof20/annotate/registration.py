"""Registration of a raw session: every frame's camera pose relative to frame (arm 0, step 0).

Works on the **opaque** phase depth only (the transparent phase's depth is unusable). Both phases
share the poses, so the result holds for every frame of the session.

Frames and conventions (mm, ``T_a_b`` maps points from frame b to frame a):

* ``cam(a,k)`` — the camera frame of arm position ``a`` at turntable step ``k``. Within an arm
  position the camera stands still and the table turns by ``k * step_deg`` (counter-clockwise seen
  from above unless ``session.json`` says ``turntable.direction = "cw"``).
* ``T_ref_frame`` of frame (a,k) maps a point of the turntable seen in ``cam(a,k)`` to where the
  same table-fixed point is seen in ``cam(0,0)``: it is the "virtual camera" pose of the frame
  relative to the reference frame, ``T_ref_frame = T_ref_arm(a) @ T_arm_frame(a,k)`` with
  ``T_arm_frame`` mapping ``cam(a,k) -> cam(a,0)`` and ``T_ref_arm`` mapping ``cam(a,0) -> cam(0,0)``.
* With the simulator's truth (``T_cam_table`` of every frame, table at angle 0),
  ``T_ref_frame(a,k) = T_cam00_table @ inv(T_cam_ak_table)``.

Stages, per arm position (:func:`register_session`):

1. table plane by RANSAC (open3d ``segment_plane``) on the centre of a few frames, the plane with a
   normal near the robot's vertical (the prior ``R_base_cam^T e_z``) wins; the normal, oriented
   towards the camera, is the first estimate of the turntable axis;
2. a first axis point from **what moves**: per sampled frame the points that stand there and not
   in another sampled frame (the objects; the static room, clutter beside the table and the
   featureless disk drop out), and between consecutive sampled frames the centre of the turn
   that carries one onto the other (``_turn_between``: a 2D rotation about the table normal by
   the nominal angle, centroid start, trimmed ICP; the centre solves ``(I - R) c = t``); the
   median centre over the pairs. Only when nothing moves enough to tell (a round cup on the axis)
   the centroid of what stands on the table. Before any arm, the same measurement over the whole
   circle checks ``turntable.direction`` and ``step_deg`` (``_check_turntable``): a direction left
   out of session.json is taken from the data, one the data contradicts and a step angle it does
   not show are refused;
3. pass 1: pairwise point-to-plane ICP (multi-scale, coarse scales only) between frames 1 step
   and ~30 deg apart (the 360 deg loop closes itself where the plan covers a full turn), each
   started from the known step angle about the axis, on points cropped to the turntable volume (a
   cylinder about the axis above the table plane), then a pose graph (open3d
   ``global_optimization``) over the frames connected to step 0; the axis (direction and point) is
   refitted to the poses (``_fit_axis``), and the table radius from the plane's points
   (``_disk_radius``: where the plane band stops filling every direction about the axis — a
   cabinet's face beside the table fills only a few);
4. pass 2: the same at every scale and with edges ~1 step / 15 / 30 deg apart, re-cropped about
   the refined axis; edges that disagree with the turntable prior (or fit badly) are dropped
   before the optimisation; the axis is refitted again;
5. per frame: fitness and inlier RMSE (median over its pairwise registrations; optionally one
   more ICP against the fused cloud of its arm position, ``refine_against_model``) and the
   residual against the turntable prior (rotation by the step angle about the axis): degrees, and
   mm as the displacement of the axis point. Frames beyond the thresholds, or without any
   registration that agrees with the prior, are flagged (with a reason) and left out of the fused
   clouds; they keep their prior pose;
6. arm positions: every arm's turntable axis, moved into the reference camera through the
   robot's poses, must agree with the others' (``_cross_check_axes``: within ``arm_axis_max_mm``
   at the table top and ``arm_axis_max_deg``; the median of three or more, each other for two);
   the robot prior ``inv(T_base_cam(0)) @ T_base_cam(a)`` is refined by ICP between the arms'
   fused turntable clouds; a correction beyond the limits keeps the prior and flags the arm, and
   the axes are checked again after the ICP. A flagged arm has none of its frames labelled.

Why the pairwise ICP is regularised towards the turntable prior (``prior_weighted_icp``): depth
is quantised (1 mm steps at ``depth_scale`` 1), and the quantisation terraces are fixed in the
image, so they pull plain ICP towards "nothing moved" wherever the geometry leaves a direction
free — a rotationally symmetric object near the axis (single-object scenes) leaves the turn
angle free, and plain ICP then reported 12 deg for a 15 deg step. The regularised ICP
(``_icp_prior``: Gauss-Newton point-to-plane plus a Gaussian prior on the deviation from the
turntable model) follows the data in the directions the geometry pins and keeps the prior in the
others.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.config import check_ranges
from tdof20.errors import TdofError
from tdof20.formats.io import read_json, write_json
from tdof20.formats.session import RawSession, depth_units_problem
from tdof20.geometry.transforms import invert, rotation_about_axis
from tdof20.o3d import o3d
from tdof20.progress import progress as _progress

REG = o3d.pipelines.registration
PHASE = "opaque"
RESULT_FORMAT = "tdof20-registration"
RESULT_VERSION = 1


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
@dataclass
class RegistrationConfig:
    """Every option of the registration; the defaults work on the simulator (640x480, 320x240)."""

    phase: str = PHASE                        # the phase whose depth is registered
    voxel_sizes_mm: tuple[float, ...] = (8.0, 4.0, 2.0)   # ICP scales, coarse to fine
    icp_dist_factor: float = 2.5              # max correspondence distance = factor * voxel
    icp_iterations: tuple[int, ...] = (20, 15, 15)        # per scale
    normal_radius_mm: float = 12.0            # normals: neighbours within this radius (wide: depth
    normal_max_nn: int = 30                   # quantisation terraces must not tilt them)
    icp_tol_rad: float = 2e-5                 # an ICP level stops when its step turns less than this (0.001 deg)
    icp_tol_mm: float = 2e-3                  # ... and moves less than this (measured: 16 -> 13 s CPU per 40 frames, same accuracy)
    normal_voxel_mm: float | None = 4.0       # normals estimated on this sparser cloud and handed to the
                                              # finest level's points (nearest): 4x fewer points and
                                              # neighbours; None = on the finest level itself
    # data: depth range and plane
    min_depth_mm: float = 150.0
    max_depth_mm: float = 2000.0
    plane_window: float = 0.6                 # central fraction of the image searched for the table
    plane_dist_mm: float = 4.0                # RANSAC inlier distance
    plane_prior_max_deg: float = 30.0         # table normal within this of the robot's vertical
    plane_max_below: float = 0.3              # most of the image centre must not lie below the table
    plane_frames: int = 6                     # frames sampled per arm for the plane / first axis
    # crop: the turntable volume
    crop_below_mm: float = 10.0               # keep points down to this far below the table top
    crop_height_mm: float = 350.0             # ... and up to this far above it
    crop_radius_mm: float | None = None       # cylinder radius; None = the table top's radius + margin
    crop_margin_mm: float = 10.0
    max_crop_radius_mm: float = 450.0         # cap (and the radius of pass 1's crop)
    min_points: int = 500                     # fewer cropped points: the frame is unusable
    max_source_points: int = 4000             # ICP source subsample per scale (targets stay dense)
    # pose graph
    edge_angles_deg: tuple[float, ...] = (0.0, 15.0, 30.0)  # 0 = one step; others rounded to steps
    pass1_edge_angles_deg: tuple[float, ...] = (0.0, 30.0)  # pass 1 (axis only): fewer edges ...
    pass1_levels: int = 1                     # ... and only the coarsest ICP scale(s)
    pass2_first_level: int = 2                # pass 2 starts at this ICP scale: pass 1 and the refitted axis
                                              # already put every frame within a fraction of a degree (measured:
                                              # 123 -> 89 s CPU per arm of 400 frames, the same accuracy)
    edge_min_fitness: float = 0.3
    prior_weighted_icp: bool = True           # pairwise ICP regularised towards the turntable prior
    prior_sigma_deg: float = 0.1              # ... its rotation uncertainty (a symmetric object
                                              #     leaves the turn angle to it)
    prior_sigma_mm: float = 5.0               # ... its uncertainty at the table centre
    prior_sigma_r_mm: float = 1.0             # depth noise of one point-to-plane residual
    pass1_edge_max_deg: float = 5.0           # edges further than this from the prior are dropped
    pass1_edge_max_mm: float = 40.0
    edge_max_deg: float = 1.5                 # pass 2
    edge_max_mm: float = 8.0
    # per-frame refinement against the arm's fused cloud
    model_voxel_mm: float = 2.0
    frame_icp_dist_mm: float = 5.0            # also the inlier distance of fitness/RMSE
    refine_against_model: bool = False        # one more ICP per frame against the fused arm cloud
    # flags
    min_fitness: float = 0.4                  # (of pairwise edges: lower for big steps)
    max_rmse_mm: float = 3.0
    max_residual_deg: float = 1.0
    max_residual_mm: float = 5.0
    # arm positions
    refine_arms: bool = True
    arm_min_fitness: float = 0.3
    arm_prior_sigma_deg: float = 0.2          # the robot prior's uncertainty (regularises the ICP;
                                              # a symmetric single object leaves the turn free)
    arm_prior_sigma_mm: float = 10.0
    max_arm_correction_deg: float = 5.0
    max_arm_correction_mm: float = 50.0
    arm_axis_max_mm: float = 15.0             # every arm's turntable axis within this of the others' (at the
    arm_axis_max_deg: float = 3.0             # table top) and this in direction, through the arms' poses

    def __post_init__(self) -> None:
        check_ranges(self, "register", positive=(
            "voxel_sizes_mm", "icp_dist_factor", "icp_iterations", "normal_radius_mm", "normal_max_nn",
            "icp_tol_rad", "icp_tol_mm", "normal_voxel_mm", "min_depth_mm", "max_depth_mm", "plane_dist_mm",
            "plane_prior_max_deg", "plane_frames", "crop_height_mm", "crop_radius_mm", "max_crop_radius_mm",
            "min_points", "max_source_points", "pass1_levels", "prior_sigma_deg", "prior_sigma_mm",
            "prior_sigma_r_mm", "pass1_edge_max_deg", "pass1_edge_max_mm", "edge_max_deg", "edge_max_mm",
            "model_voxel_mm", "frame_icp_dist_mm", "max_rmse_mm", "max_residual_deg", "max_residual_mm",
            "arm_prior_sigma_deg", "arm_prior_sigma_mm", "max_arm_correction_deg", "max_arm_correction_mm",
            "arm_axis_max_mm", "arm_axis_max_deg"),
            non_negative=("crop_below_mm", "crop_margin_mm", "edge_angles_deg", "pass1_edge_angles_deg",
                          "pass2_first_level"),
            fraction=("plane_window", "plane_max_below", "edge_min_fitness", "min_fitness", "arm_min_fitness"))
        if self.max_depth_mm <= self.min_depth_mm:
            raise TdofError(f"register.max_depth_mm ({self.max_depth_mm}) must be above register.min_depth_mm "
                            f"({self.min_depth_mm})")

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "RegistrationConfig":
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise TdofError(f"unknown registration option(s): {', '.join(unknown)}")
        kw = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**kw)


# ---------------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------------
@dataclass
class FrameRegistration:
    arm: int
    step: int
    T_ref_frame: np.ndarray                   # (4,4) cam(arm, step) -> cam(0, 0), mm
    fitness: float = 0.0
    rmse: float = float("nan")                # inlier RMSE, mm
    residual_deg: float = float("nan")        # vs the turntable prior
    residual_mm: float = float("nan")         # displacement of the axis point vs the prior
    flagged: bool = False
    reason: str = ""

    def to_dict(self) -> dict:
        return {"arm": self.arm, "step": self.step, "T_ref_frame": _T_list(self.T_ref_frame),
                "fitness": _f(self.fitness), "rmse": _f(self.rmse), "residual_deg": _f(self.residual_deg),
                "residual_mm": _f(self.residual_mm), "flagged": bool(self.flagged), "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict) -> "FrameRegistration":
        return cls(int(d["arm"]), int(d["step"]), _T_arr(d["T_ref_frame"]), _uf(d["fitness"]), _uf(d["rmse"]),
                   _uf(d["residual_deg"]), _uf(d["residual_mm"]), bool(d["flagged"]), str(d.get("reason", "")))


@dataclass
class ArmRegistration:
    arm: int
    axis_dir: np.ndarray                      # (3,) unit, camera frame of (arm, step 0)
    axis_point: np.ndarray                    # (3,) mm, where the axis meets the table top
    plane_normal: np.ndarray                  # (3,) table top normal (towards the camera)
    plane_d: float                            # plane: n . x + d = 0 (mm)
    crop_radius: float                        # mm
    T_ref_arm: np.ndarray                     # (4,4) cam(arm, 0) -> cam(0, 0)
    T_ref_arm_prior: np.ndarray               # (4,4) the robot's (hand-eye) prior
    fitness: float = float("nan")             # arm-to-arm ICP (nan for arm 0)
    rmse: float = float("nan")
    correction_deg: float = 0.0               # refined vs prior
    correction_mm: float = 0.0
    flagged: bool = False
    reason: str = ""

    def to_dict(self) -> dict:
        return {"arm": self.arm, "axis_dir": _v(self.axis_dir), "axis_point": _v(self.axis_point),
                "plane_normal": _v(self.plane_normal), "plane_d": float(self.plane_d),
                "crop_radius": float(self.crop_radius), "T_ref_arm": _T_list(self.T_ref_arm),
                "T_ref_arm_prior": _T_list(self.T_ref_arm_prior), "fitness": _f(self.fitness),
                "rmse": _f(self.rmse), "correction_deg": float(self.correction_deg),
                "correction_mm": float(self.correction_mm), "flagged": bool(self.flagged), "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict) -> "ArmRegistration":
        return cls(int(d["arm"]), np.asarray(d["axis_dir"], float), np.asarray(d["axis_point"], float),
                   np.asarray(d["plane_normal"], float), float(d["plane_d"]), float(d["crop_radius"]),
                   _T_arr(d["T_ref_arm"]), _T_arr(d["T_ref_arm_prior"]), _uf(d["fitness"]), _uf(d["rmse"]),
                   float(d["correction_deg"]), float(d["correction_mm"]), bool(d["flagged"]),
                   str(d.get("reason", "")))


@dataclass
class RegistrationResult:
    scene_id: str
    steps: int
    step_deg: float
    n_arms: int
    frames: list[FrameRegistration]
    arms: list[ArmRegistration]
    config: dict = field(default_factory=dict)
    timing_s: dict = field(default_factory=dict)
    turntable: dict = field(default_factory=dict)   # direction used and where it came from

    def frame(self, arm: int, step: int) -> FrameRegistration:
        for f in self.frames:
            if f.arm == arm and f.step == step:
                return f
        raise KeyError(f"no registration for arm {arm} step {step}")

    def poses(self) -> np.ndarray:
        """(n_arms, steps, 4, 4) T_ref_frame (NaN where a frame has none)."""
        out = np.full((self.n_arms, self.steps, 4, 4), np.nan)
        for f in self.frames:
            out[f.arm, f.step] = f.T_ref_frame
        return out

    def flagged_frames(self) -> list[tuple[int, int, str]]:
        """(arm, step, reason) of every flagged frame (also every frame of a flagged arm)."""
        bad_arms = {a.arm: a.reason for a in self.arms if a.flagged}
        out = []
        for f in self.frames:
            if f.flagged:
                out.append((f.arm, f.step, f.reason))
            elif f.arm in bad_arms:
                out.append((f.arm, f.step, f"arm {f.arm} flagged: {bad_arms[f.arm]}"))
        return out

    def usable(self, arm: int, step: int) -> bool:
        """True when the frame's pose may be used for labels."""
        f = self.frame(arm, step)
        return not f.flagged and not self.arms[arm].flagged

    def to_dict(self) -> dict:
        return {"format": RESULT_FORMAT, "version": RESULT_VERSION, "scene_id": self.scene_id,
                "steps": self.steps, "step_deg": self.step_deg, "n_arms": self.n_arms,
                "config": self.config, "timing_s": self.timing_s, "turntable": self.turntable,
                "arms": [a.to_dict() for a in self.arms], "frames": [f.to_dict() for f in self.frames]}

    @classmethod
    def from_dict(cls, d: dict, path: str | Path | None = None) -> "RegistrationResult":
        if not isinstance(d, dict) or d.get("format") != RESULT_FORMAT:
            raise TdofError(f"not a registration result (format must be '{RESULT_FORMAT}')", path)
        if int(d.get("version", 0)) > RESULT_VERSION:
            raise TdofError(f"registration result version {d.get('version')} is newer than this tdof20 "
                            f"reads ({RESULT_VERSION}): upgrade tdof20", path)
        try:
            return cls(str(d["scene_id"]), int(d["steps"]), float(d["step_deg"]), int(d["n_arms"]),
                       [FrameRegistration.from_dict(f) for f in d["frames"]],
                       [ArmRegistration.from_dict(a) for a in d["arms"]], dict(d.get("config", {})),
                       dict(d.get("timing_s", {})), dict(d.get("turntable", {})))
        except (KeyError, TypeError, ValueError) as e:
            raise TdofError(f"malformed registration result ({type(e).__name__}: {e})", path) from None

    def save(self, path: str | Path) -> Path:
        """Write atomically as JSON."""
        path = Path(path)
        write_json(path, self.to_dict())
        return path

    @classmethod
    def load(cls, path: str | Path) -> "RegistrationResult":
        return cls.from_dict(read_json(path), path)


def _f(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _uf(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _v(x: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(x).reshape(-1)]


def _T_list(T: np.ndarray) -> list[float]:
    return _v(np.asarray(T, float).reshape(16))


def _T_arr(x: list) -> np.ndarray:
    a = np.asarray(x, float)
    if a.size != 16:
        raise ValueError("a transform must be 16 numbers")
    return a.reshape(4, 4)


# ---------------------------------------------------------------------------------------------
# small maths
# ---------------------------------------------------------------------------------------------
def _rot_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in degrees of (...,3,3) rotation matrices."""
    R = np.asarray(R, float)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _T_diff(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (deg) and translation (mm) of inv(A) @ B, for stacks (...,4,4)."""
    D = invert(A) @ np.asarray(B, float)
    return _rot_deg(D[..., :3, :3]), np.linalg.norm(D[..., :3, 3], axis=-1)


def _prior(axis_dir: np.ndarray, axis_point: np.ndarray, angle_deg: float, sign: float) -> np.ndarray:
    """T_arm_frame of the turntable model: cam(a,k) -> cam(a,0) for the table at ``angle_deg``.

    The table turns by +angle (ccw, sign=+1) about the upward axis, so a table point seen at step k
    is rotated by +angle relative to step 0; mapping it back is a rotation by -angle."""
    return rotation_about_axis(axis_dir, -sign * math.radians(angle_deg), axis_point)


def _fit_axis(Ts: np.ndarray, n_hint: np.ndarray, plane_n: np.ndarray, plane_d: float,
              weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fit the common rotation axis of poses Ts (N,4,4) (rotations about one fixed line).

    Direction: the unit n minimising sum ||R_k n - n||^2 (smallest eigenvector), oriented like
    ``n_hint``. Point: least squares of (I - R_k) p = t_k, with p on the table plane."""
    Ts = np.asarray(Ts, float)
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, float)
    A = Ts[:, :3, :3] - np.eye(3)
    M = np.einsum("k,kji,kjl->il", w, A, A)
    evals, evecs = np.linalg.eigh(M)
    n = evecs[:, 0]
    if n @ n_hint < 0:
        n = -n
    # (I - R_k) p = t_k  stacked, plus p on the plane (pn . p = -d), well weighted
    rows = (-A * np.sqrt(w)[:, None, None]).reshape(-1, 3)
    rhs = (Ts[:, :3, 3] * np.sqrt(w)[:, None]).reshape(-1)
    scale = max(1.0, float(np.sqrt(w.sum())))
    rows = np.vstack([rows, scale * plane_n[None, :]])
    rhs = np.concatenate([rhs, [-scale * plane_d]])
    p, *_ = np.linalg.lstsq(rows, rhs, rcond=None)
    # move p along n onto the plane (where the axis meets the table top)
    denom = float(plane_n @ n)
    if abs(denom) > 1e-6:
        p = p - n * ((plane_n @ p + plane_d) / denom)
    return n / np.linalg.norm(n), p


# ---------------------------------------------------------------------------------------------
# point clouds
# ---------------------------------------------------------------------------------------------
def _pcd(points: np.ndarray) -> "o3d.geometry.PointCloud":
    p = o3d.geometry.PointCloud()
    p.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return p


class _Pyramid:
    """A cloud downsampled at each ICP scale with normals (estimated once at the finest scale,
    averaged into the coarser ones, oriented towards ``viewpoint``), plus a random subsample of
    each level (at most ``max_source_points``) used when the cloud is the ICP source."""

    def __init__(self, points: np.ndarray | None, cfg: RegistrationConfig, viewpoint: np.ndarray | None = None,
                 levels: list | None = None):
        self.cfg = cfg
        if levels is not None:
            self.levels = levels
        else:
            fine = _pcd(points).voxel_down_sample(cfg.voxel_sizes_mm[-1])
            sparse = fine.voxel_down_sample(cfg.normal_voxel_mm) if cfg.normal_voxel_mm else fine
            sparse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_mm,
                                                                         max_nn=cfg.normal_max_nn))
            if viewpoint is not None:
                sparse.orient_normals_towards_camera_location(viewpoint)
            if sparse is not fine:  # each fine point takes the normal of its nearest sparse point
                from scipy.spatial import cKDTree

                S = np.asarray(sparse.points)
                idx = cKDTree(S).query(np.asarray(fine.points), workers=-1)[1] if len(S) else []
                fine.normals = o3d.utility.Vector3dVector(np.asarray(sparse.normals)[idx])
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
    def from_cloud(cls, cloud: "o3d.geometry.PointCloud", cfg: RegistrationConfig) -> "_Pyramid":
        """From a cloud that has normals (e.g. a fused one): the levels keep (average) them."""
        levels = []
        for v in cfg.voxel_sizes_mm:
            d = cloud.voxel_down_sample(v)
            d.normalize_normals()
            levels.append(d)
        return cls(None, cfg, levels=levels)

    def cropped(self, n: np.ndarray, p: np.ndarray, radius: float) -> "_Pyramid":
        """The part inside the turntable volume (same normals)."""
        out = []
        for lv in self.levels:
            h, r = _height_radius(np.asarray(lv.points), n, p)
            keep = (h >= -self.cfg.crop_below_mm) & (h <= self.cfg.crop_height_mm) & (r <= radius)
            out.append(lv.select_by_index(np.flatnonzero(keep).tolist()))
        return _Pyramid(None, self.cfg, levels=out)

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


def _icp(src: _Pyramid, tgt: _Pyramid, init: np.ndarray, cfg: RegistrationConfig,
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


def _icp_prior(src: _Pyramid, tgt: _Pyramid, prior: np.ndarray, centre: np.ndarray, cfg: RegistrationConfig,
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


class _Arm:
    """The frames of one arm position: raw (loosely cropped) points and the table geometry."""

    def __init__(self, arm: int, steps: int):
        self.arm = arm
        self.points: dict[int, np.ndarray] = {}   # step -> (N,3) loosely cropped points, mm
        self.bad: dict[int, str] = {}             # step -> why it could not be used
        self.plane_n = np.array([0.0, 0.0, -1.0])
        self.plane_d = 0.0
        self.axis_dir = self.plane_n.copy()
        self.axis_point = np.zeros(3)
        self.radius = 0.0
        self.steps = steps
        self.axis_source = ""
        self.moving = np.zeros((0, 3))            # points that moved between sampled frames (the objects)


def _load_points(session: RawSession, cfg: RegistrationConfig, arm: int, step: int,
                 window: float | None = None) -> np.ndarray:
    """Valid depth points (N,3) of a frame in the camera frame, mm (optionally a central window)."""
    cam = session.info.camera
    z = session.load_depth_mm(cfg.phase, arm, step)
    valid = (z >= cfg.min_depth_mm) & (z <= cfg.max_depth_mm)
    if window is not None:
        h, w = z.shape
        m = np.zeros_like(valid)
        dh, dw = int(h * (1 - window) / 2), int(w * (1 - window) / 2)
        m[dh:h - dh, dw:w - dw] = True
        valid &= m
    pts, _ = cam.to_points(np.where(valid, z, 0))
    return pts.astype(np.float64)


def _height_radius(pts: np.ndarray, n: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = pts - p
    h = d @ n
    r = np.linalg.norm(d - h[:, None] * n, axis=1)
    return h, r


def _crop(pts: np.ndarray, n: np.ndarray, p: np.ndarray, radius: float, cfg: RegistrationConfig) -> np.ndarray:
    h, r = _height_radius(pts, n, p)
    keep = (h >= -cfg.crop_below_mm) & (h <= cfg.crop_height_mm) & (r <= radius)
    return pts[keep]


def _moving_points(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int]) -> np.ndarray:
    """Points (N,3) that change between sampled frames (the nearer surface where depth differs by
    more than 10 mm): what turns with the table."""
    cam = session.info.camera
    imgs = []
    for k in steps[:4]:
        z = session.load_depth_mm(cfg.phase, arm, k)
        imgs.append(np.where((z >= cfg.min_depth_mm) & (z <= cfg.max_depth_mm), z, 0))
    out = []
    for i in range(len(imgs)):
        for j in range(i + 1, len(imgs)):
            a, b = imgs[i], imgs[j]
            m = (a > 0) & (b > 0) & (np.abs(a - b) > np.maximum(10.0, 0.03 * np.minimum(a, b)))
            out.append(cam.to_points(np.where(m, np.minimum(a, b), 0))[0])
    return np.concatenate(out).astype(np.float64) if out else np.zeros((0, 3))


def _frame_moving_points(imgs: list[np.ndarray], cam, thr_mm: float = 10.0) -> list[np.ndarray]:
    """Per depth image (mm), the points of what stands there in that frame and not in another
    one of the list (its depth nearer by more than ``thr_mm``, or 3 %): the objects, which turn
    with the table. The static room, clutter beside the table and the featureless disk drop out."""
    out = []
    for i, a in enumerate(imgs):
        m = np.zeros(a.shape, bool)
        for j, b in enumerate(imgs):
            if j != i:
                m |= (a > 0) & (b > 0) & (b - a > np.maximum(thr_mm, 0.03 * a))
        out.append(cam.to_points(np.where(m, a, 0))[0].astype(np.float64))
    return out


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit u, v with (u, v, n) right-handed: a rotation by +theta about n turns u towards v."""
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, e)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _turn_between(P: np.ndarray, Q: np.ndarray, n: np.ndarray, origin: np.ndarray, theta_deg: float | None,
                  tol_mm: float = 6.0, max_radius_mm: float = 450.0) -> tuple[float, np.ndarray, float, bool]:
    """How the turning part moved from cloud P to cloud Q: a rotation by theta about an axis
    along ``n`` through an unknown centre. ``theta_deg`` given (the turntable's nominal turn):
    the rotation is kept and only the centre is sought; None: theta too, over the whole turn
    (the direction and step checks). Returns (theta in degrees, counter-clockwise about n; the
    centre on the plane through ``origin``; the share of P within ``tol_mm`` of Q after the
    motion; whether the shape pins the angle — False when turns 30 deg or more away from the best
    fit nearly as well, as for a round object, and then theta says nothing). Over the whole turn
    only turns about a centre within ``max_radius_mm`` of ``origin`` count: a small moving part
    shifted sideways also fits a near-zero turn about a far-away centre, which no turntable makes.

    Works in the table plane's 2D coordinates (heights kept for the matching): for each trial
    angle the translation that aligns the centroids, then a trimmed ICP (translation only, or
    rotation and translation); the centre solves (I - R) c = t."""
    from scipy.spatial import cKDTree

    u, v = _plane_basis(n)
    B = np.stack([u, v], axis=1)
    p2, q2 = (P - origin) @ B, (Q - origin) @ B
    ph, qh = (P - origin) @ n, (Q - origin) @ n
    rng = np.random.default_rng(0)
    if len(p2) > 3000:
        idx = rng.choice(len(p2), 3000, replace=False)
        p2, ph = p2[idx], ph[idx]
    tree = cKDTree(np.column_stack([q2, qh]))

    def rot(a: float) -> np.ndarray:
        c, s_ = math.cos(a), math.sin(a)
        return np.array([[c, -s_], [s_, c]])

    def score(R2, t2) -> float:
        d, _ = tree.query(np.column_stack([p2 @ R2.T + t2, ph]), distance_upper_bound=tol_mm)
        return float(np.mean(np.isfinite(d)))

    def refine(a: float, free: bool) -> tuple[float, np.ndarray, float]:
        R2 = rot(a)
        t2 = q2.mean(0) - p2.mean(0) @ R2.T
        for it in range(15):
            x = p2 @ R2.T + t2
            d, j = tree.query(np.column_stack([x, ph]), distance_upper_bound=4 * tol_mm if it < 5 else 2 * tol_mm)
            ok = np.isfinite(d)
            if ok.sum() < 10:
                break
            a_, b_ = p2[ok], q2[j[ok]]
            if free:
                ca, cb = a_.mean(0), b_.mean(0)
                U, _, Vt = np.linalg.svd((a_ - ca).T @ (b_ - cb))
                D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
                R2 = Vt.T @ D @ U.T
                t2 = cb - ca @ R2.T
            else:
                t2 = (b_ - a_ @ R2.T).mean(0)
        return math.atan2(R2[1, 0], R2[0, 0]), t2, score(R2, t2)

    free = theta_deg is None
    trials = np.radians(np.arange(-180.0, 180.0, 4.0) if free else np.array([theta_deg]))
    def centre(a: float, t2: np.ndarray) -> np.ndarray | None:
        if abs(math.sin(a / 2)) <= 0.15:
            return None
        return np.linalg.solve(np.eye(2) - rot(a), t2)

    coarse = np.array([score(rot(a), q2.mean(0) - p2.mean(0) @ rot(a).T) for a in trials])
    fits = [refine(trials[i], free) for i in np.argsort(-coarse)[:8 if free else 1]]
    if free:   # turns about a centre on the table only
        fits = [f for f in fits if (c := centre(f[0], f[1])) is not None and np.linalg.norm(c) <= max_radius_mm]
        if not fits:
            return 0.0, origin, 0.0, False
    a, t2, sc = max(fits, key=lambda r: r[2])
    pinned = True
    if free:
        far = np.abs(np.degrees(np.angle(np.exp(1j * (trials - a))))) >= 30.0
        pinned = bool(coarse[far].max(initial=0.0) <= 0.6 * max(coarse.max(), 1e-9))
    c2 = centre(a, t2)
    return math.degrees(a), origin + B @ (np.zeros(2) if c2 is None else c2), sc, pinned


def _wrap_deg(x: float) -> float:
    return (x + 180.0) % 360.0 - 180.0


def _sampled_motion(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int], n: np.ndarray,
                    d: float, sign: float, check: bool = False) -> tuple[list[dict], np.ndarray]:
    """The turn of the moving part between consecutive sampled frames of an arm position:
    [{k0, k1, nominal_deg, theta_deg, centre, score}] with theta measured near the nominal turn
    ``sign * (k1 - k0) * step_deg``, for the pairs whose nominal turn is far enough from 0 and
    180 deg to pin the centre. ``check``: every pair, also measured over the whole turn and near
    the reversed turn (``free``, ``reversed``: (theta, score)), for the direction and step checks.
    Also returns the moving points of all sampled frames (N,3): where the objects stand."""
    cam = session.info.camera
    sd = session.info.step_deg
    imgs = []
    for k in steps:
        z = session.load_depth_mm(cfg.phase, arm, k)
        imgs.append(np.where((z >= cfg.min_depth_mm) & (z <= cfg.max_depth_mm), z, 0).astype(np.float32))
    foot = -n * d
    clouds = []
    for pts in _frame_moving_points(imgs, cam):
        h = pts @ n + d
        clouds.append(pts[(h > 5.0) & (h < cfg.crop_height_mm)])
    out = []
    for i in range(len(steps) - 1):
        P, Q = clouds[i], clouds[i + 1]
        nominal = (steps[i + 1] - steps[i]) * sd
        if len(P) < 100 or len(Q) < 100 or (not check and abs(math.sin(math.radians(nominal) / 2)) < 0.15):
            continue
        if check and np.linalg.norm((P.mean(0) - Q.mean(0)) - ((P.mean(0) - Q.mean(0)) @ n) * n) < 15.0:
            continue   # the moving part's centroid hardly moved (a round object near the axis): no turn to see
        theta, centre, sc, _ = _turn_between(P, Q, n, foot, sign * nominal)
        e = {"k0": steps[i], "k1": steps[i + 1], "nominal_deg": nominal, "theta_deg": theta, "centre": centre,
             "score": sc}
        if check:
            th, _, sc_free, pinned = _turn_between(P, Q, n, foot, None, max_radius_mm=cfg.max_crop_radius_mm)
            e["free"], e["pinned"] = (th, sc_free), pinned
            e["reversed"] = _turn_between(P, Q, n, foot, -sign * nominal)[0::2]
        out.append(e)
    return out, (np.concatenate(clouds) if clouds else np.zeros((0, 3)))


def _check_turntable(session: RawSession, cfg: RegistrationConfig, sign: float, recorded: bool) -> float:
    """The turning direction and step angle the opaque depth shows, against session.json: returns
    the sign to use (+1 counter-clockwise about the table normal towards the camera, -1
    clockwise). Per pair of sampled frames of the first arm position whose moving part pins the
    turn (not a round object: :func:`_turn_between`), its fit (share of points within 6 mm) is
    compared at the nominal turn, at the reversed turn and at the best turn over the whole circle:
    the nominal explains the data when its fit is within 85 % of the best (or 0.6 at least); the
    reversed one when it does and the nominal fits half as well; another turn when the nominal
    fits half as well as the best. The pairs of every arm position vote (until three agree); a
    majority of two pairs at least decides; anything less keeps the recorded (or default) direction. A direction left out of
    session.json is taken from the data; a recorded one that the data contradicts, or a step
    angle the data does not show, is a one-line TdofError naming session.json. Silent (keeps
    ``sign``) when the moving part is too small or too symmetric to tell (one round cup on the
    axis turns without changing the depth)."""
    info = session.info
    src = session.path / "session.json"
    votes: list[tuple[str, int, dict]] = []
    for arm in range(info.n_arms):
        available = [k for k in range(info.steps) if session.has_frame(cfg.phase, arm, k)]
        if len(available) < 2:
            continue
        sample = [available[i] for i in
                  np.unique(np.linspace(0, len(available) - 1, cfg.plane_frames).round().astype(int))]
        prior_up = info.T_base_cam(arm)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        try:
            n, d, _ = _table_plane(session, cfg, arm, sample, prior_up)
            pairs = [p for p in _sampled_motion(session, cfg, arm, sample, n, d, sign, check=True)[0]
                     if p["free"][1] >= 0.45 and p["pinned"]]
        except TdofError:
            continue
        for p in pairs:
            best = max(p["score"], p["reversed"][1], p["free"][1])
            if p["score"] >= 0.85 * best or p["score"] >= 0.6:
                v = "nominal"
            elif p["reversed"][1] >= 0.85 * best and p["score"] <= 0.5 * p["reversed"][1]:
                v = "reversed"
            elif p["score"] <= 0.5 * best:
                v = "other"
            else:
                v = "unclear"
            votes.append((v, arm, p))
        decided = [v for v, _, _ in votes if v != "unclear"]
        if len(decided) >= 3 and len(set(decided[:3])) == 1:
            break
    names = [v for v, _, _ in votes]
    verdict = max(("nominal", "reversed", "other"), key=names.count) if votes else "nominal"
    if verdict == "nominal" or names.count(verdict) < 2 or names.count(verdict) * 2 <= len(names):
        return sign
    if verdict == "other":   # another step angle: the pairs must agree on it
        per_step = np.array([abs(p["free"][0]) / (p["k1"] - p["k0"]) for v, _, p in votes if v == "other"])
        if np.abs(per_step - np.median(per_step)).max() > 0.25 * np.median(per_step):
            return sign
    _, arm, p = next(x for x in votes if x[0] == verdict)
    theta = p["reversed"][0] if verdict == "reversed" else p["free"][0]
    turned = f"the table turned {abs(theta):.1f} deg between steps {p['k0']} and {p['k1']} of arm {arm}"
    if verdict == "reversed":
        if recorded:
            seen = "clockwise" if sign > 0 else "counter-clockwise"
            raise TdofError(f"turntable.direction says '{'ccw' if sign > 0 else 'cw'}', but in the opaque depth "
                            f"{turned} {seen} (seen from above): correct turntable.direction, or leave it out to "
                            f"take it from the data", src)
        return -sign
    raise TdofError(f"{turned} ({theta:+.1f} deg about the table normal), but turntable.step_deg = "
                    f"{info.step_deg:g} says {sign * p['nominal_deg']:+.1f} deg for those {p['k1'] - p['k0']} "
                    f"steps: is step_deg right?", src)


def _disk_radius(clouds: list[np.ndarray], n: np.ndarray, p: np.ndarray, cam, cfg: RegistrationConfig) -> float | None:
    """The turntable top's radius (mm) from the table-plane points of the sampled frames: the
    disk fills every direction about the axis out to its edge, while what else touches the plane
    band (a cabinet's face, a box beside the table) fills only a few. Rings of 5 mm (3 pixels at
    least), sectors of 10 deg: the radius is where the share of in-view sectors holding plane
    points falls below half of the inner rings' share. None when there are too few points."""
    pts = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    h, r = _height_radius(pts, n, p)
    keep = (np.abs(h) < cfg.plane_dist_mm) & (r < cfg.max_crop_radius_mm)
    if keep.sum() < 200:
        return None
    u, v = _plane_basis(n)
    q = pts[keep] - p
    phi = np.degrees(np.arctan2(q @ v, q @ u)) % 360.0
    width = max(5.0, 3.0 * float(np.linalg.norm(p)) / cam.fx)   # rings of at least 3 pixels
    ring = (r[keep] // width).astype(int)
    n_rings, n_sec = int(cfg.max_crop_radius_mm // width) + 1, 36
    held = np.zeros((n_rings, n_sec), bool)
    held[ring, (phi // 10.0).astype(int) % n_sec] = True
    # which (ring, sector) cells the camera sees at all (their centre inside the image, in front)
    rc = (np.arange(n_rings) + 0.5) * width
    sc = np.radians((np.arange(n_sec) + 0.5) * 10.0)
    cells = p + rc[:, None, None] * (np.cos(sc)[None, :, None] * u + np.sin(sc)[None, :, None] * v)
    uv, z = cam.project(cells.reshape(-1, 3))
    inview = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
              & (uv[:, 1] < cam.height)).reshape(n_rings, n_sec)
    share = np.where(inview.sum(1) > 0, (held & inview).sum(1) / np.maximum(inview.sum(1), 1), np.nan)
    inner = share[(rc > 50.0) & (rc < 0.5 * cfg.max_crop_radius_mm)]
    if not np.isfinite(inner).any():
        return None
    level = 0.5 * float(np.nanmedian(inner))
    for i in range(n_rings):
        if rc[i] > 50.0 and np.isfinite(share[i]) and share[i] < level:
            return float(i * width)
    return float(cfg.max_crop_radius_mm)


def _table_plane(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int],
                 prior_up: np.ndarray) -> tuple[np.ndarray, float, list[np.ndarray]]:
    """RANSAC the table top on the image centres of a few frames. Returns (n, d, full clouds)."""
    centre, full = [], []
    for k in steps:
        pts = _load_points(session, cfg, arm, k)
        full.append(pts)
        centre.append(_load_points(session, cfg, arm, k, cfg.plane_window))
    pc = _pcd(np.concatenate(centre)).voxel_down_sample(cfg.voxel_sizes_mm[1])
    cpts = np.asarray(pc.points).copy()
    cands = []                     # (n, d, inliers) of planes near the vertical prior
    first = None
    for _ in range(5):
        if len(pc.points) < 100:
            break
        model, inl = pc.segment_plane(cfg.plane_dist_mm, 3, 1000)
        if len(inl) < 50:
            break
        n = np.asarray(model[:3], float)
        d = float(model[3]) / np.linalg.norm(n)
        n = n / np.linalg.norm(n)
        if d < 0:          # orient towards the camera (origin on the positive side: n.0 + d > 0)
            n, d = -n, -d
        ang = math.degrees(math.acos(np.clip(abs(n @ prior_up), -1, 1)))
        if first is None:
            first = (n, d)
        if ang <= cfg.plane_prior_max_deg:
            cands.append((n, d, len(inl)))
        pc = pc.select_by_index(inl, invert=True)
    # the turntable top is the highest level plane with (almost) nothing that moves below it: the
    # objects turn with the table and stand on it; the bench below it stays put; an object's flat
    # top has the rest of the moving object below it
    moving = _moving_points(session, cfg, arm, steps)
    ok = []
    big = max((c[2] for c in cands), default=0)
    for c in cands:
        if c[2] < max(0.05 * len(cpts), 0.25 * big):
            continue
        if len(moving) >= 50:
            h = moving @ c[0] + c[1]
            if np.percentile(h, 5) >= -3 * cfg.plane_dist_mm:
                ok.append(c)
        elif np.mean(cpts @ c[0] + c[1] < -2 * cfg.plane_dist_mm) <= cfg.plane_max_below:
            ok.append(c)
    if ok:
        n, d, _ = min(ok, key=lambda c: c[1])
        best = (n, d)
    elif cands:
        n, d, _ = max(cands, key=lambda c: c[2])
        best = (n, d)
    else:
        best = first
    if best is None:
        raise TdofError(f"arm {arm}: no table plane found in the {cfg.phase} depth (too few valid points)")
    n, d = best
    # least-squares refinement on the inliers of all sampled points
    allp = np.concatenate(full)
    for _ in range(2):
        inl = np.abs(allp @ n + d) < cfg.plane_dist_mm
        q = allp[inl]
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        n2 = vt[2] * np.sign(vt[2] @ n)
        n, d = n2, float(-n2 @ c)
    return n, d, full


# ---------------------------------------------------------------------------------------------
# per arm position
# ---------------------------------------------------------------------------------------------
def _edge_pairs(steps: list[int], step_deg: float, angles: tuple[float, ...]) -> list[tuple[int, int]]:
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


def _pose_graph_pass(A: _Arm, pyr: dict[int, _Pyramid], cfg: RegistrationConfig, step_deg: float,
                     sign: float, max_deg: float, max_mm: float, angles: tuple[float, ...], levels: list[int],
                     prog, task) -> tuple[dict[int, np.ndarray], dict[int, list[tuple[float, float, bool]]]]:
    """Pairwise ICP + pose graph over the usable frames.
    Returns (step -> T_arm_frame, step -> [(fitness, rmse, kept) of each of its edges])."""
    steps = sorted(pyr)
    prior = {k: _prior(A.axis_dir, A.axis_point, k * step_deg, sign) for k in steps}
    pairs = _edge_pairs(steps, step_deg, angles)
    stats: dict[int, list[tuple[float, float, bool]]] = {k: [] for k in steps}
    c = np.append(A.axis_point, 1.0)
    edges = []
    for i, j in pairs:
        init = invert(prior[i]) @ prior[j]            # cam(j) -> cam(i)
        if cfg.prior_weighted_icp:
            T, fit, rmse, info = _icp_prior(pyr[j], pyr[i], init, A.axis_point, cfg, levels=levels)
        else:
            T, fit, rmse, info = _icp(pyr[j], pyr[i], init, cfg, levels=levels)
        prog.advance(task)
        rdeg, _ = _T_diff(init, T)
        rmm = float(np.linalg.norm((T @ c - init @ c)[:3]))
        ok = not (fit < cfg.edge_min_fitness or rdeg > max_deg or rmm > max_mm)
        stats[i].append((fit, rmse, ok))
        stats[j].append((fit, rmse, ok))
        if ok:
            edges.append((i, j, T, info))
    # the pose graph over the frames connected to the first one (open3d refuses a disconnected graph)
    if not steps:
        raise TdofError(f"arm {A.arm}: no frame keeps enough depth points inside the turntable volume "
                        f"(crop radius {A.radius:.0f} mm about the axis)")
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


def _register_arm(session: RawSession, cfg: RegistrationConfig, arm: int, sign: float, prog
                  ) -> tuple[_Arm, dict[int, np.ndarray], list[FrameRegistration], np.ndarray]:
    """Everything within one arm position. Returns (arm info, T_arm_frame per step, frames, fused cloud)."""
    info = session.info
    K, sd = info.steps, info.step_deg
    o3d.utility.random.seed(arm)  # RANSAC of the table plane: the same result in any process, any order
    A = _Arm(arm, K)
    available = [k for k in range(K) if session.has_frame(cfg.phase, arm, k)]
    for k in range(K):
        if k not in available:
            A.bad[k] = f"missing frame: {cfg.phase} arm {arm} step {k} was never captured"
    if not available:
        raise TdofError(f"arm {arm}: no {cfg.phase} frames to register")
    # --- table plane and the first axis ------------------------------------------------------
    R_base_cam = info.T_base_cam(arm)[:3, :3]
    prior_up = R_base_cam.T @ np.array([0.0, 0.0, 1.0])
    sample = [available[i] for i in np.unique(np.linspace(0, len(available) - 1, cfg.plane_frames).round().astype(int))]
    good_sample = []
    for k in sample:
        try:
            z = session.load_depth_mm(cfg.phase, arm, k)
            if np.count_nonzero(z) >= cfg.min_points:
                good_sample.append(k)
        except TdofError:
            pass
    if not good_sample:
        raise TdofError(f"arm {arm}: the sampled {cfg.phase} frames hold no usable depth")
    n, d, full = _table_plane(session, cfg, arm, good_sample, prior_up)
    A.plane_n, A.plane_d = n, d
    # optical axis foot on the plane: a first guess of the table centre
    ray = np.array([0.0, 0.0, 1.0])
    foot = ray * (-d / (n @ ray)) if abs(n @ ray) > 1e-3 else -n * d
    # the first axis point from what moves: the objects' turn between the sampled frames (the
    # static room and clutter beside the table do not move, so they do not pull it)
    pairs, A.moving = _sampled_motion(session, cfg, arm, good_sample, n, d, sign)
    pairs = [p for p in pairs if p["score"] >= 0.3]
    if pairs:
        centre = np.median(np.stack([p["centre"] for p in pairs]), axis=0)
        A.axis_source = f"motion of the objects ({len(pairs)} frame pairs)"
    else:   # nothing moves enough to tell (a round object on the axis): what stands on the table
        above = []
        for pts in full:
            h, r = _height_radius(pts, n, foot)
            m = (h > 5.0) & (h < cfg.crop_height_mm) & (r < cfg.max_crop_radius_mm * 0.7)
            above.append(pts[m] - h[m, None] * n)
        above = np.concatenate(above) if above else np.zeros((0, 3))
        centre = above.mean(axis=0) if len(above) > 50 else foot
        A.axis_source = "centroid above the table (too little motion to measure)"
    A.axis_dir, A.axis_point = n.copy(), centre - n * (n @ centre + d)
    # --- load every frame, loosely cropped (pass 1 crop) --------------------------------------
    task = prog.add_task(f"arm {arm}: load", total=len(available))
    for k in available:
        try:
            pts = _load_points(session, cfg, arm, k)
        except TdofError as e:
            A.bad[k] = str(e)
            prog.advance(task)
            continue
        pts = _crop(pts, A.axis_dir, A.axis_point, cfg.max_crop_radius_mm + 100.0, cfg)
        pts = np.asarray(_pcd(pts).voxel_down_sample(cfg.voxel_sizes_mm[-1]).points)
        if len(pts) < cfg.min_points:
            A.bad[k] = f"too few depth points on the turntable ({len(pts)} < {cfg.min_points})"
        else:
            A.points[k] = pts
        prog.advance(task)
    usable = sorted(A.points)
    if len(usable) < 2:
        raise TdofError(f"arm {arm}: fewer than 2 usable {cfg.phase} frames")
    origin = np.zeros(3)

    full_pyr = {k: _Pyramid(A.points[k], cfg, origin) for k in usable}

    def pyramids(radius: float) -> dict[int, _Pyramid]:
        out = {}
        for k in usable:
            c = full_pyr[k].cropped(A.axis_dir, A.axis_point, radius)
            if len(c) >= cfg.min_points:
                out[k] = c
        return out

    # --- pass 1 / pass 2: pairwise ICP, pose graph, axis refit ---------------------------------
    poses: dict[int, np.ndarray] = {}
    n_lv = len(cfg.voxel_sizes_mm)
    p1_lv = max(1, min(cfg.pass1_levels, n_lv))
    passes = [(cfg.pass1_edge_max_deg, cfg.pass1_edge_max_mm, tuple(cfg.pass1_edge_angles_deg), p1_lv),
              (cfg.edge_max_deg, cfg.edge_max_mm, tuple(cfg.edge_angles_deg), n_lv)]
    for pass_no, (mx_deg, mx_mm, angles, nl) in enumerate(passes):
        first = 0 if pass_no == 0 else max(0, min(cfg.pass2_first_level, nl - 1))
        radius = cfg.max_crop_radius_mm if pass_no == 0 else A.radius
        pyr = pyramids(radius)
        for k in usable:
            if k not in pyr:
                A.bad[k] = "too few depth points inside the turntable volume"
        n_pairs = len(_edge_pairs(sorted(pyr), sd, angles))
        task = prog.add_task(f"arm {arm}: pairwise ICP (pass {pass_no + 1})", total=n_pairs)
        poses, edge_stats = _pose_graph_pass(A, pyr, cfg, sd, sign, mx_deg, mx_mm, angles, list(range(first, nl)),
                                             prog, task)
        ks = np.array(sorted(poses))
        Ts = np.stack([poses[k] for k in ks])
        # fit the axis on frames that agree with the current prior (robust to a bad frame)
        pri = np.stack([_prior(A.axis_dir, A.axis_point, k * sd, sign) for k in ks])
        rd, _ = _T_diff(pri, Ts)
        w = (rd <= max(mx_deg, 2 * np.median(rd) + 1e-3)).astype(float)
        if w.sum() >= 2 and _rot_deg(Ts[w > 0, :3, :3]).max() > 1.0:
            A.axis_dir, A.axis_point = _fit_axis(Ts, A.plane_n, A.plane_n, A.plane_d, w)
        # table radius from the plane inliers of the sampled frames
        if cfg.crop_radius_mm is not None:
            A.radius = float(cfg.crop_radius_mm)
        else:
            disk = _disk_radius(full, A.axis_dir, A.axis_point, info.camera, cfg)
            # whatever the disk's edge looks like, the crop holds what turns with it
            _, r_mov = _height_radius(A.moving, A.axis_dir, A.axis_point)
            r_mov = r_mov[r_mov < cfg.max_crop_radius_mm]
            reach = float(np.percentile(r_mov, 98)) if len(r_mov) >= 50 else 0.0
            A.radius = (cfg.max_crop_radius_mm if disk is None
                        else float(min(cfg.max_crop_radius_mm, max(disk, reach) + cfg.crop_margin_mm)))
    # --- per-frame refinement against the arm's fused cloud, residuals, flags -----------------
    # (the pyramids of pass 2 are kept: the axis moved by a fraction of a mm since they were cropped)
    frames: list[FrameRegistration] = []
    c = np.append(A.axis_point, 1.0)
    prior = {k: _prior(A.axis_dir, A.axis_point, k * sd, sign) for k in range(K)}

    def residual(T, k):
        rd = float(_T_diff(prior[k], T)[0])
        rm = float(np.linalg.norm((T @ c - prior[k] @ c)[:3]))
        return rd, rm

    if cfg.refine_against_model:
        pre_ok = [k for k in sorted(pyr) if max(residual(poses[k], k)[0] / cfg.max_residual_deg,
                                                residual(poses[k], k)[1] / cfg.max_residual_mm) <= 1.0]
        model = _fuse([pyr[k].levels[-1] for k in pre_ok], [poses[k] for k in pre_ok], cfg.model_voxel_mm)
        model_pyr = _Pyramid.from_cloud(model, cfg)
        task = prog.add_task(f"arm {arm}: refine", total=len(pyr))
    final: dict[int, np.ndarray] = {}
    for k in range(K):
        if k in A.bad or k not in pyr:
            final[k] = prior[k]
            frames.append(FrameRegistration(arm, k, prior[k], flagged=True,
                                            reason=A.bad.get(k, "too few depth points inside the turntable volume")))
            continue
        reasons = []
        if cfg.refine_against_model:
            T, fit, rmse, _ = _icp(pyr[k], model_pyr, poses[k], cfg, cfg.frame_icp_dist_mm, levels=[n_lv - 1],
                                   information=False)
            prog.advance(task)
        else:
            # the frame's pairwise registrations (pass 2): median fitness / RMSE of its edges
            T = poses[k]
            st = edge_stats.get(k, [])
            fit = float(np.median([e[0] for e in st])) if st else 0.0
            rmse = float(np.median([e[1] for e in st])) if st else float("nan")
            if not any(e[2] for e in st):
                reasons.append("no pairwise registration agrees with the turntable prior")
        rd, rm = residual(T, k)
        if fit < cfg.min_fitness:
            reasons.append(f"fitness {fit:.2f} < {cfg.min_fitness}")
        if not rmse <= cfg.max_rmse_mm:
            reasons.append(f"inlier RMSE {rmse:.2f} mm > {cfg.max_rmse_mm}")
        if rd > cfg.max_residual_deg:
            reasons.append(f"residual {rd:.2f} deg > {cfg.max_residual_deg} vs the turntable prior")
        if rm > cfg.max_residual_mm:
            reasons.append(f"residual {rm:.1f} mm > {cfg.max_residual_mm} vs the turntable prior")
        final[k] = T
        frames.append(FrameRegistration(arm, k, T, fit, rmse, rd, rm, bool(reasons), "; ".join(reasons)))
    good = [f.step for f in frames if not f.flagged]
    fused = _fuse([pyr[k].levels[-1] for k in good], [final[k] for k in good], cfg.model_voxel_mm)
    return A, final, frames, fused


def _fuse(clouds: list, poses: list[np.ndarray], voxel: float) -> "o3d.geometry.PointCloud":
    """Clouds (with normals) moved by their poses, merged and voxel-downsampled (normals kept)."""
    pts = [np.asarray(c.points) @ T[:3, :3].T + T[:3, 3] for c, T in zip(clouds, poses)]
    nrm = [np.asarray(c.normals) @ T[:3, :3].T for c, T in zip(clouds, poses)]
    pc = _pcd(np.concatenate(pts) if pts else np.zeros((0, 3)))
    if pts:
        pc.normals = o3d.utility.Vector3dVector(np.concatenate(nrm))
    pc = pc.voxel_down_sample(voxel)
    if pts:
        pc.normalize_normals()
    return pc


class _ArmJob:
    """One arm position's registration as a picklable job for :func:`run_chunks` (worker
    processes): returns the fused cloud as arrays, since open3d clouds do not pickle."""

    def __init__(self, session_dir: Path, cfg: "RegistrationConfig", sign: float):
        self.session_dir, self.cfg, self.sign = Path(session_dir), cfg, sign

    def __call__(self, arm: int):
        session = RawSession.open(self.session_dir)
        t = time.perf_counter()
        with _progress(False) as prog:
            A, poses, fr, cloud = _register_arm(session, self.cfg, arm, self.sign, prog)
        return arm, A, poses, fr, np.asarray(cloud.points), np.asarray(cloud.normals), time.perf_counter() - t


def _cloud(points: np.ndarray, normals: np.ndarray) -> "o3d.geometry.PointCloud":
    pc = _pcd(points)
    if len(normals):
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    return pc


# ---------------------------------------------------------------------------------------------
# the session
# ---------------------------------------------------------------------------------------------
def _cross_check_axes(arms: list[ArmRegistration], pose: str, cfg: RegistrationConfig, how: str) -> None:
    """Flag every arm position whose turntable axis, moved into the reference camera by its pose
    ``pose`` ("T_ref_arm_prior": the robot's; "T_ref_arm": after the arm-to-arm ICP), stands
    more than ``arm_axis_max_mm`` (at the table top) or ``arm_axis_max_deg`` from the others'
    consensus (the median; with two arms, each other). Every arm sees the same turntable, so an
    arm that disagrees has a wrong axis or a wrong relation to the others: none of its frames is
    labelled."""
    live = [a for a in arms if not a.flagged]
    if len(live) < 2:
        return
    dirs = np.stack([getattr(a, pose)[:3, :3] @ a.axis_dir for a in live])
    pts = np.stack([(getattr(a, pose) @ np.append(a.axis_point, 1.0))[:3] for a in live])
    for i, a in enumerate(live):
        if len(live) == 2:   # no majority: each against the other
            pc, dc = pts[1 - i], dirs[1 - i]
        else:
            pc, dc = np.median(pts, axis=0), np.median(dirs, axis=0)
            dc = dc / np.linalg.norm(dc)
        rel = pts[i] - pc
        off = float(np.linalg.norm(rel - (rel @ dc) * dc))
        ang = math.degrees(math.acos(float(np.clip(abs(dirs[i] @ dc), -1.0, 1.0))))
        if off > cfg.arm_axis_max_mm or ang > cfg.arm_axis_max_deg:
            a.flagged = True
            reason = (f"its turntable axis stands {off:.1f} mm / {ang:.2f} deg from the other arm positions' "
                      f"{how} (limits {cfg.arm_axis_max_mm:g} mm / {cfg.arm_axis_max_deg:g} deg)")
            a.reason = f"{a.reason}; {reason}" if a.reason else reason


def _check_depth(session: RawSession, cfg: RegistrationConfig) -> None:
    """Session-level refusals before any arm is registered, each one line naming the file: no
    frames of the registered phase (or an arm position without any), frames of another size than
    session.json's camera, depth that is not in millimetres through ``camera.depth_scale``."""
    keys = session.require_frames(cfg.phase)
    sample = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, min(5, len(keys))).round().astype(int))]
    zs = []
    for ph, a, k in sample:
        try:
            zs.append(session.load_depth_mm(ph, a, k))
        except TdofError as e:
            if "session.json's camera" in str(e):   # every frame has that size: say so, not "no depth"
                raise
    if zs:
        problem = depth_units_problem(session.info, np.stack(zs))
        if problem:
            where = ", ".join(f"arm {a} step {k}" for _, a, k in sample)
            raise TdofError(f"{problem} (sampled {cfg.phase} frames: {where})", session.path / "session.json")


def register_session(session_dir: str | Path, cfg: RegistrationConfig | None = None,
                     progress: bool = True, workers: int | None = 1) -> RegistrationResult:
    """Register every frame of a raw session to frame (arm 0, step 0) from the opaque depth.

    The arm positions are independent until they are related at the end: with ``workers`` > 1
    (None = every core) they run on that many local worker processes, one arm each (the result
    is the same; only the progress display is coarser).

    Returns a :class:`RegistrationResult`; flagged frames keep their best (prior) pose and say why.
    Raises :class:`TdofError` (one line) when the session cannot be registered at all (no opaque
    phase, an arm position without usable frames, no table plane)."""
    cfg = cfg or RegistrationConfig()
    t0 = time.perf_counter()
    session = RawSession.open(session_dir)
    info = session.info
    if cfg.phase not in info.phases:
        raise TdofError(f"the session has no {cfg.phase} phase (phases: {list(info.phases)}): "
                        f"registration needs the opaque twins' depth", session.path / "session.json")
    _check_depth(session, cfg)
    recorded = isinstance(info.turntable, dict) and "direction" in info.turntable
    direction = str(info.turntable.get("direction", "ccw")).lower() if recorded else "ccw"
    sign = -1.0 if direction in ("cw", "clockwise") else 1.0
    t_check = time.perf_counter()
    checked = _check_turntable(session, cfg, sign, recorded)
    turntable = {"direction": "ccw" if checked > 0 else "cw",
                 "source": "session.json" if recorded else ("detected from the opaque depth" if checked != sign
                                                            else "default (ccw), confirmed or not contradicted by "
                                                                 "the opaque depth")}
    sign = checked
    timing_check = round(time.perf_counter() - t_check, 3)
    timing: dict[str, float] = {"turntable_check": timing_check}
    arms: list[ArmRegistration] = []
    frames: list[FrameRegistration] = []
    fused: dict[int, Any] = {}
    per_arm: dict[int, dict[int, np.ndarray]] = {}
    T_base_cam0 = info.T_base_cam(0)
    from tdof20.annotate.executors import resolve_workers, run_chunks

    n_workers = min(resolve_workers(workers), info.n_arms)
    results: dict[int, tuple] = {}
    if n_workers > 1:   # one arm per worker process; a failing arm raises its TdofError here
        for arm, A, poses, fr, P, N, dt in run_chunks(_ArmJob(session.path, cfg, sign), range(info.n_arms),
                                                      workers=n_workers, progress=progress,
                                                      description="register (arm positions)", unit="arm"):
            results[arm] = (A, poses, fr, _cloud(P, N), dt)
    with _progress(progress, unit="icp") as prog:
        for a in range(info.n_arms):
            if a not in results:
                ta = time.perf_counter()
                A, poses, fr, cloud = _register_arm(session, cfg, a, sign, prog)
                results[a] = (A, poses, fr, cloud, time.perf_counter() - ta)
            A, poses, fr, cloud, dt = results[a]
            timing[f"arm{a}"] = round(dt, 3)
            per_arm[a] = poses
            fused[a] = cloud
            frames.extend(fr)
            T_prior = invert(T_base_cam0) @ info.T_base_cam(a)
            arms.append(ArmRegistration(a, A.axis_dir, A.axis_point, A.plane_n, A.plane_d, A.radius,
                                        T_prior.copy() if a else np.eye(4), T_prior if a else np.eye(4)))
        # --- the arms' axes must agree through the robot's poses --------------------------------
        _cross_check_axes(arms, "T_ref_arm_prior", cfg, "through the robot's poses")
        # --- relate the arm positions ---------------------------------------------------------
        ta = time.perf_counter()
        ref = _Pyramid.from_cloud(fused[0], cfg) if len(fused[0].points) else None
        for arm_reg in arms[1:]:
            a = arm_reg.arm
            if not cfg.refine_arms or ref is None or len(fused[a].points) < cfg.min_points:
                if cfg.refine_arms:
                    arm_reg.reason = "arm-to-arm refinement skipped: too few registered points; robot prior kept"
                continue
            src = _Pyramid.from_cloud(fused[a], cfg)
            T, fit, rmse, _ = _icp_prior(src, ref, arm_reg.T_ref_arm_prior, arms[0].axis_point, cfg,
                                         sigma_deg=cfg.arm_prior_sigma_deg, sigma_mm=cfg.arm_prior_sigma_mm,
                                         information=False)
            cd, cm = _T_diff(arm_reg.T_ref_arm_prior, T)
            # correction measured at the table centre (not at the camera origin)
            c = np.append(arm_reg.axis_point, 1.0)
            cm = float(np.linalg.norm((T @ c - arm_reg.T_ref_arm_prior @ c)[:3]))
            arm_reg.fitness, arm_reg.rmse = fit, rmse
            arm_reg.correction_deg, arm_reg.correction_mm = float(cd), cm
            if fit < cfg.arm_min_fitness or cd > cfg.max_arm_correction_deg or cm > cfg.max_arm_correction_mm:
                arm_reg.flagged = True
                arm_reg.reason = (f"arm-to-arm ICP disagrees with the robot prior (fitness {fit:.2f}, correction "
                                  f"{float(cd):.2f} deg / {cm:.1f} mm); robot prior kept")
            else:
                arm_reg.T_ref_arm = T
        _cross_check_axes(arms, "T_ref_arm", cfg, "after the arm-to-arm ICP")
        timing["arms"] = round(time.perf_counter() - ta, 3)
    for f in frames:
        f.T_ref_frame = arms[f.arm].T_ref_arm @ per_arm[f.arm][f.step]
    frames.sort(key=lambda f: (f.arm, f.step))
    timing["total"] = round(time.perf_counter() - t0, 3)
    return RegistrationResult(info.scene_id, info.steps, float(info.step_deg), info.n_arms, frames, arms,
                              cfg.to_dict(), timing, turntable)


# ---------------------------------------------------------------------------------------------
# evaluation against the simulator's truth
# ---------------------------------------------------------------------------------------------
def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, float)
    if x.size == 0:
        return {"median": None, "p95": None, "max": None, "n": 0}
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)), "max": float(x.max()),
            "n": int(x.size)}


def truth_T_ref_frame(session_dir: str | Path) -> np.ndarray:
    """(n_arms, steps, 4, 4) true T_ref_frame from truth/scene_camera.json (NaN where absent):
    ``T_cam00_table @ inv(T_cam_ak_table)``."""
    session = RawSession.open(session_dir)
    if session.truth_dir is None:
        raise TdofError("no truth/ folder: evaluation needs a simulated session", session.path)
    cams = read_json(session.truth_dir / "scene_camera.json")
    n_arms, K = session.info.n_arms, session.info.steps
    T = np.full((n_arms, K, 4, 4), np.nan)
    for a in range(n_arms):
        for k in range(K):
            c = cams.get(str(a * K + k))
            if c is None or "cam_R_w2c" not in c:
                continue
            M = np.eye(4)
            M[:3, :3] = np.asarray(c["cam_R_w2c"], float).reshape(3, 3)
            M[:3, 3] = np.asarray(c["cam_t_w2c"], float)
            T[a, k] = M                                   # T_cam_table
    if np.isnan(T[0, 0]).any():
        raise TdofError("truth has no camera pose for arm 0 step 0", session.truth_dir / "scene_camera.json")
    ok = ~np.isnan(T).any(axis=(-1, -2))
    out = np.full_like(T, np.nan)
    out[ok] = T[0, 0] @ invert(T[ok])
    return out


def evaluate_against_truth(result: RegistrationResult, session_dir: str | Path, max_pairs: int = 20000,
                           seed: int = 0) -> dict:
    """Errors of the registration against the simulator's truth (flagged frames left out).

    Returns a dict with, each as {median, p95, max, n}:
    ``frame_to_ref`` (T_ref_frame itself), ``consecutive`` (motions between neighbouring steps of
    an arm) and ``pairs`` (motions between all pairs of frames, sampled to ``max_pairs``) — each
    with ``rot_deg`` and ``trans_mm`` (the motion ``inv(T_ref_i) @ T_ref_j``, cam j -> cam i,
    compared as ``inv(est) @ true``); per arm the axis direction error (deg), the axis point's
    distance from the true table centre (mm), and the T_ref_arm error of the refined and of the
    robot prior transform."""
    truth = truth_T_ref_frame(session_dir)
    est = result.poses()
    n_arms, K = truth.shape[:2]
    keys = [(f.arm, f.step) for f in result.frames
            if result.usable(f.arm, f.step) and not np.isnan(truth[f.arm, f.step]).any()]
    E = np.stack([est[a, k] for a, k in keys])
    G = np.stack([truth[a, k] for a, k in keys])
    out: dict[str, Any] = {"n_frames": len(keys), "n_flagged": len(result.flagged_frames())}
    rd, tm = _T_diff(E, G)
    out["frame_to_ref"] = {"rot_deg": _stats(rd), "trans_mm": _stats(tm)}
    pos = {key: n for n, key in enumerate(keys)}
    cons = [(pos[(a, k)], pos[(a, k + 1)]) for a, k in keys if (a, k + 1) in pos]

    def motion_err(pairs):
        if not pairs:
            return {"rot_deg": _stats([]), "trans_mm": _stats([])}
        i, j = np.array(pairs).T
        Me = invert(E[i]) @ E[j]
        Mg = invert(G[i]) @ G[j]
        r, t = _T_diff(Me, Mg)
        return {"rot_deg": _stats(r), "trans_mm": _stats(t)}
    out["consecutive"] = motion_err(cons)
    n = len(keys)
    if n * (n - 1) // 2 <= max_pairs:
        i, j = np.triu_indices(n, 1)
    else:
        rng = np.random.default_rng(seed)
        i = rng.integers(0, n, max_pairs)
        j = rng.integers(0, n, max_pairs)
        m = i != j
        i, j = i[m], j[m]
    out["pairs"] = motion_err(list(zip(i.tolist(), j.tolist())))
    # per arm: axis and arm-to-arm transforms
    session = RawSession.open(session_dir)
    cams = read_json(session.truth_dir / "scene_camera.json")
    arms = []
    for ar in result.arms:
        c = cams.get(str(ar.arm * K))
        entry: dict[str, Any] = {"arm": ar.arm}
        if c is not None:
            R = np.asarray(c["cam_R_w2c"], float).reshape(3, 3)
            t = np.asarray(c["cam_t_w2c"], float)
            up = R[:, 2]
            entry["axis_deg"] = float(np.degrees(np.arccos(np.clip(ar.axis_dir @ up, -1, 1))))
            entry["axis_point_mm"] = float(np.linalg.norm(ar.axis_point - t))
            d = ar.axis_point - t
            entry["axis_line_mm"] = float(np.linalg.norm(d - (d @ up) * up))
        if not np.isnan(truth[ar.arm, 0]).any():
            Tt = truth[ar.arm, 0]                         # cam(a,0) -> cam(0,0)
            r1, t1 = _T_diff(ar.T_ref_arm, Tt)
            r0, t0 = _T_diff(ar.T_ref_arm_prior, Tt)
            entry.update({"T_ref_arm_rot_deg": float(r1), "T_ref_arm_trans_mm": float(t1),
                          "prior_rot_deg": float(r0), "prior_trans_mm": float(t0)})
        arms.append(entry)
    out["arms"] = arms
    return out


__all__ = ["RegistrationConfig", "FrameRegistration", "ArmRegistration", "RegistrationResult",
           "register_session", "evaluate_against_truth", "truth_T_ref_frame"]
