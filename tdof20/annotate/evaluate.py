"""Labels against the simulator's exact truth: ``tdof20 annotate evaluate SCENE_DIR --truth RAW_DIR/truth``.

An annotated scene (labels) and the truth are two BOP scenes with the same image ids. Objects are
matched per image by ``obj_id`` (several instances of one ``obj_id``: by the nearest model centre,
Hungarian assignment); a track is one truth instance (its index in the truth's scene_gt lists,
fixed over a simulated session) followed over the images.

The labelled model may not be the true one — reconstructed, and in its own model frame — so
nothing compares poses directly. What is measured:

* **frame-to-frame motions** per object: for a pair of images (i, j) the object's motion in the
  camera ``M_ij = T_j @ inv(T_i)`` (model -> camera poses; M maps where a point of the object is
  seen in image i to where it is seen in image j) from the labels and from the truth. A change of
  the labelled model's frame (``T -> T @ X``) cancels in ``M``. Rotation error: the angle of
  ``R_lab @ R_true^T`` (deg). Translation error: ``|M_lab c - M_true c|`` (mm) with ``c`` the
  object's centre in image i (the centre of the true model's bounding box, posed by the truth) —
  measured at the object, not at the camera origin, where a rotation error would be multiplied
  by the object's distance from the camera. Pairs: every pair of consecutive labelled images of
  the track plus a random sample (seeded) of pairs further apart (as many as consecutive pairs,
  or ``far_pairs``).
* **surface distance** per image: the labelled model under the label pose against the true model
  under the true pose, symmetric: the mean of the distances of the labelled model's Monte-Carlo
  samples to the true posed surface and of the true model's samples to the labelled posed
  surface (mm). ``distance="mesh"`` (default) measures a sample's distance to the other model's
  *triangles* (open3d ``RaycastingScene.compute_distance``, exact); ``distance="samples"``
  measures it to the other model's samples (scipy cKDTree), which adds the sampling spacing to
  the result (about 1-2 mm for 2,000 samples of a glass) unless both models are the same mesh
  sampled alike. Each model's scene/tree is built once in its own model frame; the samples of
  the other model are moved into it per image (``inv(T_true) @ T_lab``), so nothing is rebuilt.
* **mask IoU** per image: full silhouette (``mask/``) and visible part (``mask_visib/``), numpy on
  the masks read in a few threads.

Each measure: median, p95 (and mean, p5, min, max, n) per object and over all objects ("all");
plus the truth frames missing from the labels, label frames the truth lacks, and the (image,
object) pairs with a visible IoU below ``iou_warn`` (0.9).

The registration alone against the truth (the register stage's result, before any label):
:func:`truth_T_ref_frame` (every frame's true ``T_ref_frame`` from ``truth/scene_camera.json``) and
:func:`evaluate_against_truth` (errors of the frame-to-reference poses and of the motions between
consecutive and between all pairs of frames; per arm position the turntable axis and the
arm-to-arm transform, refined and the robot's prior).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.annotate.pngread import mask_rows, mask_rows_iou
from tdof20.annotate.registration_result import RegistrationResult
from tdof20.errors import TdofError
from tdof20.formats import SCENE_CAMERA, SCENE_GT, BopScene, RawSession, dumps_json, read_json, read_scene
from tdof20.formats.bop_models import model_path, read_model_mesh, read_models_info
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.geometry.transforms import invert
from tdof20.objects import get_object

__all__ = ["evaluate_scene", "evaluate_command", "evaluate_against_truth", "model_centre", "truth_T_ref_frame",
           "truth_label_inputs",
           "TARGETS"]

# issue 4, part 7: what an annotation of a simulated scene must reach (medians)
TARGETS = {"motion_rot_deg": ("<=", 0.1), "motion_trans_mm": ("<=", 1.0), "surface_mm": ("<=", 1.0),
           "iou_visib": (">=", 0.97)}
_CHUNK = 256  # images per batch of surface-distance queries
WRONG_MIN_VISIBLE_PX = 50  # a wrong visible mask is judged where the truth shows at least this many pixels


# ---------------------------------------------------------------------------------------------
# small pieces
# ---------------------------------------------------------------------------------------------
def model_centre(vertices: np.ndarray) -> np.ndarray:
    """The centre (3,) of a model's axis-aligned bounding box, in its model frame (mm)."""
    V = np.asarray(vertices, float).reshape(-1, 3)
    return 0.5 * (V.min(0) + V.max(0))


