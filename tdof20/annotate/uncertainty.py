"""Per-label 95 % error bounds (issue 34 part 3): ``scene_gt_uncertainty.json`` beside
``scene_gt.json``, keyed like it (im_id -> a list in scene_gt's order), each entry
``{"obj_id", "rot_deg", "trans_mm", "surface_mm"}``.

No tool in the field states how wrong each of its labels may be; the annotation knows every
source of its own error, each measured on the session itself:

* **depth scale** (register): the applied factor's 95 % bound ``c`` (a fraction); a label at
  distance ``z`` from its camera moves by about ``c z`` along its ray. Not estimated (one arm
  position): ``depth_scale_prior``.
* **twin placement** (place): a corrected offset's 95 % bound (move, turn); an offset measured
  within noise and left: its size plus its bound; not checked (too few glass returns) or only
  noted: ``twin_prior_mm`` / ``twin_prior_deg`` (what the lab's slots are taken to hold).
* **model fit** (place): the fit's RMS residual (mm) of the model on the fused cluster, and its
  angular effect over the object's radius.
* **frame motion** (register): the frame's residual against the turntable's motion (mm, deg).
* **arm position** (register): how far the arm-to-arm ICP moved the frame's arm position from
  the robot's pose (mm at the table centre, deg): an arm the robot (or its hand-eye calibration)
  misplaces is corrected by the ICP, and what is left scales with what was corrected.

The measured 95 % bounds (scale, twin) enter as they are; the fit and frame residuals are not
bounds but scales, and enter times constants ``k_fit`` / ``k_frame`` / ``k_arm`` chosen on the simulator's
validation sessions (``benchmarks/label_uncertainty.py``: the smallest constants with which the
bounds cover >= 92 % of the validation labels' true errors; the figures are in docs/annotate.md).
Components add in quadrature (independent sources). The surface bound: a pose off by ``t`` at
the centre and ``θ`` in rotation moves a surface point of an object of radius ``r`` by at most
``t + r θ``; the mean distance is less (moves along the surface do not count): ``k_surface``
times that, chosen the same way.

For a continuously symmetric object the rotation bound is its axis' tilt (a turn about the axis
is no error), so the twin check's turn does not enter."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tdof20.config import check_ranges
from tdof20.errors import TdofError
from tdof20.formats import read_json, write_json

FILE = "scene_gt_uncertainty.json"


@dataclass(frozen=True)
class UncertaintyConfig:
    """How the label bounds are made (the constants: chosen on the simulator's validation
    sessions, ``python benchmarks/label_uncertainty.py --fit``). On those sessions every k_fit,
    k_fit_rot, k_frame, k_arm from 0 up covers >= 92 % of the labels (the measured bounds, twin
    and depth scale, carry them): they are not pinned down there, and stay at 1 (each residual
    at face value) rather than 0 (a bad fit on a real session would then widen nothing);
    k_surface = 0.5 is the validation part's choice."""

    write: bool = True                 # write scene_gt_uncertainty.json
    k_fit: float = 1.0                 # x the place fit's RMS residual (mm) -> translation bound
    k_fit_rot: float = 1.0             # x the fit's residual over the object's radius -> rotation bound
    k_frame: float = 1.0               # x the frame's residuals against the turntable's motion
    k_arm: float = 1.0                 # x the arm-to-arm ICP's correction of the robot's pose
    k_surface: float = 0.5             # x (translation + radius x rotation) -> surface bound
    floor_mm: float = 0.1              # no bound under this (the fused surface's voxel noise)
    floor_deg: float = 0.05
    depth_scale_prior: float = 0.01    # the depth scale's bound where no arm pair measured it
    twin_prior_mm: float = 1.0         # a twin's offset where the check could not measure it
    twin_prior_deg: float = 0.5

    def __post_init__(self) -> None:
        check_ranges(self, "uncertainty", positive=("k_surface",),
                     non_negative=("k_fit", "k_fit_rot", "k_frame", "k_arm", "floor_mm", "floor_deg", "depth_scale_prior", "twin_prior_mm", "twin_prior_deg"))


