"""The model and place stages' algorithms: which cluster of the reconstruction is which object,
and each object's pose in the reference frame.

* :func:`match_models` (model stage, with a models folder) — a shape test (height above the
  table, footprint radius: :func:`~tdof20.annotate.fusion.cluster_shape`) picks up to
  ``place.match_candidates`` clusters per object, a quick upright fit
  (:func:`~tdof20.annotate.models.fit_model`) scores each, a one-to-one assignment (scipy
  ``linear_sum_assignment``) decides;
* :func:`place_models` (place stage) — each matched fit refined with dense model samples, set
  upright on the table (:func:`upright`: the model's z along the table normal, when it is within
  ``place.upright_max_deg``), then the quality gate (fitness, mean distance): a bad fit is a
  TdofError, no label is written from it;
* :func:`copy_models` — the scene's models folder from the user's: these objects' files byte for
  byte, their ``models_info.json`` entries, ``keypoints.json`` and samples where present;
* :func:`load_meshes`, :func:`model_samples`, and :func:`T_list` / :func:`T_arr` (a pose as the
  16 numbers ``fits.json`` and ``placements.json`` hold).

Options: :class:`~tdof20.annotate.config.PlaceConfig` (``cfg.place``) and
:class:`~tdof20.annotate.models.ModelFitConfig` (``cfg.fit``).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.executors import run_chunks
from tdof20.annotate.fusion import cluster_shape, point_cloud
from tdof20.annotate.modelbuild import sample_points
from tdof20.annotate.models import fit_model
from tdof20.dataset.models import load_models
from tdof20.errors import TdofError
from tdof20.formats import atomic_write_bytes, read_json, write_json
from tdof20.formats.bop_models import read_models_info, write_models_info
from tdof20.geometry import rotation_matrix

__all__ = ["T_arr", "T_list", "copy_file", "copy_models", "load_meshes", "match_models", "model_samples",
           "place_models", "pose_figures", "refine_placement", "upright"]


# ---------------------------------------------------------------------------------------------
# models and poses
# ---------------------------------------------------------------------------------------------
def load_meshes(models_dir: Path, obj_ids: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{obj_id: (V, F)} of a models folder, checked by :func:`~tdof20.dataset.models.load_models`."""
    return {o: (V, F) for o, (V, F, _) in load_models(models_dir, obj_ids).items()}


def model_samples(models: dict, n: int) -> dict[int, np.ndarray]:
    """{obj_id: (n,3) surface samples} of {obj_id: (V, F)} (seeded: the same on every run)."""
    return {o: sample_points(v[0], v[1], n, seed=0) for o, v in models.items()}


def T_list(T: np.ndarray) -> list[float]:
    """A (4,4) pose as 16 floats (row-major)."""
    return [float(x) for x in np.asarray(T, float).reshape(16)]


def T_arr(x: Any) -> np.ndarray:
    """16 numbers (row-major) as a (4,4) pose."""
    return np.asarray(x, float).reshape(4, 4)


def _fit_jobs(jobs: list) -> list:
    """[(i, j, fit)] of the matching fits [(i, j, model samples, cluster points, fit config, up,
    model z_min, table plane)], each on one open3d thread (a worker of any executor, or this
    process): open3d's ICP sums in thread order, so more threads would change the last digits.
    The arrays are copied first: Ray hands a task's arrays out read-only, and open3d's point
    vectors take writable ones only."""
    from tdof20.o3d import o3d

    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        return [(i, j, fit_model(np.array(P), np.array(C), cfg, up=np.array(up), model_z_min=z_min,
                                 table_plane=np.array(plane)))
                for i, j, P, C, cfg, up, z_min, plane in jobs]
    finally:
        o3d.utility.set_max_threads(before)


def _thin(points: np.ndarray, voxel: float) -> np.ndarray:
    return np.asarray(point_cloud(points).voxel_down_sample(voxel).points)


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    ang = math.atan2(s, float(a @ b))
    if s < 1e-12:
        return np.eye(3)
    return rotation_matrix(axis / s, ang)


