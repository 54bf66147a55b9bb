"""One annotated scene as the reviewer sees and corrects it: what the pipeline left on disk (the
registration, the reconstruction, the fits, placements, labels, QA), the reviewer's journal
(:mod:`tdof20.annotate.corrections`) over it, and the corrections themselves.

:class:`ReviewScene` reads the scene folder, and every correction is one journal entry:

* :meth:`~ReviewScene.nudge` — move an object by ``amount`` mm along an axis of the *table frame*
  (x, y on the table top, z along its normal) or turn it by ``amount`` degrees about one (rx, ry,
  rz; about the model's centre, so a turn does not also move it);
* :meth:`~ReviewScene.set_pose` — a pose given whole (the 3D view's drag), in the table frame;
* :meth:`~ReviewScene.snap` — the place stage's fit (:func:`tdof20.annotate.place.refine_placement`:
  ICP, set upright, the quality gate) from where the object was put, on the reconstruction's object
  points within reach of it (so a cluster the reconstruction cut in pieces, or the wrong cluster,
  does not matter); a fit that fails the gate is not written;
* :meth:`~ReviewScene.assign` — the model stage's decision made by a person: this object is that
  cluster (the model stage's quick upright fit puts it there);
* :meth:`~ReviewScene.verdict` — accept or reject frames, or a whole arm position;
* :meth:`~ReviewScene.undo` — take back the last correction (an entry too);
* :meth:`~ReviewScene.relabel` — rerun place, label and QA with the scene's own options (``work/config.json``).

The table frame: origin where the turntable axis meets the table top, z along the table normal
(towards the camera side), x the reference camera's x axis laid onto the table. Poses in the
journal are in the reference frame (arm 0, step 0), as ``work/placements.json`` has them.
"""

from __future__ import annotations

import dataclasses
import io
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tdof20.annotate.config import AnnotateConfig, annotate_config_from_dict
from tdof20.annotate.corrections import (
    REJECTED,
    Corrections,
    append_entry,
    read_journal,
    replay,
    undo_target,
)
from tdof20.annotate.fusion import load_reconstruction, point_cloud, read_ply_points
from tdof20.annotate.models import fit_model
from tdof20.annotate.pipeline import annotate
from tdof20.annotate.place import (
    T_arr,
    T_list,
    load_meshes,
    model_samples,
    pose_figures,
    refine_placement,
)
from tdof20.annotate.registration import RegistrationResult
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, read_png
from tdof20.formats.io import encode_png
from tdof20.geometry import rotation_matrix
from tdof20.viz import object_colour

__all__ = ["NUDGE_AXES", "SNAP_REACH_MM", "ReviewScene"]

NUDGE_AXES = ("x", "y", "z", "rx", "ry", "rz")   # mm along, degrees about, the table frame's axes
SNAP_REACH_MM = 20.0     # snap fits the object points within this of the model where it was put
_MIN_WIDTH = 480         # frame images are enlarged (integer factor) to at least this width


@dataclass
class ObjectView:
    """One object of the scene as the review shows it."""

    index: int                   # its place in session.json's objects (fits.json's index)
    obj_id: int
    cluster: int
    T_ref_model: np.ndarray      # the pose shown: the reviewer's, else the placement, else the matching fit
    status: str                  # placed | failed | corrected
    pending: bool                # the reviewer's pose is not yet what placements.json holds (relabel)
    fitness: float | None
    score_mm: float | None
    reason: str                  # why it failed (failed objects)

    def to_dict(self, T_table_ref: np.ndarray) -> dict:
        return {"index": self.index, "obj_id": self.obj_id, "cluster": self.cluster,
                "T_ref_model": T_list(self.T_ref_model), "T_table_model": T_list(T_table_ref @ self.T_ref_model),
                "status": self.status, "pending": self.pending, "fitness": self.fitness, "score_mm": self.score_mm,
                "reason": self.reason, "colour": [int(c) for c in object_colour(self.obj_id)]}


