"""The registration's options (:class:`RegistrationConfig`), apart from the passes that use them
(:mod:`~tdof20.annotate.registration`, :mod:`~tdof20.annotate.turntable`,
:mod:`~tdof20.annotate.icp`, :mod:`~tdof20.annotate.depthmaps`) so that each of them imports it
from below."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from tdof20.config import check_ranges
from tdof20.errors import TdofError

__all__ = ["RegistrationConfig"]

PHASE = "opaque"


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
    association: str = "auto"                 # frame-to-frame correspondences: "projective" (the target
                                              # pixel a moved point projects to, on depth maps block-averaged to
                                              # each scale: tdof20.annotate.depthmaps), "closest" (the nearest
                                              # point of voxel-downsampled clouds, a k-d tree), or "auto":
                                              # projective where a pixel is at most half the finest scale at the
                                              # table (640x480: ~3x less CPU, as accurate), else closest (on
                                              # coarse pixels, ~4 mm at 160x120, its correspondences are better)
    map_max_variation: float = 0.05           # projective: a pixel whose window's smallest principal axis holds
                                              # more than this share of the spread (an edge) has no normal
    normal_voxel_mm: float | None = 4.0       # normals estimated on this sparser cloud (closest: a voxel grid;
                                              # projective: the map of the scale of this size) and handed to the
                                              # finer levels' points (nearest / the pixel holding them): 4x fewer
                                              # points; None = each level its own
    # data: depth range and plane
    min_depth_mm: float = 150.0
    max_depth_mm: float = 2000.0
    plane_window: float = 0.6                 # central fraction of the image searched for the table
    plane_dist_mm: float = 4.0                # RANSAC inlier distance
    plane_prior_max_deg: float = 30.0         # table normal within this of the robot's vertical
    plane_max_below: float = 0.3              # most of the image centre must not lie below the table
                                              # (the rule when too little moves to tell)
    plane_moving_below: float = 0.05          # the table top has at most this share of the moving points below it
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
    pass2_first_level: int = 1                # pass 2 starts at this ICP scale: pass 1 and the refitted axis
                                              # put every good frame within a fraction of a degree, and the 4 mm
                                              # scale lets a bad frame's edges slide far enough from the prior to
                                              # be dropped (with "closest", 2 saved 123 -> 89 s CPU per arm)
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
    arm_plane_max_mm: float = 10.0            # every arm's table top within this of the others' (along the axis)
    # the depth camera's scale error, from the arm positions (registration.depth_scale_from_arms)
    depth_scale_correct: bool = True          # divide the depth by the estimate (off: only measure it)
    depth_scale_rounds: int = 2               # ICP rounds: on the clouds as read, then divided by the first estimate
    depth_scale_max: float = 1.05             # a scale error beyond 1/x..x is refused, not corrected
    depth_scale_max_ci95: float = 0.01        # an estimate less sure than this (95 % half-width) is refused
    depth_scale_icp_mm: float = 0.5           # the arm-to-arm ICP's translation error along the arms' baseline
    depth_scale_min_baseline_mm: float = 50.0  # arm positions closer than this say nothing of the scale

    def __post_init__(self) -> None:
        check_ranges(self, "register", positive=(
            "voxel_sizes_mm", "icp_dist_factor", "icp_iterations", "normal_radius_mm", "normal_max_nn",
            "icp_tol_rad", "icp_tol_mm", "normal_voxel_mm", "min_depth_mm", "max_depth_mm", "plane_dist_mm",
            "plane_prior_max_deg", "plane_frames", "crop_height_mm", "crop_radius_mm", "max_crop_radius_mm",
            "min_points", "max_source_points", "pass1_levels", "prior_sigma_deg", "prior_sigma_mm",
            "prior_sigma_r_mm", "pass1_edge_max_deg", "pass1_edge_max_mm", "edge_max_deg", "edge_max_mm",
            "model_voxel_mm", "frame_icp_dist_mm", "max_rmse_mm", "max_residual_deg", "max_residual_mm",
            "arm_prior_sigma_deg", "arm_prior_sigma_mm", "max_arm_correction_deg", "max_arm_correction_mm",
            "arm_axis_max_mm", "arm_axis_max_deg", "arm_plane_max_mm", "depth_scale_rounds", "depth_scale_max", "depth_scale_max_ci95",
            "depth_scale_icp_mm", "depth_scale_min_baseline_mm"),
            non_negative=("crop_below_mm", "crop_margin_mm", "edge_angles_deg", "pass1_edge_angles_deg",
                          "pass2_first_level"),
            fraction=("map_max_variation", "plane_window", "plane_max_below", "plane_moving_below", "edge_min_fitness", "min_fitness", "arm_min_fitness"))
        if self.association not in ("auto", "projective", "closest"):
            raise TdofError(f"register.association must be 'auto', 'projective' or 'closest', got '{self.association}'")
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

