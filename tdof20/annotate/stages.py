"""The six annotation stages as the orchestrator (:func:`tdof20.annotate.pipeline.annotate`) sees
them: one :class:`Stage` record each — its name, the stages whose results it reads (``needs``),
the function that does its work (``run``), what its results depend on (``inputs``, hashed into
its fingerprint) and the signature of what it wrote (``outputs``). A new stage is one more record
in :data:`STAGE_RECORDS`; the orchestrator walks them in order.

The bodies are thin: they read the results of the stages before (paths: :class:`StageContext`),
call the stage's room and write its results:

* register — :func:`~tdof20.annotate.registration.register_session` -> ``work/registration.json``;
* reconstruct — :func:`~tdof20.annotate.reconstruct.reconstruct` with :mod:`~tdof20.annotate.fusion`
  (frames, crop, files) -> ``work/reconstruction/``;
* model — :func:`~tdof20.annotate.place.match_models` (with ``--models``) or
  :func:`~tdof20.annotate.modelbuild.build_model_from_cluster` -> ``work/fits.json`` (+ ``work/models/``);
* place — :func:`~tdof20.annotate.place.place_models` -> ``work/placements.json``, ``models/``; the
  reviewer's corrected poses (``work/corrections.jsonl``, :mod:`~tdof20.annotate.corrections`) put in;
* label — :func:`~tdof20.annotate.label.label_scene` -> the BOP scene, ``work/label.json``; the
  reviewer's rejected frames skipped, accepted ones labelled although registration flagged them;
* qa — :func:`~tdof20.annotate.qa.write_qa` and :func:`~tdof20.annotate.evaluate.evaluate_scene`
  -> ``qa/``, ``work/evaluation.json``.

:func:`parse_stages` turns ``--stages`` (``"label,qa"``, ``"register..model"``) into stage names.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import shutil
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from tdof20.annotate.config import AnnotateConfig
from tdof20.annotate.corrections import Corrections, read_journal, replay
from tdof20.annotate.evaluate import evaluate_scene
from tdof20.annotate.fusion import (crop_depth, fuse_selection, load_reconstruction, read_ply_points,
                                    write_reconstruction)
from tdof20.annotate.label import label_scene
from tdof20.annotate.modelbuild import build_model_from_cluster, write_models
from tdof20.annotate.place import (T_arr, T_list, copy_file, copy_models, load_meshes, match_models, model_samples,
                                   place_models, pose_figures)
from tdof20.annotate.qa import write_qa
from tdof20.annotate.reconstruct import reconstruct
from tdof20.annotate.registration import RegistrationResult, register_session
from tdof20.annotate.state import WORK, count_files, dir_hash, sha_file, sha_obj
from tdof20.annotate.twins import check_twins, twin_decision
from tdof20.annotate.uncertainty import FILE as UNCERTAINTY_FILE, write_scene_bounds
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, write_json
from tdof20.progress import progress as _progress

__all__ = ["STAGES", "STAGE_RECORDS", "MissingInput", "Stage", "StageContext", "one_open3d_thread", "parse_stages",
           "stage"]

# label options that change how the work runs, not what it writes
_LABEL_RUNTIME = ("workers", "executor", "ray_address", "chunk")


# ---------------------------------------------------------------------------------------------
# the record and the run context
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stage:
    """One annotation stage: everything the orchestrator knows of it."""

    name: str
    needs: tuple[str, ...]                           # the stages whose results it reads
    run: Callable[["StageContext"], dict]            # does the work; returns the figures of the summary
    inputs: Callable[["StageContext"], dict]         # its options and other inputs (besides the raw
                                                     # session and the results it needs)
    outputs: Callable[["StageContext"], dict]        # the signature of what it wrote (MissingInput
                                                     # when something is not there)


class MissingInput(Exception):
    """A stage's input is not there (its producing stage has not run)."""

    def __init__(self, stage: str, what: str):
        super().__init__(what)
        self.stage, self.what = stage, what


