"""The gates a reviewer's placement passes before it is journalled — the pipeline's own, so a hand
correction cannot write a label the pipeline would have refused.

* :func:`move_limit` — a nudge moves at most ``NUDGE_MAX_MM`` / turns at most ``NUDGE_MAX_DEG``
  (the largest steps the Place page offers), a drag at most ``DRAG_MAX_MM`` / ``DRAG_MAX_DEG`` from
  where it started (a slip of the gizmo does not carry an object onto its neighbour);
* :func:`place_gate` — the place stage's fit and quality gate
  (:func:`tdof20.annotate.place.refine_placement`: ICP, set upright, fitness and mean distance)
  run from the pose on the reconstruction's object points near it must pass, and the pose itself
  must fit those points about as well as that fit does (its mean distance,
  :func:`~tdof20.annotate.place.pose_figures`, at most ``HAND_MARGIN_MM`` worse): a pose the
  points put elsewhere is not written (an unsnapped 5 mm nudge: 2.7 mm against the fit's 1.2 mm);
* :func:`visible_check` — the label stage's gate (:func:`tdof20.annotate.label.gate_check`) in a
  few frames spread around the turntable: the model at the pose, with the other objects where
  they stand, against each frame's own opaque depth; it must be seen in at least one and agree in
  every frame where it is seen;
* :func:`snap_alternatives` — snap from the distinct turns about the model's axis (every 30° for an
  object without symmetry, within one period for an n-fold one, one for a turned body), each fit
  with the place stage's fit on the same points, each judged in the images (the share of its
  pixels that disagree with the opaque depth): a wrong turn of a mug fits the points as well as the
  right one (the handle is a few per cent of them) but not the images.

Each refusal is one line naming the gate and its figure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tdof20.annotate.label import gate_check
from tdof20.annotate.place import pose_figures, refine_placement
from tdof20.geometry import rotation_matrix

__all__ = ["CHECK_FRAMES", "DRAG_MAX_DEG", "DRAG_MAX_MM", "EVIDENCE_FRAMES", "GateResult", "HAND_MARGIN_MM",
           "NUDGE_MAX_DEG", "NUDGE_MAX_MM", "SNAP_MIN_POINTS", "SNAP_REACH_MM", "distinct_turns", "move_limit",
           "near_points", "place_gate", "snap_alternatives", "turned", "visible_check"]

NUDGE_MAX_MM = 25.0       # the largest nudge steps the Place page offers
NUDGE_MAX_DEG = 15.0
DRAG_MAX_MM = 150.0       # a drag: from where it started
DRAG_MAX_DEG = 90.0
SNAP_REACH_MM = 20.0      # the object points within this of the posed model are its evidence
SNAP_MIN_POINTS = 50      # fewer: no fit is tried
# how much worse (truncated mean distance) a hand pose may fit its points than the place stage's
# fit from it. Simulator (multi/08, a mug and a goblet): the truth 0.01 mm worse, 1 mm off 0.15,
# 2 mm off 0.4-0.5, 5 mm off 1.5, a 2 deg turn 0.07, 5 deg 0.34
HAND_MARGIN_MM = 0.15
CHECK_FRAMES = 3          # frames of the visible check (and of the Place page's outlines)
EVIDENCE_FRAMES = 8       # frames that judge snap's alternatives
TURN_STEP_DEG = 30.0      # snap's turns of an object without symmetry (as the model stage's fit)
SAME_POSE_MM = 2.0        # two alternatives this close (mean model point distance) are one
# snap chooses an alternative by itself only when the images tell it apart: its disagreement at
# most this share of the runner-up's and this much below it (simulator, a mug: 0.008 at the right
# turn, >= 0.04 at every other); else the reviewer chooses
CLEAR_RATIO = 0.5
CLEAR_MIN_DIFF = 0.01


@dataclass
class GateResult:
    """What the gates said of one pose: ``reason`` is "" when it passed, else one line."""

    reason: str = ""
    figures: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.reason


# ---------------------------------------------------------------------------------------------
# poses
# ---------------------------------------------------------------------------------------------
def turned(T: np.ndarray, deg: float) -> np.ndarray:
    """``T`` turned by ``deg`` about the model's own z axis (through its origin): the axis its
    symmetries are given about (models_info.json) and, in the catalog's convention and a built
    model's, the body's axis (a mug's, not through its handle)."""
    T = np.asarray(T, float).copy()
    T[:3, :3] = T[:3, :3] @ rotation_matrix([0.0, 0.0, 1.0], math.radians(deg))
    return T


def _moved(T0: np.ndarray, T1: np.ndarray, centre_model: np.ndarray) -> tuple[float, float]:
    """(mm the model's centre moved, degrees it turned) from T0 to T1."""
    d = float(np.linalg.norm((T1[:3, :3] - T0[:3, :3]) @ centre_model + T1[:3, 3] - T0[:3, 3]))
    c = (np.trace(T1[:3, :3] @ T0[:3, :3].T) - 1.0) / 2.0
    return d, math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def move_limit(how: str, T_from: np.ndarray, T_to: np.ndarray, centre_model: np.ndarray) -> str:
    """"" when the move from ``T_from`` to ``T_to`` is within the limit of ``how`` (nudge, drag;
    a typed pose has none), else the one line that refuses it."""
    if how not in ("nudge", "drag"):
        return ""
    mm, deg = _moved(T_from, T_to, centre_model)
    lim_mm, lim_deg = (NUDGE_MAX_MM, NUDGE_MAX_DEG) if how == "nudge" else (DRAG_MAX_MM, DRAG_MAX_DEG)
    if mm > lim_mm + 1e-6:
        return f"{how} limit: it moves the object {mm:.0f} mm (at most {lim_mm:g} mm a {how}): move it in steps"
    if deg > lim_deg + 1e-6:
        return f"{how} limit: it turns the object {deg:.0f} deg (at most {lim_deg:g} deg a {how}): turn it in steps"
    return ""


def _mean_distance(S: np.ndarray, T0: np.ndarray, T1: np.ndarray, symmetric: bool) -> float:
    """Mean distance of the model samples between two poses (closest points for a turned body)."""
    A = S @ T0[:3, :3].T + T0[:3, 3]
    B = S @ T1[:3, :3].T + T1[:3, 3]
    if not symmetric:
        return float(np.linalg.norm(A - B, axis=1).mean())
    from scipy.spatial import cKDTree

    return float(cKDTree(B).query(A[::8])[0].mean())


# ---------------------------------------------------------------------------------------------
# the place stage's gate
# ---------------------------------------------------------------------------------------------
def near_points(rs: Any, obj_id: int, poses: list[np.ndarray], reach_mm: float = SNAP_REACH_MM) -> np.ndarray:
    """The reconstruction's object points within ``reach_mm`` of the model at any of ``poses``."""
    from scipy.spatial import cKDTree

    S, P = rs.samples(obj_id), rs.object_points()
    keep = np.zeros(len(P), bool)
    for T in poses:
        d, _ = cKDTree(S @ T[:3, :3].T + T[:3, 3]).query(P, distance_upper_bound=reach_mm)
        keep |= np.isfinite(d)
    return P[keep]


def place_gate(rs: Any, obj_id: int, T: np.ndarray) -> GateResult:
    """The place stage's fit gate for a hand pose (see the module docstring)."""
    near = near_points(rs, obj_id, [T])
    if len(near) < SNAP_MIN_POINTS:
        return GateResult(f"place gate: {len(near)} reconstruction points within {SNAP_REACH_MM:g} mm of object "
                          f"{obj_id} at this pose (its fit needs {SNAP_MIN_POINTS}): move it onto its points",
                          {"points": int(len(near))})
    S = rs.samples(obj_id)
    fitness, rmse, score = pose_figures(S, near, T, rs.cfg.fit.icp_mm[-1])
    r = refine_placement(S, rs.mesh(obj_id)[0], near, T, rs.up, rs.cfg, rs.plane)
    fig = {"points": int(len(near)), "fitness": round(fitness, 4), "rmse_mm": round(rmse, 4),
           "score_mm": round(score, 4), "fit_fitness": round(r["fitness"], 4), "fit_score_mm": round(r["score_mm"], 4)}
    if r["bad"]:
        return GateResult(f"place gate: the place stage's fit from this pose fails ({', '.join(r['bad'])}): "
                          f"move object {obj_id} onto its points", fig)
    if score > r["score_mm"] + HAND_MARGIN_MM:
        return GateResult(f"place gate: mean distance {score:.2f} mm at this pose against {r['score_mm']:.2f} mm at "
                          f"the place stage's fit from it (more than {HAND_MARGIN_MM:g} mm worse: its points put "
                          f"object {obj_id} elsewhere): snap (N), or move it onto them", fig)
    return GateResult("", fig)


# ---------------------------------------------------------------------------------------------
# the label stage's gate in the images
# ---------------------------------------------------------------------------------------------
def visible_check(rs: Any, index: int, T: np.ndarray, frames: list[tuple[int, int]] | None = None) -> GateResult:
    """The label gate of object ``index`` at pose ``T`` (reference frame) in ``frames`` (default:
    :meth:`ReviewScene.check_frames`), the other objects where the review shows them."""
    frames = rs.check_frames(CHECK_FRAMES) if frames is None else frames
    ob = rs.object(index)
    if not frames:
        return GateResult(f"visible check: no registered frame with an opaque twin to check object {ob.obj_id} in")
    cfg = rs.cfg.label
    per = []
    for a, k in frames:
        lab, opaque, order = rs.render_frame(a, k, {index: T})
        g = gate_check(lab, opaque, cfg)[order.index(index)]
        per.append({"arm": a, "step": k, **g})
    fig = {"frames": per}
    seen = [p for p in per if p["ok"] is not None]
    if seen:
        fig["agree"] = round(float(np.mean([p["agree"] for p in seen])), 4)
        fig["see_through"] = round(float(np.mean([p["see_through"] for p in seen])), 4)
    where = ", ".join(f"arm {a} step {k}" for a, k in frames)
    if not seen:
        return GateResult(f"visible check: object {ob.obj_id} at this pose is seen in none of the frames {where} "
                          f"(fewer than {cfg.gate_min_pixels} of its pixels with opaque depth): off the images, "
                          f"or hidden", fig)
    bad = next((p for p in seen if p["ok"] is False), None)
    if bad is not None:
        return GateResult(f"visible check: in arm {bad['arm']} step {bad['step']} {bad['agree']:.0%} of object "
                          f"{ob.obj_id}'s {bad['pixels']} pixels agree with the opaque depth within "
                          f"{cfg.gate_tol_mm:g} mm (the label gate needs {cfg.gate_min_agree:.0%}), "
                          f"{bad['see_through']:.0%} see through it (at most {cfg.gate_max_see_through:.0%})", fig)
    return GateResult("", fig)


# ---------------------------------------------------------------------------------------------
# snap
# ---------------------------------------------------------------------------------------------
def distinct_turns(models_info_entry: dict | None) -> list[float]:
    """The turns about the model's z (degrees) snap tries: one for a turned body (continuous
    symmetry), every ``TURN_STEP_DEG`` within one period for an n-fold one, all round otherwise."""
    e = models_info_entry or {}
    if e.get("symmetries_continuous"):
        return [0.0]
    n = 1 + sum(1 for T in e.get("symmetries_discrete") or ()
                if np.allclose(np.asarray(T, float).reshape(4, 4)[:3, 2], [0.0, 0.0, 1.0], atol=1e-3))
    period = 360.0 / n
    return [float(d) for d in np.arange(0.0, period - 1e-6, TURN_STEP_DEG)]


def snap_alternatives(rs: Any, index: int, T0: np.ndarray, turns: list[float] | None = None) -> dict:
    """The place stage's fit from ``T0`` turned by each of the object's distinct turns (or the
    given ``turns``), on the object points near any of them; each alternative with its figures and,
    when it passes the fit gate, its figures in the images. Returns {"alternatives": [...] (best
    first), "chosen": the index of the one the images tell apart or None, "points": n, "reason":
    "" or why none can be used}."""
    ob = rs.object(index)
    o = ob.obj_id
    S, V = rs.samples(o), rs.mesh(o)[0]
    sym = rs.symmetry(o)
    turns = distinct_turns(sym) if turns is None else [float(t) for t in turns]
    starts = [(t, turned(T0, t)) for t in turns]
    near = near_points(rs, o, [T for _, T in starts])
    if len(near) < SNAP_MIN_POINTS:
        return {"alternatives": [], "chosen": None, "points": int(len(near)),
                "reason": f"snap: only {len(near)} reconstruction points within {SNAP_REACH_MM:g} mm of object {o} "
                          f"where it was put: move it onto its points first"}
    symmetric = bool(sym.get("symmetries_continuous")) if sym else False
    alts: list[dict] = []
    for t, T in starts:
        r = refine_placement(S, V, near, T, rs.up, rs.cfg, rs.plane)
        a = {"turn_deg": t, "T_ref_model": r["T_ref_model"], "fitness": round(r["fitness"], 4),
             "score_mm": round(r["score_mm"], 4), "rmse_mm": round(r["rmse_mm"], 4), "note": r["note"],
             "bad": r["bad"]}
        if any(_mean_distance(S, b["T_ref_model"], a["T_ref_model"], symmetric) < SAME_POSE_MM for b in alts):
            continue   # the same pose from another start
        alts.append(a)
    frames = rs.check_frames(EVIDENCE_FRAMES)
    for a in alts:
        if a["bad"]:
            a["reason"] = f"place gate: {', '.join(a['bad'])}"
            continue
        v = visible_check(rs, index, a["T_ref_model"], frames)
        a["visible_ok"], a["reason"] = v.ok, v.reason
        a["agree"], a["see_through"] = v.figures.get("agree"), v.figures.get("see_through")
        a["disagree"] = None if a["agree"] is None else round(1.0 - a["agree"], 4)
    # best first: usable ones (both gates) by their disagreement in the images, then by mean distance
    alts.sort(key=lambda a: (not (not a["bad"] and a.get("visible_ok")),
                             a.get("disagree") if a.get("disagree") is not None else 1.0, a["score_mm"]))
    usable = [a for a in alts if not a["bad"] and a.get("visible_ok")]
    chosen, reason = None, ""
    if len(usable) == 1:
        chosen = 0
    elif len(usable) > 1:
        d0, d1 = usable[0]["disagree"], usable[1]["disagree"]
        if d0 <= CLEAR_RATIO * d1 and d1 - d0 >= CLEAR_MIN_DIFF:
            chosen = 0
        else:
            reason = (f"snap: {len(usable)} turns of object {o} fit alike (mean distance "
                      f"{usable[0]['score_mm']:.2f} and {usable[1]['score_mm']:.2f} mm, "
                      f"{usable[0]['disagree']:.1%} and {usable[1]['disagree']:.1%} of their pixels off the "
                      f"opaque depth): choose one")
    else:
        first = alts[0] if alts else None
        reason = f"snap: no turn of object {o} passes the gates" + (f" ({first['reason']})" if first else "")
    for a in alts:
        a["T_ref_model"] = [float(x) for x in np.asarray(a["T_ref_model"]).reshape(16)]
    return {"alternatives": alts, "chosen": chosen, "points": int(len(near)), "reason": reason}


def jsonable(x: Any) -> Any:
    """Figures as plain JSON numbers."""
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x