def _rigid(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise TdofError(f"{what}: a pose is 16 finite numbers")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise TdofError(f"{what}: not a rigid pose (a rotation, a translation, last row 0 0 0 1)")
    # re-orthonormalise: a browser's float32 matrix drifts a little from a rotation
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


class ReviewScene:
    """An annotated scene folder under review (see the module docstring). Thread-safe: the web
    app's requests run on threads, and every correction and rerun holds one lock."""

    def __init__(self, scene: str | Path):
        self.path = Path(scene)
        self.work = self.path / "work"
        state_file = self.work / "state.json"
        if not state_file.exists():
            raise TdofError("not an annotated scene folder (no work/state.json): run tdof20 annotate first", self.path)
        state = read_json(state_file)
        raw = Path(state.get("raw_recorded") or state.get("raw") or "")
        if not (raw / "session.json").exists():
            raise TdofError(f"the raw session it was annotated from, {raw}, is not there (the review shows its "
                            f"frames and reruns stages from it)", state_file)
        self.raw = raw
        self.session = RawSession.open(raw)
        self.info = self.session.info
        self.lock = threading.RLock()
        self.cfg = self._config()
        self._meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._samples: dict[int, np.ndarray] = {}
        self._rec: tuple[dict, list[np.ndarray]] | None = None
        self.reload()

    # ------------------------------------------------------------------ reading the scene
    def _config(self) -> AnnotateConfig:
        """The options of the scene's last annotate run (``work/config.json``; defaults if absent)."""
        p = self.work / "config.json"
        if not p.exists():
            return AnnotateConfig()
        d = read_json(p)
        d = {k: ({kk: vv for kk, vv in v.items() if vv is not None} if isinstance(v, dict) else v)
             for k, v in d.items() if v is not None}
        return annotate_config_from_dict(d, str(p))

    def reload(self) -> None:
        """Read what the pipeline wrote (again, after a relabel)."""
        with self.lock:
            w = self.work
            self.reg = RegistrationResult.load(w / "registration.json") if (w / "registration.json").exists() else None
            self.fits = read_json(w / "fits.json") if (w / "fits.json").exists() else None
            self.placements = read_json(w / "placements.json") if (w / "placements.json").exists() else None
            self.label = read_json(w / "label.json") if (w / "label.json").exists() else None
            self.summary = read_json(w / "summary.json") if (w / "summary.json").exists() else {}
            self.evaluation = read_json(w / "evaluation.json") if (w / "evaluation.json").exists() else None
            gt_file = self.path / "scene_gt.json"
            self.gt = {int(k): v for k, v in read_json(gt_file).items()} if gt_file.exists() else {}
            rec = w / "reconstruction" / "reconstruction.json"
            self.rec_meta = read_json(rec) if rec.exists() else None
            self._rec = None
            self.T_table_ref = self._table_frame()

    def corrections(self) -> Corrections:
        return replay(read_journal(self.work))

    def _table_frame(self) -> np.ndarray:
        """T_table_ref (see the module docstring); identity without a reconstruction."""
        T = np.eye(4)
        if self.rec_meta is None:
            return T
        plane = np.asarray(self.rec_meta["plane"], float)
        n = plane[:3] / np.linalg.norm(plane[:3])
        if plane[3] < 0:          # towards the reference camera (its origin lies on the positive side)
            n = -n
        nn, dd = plane[:3] / np.linalg.norm(plane[:3]), plane[3] / np.linalg.norm(plane[:3])
        p = np.asarray(self.rec_meta.get("axis_point", [0.0, 0.0, 0.0]), float)
        o = p - (nn @ p + dd) * nn             # the axis point laid onto the table plane
        x = np.array([1.0, 0.0, 0.0]) - n[0] * n
        x /= np.linalg.norm(x)
        y = np.cross(n, x)
        R = np.stack([x, y, n])
        T[:3, :3] = R
        T[:3, 3] = -R @ o
        return T

    @property
    def up(self) -> np.ndarray:
        return self.T_table_ref[2, :3].copy()

    def reconstruction(self) -> tuple[dict, list[np.ndarray]]:
        if self.rec_meta is None:
            raise TdofError("no reconstruction (work/reconstruction/): run the reconstruct stage first", self.work)
        if self._rec is None:
            self._rec = load_reconstruction(self.work / "reconstruction")
        return self._rec

    def models_dir(self) -> Path:
        if self.fits is None:
            raise TdofError("no model matching (work/fits.json): run the model stage first", self.work)
        if self.fits.get("source") == "built":
            return self.work / "models"
        md = Path(self.fits.get("models_dir") or "")
        if not md.is_dir():
            raise TdofError(f"the models folder the model stage used, {md}, is not there", self.work / "fits.json")
        return md

    def mesh(self, obj_id: int) -> tuple[np.ndarray, np.ndarray]:
        if obj_id not in self._meshes:
            self._meshes.update(load_meshes(self.models_dir(), [obj_id]))
        return self._meshes[obj_id]

    def samples(self, obj_id: int) -> np.ndarray:
        if obj_id not in self._samples:
            self._samples.update(model_samples({obj_id: self.mesh(obj_id)}, self.cfg.place.fit_samples))
        return self._samples[obj_id]

    # ------------------------------------------------------------------ what the review shows
    def objects(self, corr: Corrections | None = None) -> list[ObjectView]:
        """Every object of fits.json with the pose the review shows and its state."""
        if self.fits is None:
            return []
        corr = corr or self.corrections()
        pl = self.placements or {"placements": [], "failed": []}

        def find(lst: list[dict], e: dict) -> dict | None:
            for p in lst:
                if int(p.get("index", -1)) == int(e["index"]) or (
                        "index" not in p and int(p["obj_id"]) == int(e["obj_id"]) and int(p["cluster"]) == int(e["cluster"])):
                    return p
            return None

        out = []
        for e in sorted(self.fits["objects"], key=lambda x: int(x["index"])):
            i, o = int(e["index"]), int(e["obj_id"])
            p, f, c = find(pl["placements"], e), find(pl.get("failed") or [], e), corr.placed.get(i)
            if c is not None:
                T = T_arr(c["T_ref_model"])
                pending = p is None or not np.allclose(T_arr(p["T_ref_model"]), T, atol=1e-6)
                cluster = int(c["cluster"]) if c.get("cluster") is not None else int(e["cluster"])
                out.append(ObjectView(i, o, cluster, T, "corrected", pending, p and p.get("fitness"),
                                      p and p.get("score_mm"), ""))
            elif p is not None:
                out.append(ObjectView(i, o, int(p["cluster"]), T_arr(p["T_ref_model"]),
                                      "corrected" if p.get("corrected") else "placed", False, p.get("fitness"),
                                      p.get("score_mm"), ""))
            else:
                out.append(ObjectView(i, o, int(e["cluster"]), T_arr(e["T_ref_model"]), "failed", False, None, None,
                                      (f or {}).get("reason", "not placed: the place stage has not run")))
        return out

    def object(self, index: int, corr: Corrections | None = None) -> ObjectView:
        for ob in self.objects(corr):
            if ob.index == index:
                return ob
        raise TdofError(f"no object {index} in this scene (objects 0..{len(self.objects()) - 1})")

    def frames(self, corr: Corrections | None = None) -> list[dict]:
        """Every planned frame (arm x step): its image id, whether labelled, the reasons it was
        flagged or skipped, and the reviewer's verdict."""
        corr = corr or self.corrections()
        steps = self.info.steps
        reasons: dict[tuple[int, int], list[str]] = {}
        if self.reg is not None:
            for a, k, r in self.reg.flagged_frames():
                reasons.setdefault((a, k), []).append(f"registration: {r}")
        for s in (self.label or {}).get("skipped") or []:
            r = s["reason"]
            if not r.startswith(REJECTED) and not any(r in x for x in reasons.get((s["arm"], s["step"]), [])):
                reasons.setdefault((s["arm"], s["step"]), []).append(r)
        out = []
        for a in range(self.info.n_arms):
            for k in range(steps):
                im = a * steps + k
                labelled = bool(self.gt.get(im))
                v = corr.verdict(a, k)
                rs = reasons.get((a, k), [])
                status = ("rejected" if v == "reject" else "labelled" if labelled
                          else "flagged" if rs else "not labelled")
                out.append({"arm": a, "step": k, "im_id": im, "labelled": labelled, "reasons": rs, "verdict": v,
                            "status": status, "unresolved": bool(not labelled and v != "reject")})
        return out

    def state(self) -> dict:
        """Everything the pages and the API show, in one JSON-able dict."""
        with self.lock:
            corr = self.corrections()
            frames = self.frames(corr)
            objects = self.objects(corr)
            undo = undo_target(corr.entries)
            unresolved = [f for f in frames if f["unresolved"]]
            failed = [o for o in objects if o.status == "failed"]
            return {
                "scene": str(self.path), "scene_id": self.info.scene_id, "raw": str(self.raw),
                "n_arms": self.info.n_arms, "steps": self.info.steps, "step_deg": self.info.step_deg,
                "objects": [o.to_dict(self.T_table_ref) for o in objects],
                "frames": frames, "T_table_ref": T_list(self.T_table_ref),
                "clusters": len((self.rec_meta or {}).get("clusters", [])),
                "labelled": sum(f["labelled"] for f in frames),
                "unresolved": len(unresolved) + len(failed),
                "pending": any(o.pending for o in objects) or self._verdicts_pending(corr),
                "journal": corr.entries, "undo": undo,
                "stages": self._stages(),
                "stage_errors": {k: v["error"] for k, v in (self.summary.get("stages") or {}).items() if v.get("error")},
                "evaluation": (self.evaluation or {}).get("all"),
                "partial": bool(self.summary.get("partial")),
            }

    def _stages(self) -> dict[str, str]:
        """Per stage: "failed" (the last run's error), "finished" or "not run" (work/state.json)."""
        done = (read_json(self.work / "state.json").get("stages") or {}) if (self.work / "state.json").exists() else {}
        last = self.summary.get("stages") or {}
        out = {}
        for k in ("register", "reconstruct", "model", "place", "label", "qa"):
            out[k] = ("failed" if (last.get(k) or {}).get("status") == "failed"
                      else "finished" if (done.get(k) or {}).get("finished") else "not run")
        return out

    def _verdicts_pending(self, corr: Corrections) -> bool:
        """A verdict the labels do not show yet: a rejected frame still labelled, an accepted
        flagged frame not labelled nor refused by the label gate since."""
        skipped = {(s["arm"], s["step"]) for s in (self.label or {}).get("skipped") or []
                   if not s["reason"].startswith("registration") and not s["reason"].startswith(REJECTED)}
        flagged = {(a, k) for a, k, _ in self.reg.flagged_frames()} if self.reg is not None else set()
        for a in range(self.info.n_arms):
            for k in range(self.info.steps):
                v = corr.verdict(a, k)
                labelled = bool(self.gt.get(a * self.info.steps + k))
                if v == "reject" and labelled:
                    return True
                if v == "accept" and (a, k) in flagged and not labelled and (a, k) not in skipped:
                    return True
        return False

    # ------------------------------------------------------------------ corrections
    def _centre(self, obj_id: int, T: np.ndarray) -> np.ndarray:
        V = self.mesh(obj_id)[0]
        return T[:3, :3] @ (0.5 * (V.min(0) + V.max(0))) + T[:3, 3]

    def nudge(self, index: int, axis: str, amount: float) -> dict:
        """Move (mm) or turn (deg) object ``index`` along / about a table-frame axis; one entry."""
        if axis not in NUDGE_AXES:
            raise TdofError(f"nudge axis must be one of {', '.join(NUDGE_AXES)}, got '{axis}'")
        amount = float(amount)
        if not math.isfinite(amount) or abs(amount) > (500.0 if axis in "xyz" else 180.0):
            raise TdofError(f"nudge amount must be finite and at most {'500 mm' if axis in 'xyz' else '180 deg'}")
        with self.lock:
            ob = self.object(index)
            T = ob.T_ref_model.copy()
            R_tr = self.T_table_ref[:3, :3]
            k = "xyz".index(axis[-1])
            if axis in ("x", "y", "z"):
                T[:3, 3] += R_tr[k] * amount     # table axis k in the reference frame: row k of R_table_ref
            else:
                c = self._centre(ob.obj_id, T)
                Rn = rotation_matrix(R_tr[k], math.radians(amount))
                T[:3, :3] = Rn @ T[:3, :3]
                T[:3, 3] = c + Rn @ (T[:3, 3] - c)
            return append_entry(self.work, {"op": "place", "object": index, "obj_id": ob.obj_id,
                                             "T_ref_model": T_list(T), "how": "nudge",
                                             "detail": {"axis": axis, "amount": amount,
                                                        "unit": "mm" if axis in "xyz" else "deg"}})

    def set_pose(self, index: int, T_table_model: Any, how: str = "drag") -> dict:
        """Object ``index`` at a pose given in the table frame (16 numbers, row-major); one entry."""
        T = _rigid(np.asarray(T_table_model, float).reshape(4, 4) if np.size(T_table_model) == 16 else np.zeros(0),
                   "pose")
        with self.lock:
            ob = self.object(index)
            T_ref = np.linalg.inv(self.T_table_ref) @ T
            return append_entry(self.work, {"op": "place", "object": index, "obj_id": ob.obj_id,
                                             "T_ref_model": T_list(T_ref), "how": how if how in ("drag", "set") else "set"})

    def object_points(self) -> np.ndarray:
        """The reconstruction's object points: every cluster's (what turned with the table)."""
        _, clusters = self.reconstruction()
        return np.concatenate(clusters) if clusters else np.zeros((0, 3))

    def snap(self, index: int, reach_mm: float = SNAP_REACH_MM) -> dict:
        """The place stage's fit from where object ``index`` was put, on the object points within
        ``reach_mm`` of the posed model; one entry when the fit passes the quality gate, else a
        TdofError saying why (nothing written)."""
        from scipy.spatial import cKDTree

        with self.lock:
            ob = self.object(index)
            S = self.samples(ob.obj_id)
            P = self.object_points()
            d, _ = cKDTree(S @ ob.T_ref_model[:3, :3].T + ob.T_ref_model[:3, 3]).query(P, distance_upper_bound=reach_mm)
            near = P[np.isfinite(d)]
            if len(near) < 50:
                raise TdofError(f"snap: only {len(near)} reconstruction points within {reach_mm:g} mm of object "
                                f"{ob.obj_id} where it was put: move it onto its points first")
            r = refine_placement(S, self.mesh(ob.obj_id)[0], near, ob.T_ref_model, self.up, self.cfg)
            if r["bad"]:
                raise TdofError(f"snap: the fit from here fails the quality gate ({', '.join(r['bad'])}): move "
                                f"object {ob.obj_id} closer to its points and snap again")
            moved = np.linalg.norm(r["T_ref_model"][:3, 3] - ob.T_ref_model[:3, 3])
            return append_entry(self.work, {"op": "place", "object": index, "obj_id": ob.obj_id,
                                             "T_ref_model": T_list(r["T_ref_model"]), "how": "snap",
                                             "detail": {"fitness": round(r["fitness"], 4),
                                                        "score_mm": round(r["score_mm"], 4),
                                                        "rmse_mm": round(r["rmse_mm"], 4), "points": len(near),
                                                        "moved_mm": round(float(moved), 3), "note": r["note"]}})

    def assign(self, index: int, cluster: int) -> dict:
        """Object ``index`` is cluster ``cluster``: the model stage's quick upright fit puts it
        there; one entry."""
        with self.lock:
            meta, clusters = self.reconstruction()
            if not 0 <= int(cluster) < len(clusters):
                raise TdofError(f"no cluster {cluster} (the reconstruction has clusters 0..{len(clusters) - 1})")
            ob = self.object(index)
            V = self.mesh(ob.obj_id)[0]
            pc = self.cfg.place
            samples = model_samples({ob.obj_id: self.mesh(ob.obj_id)}, pc.match_samples)[ob.obj_id]
            thin = np.asarray(point_cloud(clusters[cluster]).voxel_down_sample(pc.match_voxel_mm).points)
            quick = dataclasses.replace(self.cfg.fit, icp_mm=tuple(pc.match_icp_mm))
            f = fit_model(samples, thin, quick, up=self.up, model_z_min=float(V[:, 2].min()),
                          table_plane=np.asarray(meta["plane"], float))
            return append_entry(self.work, {"op": "assign", "object": index, "obj_id": ob.obj_id,
                                             "cluster": int(cluster), "T_ref_model": T_list(f.T_ref_model),
                                             "detail": {"score_mm": round(float(f.score), 4),
                                                        "fitness": round(float(f.fitness), 4)}})

    def verdict(self, arm: int, steps: list[int] | None, verdict: str) -> dict:
        """Accept, reject or clear frames of arm position ``arm`` (``steps`` None: all of them)."""
        if not 0 <= int(arm) < self.info.n_arms:
            raise TdofError(f"no arm position {arm} (0..{self.info.n_arms - 1})")
        if steps is not None:
            bad = [k for k in steps if not 0 <= int(k) < self.info.steps]
            if bad:
                raise TdofError(f"no step {bad[0]} (0..{self.info.steps - 1})")
        with self.lock:
            return append_entry(self.work, {"op": "frames", "arm": int(arm),
                                             "steps": None if steps is None else [int(k) for k in steps],
                                             "verdict": verdict})

    def undo(self) -> dict:
        """Take back the last correction not yet taken back (an ``undo`` entry)."""
        with self.lock:
            target = undo_target(read_journal(self.work))
            if target is None:
                raise TdofError("nothing to undo")
            return append_entry(self.work, {"op": "undo", "undoes": int(target["id"])})

    def relabel(self) -> dict:
        """Rerun place, label and QA with the scene's options and the journal; returns the
        summary (a refusal is a TdofError, the journal kept)."""
        with self.lock:
            md = None if (self.fits or {}).get("source") == "built" else self.models_dir()
            try:
                summary = annotate(self.raw, self.path, models_dir=md, stages=("place", "label", "qa"), cfg=self.cfg,
                                   progress=False)
            finally:
                self.reload()
            lab = summary.get("label") or {}
            append_entry(self.work, {"op": "relabel",
                                     "detail": {"labelled": int(lab.get("labelled", 0)) + int(lab.get("already_done", 0)),
                                                "unresolved": len(summary.get("unresolved_flags") or [])}})
            return summary

    # ------------------------------------------------------------------ pictures
    def frame_image(self, arm: int, step: int, kind: str) -> bytes:
        """PNG of a frame's colour image (``kind``: "rgb" the transparent phase, "opaque" its
        twin) with the labelled visible masks tinted and every object's model outline at the pose
        the review shows (the reviewer's corrections included), in the object's colour."""
        if kind not in ("rgb", "opaque"):
            raise TdofError(f"image kind must be rgb or opaque, got '{kind}'")
        if not (0 <= arm < self.info.n_arms and 0 <= step < self.info.steps):
            raise TdofError(f"no frame arm {arm} step {step}")
        with self.lock:
            im = arm * self.info.steps + step
            phase = "transparent" if kind == "rgb" else "opaque"
            scene_rgb = self.path / "rgb" / f"{im:06d}.png"
            if kind == "rgb" and scene_rgb.exists():
                img = read_png(scene_rgb, kind="rgb")
            elif self.session.has_frame(phase, arm, step):
                img = self.session.load_rgb(phase, arm, step)
            else:
                raise TdofError(f"arm {arm} step {step}: no {phase} colour image in the session", self.raw)
            scale = max(1, math.ceil(_MIN_WIDTH / img.shape[1]))
            out = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
            out = out.astype(np.float32)
            for g, e in enumerate(self.gt.get(im) or []):
                p = self.path / "mask_visib" / f"{im:06d}_{g:06d}.png"
                if not p.exists():
                    continue
                m = read_png(p) > 0
                m = np.repeat(np.repeat(m, scale, 0), scale, 1)
                out[m] = 0.55 * out[m] + 0.45 * object_colour(int(e["obj_id"]))
            out = np.clip(out, 0, 255).astype(np.uint8)
            fr = self.reg.frame(arm, step) if self.reg is not None else None
            if fr is not None and fr.T_ref_frame is not None and np.all(np.isfinite(fr.T_ref_frame)):
                K = np.asarray(self.info.camera.K, float).copy()
                K[:2] *= scale
                K[:2, 2] += 0.5 * (scale - 1)       # pixel centres of the enlarged image
                T_frame_ref = np.linalg.inv(fr.T_ref_frame)
                for ob in self.objects():
                    sil = self._silhouette(ob.obj_id, T_frame_ref @ ob.T_ref_model, K, out.shape[:2])
                    cs, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                    col = tuple(int(c) for c in object_colour(ob.obj_id))
                    cv2.drawContours(out, cs, -1, (0, 0, 0), 4)
                    cv2.drawContours(out, cs, -1, col, 2)
            return encode_png(out)

    def _silhouette(self, obj_id: int, T_cam_model: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        """The model's silhouette (uint8 mask) at a camera pose: its triangles filled."""
        V, F = self.mesh(obj_id)
        P = V @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        mask = np.zeros(hw, np.uint8)
        front = P[:, 2] > 1.0
        if not front.any():
            return mask
        uv = (P[:, :2] / np.where(front, P[:, 2], 1.0)[:, None]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        tri = F[front[F].all(1)]
        if len(tri):
            pts = np.round(uv[tri] * 4).astype(np.int32)    # 2 fractional bits for cv2's sub-pixel fill
            cv2.fillPoly(mask, list(pts), 1, lineType=cv2.LINE_8, shift=2)
        return mask

    def object_figure(self, index: int) -> bytes:
        """PNG of one object's fit: the reconstruction's points near it and the posed model, seen
        from above and from the side (table frame), with its figures in the title."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from scipy.spatial import cKDTree

        with self.lock:
            ob = self.object(index)
            S_all = self.samples(ob.obj_id)
            S = S_all[::4]                       # drawn; the figures use them all, as the place stage does
            T = self.T_table_ref @ ob.T_ref_model
            M = S @ T[:3, :3].T + T[:3, 3]
            P = self.object_points()
            P = P @ self.T_table_ref[:3, :3].T + self.T_table_ref[:3, 3]
            c = M.mean(0)
            r = float(np.linalg.norm(M - c, axis=1).max()) + 25.0
            near = P[np.linalg.norm(P[:, :2] - c[:2], axis=1) < r]
            near_ref = (near - self.T_table_ref[:3, 3]) @ self.T_table_ref[:3, :3]
            fit = pose_figures(S_all, near_ref, ob.T_ref_model, self.cfg.fit.icp_mm[-1]) if len(near) else (0.0, 0.0, 5.0)
            M_all = S_all @ T[:3, :3].T + T[:3, 3]
            d = cKDTree(M_all).query(near)[0] if len(near) else np.zeros(0)
        col = object_colour(ob.obj_id) / 255.0
        fig = Figure(figsize=(8.4, 3.6), dpi=100)
        FigureCanvasAgg(fig)
        for n, (i, j, name) in enumerate(((0, 1, "from above (table x, y)"), (0, 2, "from the side (table x, z)"))):
            ax = fig.add_subplot(1, 3, n + 1)
            if len(near):
                ax.scatter(near[:, i], near[:, j], s=1, c=np.minimum(d, 5.0), cmap="Greys", vmin=-2, vmax=5,
                           rasterized=True)
            ax.scatter(M[:, i], M[:, j], s=0.6, color=col, alpha=0.5, rasterized=True)
            ax.set_title(name, fontsize=9)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
        ax = fig.add_subplot(1, 3, 3)
        if len(d):
            ax.hist(np.minimum(d, 10.0), bins=40, range=(0, 10), color=col)
        ax.set_title("points to model (mm)", fontsize=9)
        ax.tick_params(labelsize=7)
        fig.suptitle(f"object {ob.obj_id} (#{ob.index}, cluster {ob.cluster}) {ob.status}"
                     f"{' (relabel pending)' if ob.pending else ''}: fitness {fit[0]:.2f}, mean distance "
                     f"{fit[2]:.2f} mm", fontsize=10)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        return buf.getvalue()

    def scene3d(self, max_points: int = 60000) -> dict:
        """The 3D view's data, in the table frame: the reconstruction's points (object points
        with their cluster, the rest -1), thinned to at most ``max_points``."""
        meta, clusters = self.reconstruction()
        rec = self.work / "reconstruction"
        scene = read_ply_points(rec / meta.get("points", "scene_points.ply"))
        pts = [np.asarray(c) for c in clusters]
        lab = [np.full(len(c), j) for j, c in enumerate(clusters)]
        # the rest of the scene (the table, what the clutter test dropped) thinned harder
        rest_n = max(1, max_points // 3)
        rest = scene[:: max(1, len(scene) // rest_n)]
        P = np.concatenate(pts + [rest]) if pts else rest
        L = np.concatenate(lab + [np.full(len(rest), -1)]) if pts else np.full(len(rest), -1)
        if len(P) > max_points:
            keep = np.linspace(0, len(P) - 1, max_points).astype(int)
            P, L = P[keep], L[keep]
        Q = P @ self.T_table_ref[:3, :3].T + self.T_table_ref[:3, 3]
        return {"points": np.round(Q, 1).ravel().tolist(), "cluster": L.astype(int).tolist(),
                "clusters": len(clusters)}

    def model3d(self, obj_id: int) -> dict:
        V, F = self.mesh(obj_id)
        return {"obj_id": obj_id, "vertices": np.round(V, 3).ravel().tolist(), "faces": F.astype(int).ravel().tolist(),
                "colour": [int(c) for c in object_colour(obj_id)]}
