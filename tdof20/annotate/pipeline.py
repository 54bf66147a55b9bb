"""The annotation pipeline: a raw capture session in, a labelled BOP scene out, in six stages.

    annotate(raw_dir, out_dir, models_dir=None, stages=None, cfg=AnnotateConfig())

This module is the orchestrator: :func:`annotate` walks the stage records
(:data:`~tdof20.annotate.stages.STAGE_RECORDS`: name, needs, run, inputs, outputs), runs the ones
asked for that are not up to date, and writes the summary (:func:`summary_text` for a person).
The scene folder's state file and lock are :mod:`~tdof20.annotate.state`, the options
:mod:`~tdof20.annotate.config`.

=============  ===============================================================================
stage          what it does, and what it leaves on disk
=============  ===============================================================================
register       every frame's camera motion to frame (arm 0, step 0) from the opaque depth
               (:func:`tdof20.annotate.registration.register_session`) -> ``work/registration.json``
reconstruct    the usable opaque frames (registration's poses) streamed one by one into a TSDF in
               the reference frame; table top; object clusters
               (:func:`tdof20.annotate.reconstruct.reconstruct`; frames, crop and files:
               :mod:`tdof20.annotate.fusion`) -> ``work/reconstruction/``:
               ``scene_points.ply``, ``scene_mesh.ply``, ``cluster_000.ply`` ..., ``reconstruction.json``
model          with ``models_dir`` (a BOP models folder in mm: a lab's CAD models, or the models
               the single-object scenes got): each object of ``session.json`` matched to a
               cluster — a shape test (height above the table, footprint radius) picks the
               candidates, a quick upright fit (:func:`tdof20.annotate.models.fit_model`) scores
               them, a one-to-one assignment (scipy ``linear_sum_assignment``) decides
               (:func:`tdof20.annotate.place.match_models`);
               without it (single-object scenes): a watertight model built from the cluster
               (:func:`tdof20.annotate.modelbuild.build_model_from_cluster`, screened Poisson) ->
               ``work/fits.json`` (+ ``work/models/`` when built)
place          every object's pose ``T_ref_model`` in the reference frame
               (:func:`tdof20.annotate.place.place_models`): the matched fit refined
               with dense samples, set upright on the table (the model's z along the table
               normal, when it is within ``place.upright_max_deg``), checked against the quality
               gate (a bad fit stops the run: no label is written from it) -> ``work/placements.json``
               and the scene's models folder ``models/`` (the built models, or the user's files
               of this scene's objects, copied byte for byte)
label          poses, masks, restored depth of every frame registration did not flag
               (:func:`tdof20.annotate.label.label_scene`; unreadable frames are skipped and
               listed) -> the BOP scene (``rgb/``, ``depth/``, ``depth_opaque/``,
               ``depth_restored/``, ``mask/``, ``mask_visib/``, the JSON files,
               ``scene_info.json``) and ``work/label.json``
qa             overlays, registration plots, HTML report (:func:`tdof20.annotate.qa.write_qa`)
               and, for a simulated session (``truth/``), the evaluation against the truth
               (:func:`tdof20.annotate.evaluate.evaluate_scene`) -> ``qa/``, ``work/evaluation.json``
=============  ===============================================================================

Resuming. ``work/state.json`` records each finished stage: when, how long, the fingerprint of its
inputs (the raw session's ``session.json`` and journal, the stage's options, the outputs of the
stages it reads, a models folder's files) and the signature of its outputs. A rerun skips a stage
whose fingerprint and outputs are unchanged, so an interrupted run resumes after the last finished
stage, and a changed option or input reruns the stages it affects (and, through their outputs,
the ones after). The label stage resumes inside itself too (frames already written are kept).
``stages=[...]`` runs only those stages (skipped when up to date, unless ``force``); a stage whose
inputs are missing stops with one line saying which stage to run first. Every run writes
``work/summary.json``: per-stage status and timing, flagged and skipped frames with their reasons,
the objects' fit scores, the evaluation, and ``unresolved_flags`` (frames left unlabelled that
the reviewer did not reject, objects that failed: what ``dataset build`` refuses unless told).
A reviewer's corrections (``work/corrections.jsonl``, written by ``tdof20 annotate review``) are
honoured by the place and label stages (:mod:`tdof20.annotate.corrections`). ``work/config.json``
holds the options of the last run.

Options (:class:`~tdof20.annotate.config.AnnotateConfig`) come from a TOML file
(:func:`~tdof20.annotate.config.load_annotate_config`) with one table per stage — ``[register]``
(RegistrationConfig), ``[reconstruct]`` (ReconstructionConfig), ``[fit]`` (ModelFitConfig),
``[build]`` (ModelBuildConfig), ``[place]`` (PlaceConfig), ``[label]`` (LabelConfig), ``[qa]``
(QAConfig) — and top-level ``fuse_max_frames``, ``fuse_crop``, ``fuse_max_height_mm``; an unknown
key is an error naming the file and the key. See ``docs/annotate.md``.

Where the work runs: ``cfg.label.executor``, ``workers`` and ``ray_address`` (the CLI's
``--executor``, ``--workers``, ``--ray-address``) hold for the whole run — an
:func:`~tdof20.annotate.executors.executor_scope` around the stages sends the registration's arm
positions as well as the label chunks there, with one Ray start for the run. Many sessions in
one call, scenes side by side on local workers or as Ray tasks: :mod:`tdof20.annotate.batch`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable

# the options and the stage names live in their rooms (config, stages); importing them from here
# (``from tdof20.annotate.pipeline import AnnotateConfig, load_annotate_config``) keeps working
from tdof20.annotate.config import (AnnotateConfig, PlaceConfig, QAConfig, annotate_config_from_dict,
                                    load_annotate_config)
from tdof20.annotate.corrections import JOURNAL, REJECTED
from tdof20.annotate.executors import executor_scope
from tdof20.annotate.registration import RegistrationResult
from tdof20.annotate.registration_result import depth_scale_text
from tdof20.annotate.stages import STAGE_RECORDS, STAGES, MissingInput, StageContext, parse_stages
from tdof20.annotate.state import (WORK, FolderLock, StateFile, clear_scene, remove_stale_temp_files,
                                   session_identity, sha_obj)
from tdof20.errors import TdofError
from tdof20.formats import RawSession, read_json, write_json

__all__ = ["STAGES", "AnnotateConfig", "PlaceConfig", "QAConfig", "annotate", "check_models_dir", "check_out",
           "load_annotate_config", "annotate_config_from_dict", "parse_stages", "summary_text"]


# ---------------------------------------------------------------------------------------------
# the summary
# ---------------------------------------------------------------------------------------------
def _summary(ctx: StageContext, state: StateFile, run: dict, warnings: list[str]) -> dict:
    info = ctx.session.info
    s: dict[str, Any] = {
        "scene_id": info.scene_id, "raw": str(ctx.raw.resolve()), "out": str(ctx.out.resolve()),
        "frames_planned": info.n_arms * info.steps, "stages": run,
        "timing_s": {st: state.entry(st).get("seconds") for st in STAGES if state.finished(st)},
        "problems": list(ctx.problems), "warnings": warnings}
    missing = ctx.session.missing_frames()
    if missing:
        s["missing_frames"] = [{"phase": p, "arm": a, "step": k} for p, a, k in missing]
    if ctx.reg_file.exists():
        try:
            reg = RegistrationResult.load(ctx.reg_file)
            s["registration"] = {"flagged": [{"arm": a, "step": k, "reason": r} for a, k, r in reg.flagged_frames()],
                                 "arms": [{"arm": a.arm, "flagged": a.flagged, "reason": a.reason,
                                           "correction_deg": a.correction_deg, "correction_mm": a.correction_mm}
                                          for a in reg.arms],
                                 "depth_scale": reg.depth_scale}
        except TdofError as e:
            s["problems"].append(str(e))
    rec = ctx.rec_dir / "reconstruction.json"
    if rec.exists():
        m = read_json(rec)
        s["reconstruction"] = {"frames_fused": m.get("frames_fused"), "clusters": len(m.get("clusters", [])),
                               "problems": m.get("problems", [])}
    if ctx.placements_file.exists():
        pl = read_json(ctx.placements_file)
        s["objects"] = pl["placements"]
        if pl.get("failed"):
            # one object refused by the quality gate, the others labelled: a partial scene (exit code 3)
            s["failed_objects"] = pl["failed"]
            s["partial"] = True
    if ctx.label_file.exists():
        lab = read_json(ctx.label_file)
        s["label"] = {k: lab.get(k) for k in ("frames", "labelled", "already_done", "skipped", "removed", "no_opaque",
                                              "seconds", "frames_per_s", "method", "executor", "workers",
                                              "uncertainty")}
    if ctx.eval_file.exists():
        ev = read_json(ctx.eval_file)
        s["evaluation"] = {"all": ev.get("all"), "objects": ev.get("objects"),
                           "wrong_labels": len(ev.get("wrong_labels") or [])}
    report = ctx.out / "qa" / "report.html"
    if report.exists():
        s["report"] = str(report)
    # what a person still has to look at (``dataset build`` refuses the scene while any is left,
    # unless told): frames left unlabelled but not rejected by the reviewer, and failed objects
    unresolved = [{"arm": sk["arm"], "step": sk["step"], "im_id": sk.get("im_id"), "reason": sk["reason"]}
                  for sk in (s.get("label") or {}).get("skipped") or [] if not sk["reason"].startswith(REJECTED)]
    unresolved += [{"obj_id": f["obj_id"], "reason": f["reason"]} for f in s.get("failed_objects") or []]
    # an object whose glass stands off its twin for certain, uncorrected (the twin check)
    unresolved += [{"obj_id": p["obj_id"], "reason": p["flag"]} for p in s.get("objects") or [] if p.get("flag")]
    s["unresolved_flags"] = unresolved
    try:
        corr = ctx.corrections()
        if corr.entries:
            s["review"] = {"journal": str(ctx.work / JOURNAL), "entries": len(corr.entries),
                           "corrected_objects": sorted(corr.placed),
                           "arm_verdicts": {str(a): v for a, v in sorted(corr.arm_verdicts.items())},
                           "frame_verdicts": [[a, k, v] for (a, k), v in sorted(corr.frame_verdicts.items())]}
    except TdofError as e:
        s["problems"].append(str(e))
    return s


# ---------------------------------------------------------------------------------------------
# the checks before anything is written
# ---------------------------------------------------------------------------------------------
def check_models_dir(models_dir: Path | None) -> None:
    """A ``--models`` folder that is not there -> TdofError naming it."""
    if models_dir is not None and not Path(models_dir).is_dir():
        raise TdofError("no such models folder (--models: a BOP models folder in mm)", models_dir)


def check_out(raw: Path, out: Path, session: RawSession | None = None, force: bool = False) -> None:
    """Refuse a scene folder ``out`` that annotate must not write (TdofError, one line naming it):
    a file, a non-empty folder without an annotate run in it, the raw session or a folder inside
    it; with ``session`` also a folder holding another session's annotation (unless ``force``) —
    read without the folder's lock, so the run itself checks that again under it."""
    raw, out = Path(raw), Path(out)
    if out.exists() and not out.is_dir():
        raise TdofError("is not a folder", out)
    state = out / WORK / "state.json"
    if out.exists() and any(out.iterdir()) and not state.exists():
        raise TdofError("folder is not empty and holds no annotate run (no work/state.json); choose another --out", out)
    if out.resolve() == raw.resolve() or raw.resolve() in out.resolve().parents:
        raise TdofError("--out must not be the raw session or inside it", out)
    if session is not None and not force and state.exists():
        recorded = StateFile(out / WORK, raw.resolve()).data.get("session")
        if recorded is not None and recorded != session_identity(session):
            raise TdofError(f"holds the annotation of another session ({recorded.get('scene_id')}); choose another "
                            f"--out, or give --force to replace it", out)


