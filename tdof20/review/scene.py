"""One annotated scene as the reviewer sees and corrects it: what the pipeline left on disk (the
registration, the reconstruction, the fits, placements, labels, QA), the reviewer's journal
(:mod:`tdof20.annotate.corrections`) over it, and the corrections themselves.

:class:`ReviewScene` reads the scene folder, and every correction is one journal entry:

* :meth:`~ReviewScene.nudge` — move an object by ``amount`` mm along an axis of the *table frame*
  (x, y on the table top, z along its normal) or turn it by ``amount`` degrees about one (rx, ry,
  rz; about the model's centre, so a turn does not also move it);
* :meth:`~ReviewScene.set_pose` — a pose given whole, in the table frame: the 3D view's drag, or
  one typed in the Place page's box;
* :meth:`~ReviewScene.snap` — the place stage's fit (:func:`tdof20.annotate.place.refine_placement`:
  ICP, set upright, the quality gate) from the object's distinct turns about the table normal, on
  the reconstruction's object points within reach of them (so a cluster the reconstruction cut in
  pieces, or the wrong cluster, does not matter), each judged in the images too
  (:func:`tdof20.review.gates.snap_alternatives`); written when one alternative is told apart,
  else the reviewer chooses;
* :meth:`~ReviewScene.assign` — the model stage's decision made by a person: this object is that
  cluster (the model stage's quick upright fit puts it there);
* :meth:`~ReviewScene.verdict` — accept or reject frames, or a whole arm position, or one object
  in frames;
* :meth:`~ReviewScene.undo` — take back the last correction (an entry too);
* :meth:`~ReviewScene.relabel` — rerun place, label and QA with the scene's own options
  (``work/config.json``), in a child process (:mod:`tdof20.review.relabel`) that dies with the app.

Every pose a person gives (nudge, drag, typed, assign) passes the gates of :mod:`tdof20.review.gates`
before it is journalled: the place stage's fit gate and the label gate in a few frames. A nudge or
drag that does not pass is kept as the object's *draft* (shown, not journalled, not labelled; the
next nudge or a snap goes on from it); a typed pose that does not pass is refused.

The journal's last entry id is the scene's ``revision``; a correction made from an older one
(``base_revision``) is refused (:class:`Stale`). A change on disk by another program (a
``tdof20 annotate`` run) is noticed at the next request (:meth:`~ReviewScene.refresh`).

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
from tdof20.annotate.place import (
    T_arr,
    T_list,
    load_meshes,
    model_samples,
    pose_figures,
)
from tdof20.annotate.registration import RegistrationResult
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, read_png
from tdof20.formats.bop_models import read_models_info
from tdof20.formats.io import encode_png
from tdof20.geometry import rotation_matrix
from tdof20.review import gates
from tdof20.review.gates import NUDGE_MAX_DEG, NUDGE_MAX_MM, SNAP_REACH_MM, jsonable
from tdof20.review.relabel import Relabeller, scene_config
from tdof20.viz import object_colour

__all__ = ["NUDGE_AXES", "SNAP_REACH_MM", "GateRefused", "ReviewScene", "Stale", "scene_config"]

NUDGE_AXES = ("x", "y", "z", "rx", "ry", "rz")   # mm along, degrees about, the table frame's axes
_MIN_WIDTH = 480         # frame images are enlarged (integer factor) to at least this width
# what a tdof20 annotate run rewrites: a change of any of them is a change of the scene on disk
_WATCHED = ("work/state.json", "work/config.json", "work/registration.json", "work/fits.json",
            "work/placements.json", "work/label.json", "work/summary.json", "work/evaluation.json",
            "work/reconstruction/reconstruction.json", "scene_gt.json")


class GateRefused(TdofError):
    """A pose the gates refused (one line); ``figures``: what they measured; ``draft``: whether it
    was kept as the object's draft."""

    def __init__(self, message: str, figures: dict | None = None, draft: bool = False):
        super().__init__(message)
        self.figures, self.draft = figures or {}, draft