@dataclass
class ObjectTerms:
    """One placement's frame-independent error scales."""

    obj_id: int
    radius_mm: float
    symmetric: bool            # a continuous symmetry: rotation = the axis' tilt
    fit_mm: float              # the fit's RMS residual
    twin_mm: float             # 95 % bounds of the twin offset left in the label
    twin_deg: float
    centre: np.ndarray         # the model's centre in its own frame (mm)


def object_terms(placements: list[dict], models_dir: Path, cfg: UncertaintyConfig, place_cfg) -> list[ObjectTerms]:
    """The frame-independent terms of each placement (in placements.json's order)."""
    info_path = models_dir / "models_info.json"
    info = read_json(info_path) if info_path.exists() else {}
    out = []
    for p in placements:
        o = int(p["obj_id"])
        mi = info.get(str(o), {})
        diam = float(mi.get("diameter", 100.0))
        centre = np.array([mi.get("min_x", 0.0) + mi.get("size_x", 0.0) / 2, mi.get("min_y", 0.0) + mi.get("size_y", 0.0) / 2,
                           mi.get("min_z", 0.0) + mi.get("size_z", 0.0) / 2], float)
        symmetric = bool(mi.get("symmetries_continuous"))
        tw = p.get("twin") or {}
        twin_mm, twin_deg = _twin_left(tw, cfg, place_cfg)
        fit = float(p.get("rmse_mm") or p.get("score_mm") or 1.0)
        out.append(ObjectTerms(o, diam / 2, symmetric, fit, twin_mm, 0.0 if symmetric else twin_deg, centre))
    return out


def _twin_left(tw: dict, cfg: UncertaintyConfig, place_cfg) -> tuple[float, float]:
    """95 % bounds (mm, deg) of the twin offset a placement's labels still carry, from its twin
    check (placements.json's "twin": :func:`tdof20.annotate.twins.twin_decision`)."""
    action = tw.get("action")
    if "offset_mm" not in tw:  # not checked (too few glass returns, no twin check)
        return cfg.twin_prior_mm, cfg.twin_prior_deg
    est, ci = float(tw["offset_mm"]), float(tw.get("ci95_mm") or 0.0)
    moved = action == "corrected" or (action == "flagged" and ci <= place_cfg.twin_max_ci95_mm
                                      and est <= place_cfg.twin_max_mm)
    move = ci if moved else est + ci
    if tw.get("ci95_deg") is None:  # no turn estimated (a continuous symmetry)
        return move, 0.0
    turn, cid = abs(float(tw.get("turn_deg") or 0.0)), float(tw["ci95_deg"])
    turned = moved and cid <= place_cfg.twin_max_ci95_deg
    return move, (cid if turned else turn + cid)


def label_bound(term: ObjectTerms, z_mm: float, scale_ci: float, frame_mm: float, frame_deg: float,
                cfg: UncertaintyConfig, arm_mm: float = 0.0, arm_deg: float = 0.0) -> dict:
    """The 95 % bounds of one label: ``z_mm`` its centre's distance from the camera, ``scale_ci``
    the depth scale's 95 % bound (fraction), ``frame_mm``/``frame_deg`` its frame's residuals."""
    t = math.sqrt((cfg.k_fit * term.fit_mm) ** 2 + term.twin_mm ** 2 + (scale_ci * z_mm) ** 2
                  + (cfg.k_frame * frame_mm) ** 2 + (cfg.k_arm * arm_mm) ** 2)
    r = math.sqrt((cfg.k_fit_rot * math.degrees(term.fit_mm / max(term.radius_mm, 1.0))) ** 2 + term.twin_deg ** 2
                  + (cfg.k_frame * frame_deg) ** 2 + (cfg.k_arm * arm_deg) ** 2)
    t, r = max(t, cfg.floor_mm), max(r, cfg.floor_deg)
    s = max(cfg.k_surface * (t + term.radius_mm * math.radians(r)), cfg.floor_mm)
    return {"obj_id": term.obj_id, "rot_deg": round(r, 4), "trans_mm": round(t, 4), "surface_mm": round(s, 4)}


