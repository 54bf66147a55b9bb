"""The twin check of the place stage: does each transparent object stand where its opaque twin
stood?

The placements are fitted to the opaque twins' reconstruction; the labels are of the transparent
objects, which stood in the same slots — never exactly (a slot holds an object to a millimetre or
two, a turn of a degree). The transparent phase shows where the glass really is: the few pixels
whose depth is the glass surface itself (noisy, ~10 % of the glass on the simulator, 6 mm), spread
over every view. :func:`check_twins` gathers those returns from a spread of transparent frames
into the reference frame (through the registration's camera motion, the depth in true millimetres)
and fits, for each object, the offset of the glass from its twin that the slot allows: a move
(dx, dy) along the table top and a turn about the table axis through the object's centre (no turn
for an object with a continuous symmetry about its axis, where a turn is invisible and harmless).

The fit is point-to-plane Gauss-Newton of the posed model's surface to the returns near it
(open3d's ``RaycastingScene.compute_closest_points``: exact distances to the model's triangles), a
Cauchy weight (``twin_scale_mm``) so that background seen through the glass and flying rim pixels
count little, returns nearer another object's model left to that object. Its 95 % bound comes from
the spread of the same fit on ``twin_groups`` interleaved groups of the frames (Student's t on
their mean): the returns of one view are correlated (a sensor's dropouts come in blobs), the views
are not, so a bound from the per-point residuals would claim too much.

What the place stage does with an object's estimate (``twin_action``):

* ``corrected``: the move's evidence is strong (bound ≤ ``twin_max_ci95_mm``) and the offset
  within ``twin_max_mm`` / ``_deg``: the transparent object's pose is the twin's moved by the
  offset, shrunk toward 0 where it is within its own noise (the Wiener factor d²/(d² + σ²), as the
  depth scale), and turned where the turn's own bound is ≤ ``twin_max_ci95_deg`` (a turn beyond
  doubt but loosely bound makes it ``flagged``, moved);
* ``within``: the bound alone says the glass stands within ``twin_within_mm`` (and ``_deg``) of the
  twin: the twin's pose is kept (a weak but reassuring estimate);
* ``flagged``: the glass stands off its twin by more than that tolerance beyond doubt (the estimate
  less its bound), and the pose can't be corrected (beyond the gate, or too weak a bound to move
  it): the twin's pose is labelled and the object is an unresolved flag with its estimate
  (``dataset build`` refuses the scene until a reviewer looks);
* ``noted``: inconclusive (weak evidence that neither keeps the glass within the tolerance nor
  puts it beyond): the twin's pose is labelled, the estimate and its bound are shown beside it
  (summary, QA report, review), never silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tdof20.errors import TdofError

__all__ = ["TwinEstimate", "check_twins", "glass_returns", "twin_decision"]


@dataclass
class TwinEstimate:
    """The offset of one transparent object from its twin (reference frame, mm / deg): ``move``
    (3,) along the table top, ``turn_deg`` about the table axis through ``centre``; 95 % bounds
    ``ci95_mm`` (of |move|) and ``ci95_deg`` (None where the turn is not estimated), the returns
    ``points`` used and the ``groups`` the bound came from."""

    move: np.ndarray
    turn_deg: float
    ci95_mm: float
    ci95_deg: float | None
    points: int
    groups: int
    centre: np.ndarray
    up: np.ndarray

    @property
    def move_mm(self) -> float:
        return float(np.linalg.norm(self.move))

    def transform(self, shrink: bool = True, turn: bool = True) -> np.ndarray:
        """The (4,4) reference-frame offset D (T_glass = D @ T_twin), each part shrunk toward 0 by
        its Wiener factor d² / (d² + σ²) (σ = the 95 % bound / 1.96) unless ``shrink`` is False;
        the move alone with ``turn`` False."""
        d, a = self.move.copy(), math.radians(self.turn_deg) if turn else 0.0
        if shrink:
            s = (self.ci95_mm / 1.96) ** 2
            m2 = float(d @ d)
            d *= m2 / (m2 + s) if m2 + s > 0 else 0.0
            if self.ci95_deg is not None:
                s = math.radians(self.ci95_deg / 1.96) ** 2
                a *= a * a / (a * a + s) if a * a + s > 0 else 0.0
        return _offset(d, a, self.centre, self.up)

    def to_dict(self) -> dict:
        return {"move_mm": [round(float(x), 4) for x in self.move], "offset_mm": round(self.move_mm, 4),
                "turn_deg": round(float(self.turn_deg), 4), "ci95_mm": round(float(self.ci95_mm), 4),
                "ci95_deg": None if self.ci95_deg is None else round(float(self.ci95_deg), 4),
                "points": int(self.points), "groups": int(self.groups)}


def _offset(move: np.ndarray, turn_rad: float, centre: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4,4): a turn by ``turn_rad`` about the axis ``up`` through ``centre``, then a move."""
    from tdof20.geometry import rotation_matrix

    D = np.eye(4)
    D[:3, :3] = rotation_matrix(up, turn_rad) if turn_rad else np.eye(3)
    D[:3, 3] = centre - D[:3, :3] @ centre + move
    return D


