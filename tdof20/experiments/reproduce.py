"""``tdof20 reproduce``: the paper's tables with one command, resumable.

    from tdof20.experiments.reproduce import reproduce
    out = reproduce("repro", preset="smoke")                  # -> repro/tables/tables.md
    out = reproduce("repro", config="my.toml", dataset="ROOT")  # a TOML over a preset; a given dataset

A fair benchmark (../shared/design.md, docs/reproduce.md "A fair comparison"): every compared row
is trained with the same budget (train.images images seen, whatever the method's batch), gets the
same number of candidate sets chosen on validation, is trained and predicted once per seed
(train.seeds; the tables show mean and spread) and sees no privileged input.

Stages (each finished job is recorded in ``DIR/reproduce.json`` with the config's digest)::

    dataset    simulated TDoF20 scenes (capture on the simulated rig + oracle labels, as
               ``tdof20 sim label`` writes them) gathered by ``dataset build`` -> DIR/dataset;
               or the given dataset root (e.g. an imported TDoF20), used in place
    train      per seed, every method on each protocol's train part minus its validation part
               -> DIR/runs/<method>_<protocol>_s<seed>/ (plus HFF6DoF's 3D-voting row's own run
               hff6dof-3d_<protocol>, trained with vector_origin = "observed", and the ablations'
               HFF6DoF runs on hard: fuse<N>_hard, noseg_hard with the segmentation network
               segnet_hard whose masks it predicts with); each for train.images images; epoch by
               epoch where epochs are chosen: each validated epoch's checkpoint is predicted and
               scored on the validation part and the best one is copied to RUN/kept/ ([select])
    choose     on the validation part only: the prediction-time options of [candidates.<method>]
               (the input depth mode, thresholds) on each kept checkpoint
    predict    each kept checkpoint on its test part, with the options chosen -> DIR/results/<name>.csv
               (+ _info.json); ``hff6dof-3d`` with voting = "3d"
    score      ADD(S), 2D projection, AUC and accuracy curves -> DIR/scores/<name>.json, with
               "oracle_masks" when ground-truth masks picked the pixels (only a row marked oracle)
    profile    Table 3 (parameters, multiply-adds at 480x640, FPS) of every method -> DIR/profile.json
    tables     DIR/tables/: tables.md (mean ± half-range over the seeds, what was chosen on
               validation), CSV, JSON, plots

The test part is predicted and scored once per result, after every choice: nothing is chosen on it.
Validation predictions go to DIR/val/<run>/ (their targets DIR/val/targets_<protocol>.json) and
their figures to reproduce.json ("validation"), so that a resumed run predicts none twice.

Executors: "local" runs the jobs one after the other; "ray" runs every training, choice,
prediction and Table 3 as a Ray task with its resource needs (CPUs, GPUs) as soon as the jobs it
needs are done (:func:`job_plan`'s "needs"), on a local instance or a cluster (``ray_address``).
Both record the same jobs in the same reproduce.json, so either resumes the other's run.

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
    images = 64                # the budget of every run: images seen (steps x batch)
    seeds = [0, 1]             # every row once per seed
    [batch]
    pvnet = 8                  # a method's own batch (default train.batch_size): the same images, fewer steps
    [ablations]
    fuse_stages = [1, 3]
    segmentation = true

    [select]
    epochs = "best"            # "last": no validation of epochs
    every = 1                  # validate every N-th epoch (and the last)
    max_images = 0             # at most this many validation images per protocol (0 = all)
    [candidates.hff6dof]       # prediction-time options chosen on validation (first = default)
    depth_mode = ["filled", "raw"]
    [candidates.pvnet]         # every compared row the same number of candidate sets
    inlier_cos = [0.99, 0.97]

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

import dataclasses
import hashlib
import json
import os
import resource
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path

from tdof20.capture import run_capture, sim_config
from tdof20.dataset.build import build_dataset
from tdof20.dataset.naming import normalize_scene_id
from tdof20.dataset.reader import open_dataset
from tdof20.dataset.results import write_results_csv
from tdof20.dataset.splits import validation_images  # noqa: F401  (re-exported: the rules live in splits)
from tdof20.dataset.validation import part_images, val_targets
from tdof20.errors import TdofError
from tdof20.experiments.reproduce_config import (CANDIDATES, CHOICE_OPTIONS, LABELS, METHODS, PRESETS,  # noqa: F401
                                                 SEGNET, AblationConfig, BatchConfig, DataConfig, ProfileConfig,
                                                 ReproduceConfig, SelectConfig, changed_keys, check_candidates,
                                                 config_data, config_digest, flat_keys, make_config,
                                                 segnet_available)
from tdof20.experiments.reproduce_plan import (budgets, candidate_grid, choice_source, estimate,  # noqa: F401
                                               job_plan, plan, planned_predictions, planned_runs, run_schedule,
                                               validated_epochs)
from tdof20.experiments.reproduce_report import (absolute_options, choices, dataset_objects, table_entries,
                                                  tables_header, test_options, validation_rows, validation_summary)
from tdof20.experiments.tables import curves_from_evaluation, write_tables
from tdof20.formats.io import read_json, write_json
from tdof20.progress import console, progress as progress_bar
from tdof20.scoring.scoring import evaluate

STATE = "reproduce.json"
FORMAT = "tdof20-reproduce"


# --------------------------------------------------------------------------------------------
# the adapter: the only calls into training, prediction, scoring and profiling


def train_run(root: Path, split: str, run: Path, method: str, cfg: ReproduceConfig, schedule: dict,
              show: bool, stop_epoch: int | None = None, **options) -> Path:
    """Train (or continue) ``run`` on the train part minus the validation part of ``split`` with
    ``schedule`` ({"epochs", "steps", "batch", "seed"}: :func:`run_schedule` of the run's budget, and
    its seed); with ``stop_epoch`` the call ends after that epoch (the schedule still spans all
    the steps). ``options``: the run's options of the method's config (an ablation's
    ``fuse_stages``, ``vector_origin``, ...) over ``[method_options.<method>]``. The run's last
    checkpoint keeps the weights, not the optimiser's state (``keep_optimizer=False``)."""
    from tdof20.methods.train import train  # imports torch

    t = cfg.train
    return train(root, split, run, method=method, method_config=cfg.method_options.get(method),
                 method_options=options, image_size=tuple(t.image_size), batch_size=int(schedule["batch"]),
                 epochs=int(schedule["epochs"]), lr=t.lr, max_steps=int(schedule["steps"]),
                 num_workers=t.num_workers, seed=int(schedule["seed"]), device=cfg.device, progress=show,
                 part="train-val", stop_epoch=stop_epoch, keep_optimizer=False)