class Stale(TdofError):
    """A correction made from an older revision of the journal than the scene's."""

    def __init__(self, base: int, revision: int):
        super().__init__(f"the scene changed since this page loaded it (journal revision {base}, now {revision}: "
                         f"another tab or program made a correction): reload and look again")
        self.base, self.revision = base, revision


@dataclass
class ObjectView:
    """One object of the scene as the review shows it."""

    index: int                   # its place in session.json's objects (fits.json's index)
    obj_id: int
    cluster: int
    T_ref_model: np.ndarray      # the pose shown: the reviewer's, else the placement, else the matching fit
    status: str                  # placed | failed | corrected
    pending: bool                # the reviewer's pose is not yet what placements.json holds (relabel)
    fitness: float | None        # the place stage's figures of the journalled / placed pose
    score_mm: float | None
    reason: str                  # why it failed (failed objects)
    draft: dict | None = None    # a pose the gates refused, shown until it passes or is discarded
    flag: str = ""               # the place stage's flag of the object (the twin check)

    def to_dict(self, T_table_ref: np.ndarray, figures: dict | None = None) -> dict:
        d = self.draft
        return {"index": self.index, "obj_id": self.obj_id, "cluster": self.cluster,
                "T_ref_model": T_list(self.T_ref_model), "T_table_model": T_list(T_table_ref @ self.T_ref_model),
                "status": self.status, "pending": self.pending, "fitness": self.fitness, "score_mm": self.score_mm,
                "reason": self.reason, "colour": [int(c) for c in object_colour(self.obj_id)], "flag": self.flag,
                "figures": figures,
                "draft": None if d is None else {"how": d["how"], "reason": d["reason"], "gates": d["gates"]}}


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
        self.drafts: dict[int, dict] = {}       # object index -> {T_ref_model, how, reason, gates, cluster}
        self.scene_version = 0                   # +1 at every reload (a relabel, a change on disk)
        self.changed_on_disk: str | None = None  # when a change by another program was last noticed
        self.relabeller = Relabeller()
        self.reload()

    # ------------------------------------------------------------------ reading the scene
    def _signature(self) -> tuple:
        out = []
        for name in _WATCHED:
            try:
                st = (self.path / name).stat()
                out.append((name, st.st_mtime_ns, st.st_size))
            except FileNotFoundError:
                out.append((name, None, None))
        return tuple(out)

    def refresh(self) -> bool:
        """Reload when another program (a ``tdof20 annotate`` run) changed the scene on disk since
        the last reload; True when it did. Drafts are dropped then (their frame may have moved).
        Never waits: while a correction or a relabel holds the scene, nothing is looked at."""
        if not self.lock.acquire(blocking=False):
            return False
        try:
            if self._signature() == self._sig:
                return False
            import datetime as _dt

            self.drafts.clear()
            self.reload()
            self.changed_on_disk = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            return True
        finally:
            self.lock.release()

    def revision(self, entries: list[dict] | None = None) -> int:
        """The journal's last entry id (0: no entry)."""
        entries = read_journal(self.work) if entries is None else entries
        return int(entries[-1]["id"]) if entries else 0

    def check_revision(self, base: int | None) -> None:
        """Refuse (:class:`Stale`) a correction made from another revision than the scene's."""
        if base is not None and int(base) != self.revision():
            raise Stale(int(base), self.revision())

    def reload(self) -> None:
        """Read what the pipeline wrote (again, after a relabel or a change on disk)."""
        with self.lock:
            w = self.work
            self._sig = self._signature()
            self.scene_version += 1
            self.cfg = scene_config(w)
            self._meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            self._samples: dict[int, np.ndarray] = {}
            self._symmetry: dict[int, dict] = {}
            self._figures: dict[tuple, dict] = {}
            self._raycaster = None
            self._opaque: dict[tuple[int, int], np.ndarray] = {}
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

    @property
    def plane(self) -> np.ndarray:
        """The table plane the place stage set objects down onto (reconstruction.json)."""
        return np.asarray(self.reconstruction()[0]["plane"], float)

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

    def symmetry(self, obj_id: int) -> dict:
        """The object's models_info.json entry (its symmetries)."""
        if obj_id not in self._symmetry:
            try:
                self._symmetry[obj_id] = read_models_info(self.models_dir()).get(obj_id) or {}
            except TdofError:
                self._symmetry[obj_id] = {}
        return self._symmetry[obj_id]

    # ------------------------------------------------------------------ frames for the checks
    def check_frames(self, n: int = gates.CHECK_FRAMES) -> list[tuple[int, int]]:
        """Up to ``n`` registered frames with an opaque twin, spread around the turntable (and
        over the arm positions): the frames of the visible check and the Place page's outlines."""
        if self.reg is None:
            return []
        cand = [(a, k) for k in range(self.info.steps) for a in range(self.info.n_arms)
                if self._usable(a, k) and self.session.has_frame("opaque", a, k)]
        if len(cand) <= n:
            return cand
        picks = [cand[int(round(i * len(cand) / n))] for i in range(n)]
        # round-robin over the arm positions where the steps allow it
        out = []
        for i, (a, k) in enumerate(picks):
            want = i % self.info.n_arms
            out.append((want, k) if (want, k) in cand else (a, k))
        return list(dict.fromkeys(out))

    def _usable(self, a: int, k: int) -> bool:
        try:
            fr = self.reg.frame(a, k)
        except KeyError:
            return False
        return (self.reg.usable(a, k) and fr.T_ref_frame is not None
                and bool(np.all(np.isfinite(fr.T_ref_frame))))

    def render_frame(self, arm: int, step: int, override: dict[int, np.ndarray]) -> tuple[Any, np.ndarray, list[int]]:
        """The label stage's rendering of frame (arm, step): every object where the review shows it
        (``override``: {index: T_ref_model} instead; a failed object only when overridden), ray cast
        in the box around them; with the frame's opaque depth in true millimetres cut to that box,
        and the object index of each rendered instance."""
        from tdof20.geometry.raycast import ModelRaycaster

        session = self.reg.corrected(self.session) if hasattr(self.reg, "corrected") else self.session
        cam = session.info.camera
        obs = self.objects()
        if self._raycaster is None:
            self._raycaster = ModelRaycaster({o.obj_id: self.mesh(o.obj_id) for o in obs}, cam)
        if (arm, step) not in self._opaque:
            self._opaque[(arm, step)] = session.load_depth("opaque", arm, step).astype(np.float32) * np.float32(
                cam.depth_scale)
        T_frame_ref = np.linalg.inv(self.reg.frame(arm, step).T_ref_frame)
        order, poses = [], []
        for o in obs:
            if o.index in override or o.status != "failed":
                T = override.get(o.index, o.T_ref_model)
                order.append(o.index)
                poses.append((o.obj_id, T_frame_ref @ np.asarray(T, float)))
        lab = self._raycaster.render_box(poses)
        v0, v1, u0, u1 = lab.box
        return lab, self._opaque[(arm, step)][v0:v1, u0:u1], order

    def figures(self, ob: "ObjectView") -> dict | None:
        """The place stage's figures (fitness, mean distance) of the pose shown, on the object points
        near it: recomputed for every new pose (a nudge, a drag)."""
        if self.rec_meta is None or self.fits is None:
            return None
        key = (ob.index, np.round(ob.T_ref_model, 6).tobytes())
        if key not in self._figures:
            near = gates.near_points(self, ob.obj_id, [ob.T_ref_model])
            f = pose_figures(self.samples(ob.obj_id), near, ob.T_ref_model, self.cfg.fit.icp_mm[-1])
            self._figures[key] = {"fitness": round(f[0], 4), "rmse_mm": round(f[1], 4), "score_mm": round(f[2], 4),
                                  "points": int(len(near))}
        return self._figures[key]

    # ------------------------------------------------------------------ what the review shows
    def objects(self, corr: Corrections | None = None, drafts: bool = True) -> list[ObjectView]:
        """Every object of fits.json with the pose the review shows and its state (``drafts``:
        an object's draft pose instead of its journalled one, where it has one)."""
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
                ob = ObjectView(i, o, cluster, T, "corrected", pending, p and p.get("fitness"),
                                p and p.get("score_mm"), "")
            elif p is not None:
                ob = ObjectView(i, o, int(p["cluster"]), T_arr(p["T_ref_model"]),
                                "corrected" if p.get("corrected") else "placed", False, p.get("fitness"),
                                p.get("score_mm"), "", flag=str(p.get("flag") or ""))
            else:
                ob = ObjectView(i, o, int(e["cluster"]), T_arr(e["T_ref_model"]), "failed", False, None, None,
                                (f or {}).get("reason", "not placed: the place stage has not run"))
            d = self.drafts.get(i) if drafts else None
            if d is not None:
                ob.draft = d
                ob.T_ref_model = T_arr(d["T_ref_model"])
                if d.get("cluster") is not None:
                    ob.cluster = int(d["cluster"])
            out.append(ob)
        return out

    def object(self, index: int, corr: Corrections | None = None) -> ObjectView:
        for ob in self.objects(corr):
            if ob.index == index:
                return ob
        raise TdofError(f"no object {index} in this scene (objects 0..{len(self.objects()) - 1})")

    def frames(self, corr: Corrections | None = None) -> list[dict]:
        """Every planned frame (arm x step): its image id, whether labelled, the reasons it was
        flagged or skipped, the reviewer's verdict and the objects rejected in it."""
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
                rej = corr.rejected_objects(a, k)
                out.append({"arm": a, "step": k, "im_id": im, "labelled": labelled, "reasons": rs, "verdict": v,
                            "status": status, "unresolved": bool(not labelled and v != "reject"),
                            "rejected_objects": [{"index": i, "obj_id": o} for i, o in sorted(rej.items())]})
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
            return jsonable({
                "scene": str(self.path), "scene_id": self.info.scene_id, "raw": str(self.raw),
                "n_arms": self.info.n_arms, "steps": self.info.steps, "step_deg": self.info.step_deg,
                "objects": [o.to_dict(self.T_table_ref, self.figures(o)) for o in objects],
                "frames": frames, "T_table_ref": T_list(self.T_table_ref),
                "clusters": len((self.rec_meta or {}).get("clusters", [])),
                "labelled": sum(f["labelled"] for f in frames),
                "unresolved": len(unresolved) + len(failed),
                "pending": any(o.pending for o in objects) or self._verdicts_pending(corr),
                "drafts": sorted(self.drafts),
                "journal": corr.entries, "undo": undo,
                "revision": self.revision(corr.entries), "scene_version": self.scene_version,
                "changed_on_disk": self.changed_on_disk,
                "check_frames": [list(f) for f in self.check_frames()],
                "limits": {"nudge_mm": NUDGE_MAX_MM, "nudge_deg": NUDGE_MAX_DEG, "drag_mm": gates.DRAG_MAX_MM,
                           "drag_deg": gates.DRAG_MAX_DEG},
                "stages": self._stages(),
                "stage_errors": {k: v["error"] for k, v in (self.summary.get("stages") or {}).items() if v.get("error")},
                "evaluation": (self.evaluation or {}).get("all"),
                "partial": bool(self.summary.get("partial")),
            })

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
        flagged frame not labelled nor refused by the label gate since, an object rejected in a
        frame still labelled there."""
        skipped = {(s["arm"], s["step"]) for s in (self.label or {}).get("skipped") or []
                   if not s["reason"].startswith("registration") and not s["reason"].startswith(REJECTED)}
        flagged = {(a, k) for a, k, _ in self.reg.flagged_frames()} if self.reg is not None else set()
        for a in range(self.info.n_arms):
            for k in range(self.info.steps):
                v = corr.verdict(a, k)
                gt = self.gt.get(a * self.info.steps + k) or []
                labelled = bool(gt)
                if v == "reject" and labelled:
                    return True
                if v == "accept" and (a, k) in flagged and not labelled and (a, k) not in skipped:
                    return True
                rej = set(corr.rejected_objects(a, k).values())
                if rej and v != "reject" and any(int(e["obj_id"]) in rej for e in gt):
                    return True
        return False

    # ------------------------------------------------------------------ corrections
    def _centre(self, obj_id: int, T: np.ndarray) -> np.ndarray:
        V = self.mesh(obj_id)[0]
        return T[:3, :3] @ (0.5 * (V.min(0) + V.max(0))) + T[:3, 3]

    def _centre_model(self, obj_id: int) -> np.ndarray:
        V = self.mesh(obj_id)[0]
        return 0.5 * (V.min(0) + V.max(0))

    def _hand(self, ob: ObjectView, T: np.ndarray, how: str, entry: dict, keep_draft: bool) -> dict:
        """A pose a person gave, through the gates (:mod:`tdof20.review.gates`): journalled as
        ``entry`` (with the gates' figures) when it passes; else kept as the object's draft
        (``keep_draft``) or not, and refused (:class:`GateRefused`)."""
        g = gates.place_gate(self, ob.obj_id, T)
        figs = {"place": g.figures}
        reason = g.reason
        if g.ok:
            v = gates.visible_check(self, ob.index, T)
            figs["visible"] = v.figures
            reason = v.reason
        figs = jsonable(figs)
        cluster = entry.get("cluster", (ob.draft or {}).get("cluster"))
        if not reason:
            e = dict(entry)
            e["detail"] = {**(e.get("detail") or {}), "gates": figs}
            if cluster is not None and e["op"] == "place":
                e["cluster"] = int(cluster)
            out = append_entry(self.work, e)
            self.drafts.pop(ob.index, None)
            return {"entry": out, "gates": figs}
        if keep_draft:
            self.drafts[ob.index] = {"T_ref_model": T_list(T), "how": how, "reason": reason, "gates": figs,
                                     "cluster": cluster}
        raise GateRefused(f"not saved: {reason}" + (" (kept as a draft: go on from it, or snap)" if keep_draft else ""),
                          figs, draft=keep_draft)

    def nudge(self, index: int, axis: str, amount: float) -> dict:
        """Move (mm) or turn (deg) object ``index`` along / about a table-frame axis, from the pose
        shown (its draft, if any); journalled when the result passes the gates, else its draft."""
        if axis not in NUDGE_AXES:
            raise TdofError(f"nudge axis must be one of {', '.join(NUDGE_AXES)}, got '{axis}'")
        amount = float(amount)
        lim = NUDGE_MAX_MM if axis in "xyz" else NUDGE_MAX_DEG
        if not math.isfinite(amount) or abs(amount) > lim:
            raise GateRefused(f"nudge limit: {amount:g} {'mm' if axis in 'xyz' else 'deg'} is more than the "
                              f"{lim:g} {'mm' if axis in 'xyz' else 'deg'} a nudge may {'move' if axis in 'xyz' else 'turn'}"
                              f" an object: nudge in steps, or type the pose")
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
            return self._hand(ob, T, "nudge", {"op": "place", "object": index, "obj_id": ob.obj_id,
                                               "T_ref_model": T_list(T), "how": "nudge",
                                               "detail": {"axis": axis, "amount": amount,
                                                          "unit": "mm" if axis in "xyz" else "deg",
                                                          **({"from": "draft"} if ob.draft else {})}},
                              keep_draft=True)

    def set_pose(self, index: int, T_table_model: Any, how: str = "drag") -> dict:
        """Object ``index`` at a pose given in the table frame (16 numbers, row-major): a drag (at
        most ``DRAG_MAX_MM`` / ``DRAG_MAX_DEG`` from the pose shown; kept as the draft when the gates
        refuse it) or a typed pose (``how`` "set": refused whole when the gates refuse it)."""
        how = how if how in ("drag", "set") else "set"
        T = _rigid(np.asarray(T_table_model, float).reshape(4, 4) if np.size(T_table_model) == 16 else np.zeros(0),
                   "pose")
        with self.lock:
            ob = self.object(index)
            T_ref = np.linalg.inv(self.T_table_ref) @ T
            lim = gates.move_limit(how, ob.T_ref_model, T_ref, self._centre_model(ob.obj_id))
            if lim:
                raise GateRefused(f"not saved: {lim}")
            return self._hand(ob, T_ref, how, {"op": "place", "object": index, "obj_id": ob.obj_id,
                                               "T_ref_model": T_list(T_ref), "how": how}, keep_draft=how == "drag")

    def discard(self, index: int) -> dict:
        """Forget object ``index``'s draft (nothing journalled)."""
        with self.lock:
            self.object(index)
            d = self.drafts.pop(index, None)
            if d is None:
                raise TdofError(f"object {index} has no draft to discard")
            return {"entry": None, "discarded": index}

    def object_points(self) -> np.ndarray:
        """The reconstruction's object points: every cluster's (what turned with the table)."""
        _, clusters = self.reconstruction()
        return np.concatenate(clusters) if clusters else np.zeros((0, 3))

    def snap(self, index: int, turn_deg: float | None = None) -> dict:
        """The place stage's fit from the distinct turns of object ``index`` (its pose shown, draft
        included; ``turn_deg``: that turn only), each judged in the images
        (:func:`~tdof20.review.gates.snap_alternatives`). One entry when an alternative is told
        apart (or the one asked for passes the gates); else nothing written and the alternatives
        returned for the reviewer to choose from (``entry`` None), or a refusal when none passes."""
        with self.lock:
            ob = self.object(index)
            turns = None if turn_deg is None else [float(turn_deg)]
            if turns is not None and not (math.isfinite(turns[0]) and -360.0 <= turns[0] <= 360.0):
                raise TdofError("snap: turn_deg must be within -360..360")
            res = gates.snap_alternatives(self, index, ob.T_ref_model, turns)
            alts = res["alternatives"]
            show = [{k: a.get(k) for k in ("turn_deg", "fitness", "score_mm", "agree", "see_through", "disagree",
                                           "reason", "T_ref_model")} for a in alts]
            for a in show:
                a["T_table_model"] = T_list(self.T_table_ref @ T_arr(a["T_ref_model"]))
            if res["chosen"] is None:
                if not any(not a["bad"] and a.get("visible_ok") for a in alts):
                    raise GateRefused(res["reason"], {"alternatives": jsonable(show)})
                return {"entry": None, "alternatives": jsonable(show), "reason": res["reason"]}
            best = alts[res["chosen"]]
            T = T_arr(best["T_ref_model"])
            moved = np.linalg.norm(self._centre(ob.obj_id, T) - self._centre(ob.obj_id, ob.T_ref_model))
            cluster = (ob.draft or {}).get("cluster")
            e = {"op": "place", "object": index, "obj_id": ob.obj_id, "T_ref_model": T_list(T), "how": "snap",
                 "detail": jsonable({"fitness": best["fitness"], "score_mm": best["score_mm"], "rmse_mm": best["rmse_mm"],
                                     "points": res["points"], "moved_mm": round(float(moved), 3),
                                     "note": best["note"], "turn_deg": best["turn_deg"],
                                     "agree": best.get("agree"), "see_through": best.get("see_through"),
                                     "alternatives": [{k: a[k] for k in ("turn_deg", "fitness", "score_mm",
                                                                         "disagree")} for a in show]})}
            if cluster is not None:
                e["cluster"] = int(cluster)
            entry = append_entry(self.work, e)
            self.drafts.pop(index, None)
            return {"entry": entry, "alternatives": jsonable(show), "chosen": 0, "reason": ""}

    def assign(self, index: int, cluster: int) -> dict:
        """Object ``index`` is cluster ``cluster``: the model stage's quick upright fit puts it
        there; one entry when that pose passes the gates, else it is the object's draft (with the
        cluster) to snap from."""
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
            return self._hand(ob, f.T_ref_model, "assign",
                              {"op": "assign", "object": index, "obj_id": ob.obj_id, "cluster": int(cluster),
                               "T_ref_model": T_list(f.T_ref_model),
                               "detail": {"score_mm": round(float(f.score), 4), "fitness": round(float(f.fitness), 4)}},
                              keep_draft=True)

    def verdict(self, arm: int, steps: list[int] | None, verdict: str, obj: int | None = None) -> dict:
        """Accept, reject or clear frames of arm position ``arm`` (``steps`` None: all of them);
        with ``obj`` (an object index): reject or clear that object only in those frames (they are
        labelled without it)."""
        if not 0 <= int(arm) < self.info.n_arms:
            raise TdofError(f"no arm position {arm} (0..{self.info.n_arms - 1})")
        if steps is not None:
            bad = [k for k in steps if not 0 <= int(k) < self.info.steps]
            if bad:
                raise TdofError(f"no step {bad[0]} (0..{self.info.steps - 1})")
        with self.lock:
            e = {"op": "frames", "arm": int(arm), "steps": None if steps is None else [int(k) for k in steps],
                 "verdict": verdict}
            if obj is not None:
                if verdict not in ("reject", "clear"):
                    raise TdofError("one object in a frame can be rejected or cleared, not accepted (accept the frame)")
                ob = self.object(int(obj))
                twins = [o.index for o in self.objects() if o.obj_id == ob.obj_id and o.index != ob.index]
                if twins:
                    raise TdofError(f"object {ob.obj_id} stands in this scene {len(twins) + 1} times (the label stage "
                                    f"tells its instances apart by model only): reject the frame instead")
                e.update(object=ob.index, obj_id=ob.obj_id)
            return {"entry": append_entry(self.work, e)}

    def undo(self) -> dict:
        """Take back the last correction not yet taken back (an ``undo`` entry); the draft of the
        object it placed goes too (the view shows the journalled pose again)."""
        with self.lock:
            target = undo_target(read_journal(self.work))
            if target is None:
                raise TdofError("nothing to undo")
            if target.get("object") is not None and target["op"] in ("place", "assign"):
                self.drafts.pop(int(target["object"]), None)
            return {"entry": append_entry(self.work, {"op": "undo", "undoes": int(target["id"])})}

    def relabel(self) -> dict:
        """Rerun place, label and QA with the scene's options and the journal, in a child process
        (:class:`~tdof20.review.relabel.Relabeller`: stopped with the app, and never outliving it);
        returns the summary (a refusal is a TdofError, the journal kept). Drafts are not labelled."""
        with self.lock:
            md = None if (self.fits or {}).get("source") == "built" else self.models_dir()
            try:
                summary = self.relabeller.run(self.path, self.raw, md)
            finally:
                self.reload()
            lab = summary.get("label") or {}
            append_entry(self.work, {"op": "relabel",
                                     "detail": {"labelled": int(lab.get("labelled", 0)) + int(lab.get("already_done", 0)),
                                                "unresolved": len(summary.get("unresolved_flags") or [])}})
            return summary

    # ------------------------------------------------------------------ pictures
    def frame_image(self, arm: int, step: int, kind: str, selected: int | None = None) -> bytes:
        """PNG of a frame's colour image (``kind``: "rgb" the transparent phase, "opaque" its
        twin) with the labelled visible masks tinted and every object's model outline at the pose
        the review shows (the reviewer's corrections and drafts included), in the object's colour;
        object ``selected``'s outline drawn wider, in white and its colour."""
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
                for ob in sorted(self.objects(), key=lambda o: o.index == selected):   # the selected one on top
                    sil = self._silhouette(ob.obj_id, T_frame_ref @ ob.T_ref_model, K, out.shape[:2])
                    cs, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                    col = tuple(int(c) for c in object_colour(ob.obj_id))
                    if ob.index == selected:
                        cv2.drawContours(out, cs, -1, (255, 255, 255), 6)
                        cv2.drawContours(out, cs, -1, col, 3)
                        continue
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
