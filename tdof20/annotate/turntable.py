"""The turntable: its motion model, and what the opaque depth of one arm position says about it.

Conventions as in :mod:`tdof20.annotate.registration` (mm; ``T_a_b`` maps frame b to frame a;
``cam(a,k)`` the camera of arm position ``a`` at turntable step ``k``).

* the model: :func:`turntable_prior` (``T_arm_frame`` of the table turned by ``k * step_deg``
  about its axis), :func:`fit_axis` (the common axis of a set of poses), :func:`rot_deg` and
  :func:`T_diff` (how far a pose is from another);
* the volume: :func:`height_radius` (cylinder coordinates about the axis), :func:`crop_points`;
* measured from the depth: :func:`table_plane` (RANSAC on the image centres, the highest level plane with
  nothing that moves below it), :func:`sampled_motion` (what moves between sampled frames and the
  turn that carries it), :func:`check_turntable` (``turntable.direction`` and ``step_deg`` of
  session.json against the data), :func:`disk_radius` (where the plane band stops filling every
  direction about the axis).

The functions take the registration's options (:class:`~tdof20.annotate.registration.RegistrationConfig`).
"""

from __future__ import annotations

import math

import numpy as np

from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.errors import TdofError
from tdof20.formats.session import RawSession
from tdof20.geometry.fitting import fit_plane
from tdof20.geometry.transforms import invert, rotation_about_axis
from tdof20.o3d import o3d


__all__ = ["T_diff", "VolumeCrop", "check_turntable", "crop_points", "disk_radius", "fit_axis", "height_radius", "load_points",
           "rot_deg", "sampled_motion", "table_plane", "turntable_prior"]


# ---------------------------------------------------------------------------------------------
# the turntable model
# ---------------------------------------------------------------------------------------------
def rot_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in degrees of (...,3,3) rotation matrices."""
    R = np.asarray(R, float)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def T_diff(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (deg) and translation (mm) of inv(A) @ B, for stacks (...,4,4)."""
    D = invert(A) @ np.asarray(B, float)
    return rot_deg(D[..., :3, :3]), np.linalg.norm(D[..., :3, 3], axis=-1)


def turntable_prior(axis_dir: np.ndarray, axis_point: np.ndarray, angle_deg: float, sign: float) -> np.ndarray:
    """T_arm_frame of the turntable model: cam(a,k) -> cam(a,0) for the table at ``angle_deg``.

    The table turns by +angle (ccw, sign=+1) about the upward axis, so a table point seen at step k
    is rotated by +angle relative to step 0; mapping it back is a rotation by -angle."""
    return rotation_about_axis(axis_dir, -sign * math.radians(angle_deg), axis_point)