# ---------------------------------------------------------------------------------------------
# the pipeline
# ---------------------------------------------------------------------------------------------
def annotate(raw_dir: str | Path, out_dir: str | Path, models_dir: str | Path | None = None,
             stages: str | Iterable[str] | None = None, cfg: AnnotateConfig = AnnotateConfig(),
             force: bool = False, progress: bool = True) -> dict:
    """Annotate a raw session into the BOP scene ``out_dir`` (see the module docstring).

    raw_dir: the raw session (``tdof20 capture``'s folder); out_dir: the scene folder (created; a
    non-empty folder must hold an earlier annotate run's ``work/state.json``); models_dir: a BOP
    models folder (mm) holding every object of the session (None: single-object scenes build
    their model); stages: the stages to run (None = all; a list, ``"label,qa"`` or
    ``"register..model"``); force: rerun the chosen stages even when up to date.

    Returns the summary (also written to ``out_dir/work/summary.json``): ``stages`` {stage:
    {status: "ran" | "up to date" | "not requested", seconds}}, ``timing_s`` (the seconds of the
    run that made each stage's current results), ``registration`` (flagged frames with reasons),
    ``reconstruction``, ``objects`` (placements with fitness / RMSE / score), ``label`` (labelled,
    skipped frames with reasons, frames/s), ``evaluation`` (simulated sessions), ``report``,
    ``problems`` and ``warnings``. Raises :class:`TdofError` (one line) on bad input."""
    raw = Path(raw_dir)
    out = Path(out_dir)
    session = RawSession.open(raw)
    chosen = parse_stages(stages)
    md = None if models_dir is None else Path(models_dir)
    check_models_dir(md)
    check_out(raw, out)
    ctx = StageContext(raw, out, md, cfg, session, progress)
    ctx.work.mkdir(parents=True, exist_ok=True)
    run: dict[str, dict] = {}
    warnings: list[str] = []
    # the stages' chunks (registration's arm positions, the label chunks) go where --executor says;
    # one Ray start for the whole run (or this Ray task's own cluster)
    scope = executor_scope(cfg.label.executor, cfg.label.ray_address, cfg.label.workers)
    with FolderLock(ctx.work), scope:
        state = StateFile(ctx.work, raw.resolve())
        identity = session_identity(session)
        recorded = state.data.get("session")
        if recorded is not None and recorded != identity:
            if not force:
                raise TdofError(f"holds the annotation of another session ({recorded.get('scene_id')} from "
                                f"{state.data.get('raw_recorded', 'elsewhere')}); choose another --out, or give "
                                f"--force to replace it", out)
            clear_scene(out)
            state = StateFile(ctx.work, raw.resolve())
        state.data["session"] = identity
        state.data["raw_recorded"] = str(raw.resolve())
        # the options of this run, for tools that rerun stages later (the review's "relabel")
        write_json(ctx.work / "config.json", cfg.to_dict())
        removed = remove_stale_temp_files(out)
        if removed:
            warnings.append(f"removed {removed} temporary file(s) left by an interrupted run")
        for record in STAGE_RECORDS:
            stage = record.name
            if stage not in chosen:
                run[stage] = {"status": "not requested"}
                continue
            for u in record.needs:
                if not state.finished(u):
                    raise TdofError(f"stage '{stage}' needs the results of stage '{u}', which has not finished: "
                                    f"run stage '{u}' first", ctx.work / "state.json")
                try:
                    sig = ctx.outputs(u)
                except MissingInput as m:
                    raise TdofError(f"stage '{stage}' needs {m.what}, which is missing: run stage '{u}' first",
                                    ctx.out) from None
                if sig != state.entry(u).get("outputs"):
                    raise TdofError(f"the results of stage '{u}' changed since it finished: run stage '{u}' "
                                    f"again first", ctx.work / "state.json")
                if u not in chosen:
                    try:
                        fp_u = sha_obj(ctx.inputs(u))
                    except MissingInput:
                        fp_u = None
                    if fp_u != state.entry(u).get("fingerprint"):
                        warnings.append(f"stage '{u}' is out of date with the current inputs or options; "
                                        f"'{stage}' used its results as they are")
            fp = sha_obj(ctx.inputs(stage))
            if not force and state.finished(stage) and state.entry(stage).get("fingerprint") == fp:
                try:
                    fresh = ctx.outputs(stage) == state.entry(stage).get("outputs")
                except MissingInput:
                    fresh = False
                if fresh:
                    run[stage] = {"status": "up to date", "seconds": 0.0}
                    continue
            state.start(stage)
            t0 = time.perf_counter()
            try:
                result = record.run(ctx)
            except TdofError as e:
                # the stage stays unfinished; the summary says why
                run[stage] = {"status": "failed", "seconds": round(time.perf_counter() - t0, 3), "error": str(e)}
                write_json(ctx.work / "summary.json", _summary(ctx, state, run, warnings))
                raise
            seconds = time.perf_counter() - t0
            state.finish(stage, fp, seconds, ctx.outputs(stage))
            run[stage] = {"status": "ran", "seconds": round(seconds, 3), **result}
        summary = _summary(ctx, state, run, warnings)
        write_json(ctx.work / "summary.json", summary)
    return summary


