"""``tdof20 reproduce``: the paper's tables with one command, resumable.

    from tdof20.experiments.reproduce import reproduce
    out = reproduce("repro", preset="smoke")                  # -> repro/tables/tables.md
    out = reproduce("repro", config="my.toml", dataset="ROOT")  # a TOML over a preset; a given dataset

Stages (each finished job is recorded in ``DIR/reproduce.json`` with the config's digest)::

    dataset    simulated TDoF20 scenes (capture on the simulated rig + oracle labels, as
               ``tdof20 sim label`` writes them) gathered by ``dataset build`` -> DIR/dataset;
               or the given dataset root (e.g. an imported TDoF20), used in place
    train      every method on each protocol's train part minus its validation part
               -> DIR/runs/<method>_<protocol>/ (plus the ablations' HFF6DoF runs on hard:
               fuse<N>_hard, noseg_hard, and the paper's pose recovery's own run hff6dof-3d_<protocol>,
               trained with vector_origin = "observed"); with several epochs, epoch by epoch: each
               validated epoch's checkpoint is predicted and scored on the validation part and the
               best one is copied to RUN/kept/ ([select])
    choose     on the validation part only: the prediction-time options of [candidates.<method>]
               (the input depth mode, thresholds) on each kept checkpoint; which of HFF6DoF's two
               pose recoveries (bearing + PnP, 3D voting + LSQ) stands for HFF6DoF in the
               agreement claims, per protocol
    predict    each kept checkpoint on its test part, with the options chosen -> DIR/results/<name>.csv
               (+ _info.json); ``hff6dof-3d`` with voting = "3d"
    score      ADD(S), 2D projection, AUC and accuracy curves -> DIR/scores/<name>.json, with
               "oracle_masks" when ground-truth masks picked the pixels (the run without the
               segmentation head)
    profile    Table 3 (parameters, multiply-adds at 480x640, FPS) of every method -> DIR/profile.json
    tables     DIR/tables/: tables.md (with what was chosen on validation), CSV, JSON, plots

The test part is predicted and scored once per result, after every choice: nothing is chosen on it.
Validation predictions go to DIR/val/<run>/ (their targets DIR/val/targets_<protocol>.json) and
their figures to reproduce.json ("validation"), so that a resumed run predicts none twice.

Resuming: a rerun on the same DIR skips the jobs recorded as done (a training interrupted in the
middle resumes from its checkpoint); a rerun with another config (another preset, TOML or
``--dataset``) is refused, naming the options that changed.

Presets (:data:`PRESETS`): ``smoke`` (the plumbing and the tables, every method, minutes on 2
cores), ``cpu`` (overnight on 2 cores), ``gpu`` (hours on one H100/H200), ``full`` (the paper's
scale). A TOML file sets any option over the preset it names (``preset = "cpu"``)::

    preset = "smoke"
    methods = ["hff6dof", "pvnet"]
    [data]
    scenes = ["single/juice_cup_340", "multi/08"]
    [train]
    image_size = [32, 48]
    max_steps = 2
    [epochs]
    hff6dof = 1
    [ablations]
    fuse_stages = [1, 3]
    segmentation = true

    [select]
    epochs = "best"            # "last": no validation of epochs
    every = 1                  # validate every N-th epoch (and the last)
    max_images = 0             # at most this many validation images per protocol (0 = all)
    [candidates.hff6dof]       # prediction-time options chosen on validation (first = default)
    depth_mode = ["filled", "raw"]

The config and the presets live in :mod:`tdof20.experiments.reproduce_config` (the methods' parts
come from their registry records), the jobs a config makes in :mod:`tdof20.experiments.reproduce_plan`
(:func:`job_plan`; :func:`plan` counts what a config asks for and :func:`estimate` multiplies it by
measured unit times: ``benchmarks/methods_profile.py --estimate PRESET``), what the tables say of
the run in :mod:`tdof20.experiments.reproduce_report`. This module runs the jobs. Train / predict /
score / profile go through the small adapter functions below (:func:`train_run`,
:func:`predict_run`, :func:`score_run`, :func:`profile_methods`): the method registry's loops
(:mod:`tdof20.methods.train`, :mod:`tdof20.methods.predict`).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import resource
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from tdof20.capture import run_capture, sim_config
from tdof20.dataset.build import build_dataset
from tdof20.dataset.naming import normalize_scene_id
from tdof20.dataset.reader import open_dataset
from tdof20.dataset.results import write_results_csv
from tdof20.dataset.splits import validation_images  # noqa: F401  (re-exported: the rules live in splits)
from tdof20.dataset.validation import part_images, val_targets
from tdof20.errors import TdofError
from tdof20.experiments.reproduce_config import (CANDIDATES, CHOICE_OPTIONS, LABELS, METHODS, PRESETS,  # noqa: F401
                                                 AblationConfig, DataConfig, EpochsConfig, ProfileConfig,
                                                 ReproduceConfig, SelectConfig, changed_keys, check_candidates,
                                                 config_data, config_digest, flat_keys, make_config)
from tdof20.experiments.reproduce_plan import (candidate_grid, choice_source, estimate, job_plan,  # noqa: F401
                                               plan, planned_predictions, planned_runs, validated_epochs)
from tdof20.experiments.reproduce_report import choices, dataset_objects, table_entries, tables_header
from tdof20.experiments.tables import curves_from_evaluation, write_tables
from tdof20.formats.io import read_json, write_json
from tdof20.progress import console, progress as progress_bar
from tdof20.scoring.scoring import evaluate

STATE = "reproduce.json"
FORMAT = "tdof20-reproduce"


# --------------------------------------------------------------------------------------------
# the adapter: the only calls into training, prediction, scoring and profiling


def train_run(root: Path, split: str, run: Path, method: str, cfg: ReproduceConfig, epochs: int,
              show: bool, stop_epoch: int | None = None, **options) -> Path:
    """Train (or continue) ``run`` on the train part minus the validation part of ``split``, for
    ``epochs`` epochs in all; with ``stop_epoch`` the call ends after that epoch (the schedule still
    spans ``epochs``). ``options``: the run's options of the method's config (an ablation's
    ``fuse_stages``, ``vector_origin``, ...) over ``[method_options.<method>]``."""
    from tdof20.methods.train import train  # imports torch

    t = cfg.train
    return train(root, split, run, method=method, method_config=cfg.method_options.get(method),
                 method_options=options, image_size=tuple(t.image_size), batch_size=t.batch_size,
                 epochs=int(epochs), lr=t.lr, max_steps=t.max_steps or None, num_workers=t.num_workers, seed=t.seed,
                 device=cfg.device, progress=show, part="train-val", stop_epoch=stop_epoch)


def predict_run(run: Path, root: Path, split: str, out_csv: Path, cfg: ReproduceConfig, show: bool,
                part: str = "test", images: list[tuple[int, int]] | None = None, **options) -> dict:
    """Predict ``part`` ('test' or 'val'; ``images``: these validation images only) of ``split`` with
    the run folder ``run`` into ``out_csv`` (+ ``_info.json``); ``options``: the method's prediction
    options (its config's names). Returns the summary."""
    from tdof20.methods.predict import info_path, predict, predict_rows  # imports torch

    for p in (out_csv, info_path(out_csv)):  # a rerun of an interrupted prediction starts afresh
        if p.exists():
            p.unlink()
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    kw = dict(device=cfg.device, num_workers=cfg.train.num_workers, seed=cfg.train.seed, progress=show,
              method_options=dict(options) or None, part=part)
    if images is None:
        predict(run, root, split, out_csv, **kw)
        return read_json(info_path(out_csv))
    rows, info = predict_rows(run, root, split, images=images, **kw)
    write_results_csv(out_csv, rows)
    write_json(info_path(out_csv), info)
    return info


def score_run(results_csv: Path, root: Path, split: str, part: str = "test", targets: Path | None = None) -> dict:
    """The scorer's dict of a results CSV on ``split``'s test part, or (``part`` 'val') against the
    validation targets file ``targets``; with the accuracy curves and the scorer's warnings."""
    if part == "val":
        if targets is None:
            raise TdofError("scoring the validation part needs its targets file")
        ev = evaluate(results_csv, root, None, targets=targets, metrics="add,proj")
    else:
        ev = evaluate(results_csv, root, split, metrics="add,proj")
    return {**ev.summary(), "curves": curves_from_evaluation(ev), "warnings": list(ev.warnings), "part": part}


def profile_methods(methods: tuple[str, ...], cfg: ReproduceConfig) -> list[dict]:
    from tdof20.methods.profile import profile_method  # imports torch

    out = []
    for m in methods:
        try:
            out.append(profile_method(m, cfg.device, cfg.profile.height, cfg.profile.width, cfg.profile.repeats,
                                      warmup=1))
        except Exception as e:  # noqa: BLE001 - one method's failure must not hide the others' figures
            out.append({"method": m, "error": f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:160]}"})
    return out


# --------------------------------------------------------------------------------------------
# state


class State:
    """DIR/reproduce.json: the config, its digest and the jobs done (written atomically)."""

    def __init__(self, out: Path, cfg: ReproduceConfig):
        self.path = out / STATE
        self.cfg_data = config_data(cfg)
        digest = config_digest(cfg)
        if self.path.exists():
            d = read_json(self.path, "reproduce state")
            if not isinstance(d, dict) or d.get("format") != FORMAT:
                raise TdofError("is not a reproduce state file", self.path)
            if d.get("digest") != digest:
                keys = changed_keys(d.get("config") or {}, self.cfg_data)
                old, new = flat_keys(d.get("config") or {}), flat_keys(self.cfg_data)
                shown = "; ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys[:6])
                raise TdofError(f"was made with another config (changed: {shown}"
                                f"{'; ...' if len(keys) > 6 else ''}): give the same options or choose another --out",
                                self.path)
            self.data = d
        else:
            if out.exists() and any(out.iterdir()):
                raise TdofError("folder is not empty and holds no reproduce state (reproduce.json); choose another "
                                "--out", out)
            self.data = {"format": FORMAT, "version": 1, "digest": digest, "config": self.cfg_data, "jobs": {}}
            self.save()

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, self.data)

    def done(self, job: str) -> bool:
        return job in self.data["jobs"]

    def get(self, job: str) -> dict:
        return self.data["jobs"][job]

    def finish(self, job: str, seconds: float, **info) -> None:
        self.data["jobs"][job] = {"seconds": round(seconds, 2), **info}
        self.save()