def glass_returns(session, frames: list, up: np.ndarray, plane_d: float, centres: list[np.ndarray],
                  reach: list[float], heights: list[float], min_height_mm: float) -> tuple[np.ndarray, ...]:
    """(points (N,3) in the reference frame, their camera centres (N,3), frame index (N,)) of the transparent depth of
    ``frames`` (FrameRegistrations) that may lie on an object: above the table by
    ``min_height_mm`` and within ``reach`` (horizontal) and ``heights`` (+10 mm) of an object's
    centre. ``session`` reads the depth in true millimetres."""
    cam = session.info.camera
    rays = cam.pixel_rays().reshape(-1, 3)
    pts, org, idx = [], [], []
    C = np.asarray(centres, float)
    for k, f in enumerate(frames):
        if not session.has_frame("transparent", f.arm, f.step):
            continue
        try:
            z = session.load_depth_mm("transparent", f.arm, f.step).reshape(-1)
        except TdofError:
            continue   # the label stage reports unreadable frames
        ok = np.flatnonzero(z > 0)
        P = (rays[ok] * z[ok, None]) @ f.T_ref_frame[:3, :3].T + f.T_ref_frame[:3, 3]
        h = P @ up + plane_d
        keep = h > min_height_mm
        near = np.zeros(len(P), bool)
        for c, r, top in zip(C, reach, heights):
            rel = P - c
            hz = rel @ up
            near |= (np.einsum("ij,ij->i", rel, rel) - hz * hz < r * r) & (h < top + 10.0)
        P = P[keep & near]
        pts.append(P)
        org.append(np.broadcast_to(f.T_ref_frame[:3, 3], P.shape))
        idx.append(np.full(len(P), k, np.int32))
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int32)
    return np.concatenate(pts), np.concatenate(org), np.concatenate(idx)