def predict_run(run: Path, root: Path, split: str, out_csv: Path, cfg: ReproduceConfig, show: bool,
                part: str = "test", images: list[tuple[int, int]] | None = None, seed: int = 0,
                **options) -> dict:
    """Predict ``part`` ('test' or 'val'; ``images``: these validation images only) of ``split`` with
    the run folder ``run`` into ``out_csv`` (+ ``_info.json``); ``seed``: the row's (its RANSAC);
    ``options``: the method's prediction options (its config's names). Returns the summary."""
    from tdof20.methods.predict import info_path, predict, predict_rows  # imports torch

    for p in (out_csv, info_path(out_csv)):  # a rerun of an interrupted prediction starts afresh
        if p.exists():
            p.unlink()
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    kw = dict(device=cfg.device, num_workers=cfg.train.num_workers, seed=seed, progress=show,
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
        """Records a finished job: its seconds and ``info``, when it finished (UTC) and the load
        average then (a run spread over several sittings says which pieces ran when, and beside what)."""
        self.data["jobs"][job] = {"seconds": round(seconds, 2), **info,
                                  "finished": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                                  "load": round(os.getloadavg()[0], 2)}
        self.save()


# --------------------------------------------------------------------------------------------
# the jobs


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (data-loader workers): a job's work on
    a machine shared with other jobs, where its wall time says little."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


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

    def figure(self, name: str, run_dir: Path, split: str, step: int, epoch: int, options: dict,
               seed: int = 0) -> dict:
        """The validation figure of run ``name``'s checkpoint at ``step`` (in ``run_dir``) predicted
        with ``options`` (``seed``: the run's): {"step", "epoch", "options", "add_s", "proj2d",
        "targets", "results"}."""
        cache = self.state.data.setdefault("validation", {}).setdefault(name, [])
        key = _opts_key(options)
        for f in cache:
            if f["step"] == step and _opts_key(f["options"]) == key:
                return f
        tag = f"step{step:06d}_" + hashlib.sha256(key.encode()).hexdigest()[:8]
        csv = self.out / "val" / name / f"{tag}.csv"
        predict_run(run_dir, self.root, split, csv, self.cfg, False, part="val", images=self.images(split),
                    seed=seed, **options)
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
    ck = read_checkpoint(run / "last.pt", needs=("model", "epoch", "step"), mmap=True)  # the weights only
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


def _train_and_keep(out: Path, root: Path, cfg: ReproduceConfig, r: dict, schedule: dict, default_options: dict,
                    val: Validation, show: bool) -> dict:
    """Train run ``r`` on train minus val (``schedule``: its steps, batch, epochs and seed), epoch by
    epoch where epochs are chosen: after each validated epoch its checkpoint is predicted and
    scored on validation (with ``default_options``) and the best one is copied to RUN/kept/.
    Resumable at any point."""
    run = out / "runs" / r["name"]
    marks = validated_epochs(cfg, schedule["epochs"])
    key = _opts_key(default_options)
    cached = {f["epoch"]: f for f in val.state.data.get("validation", {}).get(r["name"], [])
              if _opts_key(f["options"]) == key}
    figures, best = [], None
    for n, e in enumerate(marks):
        f, new = cached.get(e), False
        if f is None:
            train_run(root, r["split"], run, r["method"], cfg, schedule, show,
                      stop_epoch=None if len(marks) == 1 else e, **r["options"])
            h = _history(run)
            if len(marks) == 1 or (n == 0 and h["ended"]):
                break  # one checkpoint: nothing to choose
            if figures and figures[-1]["step"] == h["step"]:
                break  # the run ended before this epoch: the same checkpoint
            f, new = val.figure(r["name"], run, r["split"], h["step"], h["epoch"], default_options,
                                seed=r["seed"]), True
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
            "steps": h["step"], "batch": schedule["batch"], "images_seen": h["step"] * schedule["batch"],
            "seed": r["seed"], "last_loss": h["loss"],
            "validation": [{k: f[k] for k in ("epoch", "step", "add_s", "proj2d")} for f in figures]}