# --------------------------------------------------------------------------------------------
# the jobs


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (data-loader workers): a job's work on
    a machine shared with other jobs, where its wall time says little."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


@dataclass
class Job:
    name: str            # "train/pvnet/simple"
    stage: str           # dataset | train | predict | score | profile | tables
    run: Callable[[], dict]


def _sim_dataset(out: Path, cfg: ReproduceConfig, show: bool) -> Path:
    from tdof20.sim.truth import oracle_scene  # imports open3d

    d = cfg.data
    scenes = [normalize_scene_id(s) for s in d.scenes]  # known and distinct: DataConfig checked them
    labelled = []
    for s in scenes:
        raw = out / "raw" / s.replace("/", "_")
        lab = out / "labels" / s.replace("/", "_")
        if lab.exists() and not (lab / "scene_info.json").exists():
            shutil.rmtree(lab)  # oracle labels interrupted before their scene_info.json: made again
        run_capture(sim_config(s, steps=d.steps, step_deg=d.step_deg, n_arms=d.n_arms, width=d.width,
                               height=d.height, seed=d.seed), raw, yes=True, show_progress=show,
                    resume_command=f"tdof20 reproduce --out {out} (the same options)")
        labelled.append(oracle_scene(raw, lab, show_progress=show))
    root = out / "dataset"
    build_dataset(labelled, root, show_progress=show)
    return root


