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

Stages, per arm position (:func:`register_session`). This module holds the per-arm and session
passes; the options are in :mod:`~tdof20.annotate.registration_config`, the results in
:mod:`~tdof20.annotate.registration_result`, the turntable's model and what the depth says about
it in :mod:`~tdof20.annotate.turntable`, the clouds, ICP and the pose graph in
:mod:`~tdof20.annotate.icp`, the evaluation against the simulator's truth in
:mod:`~tdof20.annotate.evaluate`.

1. table plane by seeded RANSAC on the centre of a few frames: of the planes with a normal near the
   robot's vertical (the prior ``R_base_cam^T e_z``), refined by least squares, the highest with
   (almost) none of the moving points below it — the objects stand on the turntable top, the bench
   below it has them above it too but lies lower (``turntable.table_plane``); when no level plane
   qualifies the table top is a guess and the arm is flagged with that reason. The normal,
   oriented towards the camera, is the first estimate of the turntable axis;
2. a first axis point from **what moves**: per sampled frame the points that stand there and not
   in another sampled frame (the objects; the static room, clutter beside the table and the
   featureless disk drop out), and between consecutive sampled frames the centre of the turn
   that carries one onto the other (``turntable.sampled_motion``: a 2D rotation about the table
   normal by the nominal angle, centroid start, trimmed ICP; the centre solves ``(I - R) c = t``);
   the median centre over the pairs. Only when nothing moves enough to tell (a round cup on the
   axis) the centroid of what stands on the table. Before any arm, the same measurement over the
   whole circle checks ``turntable.direction`` and ``step_deg`` (``turntable.check_turntable``): a
   direction left out of session.json is taken from the data, one the data contradicts and a
   step angle it does not show are refused; an arm the check measured reuses its table plane
   and motion (same frames, same numbers);
3. pass 1: pairwise point-to-plane ICP (multi-scale, coarse scales only) between frames 1 step
   and ~30 deg apart (the 360 deg loop closes itself where the plan covers a full turn), each
   started from the known step angle about the axis, on points cropped to the turntable volume (a
   cylinder about the axis above the table plane), then a pose graph (open3d
   ``global_optimization``) over the frames connected to step 0 (``icp.pose_graph_pass``); the
   axis (direction and point) is refitted to the poses (``turntable.fit_axis``), and the table
   radius from the plane's points (``turntable.disk_radius``: where the plane band stops filling
   every direction about the axis — a cabinet's face beside the table fills only a few);
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
   at the table top and ``arm_axis_max_deg``, and its table top within ``arm_plane_max_mm`` of
   theirs along the axis; the median of three or more, each other for two);
   the robot prior ``inv(T_base_cam(0)) @ T_base_cam(a)`` is refined by ICP between the arms'
   fused turntable clouds; a correction beyond the limits keeps the prior and flags the arm, and
   the axes are checked again after the ICP. A flagged arm has none of its frames labelled.

Why the pairwise ICP is regularised towards the turntable prior (``prior_weighted_icp``): depth
is quantised (1 mm steps at ``depth_scale`` 1), and the quantisation terraces are fixed in the
image, so they pull plain ICP towards "nothing moved" wherever the geometry leaves a direction
free — a rotationally symmetric object near the axis (single-object scenes) leaves the turn
angle free, and plain ICP then reported 12 deg for a 15 deg step. The regularised ICP
(``icp.icp_prior``: Gauss-Newton point-to-plane plus a Gaussian prior on the deviation from the
turntable model) follows the data in the directions the geometry pins and keeps the prior in the
others.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.annotate.depthmaps import (DepthMap, MapPyramid, block_depth, icp_maps, map_stride, source_points,
                                      strided_camera)
from tdof20.annotate.executors import resolve_workers, run_chunks
from tdof20.annotate.icp import Pyramid, edge_pairs, icp, icp_prior, point_cloud, pose_graph_pass
from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.annotate.registration_result import ArmRegistration, FrameRegistration, RegistrationResult
from tdof20.annotate.turntable import (T_diff, VolumeCrop, check_turntable, disk_radius, fit_axis, height_radius,
                                       load_points, rot_deg, sampled_motion, table_plane, turntable_prior)
from tdof20.errors import TdofError
from tdof20.formats.session import RawSession, depth_units_problem
from tdof20.geometry.transforms import invert
from tdof20.o3d import o3d
from tdof20.progress import progress as _progress

# the options and the results have their own modules (the passes import the options from below);
# their names stay importable from here
__all__ = ["RegistrationConfig", "FrameRegistration", "ArmRegistration", "RegistrationResult", "register_session"]


# ---------------------------------------------------------------------------------------------
# per arm position
# ---------------------------------------------------------------------------------------------
class _Arm:
    """The frames of one arm position: raw (loosely cropped) points and the table geometry."""

    def __init__(self, arm: int, steps: int):
        self.arm = arm
        self.bad: dict[int, str] = {}             # step -> why it could not be used
        self.plane_n = np.array([0.0, 0.0, -1.0])
        self.plane_d = 0.0
        self.axis_dir = self.plane_n.copy()
        self.axis_point = np.zeros(3)
        self.radius = 0.0
        self.steps = steps
        self.axis_source = ""
        self.moving = np.zeros((0, 3))            # points that moved between sampled frames (the objects)
        self.plane_problem = ""                   # why the table top is a guess ("" when it is not)
        self.association = ""                     # the correspondences used ("projective" / "closest")