class _Surface:
    """A model's triangles (open3d ray casting), in its model frame."""

    def __init__(self, V: np.ndarray, F: np.ndarray):
        from tdof20.o3d import o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(V, np.float32)), o3d.core.Tensor(np.asarray(F, np.uint32)))

    def cast(self, T: np.ndarray, O: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(range to the first hit (inf where none), the hit's unit normal), reference frame, of the
        rays from O along the unit directions D to the model posed at T."""
        R, t = T[:3, :3], T[:3, 3]
        rays = np.empty((len(O), 6), np.float32)
        rays[:, :3] = (O - t) @ R
        rays[:, 3:] = D @ R
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return ans["t_hit"].numpy().astype(np.float64), ans["primitive_normals"].numpy().astype(np.float64) @ R.T


def _fit(surf: _Surface, T: np.ndarray, O: np.ndarray, D: np.ndarray, rng: np.ndarray, centre: np.ndarray,
         up: np.ndarray, turn: bool, scale: float, trunc: float, iters: int = 20,
         start: tuple[np.ndarray, float] | None = None) -> tuple[np.ndarray, float]:
    """(move (3,), turn rad) of the model posed at T that best explains the returns (rays O + r D,
    measured ranges ``rng``): Cauchy-weighted range residuals r - r_model along each ray (the
    sensor's noise is along its rays), only moves along the table top and turns about ``up``
    through ``centre``. A ray that misses the model, or meets it at a grazing angle, is no
    evidence. ``start``: the (move, turn) to start from (default none)."""
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    move, ang = (np.zeros(3), 0.0) if start is None else (np.array(start[0], float), float(start[1]))
    for _ in range(iters):
        Tc = _offset(move, ang, centre, up) @ T
        t_hit, n = surf.cast(Tc, O, D)
        nd = np.einsum("ij,ij->i", n, D)
        r = rng - t_hit
        ok = np.isfinite(t_hit) & (np.abs(nd) > 0.25) & (np.abs(r) < trunc)
        if ok.sum() < 10:
            break
        r, n, nd = r[ok], n[ok], nd[ok]
        s = O[ok] + t_hit[ok, None] * D[ok]
        w = 1.0 / (1.0 + (r / scale) ** 2)
        c = centre + move
        # a surface moved by v changes the range by (n . v) / (n . d)
        J = [-(n @ e1) / nd, -(n @ e2) / nd]
        if turn:
            J.append(-np.einsum("ij,ij->i", n, np.cross(up, s - c)) / nd)
        J = np.stack(J, axis=1)
        A = (J * w[:, None]).T @ J + 1e-9 * np.eye(J.shape[1])
        x = np.linalg.solve(A, -(J * w[:, None]).T @ r)
        move = move + x[0] * e1 + x[1] * e2
        if turn:
            ang += float(x[2])
        if abs(x[0]) + abs(x[1]) < 1e-4 and (not turn or abs(x[2]) < 1e-6):
            break
    return move, ang


def check_twins(session, frames: list, placements: list[dict], meshes: dict, plane: np.ndarray, symmetric: dict,
                cfg) -> dict[int, TwinEstimate | str]:
    """{gt_id: TwinEstimate, or the reason there is none} of every placement (``T_ref_model``,
    ``obj_id``), from the transparent depth of ``frames`` (usable FrameRegistrations, at most
    ``cfg.twin_frames`` of them used, spread over the arms and steps). ``meshes``: {obj_id: (V,
    F)}; ``symmetric``: {obj_id: True where a turn about the axis is invisible}; ``plane``: the
    table top (n, d) in the reference frame; ``cfg``: the place options."""
    from tdof20.annotate.fusion import fuse_selection

    frames = fuse_selection(frames, cfg.twin_frames)
    n = np.asarray(plane[:3], float)
    scale_n = np.linalg.norm(n)
    up, plane_d = n / scale_n, float(plane[3]) / scale_n
    Ts, centres, reach, tops = [], [], [], []
    for p in placements:
        V = meshes[int(p["obj_id"])][0]
        T = np.asarray(p["T_ref_model"], float).reshape(4, 4)
        c_model = 0.5 * (V.min(0) + V.max(0))
        c = T[:3, :3] @ c_model + T[:3, 3]
        Vw = V @ T[:3, :3].T + T[:3, 3]
        rel = Vw - c
        hz = rel @ up
        Ts.append(T)
        centres.append(c - (c @ up + plane_d) * up)   # the axis where it meets the table
        reach.append(float(np.sqrt(np.max(np.einsum("ij,ij->i", rel, rel) - hz * hz))) + cfg.twin_margin_mm)
        tops.append(float(np.max(Vw @ up + plane_d)))
    P, O, fidx = glass_returns(session, frames, up, plane_d, centres, reach, tops, cfg.twin_min_height_mm)
    surfs = {o: _Surface(*meshes[o]) for o in {int(p["obj_id"]) for p in placements}}
    out: dict[int, TwinEstimate | str] = {}
    if not len(P):
        return {int(p["gt_id"]): "no transparent depth near the object" for p in placements}
    D = P - O
    R = np.linalg.norm(D, axis=1)
    D /= R[:, None]
    # each return to the object whose model its ray meets nearest the measured range
    miss = np.stack([np.abs(R - surfs[int(p["obj_id"])].cast(T, O, D)[0]) for p, T in zip(placements, Ts)])
    miss[~np.isfinite(miss)] = np.inf
    groups = max(2, min(int(cfg.twin_groups), len(frames) // 4))   # a group of at least 4 views
    for i, p in enumerate(placements):
        gid = int(p["gt_id"])
        o = int(p["obj_id"])
        turn = not symmetric.get(o, False)
        others = np.min(np.delete(miss, i, axis=0), axis=0) if len(placements) > 1 else np.full(len(R), np.inf)
        move, ang, sel = np.zeros(3), 0.0, None
        # the returns on the glass are chosen at the glass's pose: from the twin's, then from each
        # round's fit (those where the glass stands beyond the twin's silhouette come in)
        for _ in range(cfg.twin_rounds):
            t_i = surfs[o].cast(_offset(move, ang, centres[i], up) @ Ts[i], O, D)[0]
            d_i = np.abs(R - t_i)
            sel = np.isfinite(t_i) & (d_i < cfg.twin_trunc_mm) & (d_i <= others)
            if sel.sum() < cfg.twin_min_points:
                break
            move, ang = _fit(surfs[o], Ts[i], O[sel], D[sel], R[sel], centres[i], up, turn, cfg.twin_scale_mm,
                             cfg.twin_trunc_mm, start=(move, ang))
        Oi, Di, Ri, fi = O[sel], D[sel], R[sel], fidx[sel]
        if len(Ri) < cfg.twin_min_points:
            out[gid] = f"{len(Ri)} glass returns on it (< place.twin_min_points = {cfg.twin_min_points})"
            continue
        # the bound: the same fit on interleaved groups of frames (from the whole fit's result)
        T0 = _offset(move, ang, centres[i], up) @ Ts[i]
        parts = []
        for g in range(groups):
            m = (fi % groups) == g
            if m.sum() >= max(10, cfg.twin_min_points // groups):
                parts.append(_fit(surfs[o], T0, Oi[m], Di[m], Ri[m], centres[i] + move, up, turn,
                                  cfg.twin_scale_mm, cfg.twin_trunc_mm))
        if len(parts) < 2:
            out[gid] = f"too few views with glass returns for a bound ({len(parts)} of {groups} groups)"
            continue
        from scipy.stats import t as student_t

        k = len(parts)
        tq = float(student_t.ppf(0.975, k - 1))
        mv = np.array([pm for pm, _ in parts])
        ci_mm = tq * float(np.sqrt(np.sum(np.var(mv, axis=0, ddof=1)))) / math.sqrt(k)
        ci_deg = (tq * math.degrees(float(np.std([a for _, a in parts], ddof=1))) / math.sqrt(k)) if turn else None
        out[gid] = TwinEstimate(move, math.degrees(ang), max(ci_mm, cfg.twin_min_ci95_mm),
                                None if ci_deg is None else max(ci_deg, cfg.twin_min_ci95_deg), int(len(Ri)), k,
                                centres[i], up)
    return out


def twin_decision(est: TwinEstimate | str, cfg) -> tuple[str, str, np.ndarray | None]:
    """(action, the line that says it, the offset D to apply or None) of an object's estimate
    (module docstring): ``corrected`` (the move's bound strong, within the gate: the move applied,
    the turn too where its own bound is strong), ``within`` (the bound alone keeps the glass within
    the slot's tolerance), ``flagged`` (the glass stands off its twin by more than the tolerance,
    for certain, and that part can't be corrected: beyond the gate or too weak a bound; a move
    that could be is still applied), else ``noted`` (inconclusive: the twin's pose is labelled,
    the estimate and its bound beside it)."""
    if isinstance(est, str):
        return "noted", f"twin placement not checked: {est}; the opaque twin's pose is labelled", None
    turned = est.ci95_deg is not None
    turn_txt = f", turned {est.turn_deg:+.2f} ± {est.ci95_deg:.2f} deg" if turned else ""
    what = f"the glass stands {est.move_mm:.2f} ± {est.ci95_mm:.2f} mm off its twin{turn_txt} (95 %)"
    beyond = est.move_mm > cfg.twin_max_mm or abs(est.turn_deg) > cfg.twin_max_deg
    if beyond:
        return "flagged", (what + f": beyond place.twin_max_mm = {cfg.twin_max_mm:g} / twin_max_deg = "
                           f"{cfg.twin_max_deg:g}; the twin's pose is labelled, check the slot"), None
    move_ok = est.ci95_mm <= cfg.twin_max_ci95_mm
    turn_ok = not turned or est.ci95_deg <= cfg.twin_max_ci95_deg
    turn_off = turned and abs(est.turn_deg) - est.ci95_deg > cfg.twin_within_deg
    if move_ok:
        D = est.transform(turn=turn_ok)
        if turn_ok:
            return "corrected", what + ": the pose moved onto the glass", D
        if turn_off:
            return "flagged", (what + ": moved onto the glass; turned beyond doubt but too loosely bound to "
                               "turn it, check the slot"), D
        return "corrected", what + ": moved onto the glass; the turn within its noise, not applied", D
    if est.move_mm + est.ci95_mm <= cfg.twin_within_mm and (
            not turned or abs(est.turn_deg) + est.ci95_deg <= cfg.twin_within_deg):
        return "within", what + ": within the slot's tolerance, the twin's pose kept", None
    if est.move_mm - est.ci95_mm > cfg.twin_within_mm or turn_off:
        return "flagged", what + ": too weak a bound to correct it; the twin's pose is labelled, check the slot", None
    return "noted", what + ": inconclusive; the twin's pose is labelled, the bound carried into its labels", None