def _better(a: dict, b: dict | None) -> bool:
    """Strictly better on validation: mean ADD(S), then mean 2D projection (ties keep ``b``)."""
    if b is None:
        return True
    ka = (a.get("add_s") or 0.0, a.get("proj2d") or 0.0)
    kb = (b.get("add_s") or 0.0, b.get("proj2d") or 0.0)
    return ka > kb


def _opts_key(options: dict) -> str:
    return json.dumps(options, sort_keys=True)


class Validation:
    """Predictions and scores on the validation part, for the choices only (never the test part):
    the images (at most select.max_images, evenly spaced), their targets file
    (DIR/val/targets_<split>.json, written here: a given dataset is only read), and each figure
    cached in reproduce.json ("validation": run -> [figures]) so that a resumed run predicts
    nothing twice."""

    def __init__(self, out: Path, root: Path, cfg: ReproduceConfig, state: State, show: bool):
        self.out, self.root, self.cfg, self.state, self.show = out, root, cfg, state, show
        self._images: dict[str, list] = {}

    def images(self, split: str) -> list[tuple[int, int]]:
        if split not in self._images:
            ims = part_images(self.root, split, "val")
            if not ims:
                raise TdofError(f"the {split} split's validation part is empty (too few turntable steps per arm "
                                "position for a validation arc): the choices on validation need one; give more "
                                "data.steps, or select.epochs = \"last\", no [candidates] and ablations.voting_3d = "
                                "false", self.root)
            n = self.cfg.select.max_images
            if n and len(ims) > n:
                ims = [ims[(i * len(ims)) // n] for i in range(n)]
            self._images[split] = ims
        return self._images[split]

    def targets(self, split: str) -> Path:
        path = self.out / "val" / f"targets_{split}.json"
        if not path.exists():
            keep = set(self.images(split))
            tg = [t for t in val_targets(self.root, split) if (t["scene_id"], t["im_id"]) in keep]
            if not tg:
                raise TdofError(f"the {split} split's validation images hold no targets", self.root)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json(path, tg, indent=None)
        return path

    def figure(self, name: str, run_dir: Path, split: str, step: int, epoch: int, options: dict) -> dict:
        """The validation figure of run ``name``'s checkpoint at ``step`` (in ``run_dir``) predicted
        with ``options``: {"step", "epoch", "options", "add_s", "proj2d", "targets", "results"}."""
        cache = self.state.data.setdefault("validation", {}).setdefault(name, [])
        key = _opts_key(options)
        for f in cache:
            if f["step"] == step and _opts_key(f["options"]) == key:
                return f
        tag = f"step{step:06d}_" + hashlib.sha256(key.encode()).hexdigest()[:8]
        csv = self.out / "val" / name / f"{tag}.csv"
        predict_run(run_dir, self.root, split, csv, self.cfg, False, part="val", images=self.images(split),
                    **options)
        sc = score_run(csv, self.root, split, part="val", targets=self.targets(split))
        f = {"step": int(step), "epoch": int(epoch), "options": options, "add_s": sc["mean"].get("add_s"),
             "proj2d": sc["mean"].get("proj2d"), "targets": int(sc["mean"].get("n", 0)), "results": str(csv)}
        cache.append(f)
        self.state.save()
        return f


def _history(run: Path) -> dict:
    """The run's counters from its history.json: step, epoch, whether the run ended, the last loss."""
    h = read_json(run / "history.json")
    ep = h.get("epochs") or [{}]
    return {"step": int(h.get("steps", 0)), "epoch": int(ep[-1].get("epoch", 0)),
            "ended": int(h.get("steps", 0)) >= int(h.get("total_steps", h.get("steps", 0))),
            "loss": ep[-1].get("loss")}


KEPT = "kept"


def _keep(run: Path, step: int) -> Path:
    """Copy the run's current weights (at ``step``) into RUN/kept/ (config.json + last.pt with the
    weights only): a run folder predict reads. Refused when the checkpoint is not at ``step``."""
    import torch

    from tdof20.methods.runs import read_checkpoint  # imports torch

    kept = run / KEPT
    if (kept / "kept.json").exists() and read_json(kept / "kept.json").get("step") == step:
        return kept
    ck = read_checkpoint(run / "last.pt", needs=("model", "epoch", "step"))
    if int(ck["step"]) != step:
        raise TdofError(f"holds step {int(ck['step'])}, but the validation-best checkpoint is step {step}: delete the "
                        "run folder to train it again", run / "last.pt")
    kept.mkdir(exist_ok=True)
    if (kept / "kept.json").exists():
        (kept / "kept.json").unlink()
    tmp = kept / ".last.pt.tmp"
    torch.save({"model": ck["model"], "epoch": int(ck["epoch"]), "step": step}, tmp)
    os.replace(tmp, kept / "last.pt")
    shutil.copyfile(run / "config.json", kept / ".config.json.tmp")
    os.replace(kept / ".config.json.tmp", kept / "config.json")
    write_json(kept / "kept.json", {"step": step, "epoch": int(ck["epoch"])})
    return kept


def _train_and_keep(out: Path, root: Path, cfg: ReproduceConfig, r: dict, default_options: dict,
                    val: Validation, show: bool) -> dict:
    """Train run ``r`` on train minus val, epoch by epoch where epochs are chosen: after each
    validated epoch its checkpoint is predicted and scored on validation (with ``default_options``)
    and the best one is copied to RUN/kept/. Resumable at any point."""
    run = out / "runs" / r["name"]
    marks = validated_epochs(cfg, r["epochs"])
    key = _opts_key(default_options)
    cached = {f["epoch"]: f for f in val.state.data.get("validation", {}).get(r["name"], [])
              if _opts_key(f["options"]) == key}
    figures, best = [], None
    for n, e in enumerate(marks):
        f, new = cached.get(e), False
        if f is None:
            train_run(root, r["split"], run, r["method"], cfg, r["epochs"], show,
                      stop_epoch=None if len(marks) == 1 else e, **r["options"])
            h = _history(run)
            if len(marks) == 1 or (n == 0 and h["ended"]):
                break  # one checkpoint: nothing to choose
            if figures and figures[-1]["step"] == h["step"]:
                break  # the run ended (max_steps) before this epoch: the same checkpoint
            f, new = val.figure(r["name"], run, r["split"], h["step"], h["epoch"], default_options), True
        figures.append(f)
        if _better(f, best):
            best = f
            if new:  # copied before the training goes on (a resumed run replays the figures cached)
                _keep(run, f["step"])
    if best is not None:
        _keep(run, best["step"])  # a no-op unless a kill came between a figure and its copy
    h = _history(run)
    kept = run if best is None else run / KEPT
    return {"run": str(run), "kept": str(kept), "kept_step": h["step"] if best is None else best["step"],
            "kept_epoch": h["epoch"] if best is None else best["epoch"], "epochs": h["epoch"],
            "steps": h["step"], "last_loss": h["loss"],
            "validation": [{k: f[k] for k in ("epoch", "step", "add_s", "proj2d")} for f in figures]}


def reproduce(out: str | Path, preset: str | None = None, config: str | Path | dict | None = None,
              dataset: str | Path | None = None, progress: bool = True) -> Path:
    """Run (or resume) the reproduction into ``out``; returns DIR/tables/tables.md. See the module
    docstring for the stages, presets and resume rules."""
    cfg = make_config(preset, config, dataset)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise TdofError("--out is a file, not a folder", out)
    if cfg.dataset:
        open_dataset(cfg.dataset)  # the one "not a dataset" check, before anything is written
    from tdof20.methods.devices import select_device  # imports torch

    try:
        select_device(cfg.device)  # a device this machine lacks stops here, not after the dataset
    except TdofError as e:
        raise TdofError(str(e).replace("--device", "device", 1), config if isinstance(config, (str, Path)) else None) \
            from None
    state = State(out, cfg)
    root = Path(cfg.dataset) if cfg.dataset else out / "dataset"
    val = Validation(out, root, cfg, state, progress)
    preds = {p["name"]: p for p in planned_predictions(cfg)}
    runs = {r["name"]: r for r in planned_runs(cfg)}

    def kept(p: dict) -> dict:
        return state.get(f"train/{p['run']}")

    def options_of(p: dict) -> dict:
        """The options the test prediction of ``p`` uses: the row's own, and those chosen on validation."""
        src = choice_source(cfg, p)
        c = f"choose/{src['name']}"
        chosen = state.get(c)["options"] if state.done(c) else candidate_grid(cfg, src)[0]
        return {**{k: v for k, v in chosen.items() if k not in p["options"]}, **p["options"]}

    def val_figure(p: dict) -> dict:
        """p's kept checkpoint with its chosen options, on validation (cached)."""
        k = kept(p)
        return val.figure(p["run"], Path(k["kept"]), p["split"], k["kept_step"], k["kept_epoch"], options_of(p))

    def dataset_job(spec: dict) -> dict:
        if cfg.dataset:
            return {"root": str(root), "given": True}
        _sim_dataset(out, cfg, progress)
        return {"root": str(root), "given": False}

    def train_job(spec: dict) -> dict:
        r = runs[spec["name"].removeprefix("train/")]
        p = next(q for q in preds.values() if q["run"] == r["name"])
        default = {**candidate_grid(cfg, choice_source(cfg, p))[0], **p["options"]}
        return _train_and_keep(out, root, cfg, r, default, val, progress)

    def choose_job(spec: dict) -> dict:
        p = preds[spec["name"].removeprefix("choose/")]
        k = kept(p)
        figs, best = [], None
        for combo in spec["grid"]:
            f = val.figure(p["run"], Path(k["kept"]), p["split"], k["kept_step"], k["kept_epoch"],
                           {**combo, **p["options"]})
            figs.append({"options": f["options"], "add_s": f["add_s"], "proj2d": f["proj2d"]})
            if _better(f, best):
                best, chosen = f, combo
        return {"options": chosen, "validation": figs, "epoch": k["kept_epoch"]}

    def formulation_job(spec: dict) -> dict:
        figs = {name: val_figure(preds[name]) for name in spec["pair"]}
        best = None
        for name, f in figs.items():  # the default (bearing + PnP) first: it wins ties
            if _better(f, best):
                best, primary = f, name
        return {"primary": primary,
                "validation": {n: {"add_s": f["add_s"], "proj2d": f["proj2d"]} for n, f in figs.items()}}

    def predict_job(spec: dict) -> dict:
        p = preds[spec["name"].removeprefix("predict/")]
        csv = out / "results" / f"{p['name']}.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        opts = options_of(p)
        info = predict_run(Path(kept(p)["kept"]), root, p["split"], csv, cfg, progress, part="test", **opts)
        return {"results": str(csv), "masks": info.get("masks"), "predictions": info.get("predictions"),
                "dropped_impossible_poses": info.get("dropped_impossible_poses", 0),
                "run": kept(p)["kept"], "epoch": kept(p)["kept_epoch"], "options": opts}

    def score_job(spec: dict) -> dict:
        p = preds[spec["name"].removeprefix("score/")]
        csv = out / "results" / f"{p['name']}.csv"
        masks = state.get(f"predict/{p['name']}").get("masks")
        s = score_run(csv, root, p["split"], part="test")
        s["oracle_masks"] = masks == "gt"
        s["method"], s["label"], s["split"] = p["method"], p["label"], p["split"]
        s["chosen"] = {"epoch": kept(p)["kept_epoch"], "options": state.get(f"predict/{p['name']}")["options"]}
        if p["options"].get("voting") == "3d":
            s["note"] = ("the paper's pose recovery: 3D voting on the back-projected input depth + least squares, "
                         "trained with vectors from those observed points")
        f = out / "scores" / f"{p['name']}.json"
        f.parent.mkdir(parents=True, exist_ok=True)
        write_json(f, s)
        return {"scores": str(f), "add_s": s["mean"].get("add_s"), "proj2d": s["mean"].get("proj2d"),
                "oracle_masks": s["oracle_masks"]}

    def profile_job(spec: dict) -> dict:
        recs = profile_methods(tuple(cfg.methods), cfg)
        write_json(out / "profile.json", recs)
        return {"profile": str(out / "profile.json")}

    stages = {"dataset": dataset_job, "train": train_job, "choose": choose_job, "predict": predict_job,
              "score": score_job, "profile": profile_job}
    jobs = [Job(spec["name"], spec["stage"],
                functools.partial(formulation_job if "pair" in spec else stages[spec["stage"]], spec))
            for spec in job_plan(cfg)]  # the plan tested against every preset's (tests/reproduce_plans.json)

    todo = [j for j in jobs if not state.done(j.name)]
    console.print(f"reproduce ({cfg.preset}) -> {out}: {len(jobs)} jobs, {len(jobs) - len(todo)} done already",
                  highlight=False, markup=False) if progress else None
    with progress_bar(progress, unit="job") as bar:
        task = bar.add_task("reproduce", total=len(jobs), completed=len(jobs) - len(todo))
        for j in todo:
            bar.update(task, description=f"reproduce: {j.name}")
            t0, c0 = time.perf_counter(), _cpu_seconds()
            info = j.run()
            state.finish(j.name, time.perf_counter() - t0, stage=j.stage, cpu_seconds=round(_cpu_seconds() - c0, 2),
                         **info)
            if j.stage == "train":  # over: its optimiser state is two thirds of the checkpoint, and dead
                from tdof20.methods.runs import drop_optimizer  # imports torch

                drop_optimizer(info["run"])
            bar.advance(task)

    # tables (always rebuilt from what is on disk: cheap)
    entries, fusion, seg_on, seg_off = table_entries(out, cfg, state)
    profiles = read_json(out / "profile.json") if (out / "profile.json").exists() else []
    paths = write_tables(out / "tables", entries, profiles, fusion or None, seg_on, seg_off, dataset_objects(root),
                         header=tables_header(cfg, root, state), choices=choices(cfg, state))
    if progress:
        console.print(f"tables: {paths['tables.md']}", markup=False)
    return paths["tables.md"]


__all__ = ["AblationConfig", "CANDIDATES", "CHOICE_OPTIONS", "DataConfig", "EpochsConfig", "LABELS", "METHODS",
           "PRESETS", "ProfileConfig", "ReproduceConfig", "SelectConfig", "State", "Validation", "changed_keys",
           "check_candidates", "choices", "config_data", "config_digest", "estimate", "job_plan", "make_config",
           "plan", "predict_run", "profile_methods", "reproduce", "score_run", "train_run", "validation_images"]