def summary_text(summary: dict) -> str:
    """A few lines for a person (what ``tdof20 annotate`` prints): per stage its status and
    seconds, the objects' fits, flagged and skipped frames, the evaluation's medians, the report."""
    lines = [f"{summary['scene_id']}: {summary['out']}"]
    for st in STAGES:
        e = summary["stages"].get(st, {})
        sec = f" {e['seconds']:.1f} s" if e.get("status") == "ran" else ""
        lines.append(f"  {st:<12} {e.get('status', '-')}{sec}" + (f": {e['error']}" if e.get("error") else ""))
    for p in summary.get("objects") or []:
        fit = (f"fitness {p['fitness']:.2f}, mean distance {p['score_mm']:.2f} mm" if p.get("fitness") is not None
               else "model built from the reconstruction")
        tw = p.get("twin")
        lines.append(f"  object {p['obj_id']}: {fit}" + (f"; twin {tw['action']}: {tw['note']}" if tw else ""))
    for p in summary.get("failed_objects") or []:
        lines.append(f"  object {p['obj_id']}: FAILED, not labelled: {p['reason']}")
    if summary.get("partial"):
        lines.append(f"  partial: {len(summary['failed_objects'])} object(s) not labelled (exit code 3)")
    ds = (summary.get("registration") or {}).get("depth_scale") or {}
    if ds:
        lines.append(f"  depth scale {depth_scale_text(ds)}")
    flagged = (summary.get("registration") or {}).get("flagged") or []
    lab = summary.get("label") or {}
    if lab:
        lines.append(f"  labelled {lab.get('labelled', 0) + lab.get('already_done', 0)} of {lab.get('frames')} frames"
                     f" ({len(flagged)} flagged by registration, {len(lab.get('skipped') or [])} skipped in all)")
        ub = lab.get("uncertainty") or {}
        if ub:
            lines.append("  label bounds (95 %, median per object): " + ", ".join(
                f"{o}: {b['trans_mm_median']:.2f} mm / {b['rot_deg_median']:.2f} deg" for o, b in sorted(
                    ub.items(), key=lambda kv: int(kv[0]))) + " (scene_gt_uncertainty.json)")
        for sk in (lab.get("skipped") or [])[:10]:
            lines.append(f"    skipped arm {sk['arm']} step {sk['step']}: {sk['reason']}")
        if len(lab.get("skipped") or []) > 10:
            lines.append(f"    ... {len(lab['skipped']) - 10} more in work/summary.json")
    ev = (summary.get("evaluation") or {}).get("all") or {}
    if ev:
        def med(k):
            v = (ev.get(k) or {}).get("median")
            return "-" if v is None else f"{v:.3f}"
        lines.append(f"  vs truth (median): motion {med('motion_rot_deg')} deg / {med('motion_trans_mm')} mm, "
                     f"surface {med('surface_mm')} mm, visible IoU {med('iou_visib')}; "
                     f"{summary['evaluation'].get('wrong_labels', 0)} wrong labels")
    for w in summary.get("warnings") or []:
        lines.append(f"  warning: {w}")
    for p in summary.get("problems") or []:
        lines.append(f"  problem: {p}")
    if summary.get("report"):
        lines.append(f"  report: {summary['report']}")
    return "\n".join(lines)