def upright(T: np.ndarray, up: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, float]:
    """T with the model's z axis turned onto ``up`` about the model point ``centre``; and the tilt
    removed (deg)."""
    R = T[:3, :3]
    tilt = math.degrees(math.acos(float(np.clip(R[:, 2] @ up / np.linalg.norm(up), -1, 1))))
    Rn = _rot_between(R[:, 2], up) @ R
    c = R @ centre + T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = Rn
    out[:3, 3] = c - Rn @ centre
    return out, tilt


# ---------------------------------------------------------------------------------------------
# the model stage: objects to clusters
# ---------------------------------------------------------------------------------------------
def match_models(models: dict, objects: list[int], clusters: list[np.ndarray], plane: np.ndarray,
                 cfg: AnnotateConfig, progress: bool) -> tuple[list[dict], list[int]]:
    """Assign each object (an obj_id of session.json) to a cluster, one to one.

    Shape costs (relative differences of the height above the table and of the footprint radius)
    choose up to ``match_candidates`` clusters per object; each is scored by a quick upright fit
    (truncated mean distance of the cluster to the posed model); the Hungarian assignment on those
    scores (untried pairs cost more than any tried one) decides."""
    from scipy.optimize import linear_sum_assignment

    pc = cfg.place
    up, off = plane[:3] / np.linalg.norm(plane[:3]), float(plane[3])
    n_o, n_c = len(objects), len(clusters)
    samples = model_samples({o: models[o] for o in set(objects)}, pc.match_samples)
    shape_m = {}
    for o in set(objects):
        V = models[o][0]
        P = samples[o]
        h = P[:, 2] - V[:, 2].min()
        r = np.linalg.norm(P[:, :2] - np.median(P[:, :2], axis=0), axis=1)
        shape_m[o] = (float(np.percentile(h, 99.5)), float(np.percentile(r, 99)))
    shape_c = [cluster_shape(c, up, off) for c in clusters]
    S = np.array([[abs(hc - shape_m[o][0]) / shape_m[o][0] + abs(rc - shape_m[o][1]) / shape_m[o][1]
                   for hc, rc in shape_c] for o in objects]).reshape(n_o, n_c)
    thin = {}
    quick = dataclasses.replace(cfg.fit, icp_mm=tuple(pc.match_icp_mm))
    fits: dict[tuple[int, int], Any] = {}

    def fit(i: int, j: int):
        if j not in thin:
            thin[j] = _thin(clusters[j], pc.match_voxel_mm)
        o = objects[i]
        fits[(i, j)] = fit_model(samples[o], thin[j], quick, up=up, model_z_min=float(models[o][0][:, 2].min()),
                                 table_plane=plane)
        return fits[(i, j)]

    pairs = []
    for i in range(n_o):
        order = np.argsort(S[i])
        pairs += [(i, int(j)) for j in order[:pc.match_candidates] if S[i, j] <= S[i, order[0]] + pc.match_shape_margin]
    C = np.full((n_o, n_c), 0.0)
    # the candidate fits are independent: on the worker processes (each on one open3d thread,
    # so each fit is the one this process would make)
    for j in sorted({j for _, j in pairs}):
        thin[j] = _thin(clusters[j], pc.match_voxel_mm)
    jobs = [[(i, j, samples[objects[i]], thin[j], quick, up, float(models[objects[i]][0][:, 2].min()), plane)]
            for i, j in pairs]
    for done in run_chunks(_fit_jobs, jobs, workers=None if len(jobs) > 1 else 1, progress=progress,
                           description="match models to clusters", unit="fit"):
        for i, j, f in done:
            fits[(i, j)] = f
    big = 10.0 + max([f.score for f in fits.values()], default=0.0)
    for i in range(n_o):
        for j in range(n_c):
            C[i, j] = fits[(i, j)].score if (i, j) in fits else big + S[i, j]
    rows, cols = linear_sum_assignment(C)
    out = []
    for i, j in zip(rows.tolist(), cols.tolist()):
        f = fits.get((i, j)) or fit(i, j)
        out.append({"index": i, "obj_id": int(objects[i]), "cluster": j, "T_ref_model": T_list(f.T_ref_model),
                    "match_score_mm": float(f.score), "match_fitness": float(f.fitness), "shape_cost": float(S[i, j]),
                    "tried": {int(jj): round(float(ff.score), 4) for (ii, jj), ff in fits.items() if ii == i}})
    out.sort(key=lambda e: e["index"])
    unused = sorted(set(range(n_c)) - set(cols.tolist()))
    return out, unused