def _match(gt_ids: list[int], placements: list[ObjectTerms]) -> list[ObjectTerms]:
    """scene_gt's entries of one image -> their placements: the label stage writes the
    placements in order, leaving out the objects rejected in that frame."""
    out, k = [], 0
    for o in gt_ids:
        while k < len(placements) and placements[k].obj_id != o:
            k += 1
        if k == len(placements):
            raise TdofError(f"scene_gt.json lists obj {o} in an image where placements.json does not place it")
        out.append(placements[k])
        k += 1
    return out


def scene_bounds(scene_dir: Path, placements: list[dict], registration, cfg: UncertaintyConfig, place_cfg) -> dict:
    """The bounds of every label of the scene folder ``scene_dir`` (its scene_gt.json and
    models/), from the placements (placements.json's list) and the registration result."""
    terms = object_terms(placements, scene_dir / "models", cfg, place_cfg)
    gt = read_json(scene_dir / "scene_gt.json")
    ds = registration.depth_scale or {}
    scale_ci = float(ds["ci95"]) if ds.get("ci95") is not None and ds.get("arms") else cfg.depth_scale_prior
    steps = int(registration.steps)
    frames = {(f.arm, f.step): f for f in registration.frames}
    arms = {a.arm: (float(a.correction_mm or 0.0), float(a.correction_deg or 0.0)) for a in registration.arms}
    out = {}
    for key in sorted(gt, key=int):
        im = int(key)
        f = frames.get(divmod(im, steps))
        amm, adeg = arms.get(im // steps, (0.0, 0.0))
        fmm = float(getattr(f, "residual_mm", 0.0) or 0.0) if f is not None else 0.0
        fdeg = float(getattr(f, "residual_deg", 0.0) or 0.0) if f is not None else 0.0
        entries = gt[key]
        row = []
        for e, term in zip(entries, _match([int(e["obj_id"]) for e in entries], terms)):
            R = np.asarray(e["cam_R_m2c"], float).reshape(3, 3)
            z = float(np.linalg.norm(R @ term.centre + np.asarray(e["cam_t_m2c"], float).reshape(3)))
            row.append(label_bound(term, z, scale_ci, fmm, fdeg, cfg, amm, adeg))
        out[key] = row
    return out


def write_scene_bounds(scene_dir: Path, placements: list[dict], registration, cfg: UncertaintyConfig,
                       place_cfg) -> dict:
    """Write ``scene_gt_uncertainty.json`` into ``scene_dir``; returns its per-object summary
    (:func:`per_object`)."""
    bounds = scene_bounds(scene_dir, placements, registration, cfg, place_cfg)
    write_json(scene_dir / FILE, bounds)
    return per_object(bounds)


def per_object(bounds: dict) -> dict:
    """{obj_id: {n, and per quantity its median and 95th percentile}}: the label-noise floor."""
    acc: dict[int, list[tuple[float, float, float]]] = {}
    for row in bounds.values():
        for e in row:
            acc.setdefault(int(e["obj_id"]), []).append((e["trans_mm"], e["rot_deg"], e["surface_mm"]))
    out = {}
    for o, v in sorted(acc.items()):
        a = np.asarray(v, float)
        out[o] = {"n": len(a)} | {f"{name}_{q}": round(float(np.percentile(a[:, i], p)), 3)
                                  for i, name in enumerate(("trans_mm", "rot_deg", "surface_mm"))
                                  for q, p in (("median", 50), ("p95", 95))}
    return out