class TaskState:
    """What a job run as a Ray task sees of the state: the jobs done when it was sent and the
    validation figures (read-only copies), its own new validation figures saved to
    DIR/tasks/<job>.json as they come (so that a task killed half-way predicts none of them again
    when the run resumes); the driver merges them into reproduce.json when the task returns."""

    def __init__(self, out: Path, job: str, jobs: dict, validation: dict):
        self.path = out / "tasks" / (job.replace("/", "__") + ".json")
        validation = json.loads(json.dumps(validation))
        if self.path.exists():
            try:
                _merge_validation(validation, read_json(self.path).get("validation", {}))
            except TdofError:
                pass  # a task killed while writing it: its figures are made again
        self.data = {"jobs": jobs, "validation": validation}

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, {"validation": self.data["validation"]})

    def done(self, job: str) -> bool:
        return job in self.data["jobs"]

    def get(self, job: str) -> dict:
        return self.data["jobs"][job]


def _merge_validation(into: dict, new: dict) -> dict:
    """Add the validation figures of ``new`` ({run: [figures]}) that ``into`` lacks (same step and
    options); returns ``into``."""
    for run, figs in new.items():
        have = into.setdefault(run, [])
        keys = {(f["step"], _opts_key(f["options"])) for f in have}
        have += [f for f in figs if (f["step"], _opts_key(f["options"])) not in keys]
    return into