@dataclass
class StageContext:
    """One annotate run: the raw session, the scene folder, the options; the file names the stages
    share; and a stage's fingerprinted inputs and output signature."""

    raw: Path
    out: Path
    models_dir: Path | None
    cfg: AnnotateConfig
    session: RawSession
    progress: bool
    problems: list = field(default_factory=list)

    @property
    def work(self) -> Path:
        return self.out / WORK

    # file names
    @property
    def reg_file(self) -> Path:
        return self.work / "registration.json"

    @property
    def rec_dir(self) -> Path:
        return self.work / "reconstruction"

    @property
    def fits_file(self) -> Path:
        return self.work / "fits.json"

    @property
    def built_dir(self) -> Path:
        return self.work / "models"

    @property
    def placements_file(self) -> Path:
        return self.work / "placements.json"

    @property
    def label_file(self) -> Path:
        return self.work / "label.json"

    @property
    def eval_file(self) -> Path:
        return self.work / "evaluation.json"

    def corrections(self) -> Corrections:
        """The reviewer's corrections (``work/corrections.jsonl``, :mod:`tdof20.annotate.corrections`)
        folded: the place stage puts in the corrected poses, the label stage the frame verdicts."""
        return replay(read_journal(self.work))

    def raw_fingerprint(self) -> str:
        files = [self.raw / "session.json", self.raw / "journal.jsonl"]
        return sha_obj([sha_file(f) if f.exists() else "absent" for f in files])

    def require(self, path: Path, stage: str) -> Path:
        if not path.exists():
            raise MissingInput(stage, str(path.relative_to(self.out)) if path.is_relative_to(self.out) else str(path))
        return path

    def outputs(self, name: str) -> dict:
        """The signature of what stage ``name`` wrote, read back by the stages after it."""
        return stage(name).outputs(self)

    def inputs(self, name: str) -> dict:
        """What stage ``name``'s result depends on (hashed into its fingerprint): the raw session,
        the outputs of the stages it needs, and its own inputs."""
        s = stage(name)
        return {"raw": self.raw_fingerprint(), "upstream": {u: self.outputs(u) for u in s.needs}, **s.inputs(self)}


def one_open3d_thread(run: Callable[["StageContext"], dict]) -> Callable[["StageContext"], dict]:
    """A stage body run with open3d on one OpenMP thread (restored after). open3d's feature RANSAC
    shares one random generator among its threads and its ICP sums in thread order, so with more
    than one the model stage's fits (and the placements and labels after them) differed in the
    last digits from run to run, and between this process and a worker. ``OMP_NUM_THREADS`` does
    not reach open3d's own OpenMP (``get_max_threads()`` stays at the core count); its
    ``set_max_threads`` does. The cost is small: these stages fit a few clusters."""

    @functools.wraps(run)
    def wrapped(ctx: "StageContext") -> dict:
        from tdof20.o3d import o3d

        before = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(1)
        try:
            return run(ctx)
        finally:
            o3d.utility.set_max_threads(before)

    return wrapped


# ---------------------------------------------------------------------------------------------
# register
# ---------------------------------------------------------------------------------------------
def _register(ctx: StageContext) -> dict:
    info = ctx.session.info
    if ctx.cfg.register.phase not in info.phases:
        raise TdofError(f"the session has no {ctx.cfg.register.phase} phase (phases: {', '.join(info.phases)}): "
                        f"annotation registers the opaque twins' depth; capture the opaque phase first",
                        ctx.raw / "session.json")
    reg = register_session(ctx.raw, ctx.cfg.register, progress=ctx.progress, workers=ctx.cfg.label.workers)
    check_depth_scale(reg, ctx.cfg.register, ctx.raw / "session.json")
    reg.save(ctx.reg_file)
    return {"flagged": len(reg.flagged_frames()), "depth_scale": reg.depth_scale.get("measured")}