# ---------------------------------------------------------------------------------------------
# the place stage: poses, the quality gate, the scene's models folder
# ---------------------------------------------------------------------------------------------
def place_models(objects: list[dict], meshes: dict, clusters: list[np.ndarray], cluster_files: list[str],
                 up: np.ndarray, cfg: AnnotateConfig, where: Path, failed: list | None = None,
                 plane: np.ndarray | None = None) -> list[dict]:
    """The placements of the matched objects (``fits.json``'s ``objects``: obj_id, cluster, the
    matching fit's ``T_ref_model``): each fit refined on its cluster with ``place.fit_samples``
    model samples, set upright on the table (normal ``up``) when tilted less than
    ``place.upright_max_deg``, and checked against the quality gate — a bad fit is a TdofError
    naming ``where`` and the cluster's file (``cluster_files``). Returns one placement per object
    (gt_id, obj_id, cluster, T_ref_model, fitness, rmse_mm, score_mm, upright_correction_deg,
    source, note), in the order given.

    With a ``failed`` list, an object that fails the gate is appended to it ({obj_id, cluster,
    reason}: the one line the error would say) and left out, so the others are labelled (a
    "partial" scene); only when every object fails is the first one's TdofError raised. Each
    placement and failure carries the object's ``index`` (its place in fits.json / session.json),
    which the reviewer's corrections (:mod:`tdof20.annotate.corrections`) refer to."""
    pc = cfg.place
    samples = model_samples(meshes, pc.fit_samples)
    placements: list[dict] = []
    for e in objects:
        o, j = int(e["obj_id"]), int(e["cluster"])
        r = refine_placement(samples[o], meshes[o][0], clusters[j], T_arr(e["T_ref_model"]), up, cfg, plane)
        if r["bad"]:
            err = TdofError(f"object {o} fits its cluster badly ({', '.join(r['bad'])}; work/reconstruction/"
                            f"{cluster_files[j]}): the wrong model, a model in other units, or a "
                            f"bad reconstruction; no labels are written from it", where)
            if failed is None:
                raise err
            failed.append({"index": int(e["index"]), "obj_id": o, "cluster": j, "reason": str(err)})
            continue
        placements.append({"gt_id": len(placements), "index": int(e["index"]), "obj_id": o, "cluster": j,
                           "T_ref_model": T_list(r["T_ref_model"]), "fitness": r["fitness"], "rmse_mm": r["rmse_mm"],
                           "score_mm": r["score_mm"], "upright_correction_deg": r["upright_correction_deg"],
                           "contact_mm": r["contact_mm"], "source": "models", "note": r["note"]})
    if failed and not placements:
        raise TdofError(failed[0]["reason"])
    return placements