class Runner:
    """The jobs of one reproduce config (:func:`job_plan`'s specs): ``run(spec)`` -> the info
    recorded for it. The same code runs a job in this process (``state`` the run's :class:`State`)
    or in a Ray task (a :class:`TaskState`)."""

    def __init__(self, out: Path, root: Path, cfg: ReproduceConfig, state, show: bool):
        self.out, self.root, self.cfg, self.state, self.show = out, root, cfg, state, show
        self.val = Validation(out, root, cfg, state, show)
        self.preds = {p["name"]: p for p in planned_predictions(cfg)}
        self.runs = {r["name"]: r for r in planned_runs(cfg)}
        self.plan = {r["name"]: r for r in plan(cfg)["runs"]}

    def schedule(self, r: dict) -> dict:
        n = self.plan[r["name"]]["images"]
        return {**run_schedule(r["images"], r["batch"], n), "seed": r["seed"]}

    def absolute(self, options: dict) -> dict:
        return absolute_options(self.out, options)

    def kept(self, p: dict) -> dict:
        return self.state.get(f"train/{p['run']}")

    def options_of(self, p: dict) -> dict:
        """The options the test prediction of ``p`` uses: the row's own, and those chosen on validation."""
        return test_options(self.cfg, self.state, p)

    def run(self, spec: dict) -> dict:
        return getattr(self, f"{spec['stage']}_job")(spec)

    def dataset_job(self, spec: dict) -> dict:
        if self.cfg.dataset:
            return {"root": str(self.root), "given": True}
        _sim_dataset(self.out, self.cfg, self.show)
        return {"root": str(self.root), "given": False}

    def train_job(self, spec: dict) -> dict:
        r = self.runs[spec["name"].removeprefix("train/")]
        sch = self.schedule(r)
        if r["method"] == SEGNET:  # the segmentation ablation's masks: no pose to validate, its last weights
            run = self.out / "runs" / r["name"]
            train_run(self.root, r["split"], run, r["method"], self.cfg, sch, self.show, **r["options"])
            h = _history(run)
            return {"run": str(run), "kept": str(run), "kept_step": h["step"], "kept_epoch": h["epoch"],
                    "epochs": h["epoch"], "steps": h["step"], "batch": sch["batch"],
                    "images_seen": h["step"] * sch["batch"], "seed": r["seed"], "last_loss": h["loss"],
                    "validation": []}
        p = next(q for q in self.preds.values() if q["run"] == r["name"])
        default = self.absolute({**candidate_grid(self.cfg, choice_source(self.cfg, p))[0], **p["options"]})
        return _train_and_keep(self.out, self.root, self.cfg, r, sch, default, self.val, self.show)

    def choose_job(self, spec: dict) -> dict:
        p = self.preds[spec["name"].removeprefix("choose/")]
        k = self.kept(p)
        figs, best, chosen = [], None, spec["grid"][0]
        for combo in spec["grid"]:
            f = self.val.figure(p["run"], Path(k["kept"]), p["split"], k["kept_step"], k["kept_epoch"],
                                self.absolute({**combo, **p["options"]}), seed=p["seed"])
            figs.append({"options": f["options"], "add_s": f["add_s"], "proj2d": f["proj2d"]})
            if _better(f, best):
                best, chosen = f, combo
        return {"options": chosen, "validation": figs, "epoch": k["kept_epoch"]}

    def predict_job(self, spec: dict) -> dict:
        p = self.preds[spec["name"].removeprefix("predict/")]
        csv = self.out / "results" / f"{p['name']}.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        opts = self.options_of(p)
        k = self.kept(p)
        info = predict_run(Path(k["kept"]), self.root, p["split"], csv, self.cfg, self.show, part="test",
                           seed=p["seed"], **self.absolute(opts))
        if info.get("masks") == "gt" and not p["oracle"]:
            raise TdofError(f"{p['name']} is a compared row but was predicted with ground-truth masks, a privileged "
                            "input: give its method a segmentation (masks = \"network\")", csv)
        return {"results": str(csv), "masks": info.get("masks"), "predictions": info.get("predictions"),
                "dropped_impossible_poses": info.get("dropped_impossible_poses", 0),
                "run": k["kept"], "epoch": k["kept_epoch"], "options": opts}

    def score_job(self, spec: dict) -> dict:
        p = self.preds[spec["name"].removeprefix("score/")]
        csv = self.out / "results" / f"{p['name']}.csv"
        pred = self.state.get(f"predict/{p['name']}")
        s = score_run(csv, self.root, p["split"], part="test")
        s["oracle_masks"] = pred.get("masks") == "gt"
        s["method"], s["label"], s["split"], s["seed"], s["row"] = (p["method"], p["label"], p["split"], p["seed"],
                                                                    p["row"])
        train = self.kept(p)
        s["chosen"] = {"epoch": train["kept_epoch"], "options": pred["options"]}
        s["budget"] = {"images_seen": train.get("images_seen"), "steps": train.get("steps"),
                       "batch": train.get("batch")}
        if p["role"] == "noseg" and not s["oracle_masks"]:
            seg = self.state.get(f"train/{SEGNET}_hard_s{p['seed']}")
            s["budget"]["segnet_images_seen"] = seg.get("images_seen")
        if p["options"].get("voting") == "3d":
            s["note"] = ("the paper's pose recovery: 3D voting on the back-projected input depth + least squares, "
                         "trained with vectors from those observed points")
        f = self.out / "scores" / f"{p['name']}.json"
        f.parent.mkdir(parents=True, exist_ok=True)
        write_json(f, s)
        return {"scores": str(f), "add_s": s["mean"].get("add_s"), "proj2d": s["mean"].get("proj2d"),
                "oracle_masks": s["oracle_masks"]}

    def profile_job(self, spec: dict) -> dict:
        recs = profile_methods(tuple(self.cfg.methods), self.cfg)
        write_json(self.out / "profile.json", recs)
        return {"profile": str(self.out / "profile.json")}