def check_depth_scale(reg: RegistrationResult, cfg, session_file: Path) -> None:
    """Refuse a session whose depth scale error is beyond what annotation corrects
    (``register.depth_scale_max``) or cannot be pinned down (its 95 % bound wider than
    ``register.depth_scale_max_ci95``): labels from it would be off by the error times the
    object's distance, ~10 mm at 2 % and 500 mm, and no later check would see it."""
    ds = reg.depth_scale
    if not ds.get("arms"):
        return
    m, ci = float(ds["measured"]), ds.get("ci95")
    if not 1.0 / cfg.depth_scale_max <= m <= cfg.depth_scale_max:
        raise TdofError(f"the depth reads {m:.4f} x the true depth (the arm positions' registration against the "
                        f"robot's poses), beyond the {100 * (cfg.depth_scale_max - 1):.0f} % annotation corrects: "
                        f"calibrate the camera, or multiply camera.depth_scale by {1.0 / m:.5g}", session_file)
    if ci is not None and ci > cfg.depth_scale_max_ci95:
        per = ", ".join(f"arm {a}: {v:.4f}" for a, v in (ds.get("per_arm") or {}).items())
        raise TdofError(f"the depth scale cannot be pinned down: the arm positions disagree ({per}; 95 % bound "
                        f"+-{100 * ci:.2f} %, limit {100 * cfg.depth_scale_max_ci95:.2f} %); check the robot's "
                        f"poses and the hand-eye calibration in session.json", session_file)


REGISTER = Stage(
    "register", needs=(), run=_register,
    inputs=lambda ctx: {"cfg": ctx.cfg.register.to_dict()},
    outputs=lambda ctx: {"registration.json": sha_file(ctx.require(ctx.reg_file, "register"))})


# ---------------------------------------------------------------------------------------------
# reconstruct
# ---------------------------------------------------------------------------------------------
_FUSE_PREFETCH = 4      # depth images loaded ahead of the TSDF (each 640x480 float32: 1.2 MB)


def ordered_prefetch(fn: Callable, items: list, ahead: int = 4, threads: int = 2) -> Iterator:
    """``fn(item)`` for each item, in order, computed on ``threads`` threads at most ``ahead``
    items ahead of the consumer (so at most ``ahead`` results wait in memory). An exception of
    ``fn`` is raised when its item's turn comes; the rest is cancelled when the consumer stops."""
    with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        it = iter(items)
        pending: deque = deque(ex.submit(fn, x) for x in itertools.islice(it, max(1, ahead)))
        try:
            while pending:
                result = pending.popleft().result()
                for x in itertools.islice(it, 1):
                    pending.append(ex.submit(fn, x))
                yield result
        finally:
            for fut in pending:
                fut.cancel()