def fit_axis(Ts: np.ndarray, n_hint: np.ndarray, plane_n: np.ndarray, plane_d: float,
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
# the depth of one arm position: points, the turntable volume, what moves
# ---------------------------------------------------------------------------------------------
def load_points(session: RawSession, cfg: RegistrationConfig, arm: int, step: int,
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


def height_radius(pts: np.ndarray, n: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cylinder coordinates of points (N,3) about the axis along unit ``n`` through ``p``: the
    height along n and the distance from the axis (mm)."""
    d = pts - p
    h = d @ n
    r2 = np.einsum("ij,ij->i", d, d) - h * h
    return h, np.sqrt(np.maximum(r2, 0.0))


def crop_points(pts: np.ndarray, n: np.ndarray, p: np.ndarray, radius: float, cfg: RegistrationConfig) -> np.ndarray:
    h, r = height_radius(pts, n, p)
    keep = (h >= -cfg.crop_below_mm) & (h <= cfg.crop_height_mm) & (r <= radius)
    return pts[keep]


class VolumeCrop:
    """The depth points of a frame inside the turntable volume (a cylinder of ``radius`` about the
    axis along unit ``n`` through ``p``, from ``crop_below_mm`` under the table top to
    ``crop_height_mm`` above it), straight from the depth image: ``load_points`` then
    ``crop_points`` in one pass, with the cylinder test on per-pixel maps of the camera's rays
    (ray.n, ray.p, |ray|^2, computed once per axis) so only the kept pixels become points."""

    def __init__(self, cam, cfg: RegistrationConfig, n: np.ndarray, p: np.ndarray, radius: float):
        rays = cam.pixel_rays().astype(np.float64)
        self.cam, self.cfg, self.radius = cam, cfg, float(radius)
        self.pn = float(np.asarray(p, float) @ np.asarray(n, float))
        self.pp = float(np.asarray(p, float) @ np.asarray(p, float))
        self.rn = rays @ np.asarray(n, float)                        # (H,W)
        self.rp = rays @ np.asarray(p, float)
        self.rr = np.einsum("hwc,hwc->hw", rays, rays)

    def mask(self, z: np.ndarray) -> np.ndarray:
        """(H,W) bool: the pixels of the depth image ``z`` (mm, this crop's camera) whose points lie
        inside the volume (and within the depth range)."""
        cfg = self.cfg
        z64 = np.asarray(z, np.float64)
        h = z64 * self.rn - self.pn
        r2 = z64 * (z64 * self.rr - 2.0 * self.rp) + self.pp - h * h
        return ((z64 >= cfg.min_depth_mm) & (z64 <= cfg.max_depth_mm) & (h >= -cfg.crop_below_mm)
                & (h <= cfg.crop_height_mm) & (r2 <= self.radius * self.radius))

    def points(self, z: np.ndarray) -> np.ndarray:
        """(N,3) float64 points (mm, camera frame) of the depth image ``z`` (mm) inside the volume,
        in pixel order — the points ``crop_points(load_points(...))`` gives."""
        v, u = np.nonzero(self.mask(z))
        zf = np.asarray(z, np.float32)
        return (self.cam.pixel_rays()[v, u] * zf[v, u, None]).astype(np.float64)


def _moving_points(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int]) -> np.ndarray:
    """Points (N,3) that change between sampled frames (the nearer surface where depth differs by
    more than 10 mm or 3 %): what turns with the table. Only regions of 2x2 pixels at least count
    (a binary opening of each pair's mask): far static surfaces (a back wall at 1.6 m, ~+-50 mm
    of sensor noise) flicker past the threshold in isolated pixels, and those speckles, far below
    the table top, made up 9 % of the "moving" points of a small cup and pushed the table-top
    choice onto the bench below the turntable (arm 0 of single/water_cup_270, 39 mm low)."""
    from scipy import ndimage

    cam = session.info.camera
    imgs = []
    for k in steps[:4]:
        z = session.load_depth_mm(cfg.phase, arm, k)
        imgs.append(np.where((z >= cfg.min_depth_mm) & (z <= cfg.max_depth_mm), z, 0))
    out = []
    block = np.ones((2, 2), bool)
    for i in range(len(imgs)):
        for j in range(i + 1, len(imgs)):
            a, b = imgs[i], imgs[j]
            m = (a > 0) & (b > 0) & (np.abs(a - b) > np.maximum(10.0, 0.03 * np.minimum(a, b)))
            m = ndimage.binary_opening(m, block)
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
        for it in range(10):
            x = p2 @ R2.T + t2
            d, j = tree.query(np.column_stack([x, ph]), distance_upper_bound=4 * tol_mm if it < 4 else 2 * tol_mm)
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
    fits = [refine(trials[i], free) for i in np.argsort(-coarse)[:5 if free else 1]]
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


# ---------------------------------------------------------------------------------------------
# the turn between sampled frames, the direction and step checks, the table top
# ---------------------------------------------------------------------------------------------
MOTION_POINTS = 20_000   # at most this many moving points of a sampled frame measure its turn


def sampled_motion(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int], n: np.ndarray,
                   d: float, sign: float, check: bool = False) -> tuple[list[dict], np.ndarray]:
    """The turn of the moving part between consecutive sampled frames of an arm position:
    [{k0, k1, nominal_deg, theta_deg, centre, score}] with theta measured near the nominal turn
    ``sign * (k1 - k0) * step_deg``, for the pairs whose nominal turn is far enough from 0 and
    180 deg to pin the centre. ``check``: also every pair whose moving part's centroid moves,
    measured over the whole turn and near the reversed turn too (``free``, ``reversed``: (theta,
    score)), for the direction and step checks; ``for_axis`` says which pairs the plain call
    returns (the same numbers: the registration reuses the check's measurement).
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
        pts = pts[(h > 5.0) & (h < cfg.crop_height_mm)]
        # at most MOTION_POINTS (a seeded subsample): 640x480 gives ~4x the points of 320x240, and
        # the k-d tree matching in _turn_between took 2/3 of the check's time; smaller images keep all
        if len(pts) > MOTION_POINTS:
            pts = pts[np.sort(np.random.default_rng(len(pts)).choice(len(pts), MOTION_POINTS, replace=False))]
        clouds.append(pts)
    out = []
    for i in range(len(steps) - 1):
        P, Q = clouds[i], clouds[i + 1]
        nominal = (steps[i + 1] - steps[i]) * sd
        if len(P) < 100 or len(Q) < 100:
            continue
        for_axis = abs(math.sin(math.radians(nominal) / 2)) >= 0.15
        # the moving part's centroid hardly moved (a round object near the axis): no turn to see
        moved = np.linalg.norm((P.mean(0) - Q.mean(0)) - ((P.mean(0) - Q.mean(0)) @ n) * n) >= 15.0
        if not (for_axis or (check and moved)):
            continue
        theta, centre, sc, _ = _turn_between(P, Q, n, foot, sign * nominal)
        e = {"k0": steps[i], "k1": steps[i + 1], "nominal_deg": nominal, "theta_deg": theta, "centre": centre,
             "score": sc, "for_axis": for_axis}
        if not check:
            out.append(e)
            continue
        e["moved"] = bool(moved)
        if moved:
            th, _, sc_free, pinned = _turn_between(P, Q, n, foot, None, max_radius_mm=cfg.max_crop_radius_mm)
            e["free"], e["pinned"] = (th, sc_free), pinned
            e["reversed"] = _turn_between(P, Q, n, foot, -sign * nominal)[0::2]
        out.append(e)
    return out, (np.concatenate(clouds) if clouds else np.zeros((0, 3)))


def measure_arm(session: RawSession, cfg: RegistrationConfig, arm: int, sign: float) -> dict | None:
    """What :func:`check_turntable` measures of one arm position (None when it cannot): the record
    the arm's registration reuses ({"steps", "n", "d", "sign", "moving", "plane", "pairs"}) and,
    under "motion", every sampled pair measured for the checks."""
    info = session.info
    available = [k for k in range(info.steps) if session.has_frame(cfg.phase, arm, k)]
    if len(available) < 2:
        return None
    sample = [available[i] for i in np.unique(np.linspace(0, len(available) - 1, cfg.plane_frames).round().astype(int))]
    prior_up = info.T_base_cam(arm)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    plane: dict = {}
    try:
        n, d, _ = table_plane(session, cfg, arm, sample, prior_up, plane)
        motion, moving = sampled_motion(session, cfg, arm, sample, n, d, sign, check=True)
    except TdofError:
        return None
    return {"steps": list(sample), "n": n, "d": d, "sign": sign, "moving": moving, "plane": plane,
            "pairs": [{k: v for k, v in p.items() if k not in ("moved", "free", "pinned", "reversed")}
                      for p in motion if p["for_axis"]], "motion": motion}


def check_turntable(session: RawSession, cfg: RegistrationConfig, sign: float, recorded: bool,
                    measured: dict | None = None, outcome: dict | None = None) -> float:
    """The turning direction and step angle the opaque depth shows, against session.json: returns
    the sign to use (+1 counter-clockwise about the table normal towards the camera, -1
    clockwise). Per pair of sampled frames of the first arm position whose moving part pins the
    turn (not a round object: :func:`_turn_between`), its fit (share of points within 6 mm) is
    compared at the nominal turn, at the reversed turn and at the best turn over the whole circle:
    the nominal explains the data when its fit is within 85 % of the best (or 0.6 at least); the
    reversed one when it does and the nominal fits half as well; another turn when the nominal
    fits half as well as the best. The pairs of the arm positions vote (until two or more agree, unopposed); a
    majority of two pairs at least decides; anything less keeps the recorded (or default) direction. A direction left out of
    session.json is taken from the data; a recorded one that the data contradicts, or a step
    angle the data does not show, is a one-line TdofError naming session.json. Silent (keeps
    ``sign``) when the moving part is too small or too symmetric to tell (one round cup on the
    axis turns without changing the depth).

    ``measured`` (a dict, filled): per arm position checked, what the registration of that arm
    would measure again — {"steps", "n", "d", "sign", "pairs" (those ``sampled_motion`` returns
    without ``check``), "moving"}; :func:`~tdof20.annotate.registration.register_session` hands
    it to the arm's registration. (Measuring the arms on worker processes side by side was tried:
    no faster on 2 cores, the early stop then saves nothing and each worker opens the session.)
    ``outcome`` (a dict, filled): {"told": whether the data decided the direction (two or more
    pairs, a majority, for the nominal or the reversed turn)}."""
    info = session.info
    src = session.path / "session.json"
    votes: list[tuple[str, int, dict]] = []
    for arm in range(info.n_arms):
        m = measure_arm(session, cfg, arm, sign)
        if m is None:
            continue
        plane, motion = m["plane"], m.pop("motion")
        if measured is not None:
            measured[arm] = m
        if plane.get("problem"):
            continue       # the motion about a guessed table top says nothing about the direction
        pairs = [p for p in motion if p["moved"] and p["free"][1] >= 0.45 and p["pinned"]]
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
        if len(decided) >= 2 and len(set(decided)) == 1 and len(decided) * 2 > len(votes):
            break   # the arms so far agree: the others would only cost time
    names = [v for v, _, _ in votes]
    verdict = max(("nominal", "reversed", "other"), key=names.count) if votes else "nominal"
    decided = names.count(verdict) >= 2 and names.count(verdict) * 2 > len(names)
    if outcome is not None:
        outcome["told"] = decided and verdict != "other"
    if verdict == "nominal" or not decided:
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


def disk_radius(clouds: list[np.ndarray], n: np.ndarray, p: np.ndarray, cam, cfg: RegistrationConfig) -> float | None:
    """The turntable top's radius (mm) from the table-plane points of the sampled frames: the
    disk fills every direction about the axis out to its edge, while what else touches the plane
    band (a cabinet's face, a box beside the table) fills only a few. Rings of 5 mm (3 pixels at
    least), sectors of 10 deg: the radius is where the share of in-view sectors holding plane
    points falls below half of the inner rings' share. None when there are too few points."""
    pts = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    h, r = height_radius(pts, n, p)
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


def _refine_plane(pts: np.ndarray, n: np.ndarray, d: float, dist: float, iters: int = 2) -> tuple[np.ndarray, float, int]:
    """Least squares of the plane n.x + d = 0 on the points within ``dist`` of it (``iters``
    rounds; the normal keeps its orientation). Returns (n, d, inliers of the last round)."""
    count = 0
    for _ in range(iters):
        inl = np.abs(pts @ n + d) < dist
        count = int(inl.sum())
        if count < 3:
            break
        q = pts[inl]
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        n2 = vt[2] * np.sign(vt[2] @ n)
        n, d = n2, float(-n2 @ c)
    return n, d, count


PLANE_REFINE_POINTS = 300_000   # at most about this many of the sampled frames' points refine a plane


def table_plane(session: RawSession, cfg: RegistrationConfig, arm: int, steps: list[int],
                prior_up: np.ndarray, report: dict | None = None) -> tuple[np.ndarray, float, list[np.ndarray]]:
    """The turntable top of one arm position. Returns (n, d, full clouds): n.x + d = 0, n towards
    the camera, and the sampled frames' valid points.

    Candidates: seeded RANSAC planes on the image centres of the sampled frames, level ones (normal
    within ``plane_prior_max_deg`` of the robot's vertical) holding a fair share of the points,
    each refined by least squares on all sampled points (a candidate's RANSAC plane is tilted by a
    few tenths of a degree: several mm across the view). The turntable top is the highest
    candidate with (almost: ``plane_moving_below``) none of the moving points below it: the
    objects turn with the table and stand on it, the bench below the turntable stays put, an
    object's flat top has the rest of the moving object below it. Without enough moving points (a
    round cup on the axis): the highest candidate with at most ``plane_max_below`` of the image
    centre below it.

    ``report`` (a dict, filled): ``candidates`` [{d, angle_deg, inliers, moving_below}], the
    chosen ``d``, and ``problem`` — a sentence when no candidate qualifies (then the largest
    level plane is returned, and the caller flags the arm: its plane is a guess)."""
    centre, full = [], []
    for k in steps:
        pts = load_points(session, cfg, arm, k)
        full.append(pts)
        centre.append(load_points(session, cfg, arm, k, cfg.plane_window))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(centre).reshape(-1, 3)))
    pc = pc.voxel_down_sample(cfg.voxel_sizes_mm[1])
    cpts = np.asarray(pc.points).copy()
    allp = np.concatenate(full)
    allp = allp[::max(1, len(allp) // PLANE_REFINE_POINTS)]   # least squares on ~300k points is as good as on millions
    cands = []                     # (n, d, inliers, angle) of planes near the vertical prior
    first = None
    for it in range(5):   # seeded numpy RANSAC: open3d's segment_plane is not repeatable on several threads
        if len(pc.points) < 100:
            break
        model, inl = fit_plane(np.asarray(pc.points), cfg.plane_dist_mm, 1000, seed=(arm, it), refine_iters=0)
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
            cands.append((n, d, len(inl), ang))
        pc = pc.select_by_index(inl.tolist(), invert=True)
    big = max((c[2] for c in cands), default=0)
    level = []
    for n, d, count, ang in cands:
        if count < max(0.05 * len(cpts), 0.25 * big):
            continue
        n, d, _ = _refine_plane(allp, n, d, cfg.plane_dist_mm)
        if any(abs(d - e[1]) < cfg.plane_dist_mm and e[0] @ n > math.cos(math.radians(1.0)) for e in level):
            continue       # the same plane found twice (two bands of one tilted plane)
        level.append((n, d, count, ang))
    moving = _moving_points(session, cfg, arm, steps)
    use_moving = len(moving) >= 50
    rows, ok = [], []
    for n, d, count, ang in level:
        if use_moving:
            below = float(np.mean(moving @ n + d < -3 * cfg.plane_dist_mm))
            good = below <= cfg.plane_moving_below
        else:
            below = float(np.mean(cpts @ n + d < -2 * cfg.plane_dist_mm))
            good = below <= cfg.plane_max_below
        rows.append({"d": round(float(d), 2), "angle_deg": round(float(ang), 2), "inliers": int(count),
                     ("moving_below" if use_moving else "centre_below"): round(below, 4), "ok": bool(good)})
        if good:
            ok.append((n, d))
    problem = ""
    if ok:
        best = min(ok, key=lambda c: c[1])           # the highest: nearest the camera along n
    elif level:
        n, d, _, _ = max(level, key=lambda c: c[2])
        best = (n, d)
        what = f"{len(moving)} moving points" if use_moving else "the image centre"
        where = ", ".join(f"{r['d']:.0f}" for r in rows)
        problem = (f"the table top is ambiguous: none of the {len(level)} level plane(s) in view (at {where} mm "
                   f"from the camera) has (almost) all of {what} above it")
    elif first is not None:
        best = first
        problem = "no level plane in view: the table top is a guess (the first RANSAC plane)"
    else:
        raise TdofError(f"arm {arm}: no table plane found in the {cfg.phase} depth (too few valid points)")
    n, d = best
    if not level:       # the level candidates are refined already
        n, d, _ = _refine_plane(allp, n, d, cfg.plane_dist_mm)
    if report is not None:
        report.update({"candidates": rows, "moving_points": int(len(moving)), "d": float(d), "problem": problem})
    return n, d, full