#: the stages ``validation_only`` runs: nothing that predicts a test part (nor Table 3's profile)
VALIDATION_STAGES = ("dataset", "train", "choose")

#: the stages a Ray executor runs as tasks (the others, cheap, run in the driver)
RAY_STAGES = ("train", "choose", "predict", "profile")


def job_resources(cfg: ReproduceConfig, stage: str, gpus_per_job: float) -> dict:
    """A Ray task's resource needs: a training, choice or prediction one CPU plus its data-loader
    workers and ``gpus_per_job`` GPUs; Table 3's profiling one CPU and the same GPUs."""
    cpus = 1 if stage == "profile" else 1 + cfg.train.num_workers
    return {"num_cpus": cpus, "num_gpus": gpus_per_job}


def _ray_job(out: Path, root: Path, cfg: ReproduceConfig, spec: dict, jobs: dict, validation: dict) -> dict:
    """One job in a Ray task: (seconds, CPU seconds, info, the validation figures it holds)."""
    import ray
    import torch

    # torch's threads = the task's CPUs: a Ray worker's OMP_NUM_THREADS is not set for it, and N
    # tasks of one CPU on N cores each spinning up N threads oversubscribed the machine N-fold
    cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0)
    torch.set_num_threads(max(1, int(cpus)))
    state = TaskState(out, spec["name"], jobs, validation)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    info = Runner(out, root, cfg, state, False).run(spec)
    return {"seconds": time.perf_counter() - t0, "cpu_seconds": _cpu_seconds() - c0,
            "info": {**info, **_threads(spec)}, "validation": state.data["validation"]}


def _threads(spec: dict) -> dict:
    """{"threads": torch's intra-op threads} for a job that ran torch (training, choice, prediction)."""
    import sys

    torch = sys.modules.get("torch")
    return {"threads": torch.get_num_threads()} if torch is not None and spec["stage"] in RAY_STAGES else {}


def _finish(state: State, spec: dict, seconds: float, cpu: float, info: dict) -> None:
    state.finish(spec["name"], seconds, stage=spec["stage"], cpu_seconds=round(cpu, 2), **info)
    if spec["stage"] == "train":  # over: its optimiser state is two thirds of the checkpoint, and dead;
        # train_run's last save left it out already (keep_optimizer=False): this drops it from a run
        # an older tdof20 trained, and otherwise only checks and maps the file (no tensor read, nothing written)
        from tdof20.methods.runs import drop_optimizer  # imports torch

        drop_optimizer(info["run"])


def _run_local(runner: Runner, todo: list[dict], state: State, bar, task) -> None:
    for spec in todo:
        bar.update(task, description=f"reproduce: {spec['name']}")
        t0, c0 = time.perf_counter(), _cpu_seconds()
        info = runner.run(spec)
        _finish(state, spec, time.perf_counter() - t0, _cpu_seconds() - c0, {**info, **_threads(spec)})
        bar.advance(task)