def _register_arm(session: RawSession, cfg: RegistrationConfig, arm: int, sign: float, prog,
                  measured: dict | None = None
                  ) -> tuple[_Arm, dict[int, np.ndarray], list[FrameRegistration], np.ndarray]:
    """Everything within one arm position. Returns (arm info, T_arm_frame per step, frames, fused cloud).
    ``measured``: what :func:`~tdof20.annotate.turntable.check_turntable` measured of this arm
    (its table plane and sampled motion, reused when taken on the same frames)."""
    info = session.info
    K, sd = info.steps, info.step_deg
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
    # the turntable check measured the plane and the motion of this arm on the same frames already
    m = measured if measured and measured.get("steps") == good_sample else None
    if m is not None:
        n, d = np.asarray(m["n"], float), float(m["d"])
        full = [load_points(session, cfg, arm, k) for k in good_sample]
        plane = m.get("plane", {})
    else:
        plane = {}
        n, d, full = table_plane(session, cfg, arm, good_sample, prior_up, plane)
    A.plane_n, A.plane_d = n, d
    A.plane_problem = plane.get("problem", "")
    # optical axis foot on the plane: a first guess of the table centre
    ray = np.array([0.0, 0.0, 1.0])
    foot = ray * (-d / (n @ ray)) if abs(n @ ray) > 1e-3 else -n * d
    # the first axis point from what moves: the objects' turn between the sampled frames (the
    # static room and clutter beside the table do not move, so they do not pull it)
    if m is not None and m["sign"] == sign:
        pairs, A.moving = m["pairs"], np.asarray(m["moving"], float)
    else:
        pairs, A.moving = sampled_motion(session, cfg, arm, good_sample, n, d, sign)
    good = [p for p in pairs if p["score"] >= 0.3]
    agree = _agreeing_centres([p["centre"] for p in pairs if p["score"] >= 0.1], n)
    _, r_mov = height_radius(A.moving, n, foot)
    if good:
        centre = np.median(np.stack([p["centre"] for p in good]), axis=0)
        A.axis_source = f"motion of the objects ({len(good)} frame pairs)"
    elif agree is not None:   # big turns between the sampled frames fit poorly (the objects look
        # different from afar), but independent pairs that turn about one centre agree on it
        centre = agree
        A.axis_source = "motion of the objects (frame pairs that fit poorly but agree on the centre)"
    elif (r_mov < cfg.max_crop_radius_mm).sum() >= 200:   # what moves: the objects, never the static room
        mov = A.moving[r_mov < cfg.max_crop_radius_mm]
        centre = mov.mean(axis=0)
        A.axis_source = "centroid of the moving points (their turn could not be measured)"
    else:   # nothing moves enough to tell (a round object on the axis): what stands on the table
        above = []
        for pts in full:
            h, r = height_radius(pts, n, foot)
            m = (h > 5.0) & (h < cfg.crop_height_mm) & (r < cfg.max_crop_radius_mm * 0.7)
            above.append(pts[m] - h[m, None] * n)
        above = np.concatenate(above) if above else np.zeros((0, 3))
        centre = above.mean(axis=0) if len(above) > 50 else foot
        A.axis_source = "centroid above the table (too little motion to measure)"
    A.axis_dir, A.axis_point = n.copy(), centre - n * (n @ centre + d)
    # --- load every frame, loosely cropped; pass 1's levels cropped at once ---------------------
    # Memory (one arm of 400 frames at 640x480): only what a pass uses is kept — pass 1's coarse
    # level(s) in its crop, and the levels of pass 2 in the loose crop (float32) until pass 2 crops
    # them about the refined axis; the nearest-neighbour trees live while their frame is an ICP target.
    n_lv = len(cfg.voxel_sizes_mm)
    p1_lv = max(1, min(cfg.pass1_levels, n_lv))
    p2_first = max(0, min(cfg.pass2_first_level, n_lv - 1))
    pass_levels = [list(range(0, p1_lv)), list(range(p2_first, n_lv))]
    loose_levels = set(pass_levels[1]) | {n_lv - 1}          # the fused cloud takes the finest level
    task = prog.add_task(f"arm {arm}: load", total=len(available))
    cam = info.camera
    depth = float(A.axis_point[2]) if A.axis_point[2] > 0 else float(np.median(full[0][:, 2])) if len(full) else 500.0
    strides = {i: map_stride(cam, depth, cfg.voxel_sizes_mm[i]) for i in range(n_lv)}
    projective = cfg.association == "projective" or (cfg.association == "auto" and strides[n_lv - 1] >= 2)
    A.association = "projective" if projective else "closest"
    if projective:   # depth maps at each scale's stride; their crops (ray maps) made once per camera
        cams = {i: strided_camera(cam, strides[i]) for i in range(n_lv)}
        windows = {i: 2 * int(cfg.normal_radius_mm // (cfg.voxel_sizes_mm[i] * 1.0)) + 1 for i in range(n_lv)}
        crops1 = {i: VolumeCrop(cams[i], cfg, A.axis_dir, A.axis_point, cfg.max_crop_radius_mm) for i in pass_levels[0]}
        loose_crops = {i: VolumeCrop(cams[i], cfg, A.axis_dir, A.axis_point, cfg.max_crop_radius_mm + 100.0)
                       for i in loose_levels if i not in crops1}
        all_crops = {**crops1, **loose_crops}
        # normals estimated once, on the normal_voxel_mm scale, and handed to the finer maps (the
        # same window in mm on 4x fewer pixels), where the strides allow it
        normal_level = next((i for i in range(n_lv) if cfg.normal_voxel_mm and cfg.voxel_sizes_mm[i] == cfg.normal_voxel_mm
                             and all(strides[i] % strides[j] == 0 for j in range(i + 1, n_lv))), n_lv)
        fine_crop1 = VolumeCrop(cams[n_lv - 1], cfg, A.axis_dir, A.axis_point, cfg.max_crop_radius_mm)
    else:
        crop = VolumeCrop(info.camera, cfg, A.axis_dir, A.axis_point, cfg.max_crop_radius_mm + 100.0)
    origin = np.zeros(3)
    loose: dict[int, Any] = {}
    pass1: dict[int, Any] = {}
    for k in available:
        try:
            z = session.load_depth_mm(cfg.phase, arm, k)
        except TdofError as e:
            A.bad[k] = str(e)
            prog.advance(task)
            continue
        if projective:
            zb = block_depth(z, [strides[i] for i in all_crops], cfg.min_depth_mm, cfg.max_depth_mm, cam.fx)
            maps = {}
            for i in sorted(all_crops):   # coarse to fine: a finer map may take the normal level's normals
                src = maps.get(normal_level) if i > normal_level and normal_level in loose_crops else None
                maps[i] = DepthMap(zb[strides[i]], all_crops[i], cfg, windows[i], source_points(cfg, i),
                                   normals_from=src if i in loose_crops else None)
            fine = MapPyramid([maps.get(i) if i in loose_levels else None for i in range(n_lv)])
            if len(fine) < cfg.min_points:
                A.bad[k] = f"too few depth points on the turntable ({len(fine)} < {cfg.min_points})"
            else:
                c1 = MapPyramid([maps.get(i) if i in crops1 else None for i in range(n_lv)],
                                n_fine=fine.count_inside(fine_crop1))
                if len(c1) >= cfg.min_points:
                    pass1[k] = c1
                loose[k] = fine
            prog.advance(task)
            continue
        fine = point_cloud(crop.points(z)).voxel_down_sample(cfg.voxel_sizes_mm[-1])
        if len(fine.points) < cfg.min_points:
            A.bad[k] = f"too few depth points on the turntable ({len(fine.points)} < {cfg.min_points})"
        else:   # the finest level as it is (already on its grid), normals, the coarser levels
            built = Pyramid.from_fine(fine, cfg, origin, keep=set(pass_levels[0]) | loose_levels)
            c1 = built.cropped(A.axis_dir, A.axis_point, cfg.max_crop_radius_mm, levels=pass_levels[0])
            if len(c1) >= cfg.min_points:
                pass1[k] = c1
            loose[k] = Pyramid([lv if i in loose_levels else None for i, lv in enumerate(built.levels)], cfg)
        prog.advance(task)
    usable = sorted(loose)
    if len(usable) < 2:
        raise TdofError(f"arm {arm}: fewer than 2 usable {cfg.phase} frames")

    def pass2_pyramids(radius: float) -> dict[int, Any]:
        """Pass 2's levels cropped about the refined axis; the loose crops are dropped on the way."""
        out = {}
        if projective:
            crops = {i: VolumeCrop(cams[i], cfg, A.axis_dir, A.axis_point, radius) for i in pass_levels[1]}
        for k in usable:
            c = loose.pop(k)
            c = c.cropped(crops) if projective else c.cropped(A.axis_dir, A.axis_point, radius, levels=pass_levels[1])
            if len(c) >= cfg.min_points:
                out[k] = c
        return out

    # --- pass 1 / pass 2: pairwise ICP, pose graph, axis refit ---------------------------------
    poses: dict[int, np.ndarray] = {}
    passes = [(cfg.pass1_edge_max_deg, cfg.pass1_edge_max_mm, tuple(cfg.pass1_edge_angles_deg), p1_lv),
              (cfg.edge_max_deg, cfg.edge_max_mm, tuple(cfg.edge_angles_deg), n_lv)]
    for pass_no, (mx_deg, mx_mm, angles, nl) in enumerate(passes):
        first = 0 if pass_no == 0 else p2_first
        pyr = pass1 if pass_no == 0 else pass2_pyramids(A.radius)
        pass1 = {}
        for k in usable:
            if k not in pyr:
                A.bad[k] = "too few depth points inside the turntable volume"
        n_pairs = len(edge_pairs(sorted(pyr), sd, angles))
        task = prog.add_task(f"arm {arm}: pairwise ICP (pass {pass_no + 1})", total=n_pairs)
        poses, edge_stats = pose_graph_pass(pyr, cfg, arm, A.axis_dir, A.axis_point, A.radius, sd, sign, mx_deg,
                                            mx_mm, angles, list(range(first, nl)), prog, task,
                                            pair_icp=icp_maps if projective else None)
        ks = np.array(sorted(poses))
        Ts = np.stack([poses[k] for k in ks])
        # fit the axis on frames that agree with the current prior (robust to a bad frame)
        pri = np.stack([turntable_prior(A.axis_dir, A.axis_point, k * sd, sign) for k in ks])
        rd, _ = T_diff(pri, Ts)
        w = (rd <= max(mx_deg, 2 * np.median(rd) + 1e-3)).astype(float)
        if w.sum() >= 2 and rot_deg(Ts[w > 0, :3, :3]).max() > 1.0:
            A.axis_dir, A.axis_point = fit_axis(Ts, A.plane_n, A.plane_n, A.plane_d, w)
        # table radius from the plane inliers of the sampled frames
        if cfg.crop_radius_mm is not None:
            A.radius = float(cfg.crop_radius_mm)
        else:
            disk = disk_radius(full, A.axis_dir, A.axis_point, info.camera, cfg)
            # whatever the disk's edge looks like, the crop holds what turns with it
            _, r_mov = height_radius(A.moving, A.axis_dir, A.axis_point)
            r_mov = r_mov[r_mov < cfg.max_crop_radius_mm]
            reach = float(np.percentile(r_mov, 98)) if len(r_mov) >= 50 else 0.0
            A.radius = (cfg.max_crop_radius_mm if disk is None
                        else float(min(cfg.max_crop_radius_mm, max(disk, reach) + cfg.crop_margin_mm)))
    # --- per-frame refinement against the arm's fused cloud, residuals, flags -----------------
    # (the pyramids of pass 2 are kept: the axis moved by a fraction of a mm since they were cropped)
    frames: list[FrameRegistration] = []
    c = np.append(A.axis_point, 1.0)
    prior = {k: turntable_prior(A.axis_dir, A.axis_point, k * sd, sign) for k in range(K)}

    def residual(T, k):
        rd = float(T_diff(prior[k], T)[0])
        rm = float(np.linalg.norm((T @ c - prior[k] @ c)[:3]))
        return rd, rm

    if cfg.refine_against_model:
        pre_ok = [k for k in sorted(pyr) if max(residual(poses[k], k)[0] / cfg.max_residual_deg,
                                                residual(poses[k], k)[1] / cfg.max_residual_mm) <= 1.0]
        model = _fuse([_fine_cloud(pyr[k]) for k in pre_ok], [poses[k] for k in pre_ok], cfg.model_voxel_mm)
        model_pyr = Pyramid.from_cloud(model, cfg)
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
            src = Pyramid([None] * (n_lv - 1) + [_fine_cloud(pyr[k])], cfg) if projective else pyr[k]
            T, fit, rmse, _ = icp(src, model_pyr, poses[k], cfg, cfg.frame_icp_dist_mm, levels=[n_lv - 1],
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
    fused = _fuse([_fine_cloud(pyr[k]) for k in good], [final[k] for k in good], cfg.model_voxel_mm)
    return A, final, frames, fused


def _agreeing_centres(centres: list[np.ndarray], n: np.ndarray, tol_mm: float = 15.0) -> np.ndarray | None:
    """The median of the turn centres (measured between sampled frames) when at least three of them,
    and most, lie within ``tol_mm`` of it across the axis (along ``n``, the table normal, the
    centres may differ: the axis is a line); else None."""
    if len(centres) < 3:
        return None
    C = np.stack(centres)
    med = np.median(C, axis=0)
    d = C - med
    off = np.linalg.norm(d - np.outer(d @ n, n), axis=1)
    close = off <= tol_mm
    if close.sum() >= 3 and 2 * close.sum() > len(C):
        return np.median(C[close], axis=0)
    return None


def _fine_cloud(pyr) -> tuple[np.ndarray, np.ndarray]:
    """(points, normals) of a frame's finest scale: a Pyramid's finest level, a MapPyramid's pixels with a normal."""
    return pyr.finest().points() if isinstance(pyr, MapPyramid) else pyr.levels[-1]


def _fuse(clouds: list, poses: list[np.ndarray], voxel: float) -> "o3d.geometry.PointCloud":
    """Clouds ((points, normals) arrays) moved by their poses, merged and voxel-downsampled (normals
    averaged, then normalised): open3d's ``voxel_down_sample`` grid (anchored half a cell below the
    merged cloud's lowest corner) and cell means, streamed frame by frame — the merged cloud of an
    arm (400 frames, ~10 M points) is never held (measured: 1.2 GB less peak memory per arm).
    Cells in the order of their index."""
    if not clouds:
        return point_cloud(np.zeros((0, 3)))

    def moved(c, T):
        return np.asarray(c[0], np.float64) @ T[:3, :3].T + T[:3, 3]
    bounds = [(X.min(axis=0), X.max(axis=0)) for c, T in zip(clouds, poses) if len(c[0]) for X in [moved(c, T)]]
    if not bounds:
        return point_cloud(np.zeros((0, 3)))
    lo = np.min([b[0] for b in bounds], axis=0) - 0.5 * voxel
    dims = np.floor((np.max([b[1] for b in bounds], axis=0) - lo) / voxel).astype(np.int64) + 1
    kt = np.int32 if int(np.prod(dims)) < 2**31 else np.int64

    def key(c, T) -> np.ndarray:
        i = np.floor((moved(c, T) - lo) / voxel).astype(np.int64)
        return ((i[:, 0] * dims[1] + i[:, 1]) * dims[2] + i[:, 2]).astype(kt)
    # per chunk of ~2 M points: the chunk's cells (key, sums of points and normals, count), then the
    # chunks' cells merged the same way — the same cell means as one pass over the merged cloud
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    chunk: list[int] = []

    def flush() -> None:
        keys = [key(clouds[f], poses[f]) for f in chunk]
        uniq, inv = np.unique(np.concatenate(keys), return_inverse=True)
        inv = inv.reshape(-1)
        PN = np.concatenate([np.hstack([moved(clouds[f], poses[f]),
                                        np.asarray(clouds[f][1], np.float64) @ poses[f][:3, :3].T]) for f in chunk])
        acc = np.stack([np.bincount(inv, PN[:, a], minlength=len(uniq)) for a in range(6)], axis=1)
        parts.append((uniq, acc, np.bincount(inv, minlength=len(uniq)).astype(np.float64)))
        chunk.clear()
    n_chunk = 0
    for f, c in enumerate(clouds):
        if len(c[0]):
            chunk.append(f)
            n_chunk += len(c[0])
        if n_chunk >= 2_000_000:
            flush()
            n_chunk = 0
    if chunk:
        flush()
    if len(parts) == 1:
        uniq, sums, count = parts[0]
    else:
        uniq, inv = np.unique(np.concatenate([u for u, _, _ in parts]), return_inverse=True)
        inv = inv.reshape(-1)
        allsums = np.concatenate([a for _, a, _ in parts])
        sums = np.stack([np.bincount(inv, allsums[:, a], minlength=len(uniq)) for a in range(6)], axis=1)
        count = np.bincount(inv, np.concatenate([n for _, _, n in parts]), minlength=len(uniq))
    count = count[:, None]
    pc = point_cloud(sums[:, :3] / count)
    nrm = sums[:, 3:] / count
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    pc.normals = o3d.utility.Vector3dVector(nrm)
    return pc


class _ArmJob:
    """One arm position's registration as a picklable job for :func:`run_chunks` (worker
    processes): returns the fused cloud as arrays, since open3d clouds do not pickle."""

    def __init__(self, session_dir: Path, cfg: RegistrationConfig, sign: float, measured: dict | None = None):
        self.session_dir, self.cfg, self.sign = Path(session_dir), cfg, sign
        self.measured = measured or {}

    def __call__(self, arm: int):
        session = RawSession.open(self.session_dir)
        t = time.perf_counter()
        with _progress(False) as prog:
            A, poses, fr, cloud = _register_arm(session, self.cfg, arm, self.sign, prog, self.measured.get(arm))
        return arm, A, poses, fr, np.asarray(cloud.points), np.asarray(cloud.normals), time.perf_counter() - t


def _cloud(points: np.ndarray, normals: np.ndarray) -> "o3d.geometry.PointCloud":
    pc = point_cloud(points)
    if len(normals):
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    return pc


# ---------------------------------------------------------------------------------------------
# the session
# ---------------------------------------------------------------------------------------------
def _cross_check_axes(arms: list[ArmRegistration], pose: str, cfg: RegistrationConfig, how: str,
                      slack_mm: float = 0.0) -> None:
    """Flag every arm position whose turntable axis, moved into the reference camera by its pose
    ``pose`` ("T_ref_arm_prior": the robot's; "T_ref_arm": after the arm-to-arm ICP), stands
    more than ``arm_axis_max_mm`` (at the table top) or ``arm_axis_max_deg`` from the others'
    consensus (the median; with two arms, each other). Every arm sees the same turntable, so an
    arm that disagrees has a wrong axis or a wrong relation to the others: none of its frames is
    labelled. ``slack_mm`` widens both millimetre limits (a check before the depth's scale is known)."""
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
        along = float(rel @ dc)              # the table tops' heights apart (the axis points lie on them)
        off = float(np.linalg.norm(rel - along * dc))
        ang = math.degrees(math.acos(float(np.clip(abs(dirs[i] @ dc), -1.0, 1.0))))
        reasons = []
        max_mm, plane_mm = cfg.arm_axis_max_mm + slack_mm, cfg.arm_plane_max_mm + slack_mm
        if off > max_mm or ang > cfg.arm_axis_max_deg:
            reasons.append(f"its turntable axis stands {off:.1f} mm / {ang:.2f} deg from the other arm positions' "
                           f"{how} (limits {max_mm:.3g} mm / {cfg.arm_axis_max_deg:g} deg)")
        if abs(along) > plane_mm:
            reasons.append(f"its table top lies {abs(along):.1f} mm {'above' if along > 0 else 'below'} the other "
                           f"arm positions' {how} (limit {plane_mm:.3g} mm)")
        if reasons:
            a.flagged = True
            reason = "; ".join(reasons)
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
    sign = -1.0 if direction == "cw" else 1.0
    t_check = time.perf_counter()
    measured: dict[int, dict] = {}     # the check's plane and motion per arm, reused by the arm's registration
    outcome: dict = {}
    checked = check_turntable(session, cfg, sign, recorded, measured, outcome)
    turntable = {"direction": "ccw" if checked > 0 else "cw",
                 "source": "session.json" if recorded else ("detected from the opaque depth" if checked != sign
                                                            else "default (ccw), confirmed by the opaque depth")}
    sign = checked
    results: dict[int, tuple] = {}
    if not recorded and not outcome.get("told"):
        # the objects' turn does not tell the direction (one round object near the axis): arm 0
        # is registered both ways, and the way with fewer frames off the turntable prior is kept
        tried = {}
        with _progress(progress, unit="icp") as prog:
            for s in (1.0, -1.0):
                ta = time.perf_counter()
                A, poses, fr, cloud = _register_arm(session, cfg, 0, s, prog, measured.get(0))
                tried[s] = (A, poses, fr, cloud, time.perf_counter() - ta)
        off = {s: sum(f.flagged for f in tried[s][2]) for s in tried}
        sign = -1.0 if off[-1.0] < off[1.0] else 1.0
        results[0] = tried[sign]
        turntable = {"direction": "ccw" if sign > 0 else "cw",
                     "source": f"not told by the objects' turn (too round); arm 0 registered both ways: "
                               f"{off[1.0]} frames flagged counter-clockwise, {off[-1.0]} clockwise"}
    timing_check = round(time.perf_counter() - t_check, 3)
    timing: dict[str, float] = {"turntable_check": timing_check}
    arms: list[ArmRegistration] = []
    frames: list[FrameRegistration] = []
    fused: dict[int, Any] = {}
    per_arm: dict[int, dict[int, np.ndarray]] = {}
    T_base_cam0 = info.T_base_cam(0)
    todo = [a for a in range(info.n_arms) if a not in results]
    n_workers = min(resolve_workers(workers), len(todo))
    if n_workers > 1:   # one arm per worker process; a failing arm raises its TdofError here
        for arm, A, poses, fr, P, N, dt in run_chunks(_ArmJob(session.path, cfg, sign, measured), todo,
                                                      workers=n_workers, progress=progress,
                                                      description="register (arm positions)", unit="arm"):
            results[arm] = (A, poses, fr, _cloud(P, N), dt)
    with _progress(progress, unit="icp") as prog:
        for a in range(info.n_arms):
            if a not in results:
                ta = time.perf_counter()
                A, poses, fr, cloud = _register_arm(session, cfg, a, sign, prog, measured.get(a))
                results[a] = (A, poses, fr, cloud, time.perf_counter() - ta)
            A, poses, fr, cloud, dt = results[a]
            timing[f"arm{a}"] = round(dt, 3)
            per_arm[a] = poses
            fused[a] = cloud
            frames.extend(fr)
            T_prior = invert(T_base_cam0) @ info.T_base_cam(a)
            arms.append(ArmRegistration(a, A.axis_dir, A.axis_point, A.plane_n, A.plane_d, A.radius,
                                        T_prior.copy() if a else np.eye(4), T_prior if a else np.eye(4),
                                        flagged=bool(A.plane_problem), reason=A.plane_problem,
                                        association=A.association))
        # --- the arms' axes must agree through the robot's poses: first up to what a scale error
        # annotation corrects can explain ((s - 1) |t| between arm positions |t| apart), so that an
        # arm the robot misreports is kept out of the scale estimate; strictly once it is corrected
        ta = time.perf_counter()
        slack = 0.0
        if cfg.refine_arms and cfg.depth_scale_correct:
            slack = (cfg.depth_scale_max - 1.0) * max(float(np.linalg.norm(a.T_ref_arm_prior[:3, 3])) for a in arms)
        _cross_check_axes(arms, "T_ref_arm_prior", cfg, "through the robot's poses", slack)
        # --- relate the arm positions, and what they say of the depth's scale -------------------
        scale = _relate_arms(arms, fused, cfg) if cfg.refine_arms else DepthScale(
            1.0, None, 0, "not estimated: register.refine_arms is off")
        # every length of the arms' own registrations is the depth's: in true millimetres now
        for arm_reg in arms:
            arm_reg.axis_point = arm_reg.axis_point / scale.factor
            arm_reg.plane_d /= scale.factor
            arm_reg.crop_radius /= scale.factor
        for poses in per_arm.values():
            for T in poses.values():
                T[:3, 3] /= scale.factor
        for f in frames:
            f.residual_mm /= scale.factor
        # --- the arms' axes must agree through the robot's poses, and after the ICP ------------
        if slack:
            _cross_check_axes(arms, "T_ref_arm_prior", cfg, "through the robot's poses")
        _cross_check_axes(arms, "T_ref_arm", cfg, "after the arm-to-arm ICP")
        timing["arms"] = round(time.perf_counter() - ta, 3)
    for f in frames:
        f.T_ref_frame = arms[f.arm].T_ref_arm @ per_arm[f.arm][f.step]
    frames.sort(key=lambda f: (f.arm, f.step))
    timing["total"] = round(time.perf_counter() - t0, 3)
    return RegistrationResult(info.scene_id, info.steps, float(info.step_deg), info.n_arms, frames, arms,
                              cfg.to_dict(), timing, turntable, depth_scale=scale.to_dict())


def _icp_arm(arm_reg: ArmRegistration, src, ref, ref_axis_point: np.ndarray, cfg: RegistrationConfig,
             factor: float = 1.0) -> None:
    """The arm-to-arm ICP of one arm position from its robot prior: its refined pose, or a flag
    (the prior kept) when the ICP disagrees with the robot beyond the limits."""
    T, fit, rmse, _ = icp_prior(src, ref, arm_reg.T_ref_arm_prior, ref_axis_point, cfg,
                                sigma_deg=cfg.arm_prior_sigma_deg, sigma_mm=cfg.arm_prior_sigma_mm,
                                information=False)
    cd, _ = T_diff(arm_reg.T_ref_arm_prior, T)
    # correction measured at the table centre (not at the camera origin)
    c = np.append(arm_reg.axis_point / factor, 1.0)
    cm = float(np.linalg.norm((T @ c - arm_reg.T_ref_arm_prior @ c)[:3]))
    arm_reg.fitness, arm_reg.rmse = fit, rmse
    arm_reg.correction_deg, arm_reg.correction_mm = float(cd), cm
    arm_reg.T_ref_arm = arm_reg.T_ref_arm_prior.copy()
    if fit < cfg.arm_min_fitness or cd > cfg.max_arm_correction_deg or cm > cfg.max_arm_correction_mm:
        arm_reg.flagged = True
        why = (f"arm-to-arm ICP disagrees with the robot prior (fitness {fit:.2f}, correction "
               f"{float(cd):.2f} deg / {cm:.1f} mm); robot prior kept")
        arm_reg.reason = f"{arm_reg.reason}; {why}" if arm_reg.reason else why
    else:
        arm_reg.T_ref_arm = T


def _relate_arms(arms: list[ArmRegistration], fused: dict, cfg: RegistrationConfig) -> "DepthScale":
    """Refine every arm position's robot prior by ICP between the arms' fused turntable clouds,
    and estimate the depth's scale error from the same ICP (:func:`depth_scale_from_arms`).

    A depth camera that reads ``s`` times the true depth scales every arm's cloud by ``s`` about
    its camera, so the arm-to-arm ICP finds the robot's rotation but ``s`` times its translation:
    ~6 mm between elevations ~300 mm apart at s = 1.02. The clouds are divided by the first
    round's estimate and the ICP run again (each round's ICP starts from the robot prior,
    regularised towards it, so the first round's estimate is pulled a little towards 1);
    ``cfg.depth_scale_rounds`` rounds at most. No more: the ICP jitters by ~0.5 mm from round to
    round on a few-object scene (the voxel grids sample other points of a rescaled cloud), and
    rounds chasing that jitter walked the estimate away (0.99985 -> 1.0016 in four rounds on a
    perfect sensor, a single cup). Returns the estimate; the arms' poses are those of the last
    round, in true millimetres once the caller divides the arms' own lengths by its factor."""
    base = {a.arm: (a.flagged, a.reason) for a in arms}
    factor = 1.0
    usable = [a for a in arms[1:] if len(fused[a.arm].points) >= cfg.min_points]
    for a in arms[1:]:
        if a not in usable:
            why = "arm-to-arm refinement skipped: too few registered points; robot prior kept"
            a.reason = f"{a.reason}; {why}" if a.reason else why
    if not len(fused[0].points) or not usable:
        return DepthScale(1.0, None, 0, "not estimated: fewer than two arm positions with registered points")
    estimate = None
    for r in range(cfg.depth_scale_rounds):
        ref = Pyramid.from_cloud(_scaled(fused[0], 1.0 / factor), cfg)
        for a in usable:
            a.flagged, a.reason = base[a.arm]
            _icp_arm(a, Pyramid.from_cloud(_scaled(fused[a.arm], 1.0 / factor), cfg), ref,
                     arms[0].axis_point / factor, cfg, factor)
        estimate = depth_scale_from_arms([a for a in usable if not a.flagged], factor, cfg)
        if (estimate.n == 0 or not cfg.depth_scale_correct or r == cfg.depth_scale_rounds - 1
                or abs(estimate.factor / factor - 1.0) < 1e-4
                or not (1.0 / cfg.depth_scale_max <= estimate.factor <= cfg.depth_scale_max)):
            break  # (beyond what this rig can be trusted to correct: refused by the register stage)
        factor = estimate.factor
    # The last round's ICP ran on clouds divided by ``factor`` and measured ``estimate.factor``.
    # Clouds both scaled by l about their cameras are related by the same rotation and l times the
    # translation, so the arms' poses are carried to the measured scale exactly (no ICP round
    # more); the step from the factor that round ran at (the ICP's jitter between rounds: a voxel
    # grid over a cloud 0.1 % larger samples other points) widens the bound. What is applied is
    # the measurement shrunk towards 1 by its own noise (:func:`shrunk_scale`).
    if cfg.depth_scale_correct and estimate.n and 1.0 / cfg.depth_scale_max <= estimate.factor <= cfg.depth_scale_max:
        measured = estimate.factor
        ci = math.hypot(estimate.ci95, measured - factor)
        applied = shrunk_scale(measured, ci)
        for a in usable:
            if not a.flagged:
                a.T_ref_arm[:3, 3] *= factor / applied
        estimate.measured, estimate.factor = measured, applied
        estimate.ci95 = ci + abs(measured - applied)  # the applied factor's own 95 % bound
    else:
        estimate.measured, estimate.factor = estimate.factor, factor
    if not cfg.depth_scale_correct and estimate.n:
        estimate.note = "measured, not corrected: register.depth_scale_correct is off"
    return estimate


def shrunk_scale(measured: float, ci95: float) -> float:
    """The depth-scale correction applied for a measurement with 95 % half-width ``ci95``: its
    departure from 1 times ``d² / (d² + σ²)`` (σ = ci95 / 1.96; the least-squares weight of a
    measurement against the prior "no error"). A 2 % error measured to ±0.3 % is applied at
    99.5 % of itself; a departure of the size of the noise (a perfect sensor measured 0.9983 ±
    0.3 % on a 2-arm session) about half, so that correcting noise does not cost more than it
    gains (unshrunk, that session's surface error went 0.20 -> 0.39 mm)."""
    d, sigma = measured - 1.0, ci95 / 1.96
    return 1.0 + d * (d * d / (d * d + sigma * sigma)) if d else 1.0


def _scaled(cloud, f: float):
    """A copy of an open3d cloud with its points scaled by ``f`` about the camera (normals kept)."""
    out = o3d.geometry.PointCloud(cloud)
    if f != 1.0:
        out.points = o3d.utility.Vector3dVector(np.asarray(cloud.points) * f)
    return out


class DepthScale:
    """What the arm positions say of the depth camera's scale: ``factor`` = reported / true depth
    (the sessions' depth is divided by it), its 95 % half-width ``ci95`` (None: not estimated),
    the arm positions it rests on and a note."""

    def __init__(self, factor: float, ci95: float | None, n: int, note: str = "", per_arm: dict | None = None,
                 measured: float | None = None):
        self.factor, self.ci95, self.n, self.note = float(factor), ci95, int(n), note
        self.per_arm = per_arm or {}
        self.measured = factor if measured is None else float(measured)

    def to_dict(self) -> dict:
        return {"factor": self.factor, "measured": self.measured, "ci95": self.ci95, "arms": self.n,
                "per_arm": self.per_arm, "note": self.note}


def depth_scale_from_arms(arms: list[ArmRegistration], factor: float, cfg: RegistrationConfig) -> DepthScale:
    """The depth-scale estimate from the arm-to-arm ICP of clouds already divided by ``factor``:
    each arm ``a`` with robot translation ``t_a`` (to the reference camera) and ICP translation
    ``u_a`` says ``s_a = factor * (u_a . t_a) / |t_a|^2``; the estimate is their least-squares
    combination ``factor * sum(u_a . t_a) / sum(|t_a|^2)``. Its 95 % bound: the ICP's translation
    error along ``t`` (``cfg.depth_scale_icp_mm``, measured on the simulator's sessions with hand-eye
    error, clutter and step jitter), or the arms' own disagreement where larger, over
    ``sqrt(sum |t_a|^2)``, times 1.96."""
    rows = [(a.arm, a.T_ref_arm_prior[:3, 3], a.T_ref_arm[:3, 3]) for a in arms]
    rows = [(i, t, u) for i, t, u in rows if float(t @ t) > cfg.depth_scale_min_baseline_mm ** 2]
    if not rows:
        return DepthScale(factor, None, 0, f"not estimated: no two arm positions {cfg.depth_scale_min_baseline_mm:g} mm "
                                           f"or more apart with an arm-to-arm registration")
    tt = sum(float(t @ t) for _, t, _ in rows)
    s = factor * sum(float(u @ t) for _, t, u in rows) / tt
    per_arm = {str(i): factor * float(u @ t) / float(t @ t) for i, t, u in rows}
    miss = [float(np.linalg.norm(t)) * (per_arm[str(i)] - s) / factor for i, t, _ in rows]  # mm along t
    spread = math.sqrt(sum(m * m for m in miss) / (len(rows) - 1)) if len(rows) > 1 else 0.0
    ci95 = 1.96 * max(cfg.depth_scale_icp_mm, spread) / math.sqrt(tt)
    return DepthScale(s, ci95, len(rows), "from the arm positions' registration against the robot's poses",
                      per_arm, s)