def _reconstruct(ctx: StageContext) -> dict:
    reg = RegistrationResult.load(ctx.reg_file)
    s = reg.corrected(ctx.session)  # the depth in true millimetres (the registration's scale estimate)
    todo = fuse_selection([f for f in reg.frames if reg.usable(f.arm, f.step)], ctx.cfg.fuse_max_frames)
    used: list[list[int]] = []
    problems: list[dict] = []

    def load(f) -> tuple[np.ndarray | None, str | None]:
        """(cropped depth, None), (None, problem), or (None, None) for a frame never captured."""
        if not s.has_frame("opaque", f.arm, f.step):
            return None, None
        try:
            z = s.load_depth_mm("opaque", f.arm, f.step, verify=True)
        except TdofError as e:
            return None, str(e)
        if not np.any(z):
            return None, "the opaque depth is all zero"
        if ctx.cfg.fuse_crop:
            z = crop_depth(z, s.info.camera, f.T_ref_frame, a0.axis_point, up,
                           ctx.cfg.reconstruct.crop_radius_mm + 20.0, ctx.cfg.fuse_max_height_mm)
        return z, None

    def frames():
        # one depth image at a time: the TSDF integrates each and drops it. The next few are read,
        # checked, decoded and cropped on threads meanwhile (the checksum, the PNG decoder and
        # numpy let go of the GIL), in order, so the same frames go in as one by one.
        with _progress(ctx.progress, unit="fr") as bar:
            task = bar.add_task("fuse (TSDF)", total=len(todo))
            for f, (z, problem) in zip(todo, ordered_prefetch(load, todo, ahead=_FUSE_PREFETCH)):
                bar.advance(task)
                if problem is not None:
                    problems.append({"arm": f.arm, "step": f.step, "problem": problem})
                if z is None:
                    continue
                used.append([f.arm, f.step])
                yield z, f.T_ref_frame

    a0 = reg.arms[0]
    up = np.asarray(a0.axis_dir, float) / np.linalg.norm(a0.axis_dir)
    if up @ (np.zeros(3) - a0.axis_point) < 0:   # from the table towards the reference camera
        up = -up
    rec = reconstruct(frames(), s.info.camera, a0.axis_point, a0.axis_dir, ctx.cfg.reconstruct)
    if not used:
        reasons = sorted({f.reason for f in reg.frames if f.flagged and f.reason})
        why = f" (registration: {'; '.join(reasons[:2])})" if reasons else ""
        raise TdofError(f"no usable opaque frame to fuse: registration flagged them all or they are unreadable"
                        f"{why}; see work/registration.json", ctx.reg_file)
    if not len(rec.points):
        raise TdofError(f"the reconstruction is empty: no surface was seen by reconstruct.min_weight = "
                        f"{ctx.cfg.reconstruct.min_weight:g} of the {len(used)} fused frames (too few turntable "
                        f"steps or arm positions; capture more, or lower reconstruct.min_weight)", ctx.rec_dir)
    if not rec.clusters:
        raise TdofError(f"the reconstruction holds no object on the turntable ({len(used)} frames fused, "
                        f"{len(rec.points)} surface points): see work/reconstruction/scene_points.ply",
                        ctx.rec_dir)
    meta = write_reconstruction(ctx.rec_dir, rec, a0.axis_point, a0.axis_dir, len(used), ctx.cfg.fuse_max_frames,
                                problems, [f.T_ref_frame[:3, 3] for f in todo[:: max(1, len(todo) // 64)]])
    return {"clusters": len(meta["clusters"]), "frames_fused": len(used), "problems": len(problems)}


def _reconstruct_outputs(ctx: StageContext) -> dict:
    meta = ctx.require(ctx.rec_dir / "reconstruction.json", "reconstruct")
    d = read_json(meta)
    for c in d.get("clusters", []):
        ctx.require(ctx.rec_dir / c["file"], "reconstruct")
    return {"reconstruction.json": sha_file(meta)}


RECONSTRUCT = Stage(
    "reconstruct", needs=("register",), run=_reconstruct,
    inputs=lambda ctx: {"cfg": [dataclasses.asdict(ctx.cfg.reconstruct), ctx.cfg.fuse_max_frames, ctx.cfg.fuse_crop,
                                ctx.cfg.fuse_max_height_mm]},
    outputs=_reconstruct_outputs)


# ---------------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------------
def _model(ctx: StageContext) -> dict:
    meta, clusters = load_reconstruction(ctx.rec_dir)
    plane = np.asarray(meta["plane"], float)
    objects = ctx.session.info.obj_ids
    if ctx.models_dir is not None:
        models = load_meshes(ctx.models_dir, sorted(set(objects)))
        if len(clusters) < len(objects):
            small = meta.get("dropped_clusters") or []
            mcp = ctx.cfg.reconstruct.min_cluster_points
            why = (f"the largest of {len(small)} clusters dropped as noise had {small[0]} points, under "
                   f"reconstruct.min_cluster_points = {mcp} (few frames or small images? lower it)"
                   if small and small[0] >= mcp // 3 else
                   "objects touching? try a smaller reconstruct.cluster_eps_mm")
            raise TdofError(f"{len(objects)} objects in session.json but the reconstruction split the scene into "
                            f"{len(clusters)} clusters ({why})", ctx.rec_dir / "reconstruction.json")
        matched, unused = match_models(models, objects, clusters, plane, ctx.cfg, ctx.progress)
        fits = {"format": "tdof20-fits", "source": "models", "models_dir": str(Path(ctx.models_dir).resolve()),
                "models_fingerprint": dir_hash(Path(ctx.models_dir)), "objects": matched,
                "unused_clusters": unused}
    else:
        if len(objects) != 1:
            raise TdofError(f"a scene with {len(objects)} objects needs their models (--models: the models folder "
                            f"of the lab's CAD models or of the single-object scenes); only single-object scenes "
                            f"build their model from the reconstruction", ctx.raw / "session.json")
        view = np.asarray(meta.get("viewpoints") or [], float).reshape(-1, 3)
        # the TSDF's normals tell the two sides of a thin glass wall apart, estimated ones cannot
        _, normals = read_ply_points(ctx.rec_dir / meta["clusters"][0]["file"], with_normals=True)
        built = build_model_from_cluster(clusters[0], plane, ctx.cfg.build, viewpoints=view if len(view) else None,
                                         normals=normals)
        if ctx.built_dir.exists():
            shutil.rmtree(ctx.built_dir)
        write_models({int(objects[0]): built}, ctx.built_dir)
        fits = {"format": "tdof20-fits", "source": "built", "models_dir": None,
                "objects": [{"index": 0, "obj_id": int(objects[0]), "cluster": 0,
                             "T_ref_model": T_list(built.T_ref_model), "watertight": bool(built.watertight),
                             "symmetries": built.symmetries}],
                "unused_clusters": list(range(1, len(clusters)))}
        if not built.watertight:
            ctx.problems.append(f"object {objects[0]}: the built model is not watertight (see work/models/)")
    write_json(ctx.fits_file, fits)
    return {"source": fits["source"], "objects": len(fits["objects"]), "unused_clusters": fits["unused_clusters"]}


def _model_inputs(ctx: StageContext) -> dict:
    c = ctx.cfg
    return {"cfg": [dataclasses.asdict(c.fit), dataclasses.asdict(c.place)],
            "build": dataclasses.asdict(c.build) if ctx.models_dir is None else None,
            "models_dir": None if ctx.models_dir is None else dir_hash(ctx.models_dir)}


def _model_outputs(ctx: StageContext) -> dict:
    out = {"fits.json": sha_file(ctx.require(ctx.fits_file, "model"))}
    if read_json(ctx.fits_file).get("source") == "built":
        ctx.require(ctx.built_dir / "models_info.json", "model")
        out["models"] = dir_hash(ctx.built_dir)
    return out


MODEL = Stage("model", needs=("reconstruct",), run=one_open3d_thread(_model), inputs=_model_inputs,
              outputs=_model_outputs)


# ---------------------------------------------------------------------------------------------
# place
# ---------------------------------------------------------------------------------------------
def _place(ctx: StageContext) -> dict:
    fits = read_json(ctx.fits_file)
    meta, clusters = load_reconstruction(ctx.rec_dir)
    plane = np.asarray(meta["plane"], float)
    up = plane[:3] / np.linalg.norm(plane[:3])
    dst = ctx.out / "models"
    failed: list[dict] = []   # objects the quality gate refused: the others are labelled ("partial")
    corr = ctx.corrections()  # the reviewer's poses (work/corrections.jsonl)
    if fits["source"] == "models":
        md = ctx.models_dir if ctx.models_dir is not None else (Path(fits["models_dir"]) if fits.get("models_dir") else None)
        if md is None or not Path(md).is_dir():
            raise TdofError("the model stage used a models folder that is not there now: pass --models", ctx.fits_file)
        md = Path(md)
        obj_ids = sorted({int(e["obj_id"]) for e in fits["objects"]})
        meshes = load_meshes(md, obj_ids)
        try:
            placements = place_models(fits["objects"], meshes, clusters, [c["file"] for c in meta["clusters"]], up,
                                      ctx.cfg, ctx.fits_file, failed, plane)
        except TdofError:
            if not (failed and corr.placed):   # every object failed, and the reviewer placed none
                raise
            placements = []
        # the scene's models folder: the user's files of these objects, byte for byte
        copy_models(md, dst, obj_ids)
    else:
        placements = []
        for e in fits["objects"]:
            placements.append({"gt_id": len(placements), "index": int(e["index"]), "obj_id": int(e["obj_id"]),
                               "cluster": int(e["cluster"]),
                               "T_ref_model": e["T_ref_model"], "fitness": None, "rmse_mm": None, "score_mm": None,
                               "upright_correction_deg": None, "source": "built",
                               "watertight": e.get("watertight"), "note": ""})
        if dst.exists():
            shutil.rmtree(dst)
        for p in sorted(ctx.built_dir.iterdir()):
            if p.is_file():
                copy_file(p, dst / p.name)
    if ctx.cfg.place.twin_check and placements:
        _check_twins(ctx, placements, dst, np.asarray(meta["plane"], float))
    if corr.placed:   # the reviewer's poses replace the fits (the label gate still judges every frame)
        samples = model_samples(load_meshes(dst, sorted({int(e["obj_id"]) for e in fits["objects"]})),
                                ctx.cfg.place.fit_samples)
        placements, failed[:] = corr.apply(
            placements, failed, fits["objects"],
            lambda o, j, T: pose_figures(samples[o], clusters[j], T, ctx.cfg.fit.icp_mm[-1]))
        if not placements:
            raise TdofError(failed[0]["reason"])
    write_json(ctx.placements_file, {"format": "tdof20-placements", "plane": meta["plane"],
                                     "placements": placements, "failed": failed})
    return {"objects": len(placements), **({"failed_objects": len(failed)} if failed else {})}


def _check_twins(ctx: StageContext, placements: list[dict], models_dir: Path, plane: np.ndarray) -> None:
    """The twin check (:mod:`tdof20.annotate.twins`) of every placement, in place: ``twin`` (the
    estimate, its action and line), the pose moved onto the glass where the evidence is strong
    (``T_ref_twin`` keeps the twin's), ``flag`` where a person has to look."""
    from tdof20.formats.bop_models import read_models_info

    reg = RegistrationResult.load(ctx.reg_file)
    session = reg.corrected(ctx.session)   # true millimetres
    obj_ids = sorted({int(p["obj_id"]) for p in placements})
    meshes = load_meshes(models_dir, obj_ids)
    info = read_models_info(models_dir)
    symmetric = {o: bool((info.get(o) or {}).get("symmetries_continuous")) for o in obj_ids}
    frames = [f for f in reg.frames if reg.usable(f.arm, f.step)]
    found = check_twins(session, frames, placements, meshes, plane, symmetric, ctx.cfg.place)
    for p in placements:
        est = found[int(p["gt_id"])]
        action, line, D = twin_decision(est, ctx.cfg.place)
        p["twin"] = {**(est.to_dict() if not isinstance(est, str) else {}), "action": action, "note": line}
        if D is not None:
            p["T_ref_twin"] = p["T_ref_model"]
            p["T_ref_model"] = T_list(D @ T_arr(p["T_ref_model"]))
        if action == "flagged":
            p["flag"] = f"object {p['obj_id']}: {line}"


def _place_inputs(ctx: StageContext) -> dict:
    c = ctx.cfg
    md = ctx.models_dir
    if md is None and ctx.fits_file.exists():   # the models folder the model stage used
        rec = read_json(ctx.fits_file).get("models_dir")
        md = Path(rec) if rec else None
    return {"cfg": [dataclasses.asdict(c.fit), dataclasses.asdict(c.place)],
            "models_dir": None if md is None else dir_hash(md), "corrections": ctx.corrections().placement_key()}


def _place_outputs(ctx: StageContext) -> dict:
    ctx.require(ctx.out / "models" / "models_info.json", "place")
    return {"placements.json": sha_file(ctx.require(ctx.placements_file, "place")),
            "models": dir_hash(ctx.out / "models")}


PLACE = Stage("place", needs=("reconstruct", "model"), run=one_open3d_thread(_place), inputs=_place_inputs,
              outputs=_place_outputs)


# ---------------------------------------------------------------------------------------------
# label
# ---------------------------------------------------------------------------------------------
def _label(ctx: StageContext) -> dict:
    reg = RegistrationResult.load(ctx.reg_file)
    pl = read_json(ctx.placements_file)["placements"]
    obj_ids = sorted({int(p["obj_id"]) for p in pl})
    models = load_meshes(ctx.out / "models", obj_ids)
    info = ctx.session.info
    # labels kept from an earlier run passed the gate they met then: with other gate options
    # every frame is judged (and labelled) again
    gate = {k: v for k, v in ctx.cfg.label.to_dict().items() if k.startswith("gate")}
    old = ctx.out / "scene_info.json"
    reuse = old.exists() and read_json(old).get("label_gate") == gate
    write_json(ctx.out / "scene_info.json", {
        "scene_id": info.scene_id, "n_arms": info.n_arms, "steps": info.steps, "step_deg": info.step_deg,
        "labels": "tdof20 annotate (registered opaque depth, placed models)",
        "source_session": str(ctx.raw.resolve()), "label_method": ctx.cfg.label.method, "label_gate": gate,
        "depth_scale": reg.depth_scale,
        "objects": [{"gt_id": p["gt_id"], "obj_id": p["obj_id"], "source": p["source"]} for p in pl]})
    T_ref_frames = {(f.arm, f.step): f.T_ref_frame for f in reg.frames}
    summary = label_scene(ctx.raw, ctx.out, T_ref_frames, [(int(p["obj_id"]), T_arr(p["T_ref_model"])) for p in pl],
                          models, ctx.cfg.label, skip=ctx.corrections().skip(reg.flagged_frames(), info.n_arms, info.steps),
                          progress=ctx.progress, reuse=reuse, depth_factor=1.0 / reg.depth_factor)
    if summary["labelled"] + summary["already_done"] == 0:
        write_json(ctx.label_file, summary)
        first = "; ".join(sorted({s["reason"] for s in summary["skipped"]})[:3])
        raise TdofError(f"no frame could be labelled ({len(summary['skipped'])} skipped: {first})", ctx.label_file)
    if ctx.cfg.uncertainty.write:  # every label's 95 % error bounds (tdof20.annotate.uncertainty)
        summary["uncertainty"] = {str(o): v for o, v in write_scene_bounds(
            ctx.out, pl, reg, ctx.cfg.uncertainty, ctx.cfg.place).items()}
    else:
        (ctx.out / UNCERTAINTY_FILE).unlink(missing_ok=True)
    write_json(ctx.label_file, summary)
    return {k: summary[k] for k in ("labelled", "already_done", "frames_per_s")} | {"skipped": len(summary["skipped"])}


def _label_outputs(ctx: StageContext) -> dict:
    out = {n: sha_file(ctx.require(ctx.out / n, "label"))
           for n in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")}
    if ctx.cfg.uncertainty.write:
        out[UNCERTAINTY_FILE] = sha_file(ctx.require(ctx.out / UNCERTAINTY_FILE, "label"))
    out["label.json"] = sha_file(ctx.require(ctx.label_file, "label"))
    for sub in ("rgb", "depth", "depth_opaque", "depth_restored", "mask", "mask_visib"):
        out[sub] = count_files(ctx.out / sub)
    return out


LABEL = Stage(
    "label", needs=("register", "place"), run=_label,
    inputs=lambda ctx: {"cfg": {k: v for k, v in dataclasses.asdict(ctx.cfg.label).items()
                                if k not in _LABEL_RUNTIME}, "verdicts": ctx.corrections().verdict_key(),
                    "uncertainty": dataclasses.asdict(ctx.cfg.uncertainty)},
    outputs=_label_outputs)


# ---------------------------------------------------------------------------------------------
# qa
# ---------------------------------------------------------------------------------------------
def _qa(ctx: StageContext) -> dict:
    reg = RegistrationResult.load(ctx.reg_file)
    lab = read_json(ctx.label_file)
    flagged = [(s["arm"], s["step"], s["reason"]) for s in lab.get("skipped", [])]
    evaluation = None
    truth = ctx.session.truth_dir
    if ctx.cfg.qa.evaluate and truth is not None and (truth / "scene_gt.json").exists():
        evaluation = evaluate_scene(ctx.out, truth, max_frames=ctx.cfg.qa.evaluate_max_frames or None,
                                    n_points=ctx.cfg.qa.evaluate_points)
        write_json(ctx.eval_file, evaluation)
    else:
        ctx.eval_file.unlink(missing_ok=True)
    pl = read_json(ctx.placements_file) if ctx.placements_file.exists() else {}
    kw = dict(registration=reg, sample=ctx.cfg.qa.sample, evaluation=evaluation, progress=ctx.progress,
              session_dir=ctx.raw, failed_objects=pl.get("failed", []),
              twins=[{"obj_id": p["obj_id"], **p["twin"]} for p in pl.get("placements", []) if p.get("twin")],
              uncertainty=lab.get("uncertainty"))
    try:
        report = write_qa(ctx.out, flagged=flagged, **kw)
    except TdofError:
        # write_qa draws every flagged frame on its colour image and stops on one it cannot read;
        # leave those out of its list (they stay listed, with reasons, in work/summary.json)
        keep, gone = [], []
        for a, k, r in flagged:
            try:
                ctx.session.load_rgb("transparent", a, k)
                keep.append((a, k, r))
            except TdofError:
                gone.append((a, k, r))
        if not gone:
            raise
        for a, k, r in gone:
            ctx.problems.append(f"qa: arm {a} step {k} not drawn (its colour image is unreadable): {r}")
        report = write_qa(ctx.out, flagged=keep, **kw)
    return {"report": str(report), "evaluated": evaluation is not None}


def _qa_inputs(ctx: StageContext) -> dict:
    t = ctx.session.truth_dir
    return {"cfg": dataclasses.asdict(ctx.cfg.qa),
            "truth": sha_file(t / "scene_gt.json") if t is not None and (t / "scene_gt.json").exists() else None}


def _qa_outputs(ctx: StageContext) -> dict:
    out = {"qa.json": sha_file(ctx.require(ctx.out / "qa" / "qa.json", "qa"))}
    ctx.require(ctx.out / "qa" / "report.html", "qa")
    if ctx.eval_file.exists():
        out["evaluation.json"] = sha_file(ctx.eval_file)
    return out


QA = Stage("qa", needs=("register", "label"), run=_qa, inputs=_qa_inputs, outputs=_qa_outputs)


# ---------------------------------------------------------------------------------------------
# the stages in order
# ---------------------------------------------------------------------------------------------
STAGE_RECORDS: tuple[Stage, ...] = (REGISTER, RECONSTRUCT, MODEL, PLACE, LABEL, QA)
STAGES = tuple(s.name for s in STAGE_RECORDS)
_BY_NAME = {s.name: s for s in STAGE_RECORDS}


def stage(name: str) -> Stage:
    """The record of stage ``name``."""
    return _BY_NAME[name]


def parse_stages(spec: str | Iterable[str] | None) -> tuple[str, ...]:
    """Stage names in pipeline order from ``None`` (all), a list, ``"label,qa"`` or a range
    ``"register..model"`` (either end may be left out: ``"place.."``)."""
    if spec is None:
        return STAGES
    items = [spec] if isinstance(spec, str) else list(spec)
    chosen: set[str] = set()
    for item in items:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            if ".." in part:
                a, b = (s.strip() for s in part.split("..", 1))
                for s in (a, b):
                    if s and s not in STAGES:
                        raise TdofError(f"unknown stage '{s}' (stages: {', '.join(STAGES)})")
                i = STAGES.index(a) if a else 0
                j = STAGES.index(b) if b else len(STAGES) - 1
                if i > j:
                    raise TdofError(f"stage range '{part}' runs backwards (order: {' -> '.join(STAGES)})")
                chosen.update(STAGES[i:j + 1])
            elif part in STAGES:
                chosen.add(part)
            else:
                raise TdofError(f"unknown stage '{part}' (stages: {', '.join(STAGES)})")
    if not chosen:
        raise TdofError(f"no stage given (stages: {', '.join(STAGES)})")
    return tuple(s for s in STAGES if s in chosen)