def _stats(x: Any) -> dict:
    a = np.asarray(x, float).reshape(-1)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"n": 0, "median": None, "p95": None, "mean": None, "p5": None, "min": None, "max": None}
    r = lambda v: round(float(v), 6)  # noqa: E731
    return {"n": int(a.size), "median": r(np.median(a)), "p95": r(np.percentile(a, 95)), "mean": r(a.mean()),
            "p5": r(np.percentile(a, 5)), "min": r(a.min()), "max": r(a.max())}


def _rot_deg(R: np.ndarray) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _open(path: str | Path, what: str) -> BopScene:
    p = Path(path)
    if not p.is_dir():
        raise TdofError(f"no such {what} folder", p)
    if what == "truth" and not (p / SCENE_GT).exists() and (p / "truth" / SCENE_GT).exists():
        p = p / "truth"  # RAW_DIR given instead of RAW_DIR/truth
    if what == "truth" and not (p / SCENE_GT).exists():
        raise TdofError(f"truth has no {SCENE_GT} (pass RAW_DIR/truth of a simulated session)", p)
    if not (p / SCENE_CAMERA).exists() or not (p / SCENE_GT).exists():
        missing = [f for f in (SCENE_CAMERA, SCENE_GT) if not (p / f).exists()]
        raise TdofError(f"not an annotated scene: no {' or '.join(missing)} (pass the folder "
                        f"'tdof20 annotate --out' wrote)", p)
    return read_scene(p)


class _Model:
    """One model: mesh, bounding-box centre, Monte-Carlo samples, and a distance structure built
    once in its model frame."""

    def __init__(self, V: np.ndarray, F: np.ndarray, n_points: int, seed: int, distance: str):
        self.V, self.F = V, F
        self.centre = model_centre(V)
        self.samples = sample_mesh_surface(V, F, n_points, seed=seed)
        self.distance = distance
        if distance == "mesh":
            from tdof20.o3d import o3d

            self._o3d = o3d
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        else:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.samples)

    def dist(self, Q: np.ndarray) -> np.ndarray:
        """Distances (N,) of points (N,3) in this model's frame to its surface (or samples)."""
        if self.distance == "mesh":
            q = self._o3d.core.Tensor(np.ascontiguousarray(Q, np.float32))
            return self._scene.compute_distance(q).numpy().astype(np.float64)
        return self._tree.query(Q, workers=-1)[0]