def refine_placement(samples: np.ndarray, vertices: np.ndarray, points: np.ndarray, T_init: np.ndarray,
                     up: np.ndarray, cfg: AnnotateConfig, plane: np.ndarray | None = None) -> dict:
    """The place stage's fit of one object: ICP of the model samples into ``points`` (its cluster)
    from ``T_init`` (``cfg.fit.icp_mm``), set upright on the table (normal ``up``) when tilted
    less than ``place.upright_max_deg``, judged by the quality gate. Also the review's "snap"
    (from where the reviewer put the model). Returns {T_ref_model, fitness, rmse_mm, score_mm,
    upright_correction_deg, contact_mm, note, bad (the gate's failed tests, [] when it passes)}.

    With the table ``plane`` (a x + b y + c z + d = 0, normal towards the objects) an object set
    upright is also set down onto it (``place.contact``): moved along the normal by its lowest
    point's height above the table (``contact_mm``, where within ``place.contact_max_mm``). An
    upright object's fit is weak along its axis: the fused cluster lacks its foot (the points
    within reconstruct.above_table_mm of the table are the table's) and an open vessel's rim says
    little, so a cup's fit floated 3-4.5 mm above the table on the simulator's perfect sessions
    (labels 3-4 mm off at the centre while 0.7 mm off on the surface)."""
    pc = cfg.place
    f = fit_model(samples, points, cfg.fit, init=T_init)
    T, tilt, note, contact = f.T_ref_model, None, "", None
    if pc.upright:
        Tu, tilt = upright(f.T_ref_model, up, 0.5 * (vertices.min(0) + vertices.max(0)))
        if tilt <= pc.upright_max_deg:
            T = Tu
            if pc.contact and plane is not None:
                n = np.asarray(plane[:3], float)
                s = float(np.linalg.norm(n))
                gap = float(np.min(vertices @ (T[:3, :3].T @ (n / s)) + (T[:3, 3] @ n + plane[3]) / s))
                if abs(gap) <= pc.contact_max_mm:
                    T = T.copy()
                    T[:3, 3] -= gap * n / s
                    contact = gap
        else:
            note = f"tilted {tilt:.1f} deg from the table normal (> place.upright_max_deg): kept as fitted"
    bad = []
    if f.fitness < pc.min_fitness:
        bad.append(f"fitness {f.fitness:.2f} < {pc.min_fitness}")
    if f.score > pc.max_score_mm:
        bad.append(f"mean distance {f.score:.2f} mm > {pc.max_score_mm}")
    return {"T_ref_model": T, "fitness": float(f.fitness), "rmse_mm": float(f.rmse), "score_mm": float(f.score),
            "upright_correction_deg": None if tilt is None or note else round(float(tilt), 4),
            "contact_mm": None if contact is None else round(contact, 4), "note": note, "bad": bad}


def pose_figures(samples: np.ndarray, points: np.ndarray, T: np.ndarray, inlier_mm: float) -> tuple[float, float, float]:
    """(fitness, inlier RMSE mm, truncated mean distance mm) of the posed model samples against
    ``points`` (a cluster), as :func:`~tdof20.annotate.models.fit_model` reports them: the share
    of points within ``inlier_mm`` of the model, their RMSE, and the mean distance capped at 5 mm."""
    from scipy.spatial import cKDTree

    if not len(points):
        return 0.0, 0.0, 5.0
    d, _ = cKDTree(samples @ T[:3, :3].T + T[:3, 3]).query(points, workers=-1)
    inl = d <= inlier_mm
    rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else 0.0
    return float(inl.mean()), rmse, float(np.minimum(d, 5.0).mean())


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` byte for byte, atomically (the folder created)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(dst, src.read_bytes())


def copy_models(md: Path, dst: Path, obj_ids: list[int]) -> None:
    """The scene's models folder ``dst`` (replaced) from the models folder ``md``: the objects'
    files byte for byte (and their ``_samples.npy``), their ``models_info.json`` entries and, where
    ``md`` has one, their part of ``keypoints.json``."""
    if dst.exists():
        shutil.rmtree(dst)
    infos = read_models_info(md)
    for o in obj_ids:
        copy_file(md / f"obj_{o:06d}.ply", dst / f"obj_{o:06d}.ply")
        for extra in (f"obj_{o:06d}_samples.npy",):
            if (md / extra).exists():
                copy_file(md / extra, dst / extra)
    write_models_info(dst, {o: infos[o] for o in obj_ids})
    kp = md / "keypoints.json"
    if kp.exists():
        k = read_json(kp)
        if isinstance(k, dict):
            write_json(dst / "keypoints.json", {str(o): k[str(o)] for o in obj_ids if str(o) in k})