def _ray_gpus(cfg: ReproduceConfig, gpus_per_job: float | None) -> float:
    """GPUs per task: as given, else 1 where the device may be a GPU and the cluster has some, else 0."""
    import ray

    if gpus_per_job is not None:
        return float(gpus_per_job)
    has = float(ray.cluster_resources().get("GPU", 0)) > 0
    return 1.0 if has and cfg.device not in ("cpu", "mps") else 0.0


def _run_ray(runner: Runner, todo: list[dict], state: State, bar, task, address: str | None,
             gpus_per_job: float | None, workers: int | None) -> None:
    """Run the jobs on a Ray cluster (``address``; None: a local instance of ``workers`` CPUs, all
    by default): each training, choice, prediction and Table 3 as a task with its resource needs
    (:func:`job_resources`) as soon as the jobs it needs are done; the dataset and the scoring in
    this process. Each finished job is recorded at once, so a run stopped anywhere resumes."""
    from tdof20.annotate.executors import ray_init

    own = ray_init(address, workers)
    import ray

    try:
        gpus = _ray_gpus(runner.cfg, gpus_per_job)
        remote = ray.remote(_ray_job)
        waiting = list(todo)
        running: dict = {}
        while waiting or running:
            ready = [s for s in waiting if all(state.done(n) for n in s["needs"])]
            for spec in ready:
                waiting.remove(spec)
                if spec["stage"] in RAY_STAGES:
                    opts = job_resources(runner.cfg, spec["stage"], gpus)
                    ref = remote.options(**opts, max_retries=0).remote(
                        runner.out, runner.root, runner.cfg, spec, state.data["jobs"],
                        state.data.get("validation", {}))
                    running[ref] = spec
                else:
                    bar.update(task, description=f"reproduce: {spec['name']}")
                    t0, c0 = time.perf_counter(), _cpu_seconds()
                    info = runner.run(spec)
                    _finish(state, spec, time.perf_counter() - t0, _cpu_seconds() - c0, info)
                    bar.advance(task)
                    break  # what it finished may make others ready
            else:
                if not running:
                    if waiting:
                        raise TdofError(f"jobs wait for jobs that are not planned: {waiting[0]['name']} needs "
                                        f"{waiting[0]['needs']}")
                    break
                bar.update(task, description=f"reproduce: {len(running)} job(s) on Ray")
                done, _ = ray.wait(list(running), num_returns=1)
                spec = running.pop(done[0])
                try:
                    got = ray.get(done[0])
                except ray.exceptions.RayTaskError as e:
                    for ref in running:
                        ray.cancel(ref)
                    cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
                    text = (str(cause).strip().splitlines() or [""])[0]
                    raise TdofError(f"job {spec['name']} failed on Ray: {type(cause).__name__}: {text} (rerun to "
                                    "resume: finished jobs are kept)") from None
                state.data["validation"] = _merge_validation(state.data.get("validation", {}), got["validation"])
                _finish(state, spec, got["seconds"], got["cpu_seconds"], got["info"])
                (runner.out / "tasks" / (spec["name"].replace("/", "__") + ".json")).unlink(missing_ok=True)
                bar.advance(task)
    finally:
        if own:
            ray.shutdown()


EXECUTORS = ("local", "ray")