def _move(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(n, p, 3): the points P (p,3) under each of the transforms T (n,4,4), as one matrix
    product (einsum's loop took 9x as long; the float32 the mesh distance takes is the same)."""
    return np.matmul(P, T[:, :3, :3].transpose(0, 2, 1)) + T[:, None, :3, 3]


def _surface(lab: _Model, tru: _Model, TL: np.ndarray, TG: np.ndarray) -> np.ndarray:
    """Symmetric mean surface distance (n,) between lab under TL (n,4,4) and tru under TG."""
    out = np.empty(len(TL))
    for s in range(0, len(TL), _CHUNK):
        L, G = TL[s:s + _CHUNK], TG[s:s + _CHUNK]
        A = invert(G) @ L                      # label model frame -> true model frame
        B = invert(A)
        qa = _move(A, lab.samples)
        qb = _move(B, tru.samples)
        da = tru.dist(qa.reshape(-1, 3)).reshape(len(L), -1).mean(1)
        db = lab.dist(qb.reshape(-1, 3)).reshape(len(L), -1).mean(1)
        out[s:s + len(L)] = 0.5 * (da + db)
    return out


def _pairs(n: int, n_far: int | None, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j), i < j: all consecutive ones plus up to n_far (default n - 1) further apart."""
    if n < 2:
        return np.zeros(0, int), np.zeros(0, int)
    i0 = np.arange(n - 1)
    want = (n - 1) if n_far is None else int(n_far)
    total = (n - 1) * (n - 2) // 2  # pairs with j - i >= 2
    if want <= 0 or total == 0:
        return i0, i0 + 1
    if total <= want:
        fi, fj = np.triu_indices(n, 2)
    else:
        c = np.sort(rng.integers(0, n, (4 * want + 16, 2)), axis=1)
        c = c[c[:, 1] - c[:, 0] >= 2]
        _, first = np.unique(c, axis=0, return_index=True)
        c = c[np.sort(first)][:want]
        fi, fj = c[:, 0], c[:, 1]
    return np.concatenate([i0, fi]), np.concatenate([i0 + 1, fj])


def _motion_errors(TL: np.ndarray, TG: np.ndarray, centre: np.ndarray, i: np.ndarray, j: np.ndarray):
    """Rotation (deg) and translation-at-the-centre (mm) errors of the motions i -> j."""
    ML = TL[j] @ invert(TL[i])
    MG = TG[j] @ invert(TG[i])
    rot = _rot_deg(ML[:, :3, :3] @ np.swapaxes(MG[:, :3, :3], 1, 2))
    c = np.einsum("nij,j->ni", TG[i, :3, :3], centre) + TG[i, :3, 3]     # centre in image i
    d = np.einsum("nij,nj->ni", ML[:, :3, :3] - MG[:, :3, :3], c) + ML[:, :3, 3] - MG[:, :3, 3]
    return rot, np.linalg.norm(d, axis=1)


def _ious(lab: BopScene, tru: BopScene, jobs: list[tuple[int, int, int]], workers: int) -> np.ndarray:
    """(n, 2) full and visible IoU for jobs [(im_id, label gt_id, truth gt_id)]."""
    def one(job):
        # only the box around a mask's non-zero pixels is decoded and compared
        im, lg, tg = job
        out = []
        for sub in ("mask", "mask_visib"):
            a = mask_rows(lab.path / sub / f"{im:06d}_{lg:06d}.png")
            b = mask_rows(tru.path / sub / f"{im:06d}_{tg:06d}.png")
            if a[3] != b[3]:
                raise TdofError(f"mask is {a[3]}, the truth's is {b[3]}", lab.path / sub / f"{im:06d}_{lg:06d}.png")
            out.append(mask_rows_iou(a, b))
        return out
    if not jobs:
        return np.zeros((0, 2))
    with ThreadPoolExecutor(max_workers=max(1, workers)) as ex:
        return np.asarray(list(ex.map(one, jobs)), float)


# ---------------------------------------------------------------------------------------------
# the evaluation
# ---------------------------------------------------------------------------------------------
def evaluate_scene(scene_dir: str | Path, truth_dir: str | Path, max_frames: int | None = None,
                   n_points: int = 2000, far_pairs: int | None = None, distance: str = "mesh",
                   iou_warn: float = 0.9, seed: int = 0, workers: int | None = None,
                   per_frame: bool = False) -> dict:
    """Compare an annotated scene with the simulator's truth (see the module docstring).

    ``max_frames``: evaluate at most this many common images, spread evenly over the ids;
    ``n_points``: Monte-Carlo samples per model for the surface distance; ``far_pairs``: far pairs
    sampled per track (default: as many as consecutive pairs); ``distance``: "mesh" or "samples".
    Returns a JSON-ready dict: ``objects`` {obj_id: {motion_rot_deg, motion_trans_mm, surface_mm,
    iou_full, iou_visib: {n, median, p95, mean, p5, min, max}, n_frames, missing_frames}}, ``all``
    (the same pooled, plus ``targets``), ``missing_frames``, ``extra_frames``, ``low_visib_iou``;
    with ``per_frame`` also ``frames``: [{im_id, obj_id, surface_mm, iou_full, iou_visib}]."""
    if distance not in ("mesh", "samples"):
        raise TdofError(f"distance must be 'mesh' or 'samples', got {distance!r}")
    if n_points < 1:
        raise TdofError(f"n_points must be >= 1, got {n_points}")
    lab = _open(scene_dir, "scene")
    tru = _open(truth_dir, "truth")
    lab_ids, tru_ids = set(lab.gt), set(tru.gt)
    common = sorted(lab_ids & tru_ids)
    if not common:
        rng_txt = lambda s: f"{min(s)}..{max(s)}" if s else "none"  # noqa: E731
        raise TdofError(f"no image in common with the truth (labels: {rng_txt(lab_ids)}, truth "
                        f"{tru.path}: {rng_txt(tru_ids)})", lab.path / SCENE_GT)
    if max_frames is not None and len(common) > max_frames:
        if max_frames < 1:
            raise TdofError(f"max_frames must be >= 1, got {max_frames}")
        pick = np.unique(np.linspace(0, len(common) - 1, int(max_frames)).round().astype(int))
        common = [common[k] for k in pick]

    # models (built once per object)
    lab_models: dict[int, _Model] = {}
    tru_models: dict[int, _Model] = {}

    def model(store, scene, obj_id):
        if obj_id not in store:
            store[obj_id] = _Model(*read_model_mesh(model_path(scene.path / "models", obj_id)), n_points, seed, distance)
        return store[obj_id]

    # match instances per image
    tracks: dict[int, dict[str, list]] = {}     # truth gt_id -> im, lg, TL, TG
    track_obj: dict[int, int] = {}
    missing_inst: dict[int, list[int]] = {}     # obj_id -> images where the labels lack it
    extra_inst: list[dict] = []
    from scipy.optimize import linear_sum_assignment

    for im in common:
        L, G = lab.gt[im], tru.gt[im]
        for o in sorted({e["obj_id"] for e in L} | {e["obj_id"] for e in G}):
            lg = [g for g, e in enumerate(L) if e["obj_id"] == o]
            tg = [g for g, e in enumerate(G) if e["obj_id"] == o]
            if len(lg) == 1 and len(tg) == 1:
                pairs = [(lg[0], tg[0])]
            elif lg and tg:
                cl = np.stack([L[g]["cam_R_m2c"] @ model(lab_models, lab, o).centre + L[g]["cam_t_m2c"] for g in lg])
                ct = np.stack([G[g]["cam_R_m2c"] @ model(tru_models, tru, o).centre + G[g]["cam_t_m2c"] for g in tg])
                r, c = linear_sum_assignment(np.linalg.norm(cl[:, None] - ct[None], axis=2))
                pairs = [(lg[a], tg[b]) for a, b in zip(r, c)]
            else:
                pairs = []
            for a, b in pairs:
                tr = tracks.setdefault(b, {"im": [], "lg": [], "TL": [], "TG": []})
                track_obj[b] = o
                tr["im"].append(im), tr["lg"].append(a)
                tr["TL"].append(_T(L[a]["cam_R_m2c"], L[a]["cam_t_m2c"]))
                tr["TG"].append(_T(G[b]["cam_R_m2c"], G[b]["cam_t_m2c"]))
            for b in set(tg) - {b for _, b in pairs}:
                missing_inst.setdefault(o, []).append(im)
            for a in set(lg) - {a for a, _ in pairs}:
                extra_inst.append({"im_id": im, "obj_id": o, "gt_id": a})

    # measures per track
    rng = np.random.default_rng(seed)
    per_obj: dict[int, dict[str, list]] = {}
    low: list[dict] = []
    wrong: list[dict] = [{"im_id": e["im_id"], "obj_id": e["obj_id"], "surface_mm": None, "iou_visib": None,
                          "why": "an instance the truth does not hold"} for e in extra_inst]
    rows: list[dict] = []
    infos: dict[int, float] = {}

    def diameter(obj_id: int) -> float:
        if obj_id not in infos:
            info = read_models_info(tru.path / "models")
            infos.update({int(k): float(v["diameter"]) for k, v in info.items()})
        return infos[obj_id]

    workers = workers or min(4, os.cpu_count() or 1)
    for b in sorted(tracks):
        tr, o = tracks[b], track_obj[b]
        TL, TG = np.stack(tr["TL"]), np.stack(tr["TG"])
        acc = per_obj.setdefault(o, {"rot": [], "trans": [], "surf": [], "full": [], "vis": [], "frames": set()})
        lm, tm = model(lab_models, lab, o), model(tru_models, tru, o)
        i, j = _pairs(len(TL), far_pairs, rng)
        if len(i):
            rot, trans = _motion_errors(TL, TG, tm.centre, i, j)
            acc["rot"].append(rot), acc["trans"].append(trans)
        surf = _surface(lm, tm, TL, TG)
        acc["surf"].append(surf)
        iou = _ious(lab, tru, [(im, lg, b) for im, lg in zip(tr["im"], tr["lg"])], workers)
        acc["full"].append(iou[:, 0]), acc["vis"].append(iou[:, 1])
        acc["frames"].update(tr["im"])
        if per_frame:
            rows += [{"im_id": int(im), "obj_id": int(o), "surface_mm": float(d), "iou_full": float(f),
                      "iou_visib": float(v)} for im, d, (f, v) in zip(tr["im"], surf, iou)]
        diam = diameter(o)
        for im, d, (f, v) in zip(tr["im"], surf, iou):
            why = []
            if d > 0.1 * diam:
                why.append(f"surface {d:.1f} mm > 10 % of the diameter ({0.1 * diam:.1f} mm)")
            gi = tru.gt_info.get(im) or []
            px = gi[b]["px_count_visib"] if b < len(gi) and "px_count_visib" in gi[b] else None
            if v < 0.5 and (px is None or px >= WRONG_MIN_VISIBLE_PX):
                why.append(f"visible IoU {v:.2f} < 0.5")
            if why:
                wrong.append({"im_id": int(im), "obj_id": int(o), "surface_mm": round(float(d), 3),
                              "iou_visib": round(float(v), 4), "why": "; ".join(why)})
        for im, (f, v) in zip(tr["im"], iou):
            if v < iou_warn:
                low.append({"im_id": int(im), "obj_id": int(o), "iou_visib": round(float(v), 4),
                            "iou_full": round(float(f), 4)})

    def block(parts: dict[str, list]) -> dict:
        cat = {k: (np.concatenate(parts[k]) if parts[k] else np.zeros(0)) for k in ("rot", "trans", "surf", "full", "vis")}
        return {"motion_rot_deg": _stats(cat["rot"]), "motion_trans_mm": _stats(cat["trans"]),
                "surface_mm": _stats(cat["surf"]), "iou_full": _stats(cat["full"]), "iou_visib": _stats(cat["vis"])}

    objects = {}
    for o in sorted(set(per_obj) | set(missing_inst)):
        acc = per_obj.get(o, {"rot": [], "trans": [], "surf": [], "full": [], "vis": [], "frames": set()})
        objects[str(o)] = {"n_frames": len(acc["frames"]), **block(acc),
                           "missing_frames": sorted(set(missing_inst.get(o, [])))}
    pooled = {k: [a for acc in per_obj.values() for a in acc[k]] for k in ("rot", "trans", "surf", "full", "vis")}
    all_ = {"n_frames": len(common), **block(pooled)}
    targets = {}
    for key, (op, thr) in TARGETS.items():
        v = all_[key]["median"]
        ok = None if v is None else (v <= thr if op == "<=" else v >= thr)
        targets[key] = {"median": v, "target": f"{op} {thr}", "ok": ok}
    all_["targets"] = targets
    low.sort(key=lambda d: (d["im_id"], d["obj_id"]))
    result = {
        "scene": str(lab.path), "truth": str(tru.path),
        "n_truth_frames": len(tru_ids), "n_labelled_frames": len(lab_ids), "n_evaluated_frames": len(common),
        "missing_frames": sorted(tru_ids - lab_ids), "extra_frames": sorted(lab_ids - tru_ids),
        "extra_instances": extra_inst,
        "settings": {"max_frames": max_frames, "n_points": int(n_points), "far_pairs": far_pairs,
                     "distance": distance, "iou_warn": iou_warn, "seed": seed},
        "objects": objects, "all": all_,
        "low_visib_iou": low,
        "wrong_labels": sorted(wrong, key=lambda d: (d["im_id"], d["obj_id"])),
        "definitions": {
            "motion_rot_deg": "angle of R_lab R_true^T for M_ij = T_j inv(T_i), pairs: consecutive + sampled far",
            "motion_trans_mm": "|M_lab c - M_true c|, c = the object's centre (true model bbox centre) in image i",
            "surface_mm": "symmetric mean distance between the posed labelled and true models' surfaces"
                          + (" (samples to triangles)" if distance == "mesh" else " (samples to samples)"),
            "iou_full": "IoU of mask/ (full silhouette)", "iou_visib": "IoU of mask_visib/ (visible part)",
            "wrong_labels": "labelled instances with a surface distance over 10 % of the object's diameter, a "
                            f"visible IoU under 0.5 (where the truth shows at least {WRONG_MIN_VISIBLE_PX} visible "
                            "pixels), or no true instance"},
    }
    if per_frame:
        result["frames"] = sorted(rows, key=lambda d: (d["im_id"], d["obj_id"]))
    return result


def evaluate_command(scene_dir: str | Path, truth_dir: str | Path, max_frames: int | None = None,
                     n_points: int = 2000) -> str:
    """The JSON text ``tdof20 annotate evaluate SCENE_DIR --truth RAW_DIR/truth`` prints."""
    return dumps_json(evaluate_scene(scene_dir, truth_dir, max_frames=max_frames, n_points=n_points), indent=2)


# ---------------------------------------------------------------------------------------------
# the registration against the simulator's truth
# ---------------------------------------------------------------------------------------------
def _T_diff(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (deg) and translation (mm) of inv(A) @ B, for stacks (...,4,4)."""
    D = invert(A) @ np.asarray(B, float)
    return _rot_deg(D[..., :3, :3]), np.linalg.norm(D[..., :3, 3], axis=-1)


def _reg_stats(x: np.ndarray) -> dict:
    """{median, p95, max, n} of a registration error."""
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


def truth_label_inputs(session_dir: str | Path) -> tuple[dict, list, dict]:
    """What the label stage needs, from a simulated session's exact truth (the labels a perfect
    registration and placement would give): ``T_ref_frames`` {(arm, step): (4,4)}, the
    placements [(obj_id, T_ref_model)] (the truth's poses in image 0, the reference camera) and
    the catalog's models {obj_id: (vertices, faces)}."""
    T = truth_T_ref_frame(session_dir)
    frames = {(a, k): T[a, k] for a in range(T.shape[0]) for k in range(T.shape[1])}
    truth = read_scene(Path(session_dir) / "truth")
    placements = []
    for g, e in enumerate(truth.gt[0]):
        R, t = truth.pose(0, g)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, t
        placements.append((int(e["obj_id"]), M))
    models = {o: (get_object(o).vertices, get_object(o).faces) for o, _ in placements}
    return frames, placements, models


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
    out["frame_to_ref"] = {"rot_deg": _reg_stats(rd), "trans_mm": _reg_stats(tm)}
    pos = {key: n for n, key in enumerate(keys)}
    cons = [(pos[(a, k)], pos[(a, k + 1)]) for a, k in keys if (a, k + 1) in pos]

    def motion_err(pairs):
        if not pairs:
            return {"rot_deg": _reg_stats([]), "trans_mm": _reg_stats([])}
        i, j = np.array(pairs).T
        Me = invert(E[i]) @ E[j]
        Mg = invert(G[i]) @ G[j]
        r, t = _T_diff(Me, Mg)
        return {"rot_deg": _reg_stats(r), "trans_mm": _reg_stats(t)}
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