def reproduce(out: str | Path, preset: str | None = None, config: str | Path | dict | None = None,
              dataset: str | Path | None = None, progress: bool = True, executor: str = "local",
              ray_address: str | None = None, gpus_per_job: float | None = None,
              workers: int | None = None, validation_only: bool = False) -> Path:
    """Run (or resume) the reproduction into ``out``; returns DIR/tables/tables.md. See the module
    docstring for the stages, presets and resume rules. ``validation_only``: the dataset, the
    trainings and the choices only (:data:`VALIDATION_STAGES`), nothing predicted on a test part
    nor profiled: the tables give the validation figures (a scale or budget study that never looks
    at test); the same call without it goes on from there to the test part. ``executor``: "local" (the jobs one after
    the other in this process) or "ray" (the independent jobs side by side as Ray tasks on the
    cluster at ``ray_address``, None = a local instance of ``workers`` CPUs; ``gpus_per_job``: GPUs
    per task, None = 1 where the cluster has GPUs and the device is not the CPU). Both make the
    same jobs, record them in the same reproduce.json and so resume each other's runs."""
    if executor not in EXECUTORS:
        raise TdofError(f"--executor must be one of {', '.join(EXECUTORS)}, got '{executor}'")
    if executor != "ray" and (ray_address or gpus_per_job is not None):
        raise TdofError("--ray-address and --gpus-per-job go with --executor ray")
    if gpus_per_job is not None and gpus_per_job < 0:
        raise TdofError(f"--gpus-per-job must be >= 0, got {gpus_per_job}")
    cfg = make_config(preset, config, dataset)
    if cfg.ablations.segmentation and cfg.ablations.segmentation_masks == "segnet" and not segnet_available():
        cfg = dataclasses.replace(cfg, ablations=dataclasses.replace(cfg.ablations, segmentation_masks="gt"))
        if progress:
            console.print("segmentation ablation: this version has no separately trained segmentation network "
                          f"('{SEGNET}'): the row without HFF6DoF's head takes ground-truth masks, an oracle row "
                          "outside every claim", markup=False, highlight=False)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise TdofError("--out is a file, not a folder", out)
    if cfg.dataset:
        open_dataset(cfg.dataset)  # the one "not a dataset" check, before anything is written
    from tdof20.methods.devices import select_device  # imports torch

    if executor == "local":  # a Ray cluster's devices are its workers', not this machine's
        try:
            select_device(cfg.device)  # a device this machine lacks stops here, not after the dataset
        except TdofError as e:
            raise TdofError(str(e).replace("--device", "device", 1),
                            config if isinstance(config, (str, Path)) else None) from None
    state = State(out, cfg)
    root = Path(cfg.dataset) if cfg.dataset else out / "dataset"
    runner = Runner(out, root, cfg, state, progress and executor == "local")
    specs = job_plan(cfg)  # the plan tested against every preset's (tests/reproduce_plans.json)
    if validation_only:
        specs = [s for s in specs if s["stage"] in VALIDATION_STAGES]
    todo = [s for s in specs if not state.done(s["name"])]
    if progress:
        console.print(f"reproduce ({cfg.preset}, {executor}{', validation only' if validation_only else ''}) -> "
                      f"{out}: {len(specs)} jobs, {len(specs) - len(todo)} done already",
                      highlight=False, markup=False)
    with progress_bar(progress, unit="job") as bar:
        task = bar.add_task("reproduce", total=len(specs), completed=len(specs) - len(todo))
        if executor == "ray":
            _run_ray(runner, todo, state, bar, task, ray_address, gpus_per_job, workers)
        else:
            _run_local(runner, todo, state, bar, task)

    # tables (always rebuilt from what is on disk: cheap)
    entries, fusion, seg_on, seg_off = table_entries(out, cfg, state)
    profiles = read_json(out / "profile.json") if (out / "profile.json").exists() else []
    header = tables_header(cfg, root, state)
    if validation_only and not entries:
        header.append("Validation only (--validation-only): nothing was predicted on a test part; the same command "
                      "without the flag goes on to it.")
    paths = write_tables(out / "tables", entries, profiles, fusion or None, seg_on, seg_off, dataset_objects(root),
                         header=header, choices=choices(cfg, state),
                         validation=validation_summary(validation_rows(cfg, state, out)))
    if progress:
        console.print(f"tables: {paths['tables.md']}", markup=False)
    return paths["tables.md"]


__all__ = ["AblationConfig", "BatchConfig", "CANDIDATES", "CHOICE_OPTIONS", "DataConfig", "EXECUTORS", "LABELS",
           "METHODS", "PRESETS", "ProfileConfig", "ReproduceConfig", "Runner", "SelectConfig", "State", "TaskState",
           "VALIDATION_STAGES", "Validation", "changed_keys", "check_candidates", "choices", "config_data", "config_digest", "estimate",
           "job_plan", "job_resources", "make_config", "plan", "predict_run", "profile_methods", "reproduce",
           "score_run", "train_run", "validation_images"]
