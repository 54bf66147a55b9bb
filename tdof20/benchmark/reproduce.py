"""``tdof20 reproduce``: the paper's tables with one command, resumable.

    from tdof20.benchmark.reproduce import reproduce
    out = reproduce("repro", preset="smoke")                  # -> repro/tables/tables.md
    out = reproduce("repro", config="my.toml", dataset="ROOT")  # a TOML over a preset; a given dataset

Stages (each finished job is recorded in ``DIR/reproduce.json`` with the config's digest)::

    dataset    simulated TDoF20 scenes (capture on the simulated rig + oracle labels, as
               ``tdof20 sim label`` writes them) gathered by ``dataset build`` -> DIR/dataset;
               or the given dataset root (e.g. an imported TDoF20), used in place
    train      every method on each protocol -> DIR/runs/<method>_<protocol>/ (plus the ablations'
               HFF6DoF runs on hard: fuse<N>_hard, noseg_hard)
    predict    each run's test part -> DIR/results/<name>.csv (+ _info.json); HFF6DoF also with the
               paper's 3D voting + least squares (``hff6dof-3d``): its own run, trained with
               vector_origin = "observed" (vectors from the input depth's points, the points 3D
               voting back-projects; docs/hff6dof.md), predicted with voting = "3d"
    score      ADD(S), 2D projection, AUC and accuracy curves -> DIR/scores/<name>.json, with
               "oracle_masks" when ground-truth masks picked the pixels (the run without the
               segmentation head)
    profile    Table 3 (parameters, multiply-adds at 480x640, FPS) of every method -> DIR/profile.json
    tables     DIR/tables/: tables.md, CSV, JSON, plots (tdof20.benchmark.tables)

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

Train / predict / score / profile go through the small adapter functions below
(:func:`train_run`, :func:`predict_run`, :func:`score_run`, :func:`profile_methods`): the method
registry's loops (:mod:`tdof20.methods.train`, :mod:`tdof20.methods.predict`).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from tdof20.benchmark.splits import validation_images  # noqa: F401  (re-exported: the rules live in splits)
from tdof20.config import ConfigError, check_ranges, config_from_data
from tdof20.errors import TdofError
from tdof20.progress import console, progress as progress_bar

METHODS = ("pvnet", "densefusion", "ffb6d", "hff6dof")
LABELS = {"pvnet": "PVNet", "densefusion": "DenseFusion", "ffb6d": "FFB6D", "hff6dof": "HFF6DoF (bearing + PnP)",
          "hff6dof-3d": "HFF6DoF (3D voting + LSQ)"}
PROTOCOLS = ("simple", "hard")
STATE = "reproduce.json"
FORMAT = "tdof20-reproduce"


# --------------------------------------------------------------------------------------------
# config


@dataclass
class DataConfig:
    """[data]: the simulated scenes (capture on the simulated rig, oracle labels); ignored with a
    given dataset root. steps x step_deg per arm position, n_arms arm positions, width x height."""

    scenes: tuple[str, ...] = ("single/juice_cup_340", "multi/08")
    steps: int = 12
    step_deg: float = 2.5
    n_arms: int = 4
    width: int = 80
    height: int = 60
    seed: int = 0

    def __post_init__(self) -> None:
        check_ranges(self, "data", positive=("steps", "step_deg", "n_arms", "width", "height"))
        if not self.scenes:
            raise ConfigError("data.scenes must not be empty")
        if self.steps * self.step_deg > 360.0 + 1e-6:
            raise ConfigError(f"data.steps x data.step_deg is more than one turn ({self.steps} x {self.step_deg})")


@dataclass
class TrainConfig:
    """[train]: the shared training options of every method (tdof20.methods.train.train)."""

    image_size: tuple[int, ...] = (32, 48)
    batch_size: int = 4
    lr: float = 1e-3
    max_steps: int = 0       # 0 = the epochs decide
    num_workers: int = 1
    seed: int = 0

    def __post_init__(self) -> None:
        self.image_size = tuple(int(v) for v in self.image_size)
        if len(self.image_size) != 2:
            raise ConfigError(f"train.image_size must be [H, W], got {list(self.image_size)}")
        check_ranges(self, "train", positive=("image_size", "batch_size", "lr"), non_negative=("max_steps",))


@dataclass
class EpochsConfig:
    """[epochs]: training epochs per method."""

    hff6dof: int = 1
    pvnet: int = 1
    densefusion: int = 1
    ffb6d: int = 1

    def __post_init__(self) -> None:
        check_ranges(self, "epochs", positive=METHODS)


@dataclass
class AblationConfig:
    """[ablations]: fuse_stages (HFF6DoF trained on hard with each number of fused stages; () =
    no fusion ablation; 3 is the main run), segmentation (HFF6DoF on hard without its head, its
    prediction then on ground-truth masks: marked "oracle masks"), voting_3d (the paper's 3D
    voting + least squares as a row beside the default bearing + PnP)."""

    fuse_stages: tuple[int, ...] = ()
    segmentation: bool = False
    voting_3d: bool = True

    def __post_init__(self) -> None:
        self.fuse_stages = tuple(sorted({int(v) for v in self.fuse_stages}))
        if any(not 1 <= v <= 5 for v in self.fuse_stages):
            raise ConfigError(f"ablations.fuse_stages must be in 1..5, got {list(self.fuse_stages)}")


@dataclass
class ProfileConfig:
    """[profile]: Table 3 (enabled; timing at height x width, multiply-adds always at 480x640)."""

    enabled: bool = True
    height: int = 480
    width: int = 640
    repeats: int = 3

    def __post_init__(self) -> None:
        check_ranges(self, "profile", positive=("height", "width", "repeats"))


@dataclass
class ReproduceConfig:
    """What ``tdof20 reproduce`` runs (a preset, a TOML over it). dataset: a dataset root to use
    instead of simulating one ("" = simulate [data])."""

    preset: str = "smoke"
    methods: tuple[str, ...] = METHODS
    protocols: tuple[str, ...] = PROTOCOLS
    device: str = "auto"
    dataset: str = ""
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    epochs: EpochsConfig = field(default_factory=EpochsConfig)
    ablations: AblationConfig = field(default_factory=AblationConfig)
    profile: ProfileConfig = field(default_factory=ProfileConfig)
    #: [method_options.<method>]: options of that method's config (checked by it), e.g. ffb6d n_points
    method_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ConfigError(f"preset must be one of {', '.join(PRESETS)}, got '{self.preset}'")
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise ConfigError(f"methods must be some of {', '.join(METHODS)}, got {list(self.methods)}")
        bad = [p for p in self.protocols if p not in PROTOCOLS]
        if bad or not self.protocols:
            raise ConfigError(f"protocols must be some of simple, hard, got {list(self.protocols)}")
        if (self.ablations.fuse_stages or self.ablations.segmentation) and (
                "hff6dof" not in self.methods or "hard" not in self.protocols):
            raise ConfigError("the ablations run HFF6DoF on hard: methods needs hff6dof and protocols hard")


ALL_SCENES = tuple([f"single/{i:02d}" for i in range(1, 21)] + [f"multi/{i:02d}" for i in range(20)])

#: the presets, as TOML-like data over the defaults
PRESETS: dict[str, dict] = {
    "smoke": {"data": {"scenes": ["single/juice_cup_340", "single/handle_cup_280", "multi/08", "multi/01"],
                       "steps": 12, "step_deg": 2.5, "n_arms": 4, "width": 80, "height": 60},
              "train": {"image_size": [32, 48], "batch_size": 4, "lr": 2e-3, "max_steps": 6},
              "epochs": {m: 1 for m in METHODS},
              "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
              "profile": {"height": 120, "width": 160, "repeats": 1},
              "method_options": {"ffb6d": {"n_points": 1024, "meanshift_iters": 30, "max_votes": 500},
                                 "densefusion": {"n_points": 200, "crop_size": 64}}},
    "cpu": {"data": {"scenes": list(ALL_SCENES), "steps": 24, "step_deg": 15.0, "n_arms": 4, "width": 160,
                     "height": 120},
            "train": {"image_size": [96, 128], "batch_size": 4, "lr": 1e-3},
            "epochs": {"hff6dof": 8, "pvnet": 8, "densefusion": 4, "ffb6d": 4},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 240, "width": 320, "repeats": 3}},
    "gpu": {"data": {"scenes": list(ALL_SCENES), "steps": 100, "step_deg": 3.6, "n_arms": 4, "width": 640,
                     "height": 480},
            "train": {"image_size": [240, 320], "batch_size": 8, "lr": 1e-3, "num_workers": 4},
            "epochs": {"hff6dof": 30, "pvnet": 30, "densefusion": 15, "ffb6d": 15},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 480, "width": 640, "repeats": 20}},
    "full": {"data": {"scenes": list(ALL_SCENES), "steps": 400, "step_deg": 0.9, "n_arms": 4, "width": 640,
                      "height": 480},
             "train": {"image_size": [480, 640], "batch_size": 8, "lr": 1e-3, "num_workers": 8},
             "epochs": {"hff6dof": 100, "pvnet": 100, "densefusion": 50, "ffb6d": 50},
             "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
             "profile": {"height": 480, "width": 640, "repeats": 50}},
}


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def make_config(preset: str | None = None, config: str | Path | dict | None = None,
                dataset: str | Path | None = None) -> ReproduceConfig:
    """The config: ``preset`` (or the TOML's ``preset``), the TOML file or dict ``config`` over it,
    and ``dataset`` (a root to use instead of simulating). Strict keys, one-line errors naming the file."""
    from tdof20.formats.io import read_toml

    src = ""
    data: dict = {}
    if isinstance(config, dict):
        data = copy.deepcopy(config)
    elif config is not None:
        src = str(config)
        data = read_toml(config, "reproduce config")
    name = data.get("preset", preset or "smoke")
    if preset is not None and "preset" in data and data["preset"] != preset:
        raise TdofError(f"names preset '{data['preset']}' but --preset {preset} was given", src or None)
    if name not in PRESETS:
        raise TdofError(f"preset must be one of {', '.join(PRESETS)}, got '{name}'", src or None)
    merged = _merge(PRESETS[name], data)
    merged["preset"] = name
    if dataset is not None:
        merged["dataset"] = str(Path(dataset).resolve())
    options = merged.pop("method_options", {})
    cfg = config_from_data(ReproduceConfig, merged, src)
    if not isinstance(options, dict) or any(not isinstance(v, dict) for v in options.values()):
        raise TdofError("method_options must hold one table per method ([method_options.ffb6d] ...)", src or None)
    bad = sorted(set(options) - set(METHODS))
    if bad:
        raise TdofError(f"unknown method_options.{bad[0]} (known: {', '.join(METHODS)})", src or None)
    from tdof20.methods.registry import get_method

    for m, table in options.items():
        try:
            get_method(m).config_from(table, "")  # strict keys, typed values: the method's own check
        except TdofError as e:
            raise TdofError(f"method_options.{m}: {e}", src or None) from None
    cfg.method_options = json.loads(json.dumps(options))
    return cfg


def config_data(cfg: ReproduceConfig) -> dict:
    """The config as plain JSON types (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def config_digest(cfg: ReproduceConfig) -> str:
    """sha256 of the config's canonical JSON (the device left out: it changes no result's meaning)."""
    d = config_data(cfg)
    d.pop("device", None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


def _flat(d: Any, prefix: str = "") -> dict:
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else k))
        return out
    return {prefix: d}


def changed_keys(old: dict, new: dict) -> list[str]:
    """The dotted option names whose values differ between two configs' data (device ignored)."""
    a, b = _flat(old), _flat(new)
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and k != "device")


# --------------------------------------------------------------------------------------------
# the adapter: the only calls into training, prediction, scoring and profiling


def train_run(root: Path, split: str, run: Path, method: str, cfg: ReproduceConfig, epochs: int,
              show: bool, **options) -> Path:
    from tdof20.methods.train import train

    t = cfg.train
    mcfg = cfg.method_options.get(method)
    if "vector_origin" in options:  # a method option, not a shortcut of train()
        mcfg = {**(mcfg or {}), "vector_origin": options.pop("vector_origin")}
    return train(root, split, run, method=method, method_config=mcfg, image_size=tuple(t.image_size), batch_size=t.batch_size,
                 epochs=int(epochs), lr=t.lr, max_steps=t.max_steps or None, num_workers=t.num_workers, seed=t.seed,
                 device=cfg.device, progress=show, **options)


def predict_run(run: Path, root: Path, split: str, out_csv: Path, cfg: ReproduceConfig, show: bool,
                **options) -> dict:
    from tdof20.formats.io import read_json
    from tdof20.methods.predict import info_path, predict

    for p in (out_csv, info_path(out_csv)):  # a rerun of an interrupted prediction starts afresh
        if p.exists():
            p.unlink()
    predict(run, root, split, out_csv, device=cfg.device, num_workers=cfg.train.num_workers, seed=cfg.train.seed,
            progress=show, **options)
    return read_json(info_path(out_csv))


def score_run(results_csv: Path, root: Path, split: str) -> dict:
    from tdof20.benchmark.scoring import evaluate
    from tdof20.benchmark.tables import curves_from_evaluation

    ev = evaluate(results_csv, root, split, metrics="add,proj")
    return {**ev.summary(), "curves": curves_from_evaluation(ev), "warnings": list(ev.warnings)}


def profile_methods(methods: tuple[str, ...], cfg: ReproduceConfig) -> list[dict]:
    from tdof20.methods.profile import profile_method

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
        from tdof20.formats.io import read_json

        self.path = out / STATE
        self.cfg_data = config_data(cfg)
        digest = config_digest(cfg)
        if self.path.exists():
            d = read_json(self.path, "reproduce state")
            if not isinstance(d, dict) or d.get("format") != FORMAT:
                raise TdofError("is not a reproduce state file", self.path)
            if d.get("digest") != digest:
                keys = changed_keys(d.get("config") or {}, self.cfg_data)
                old, new = _flat(d.get("config") or {}), _flat(self.cfg_data)
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
        from tdof20.formats.io import write_json

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


@dataclass
class Job:
    name: str            # "train/pvnet/simple"
    stage: str           # dataset | train | predict | score | profile | tables
    run: Callable[[], dict]


def _sim_dataset(out: Path, cfg: ReproduceConfig, show: bool) -> Path:
    from tdof20.benchmark.dataset import build_dataset
    from tdof20.capture import run_capture, sim_config
    from tdof20.sim.scenes import normalize_scene_id
    from tdof20.sim.truth import oracle_scene

    d = cfg.data
    scenes = [normalize_scene_id(s) for s in d.scenes]
    if len(set(scenes)) != len(scenes):
        raise TdofError(f"data.scenes names a scene twice: {', '.join(scenes)}")
    labelled = []
    for s in scenes:
        raw = out / "raw" / s.replace("/", "_")
        lab = out / "labels" / s.replace("/", "_")
        if lab.exists() and not (lab / "scene_info.json").exists():
            import shutil

            shutil.rmtree(lab)  # oracle labels interrupted before their scene_info.json: made again
        run_capture(sim_config(s, steps=d.steps, step_deg=d.step_deg, n_arms=d.n_arms, width=d.width,
                               height=d.height, seed=d.seed), raw, yes=True, show_progress=show,
                    resume_command=f"tdof20 reproduce --out {out} (the same options)")
        labelled.append(oracle_scene(raw, lab, show_progress=show))
    root = out / "dataset"
    build_dataset(labelled, root, show_progress=show)
    return root


def _runs(cfg: ReproduceConfig) -> list[dict]:
    """Every training: {"name", "method", "split", "options"} (the main runs, then the ablations')."""
    runs = [{"name": f"{m}_{p}", "method": m, "split": p, "options": {}, "epochs": getattr(cfg.epochs, m)}
            for m in cfg.methods for p in cfg.protocols]
    if "hff6dof" in cfg.methods and cfg.ablations.voting_3d:  # the paper's pose recovery, its own targets
        runs += [{"name": f"hff6dof-3d_{p}", "method": "hff6dof", "split": p, "options": {"vector_origin": "observed"},
                  "epochs": cfg.epochs.hff6dof} for p in cfg.protocols]
    for k in cfg.ablations.fuse_stages:
        if k != 3:  # 3 is the main hard run
            runs.append({"name": f"hff6dof_fuse{k}_hard", "method": "hff6dof", "split": "hard",
                         "options": {"fuse_stages": k}, "epochs": cfg.epochs.hff6dof})
    if cfg.ablations.segmentation:
        runs.append({"name": "hff6dof_noseg_hard", "method": "hff6dof", "split": "hard",
                     "options": {"seg_head": False}, "epochs": cfg.epochs.hff6dof})
    return runs


def _predictions(cfg: ReproduceConfig) -> list[dict]:
    """Every prediction: {"name", "run", "label", "method", "split", "options", "role"}."""
    out = []
    for r in _runs(cfg):
        base = {"run": r["name"], "method": r["method"], "split": r["split"]}
        if r["name"] == f"{r['method']}_{r['split']}":
            out.append({**base, "name": r["name"], "label": LABELS[r["method"]], "options": {}, "role": "main"})
        elif r["name"] == f"hff6dof-3d_{r['split']}":
            out.append({**base, "name": r["name"], "label": LABELS["hff6dof-3d"], "options": {"voting": "3d"},
                        "role": "main"})
        elif "fuse_stages" in r["options"]:
            k = r["options"]["fuse_stages"]
            out.append({**base, "name": r["name"], "label": f"HFF6DoF {k} fused", "options": {}, "role": f"fuse{k}"})
        else:
            out.append({**base, "name": r["name"], "label": "HFF6DoF without segmentation head", "options": {},
                        "role": "noseg"})
    return out


def _entries(out: Path, cfg: ReproduceConfig, state: State):
    """The tables' inputs from the scores written: (entries, fusion, seg_on, seg_off, objects)."""
    from tdof20.benchmark.tables import Entry
    from tdof20.formats.io import read_json

    entries, fusion, seg_on, seg_off = [], {}, None, None
    for p in _predictions(cfg):
        f = out / "scores" / f"{p['name']}.json"
        if not f.exists():
            continue
        s = read_json(f)
        e = Entry(p["label"], p["method"], p["split"], s, oracle_masks=bool(s.get("oracle_masks")),
                  note=s.get("note", ""))
        if p["role"] == "main":
            entries.append(e)
            if p["method"] == "hff6dof" and p["split"] == "hard" and p["name"] == "hff6dof_hard":
                if 3 in cfg.ablations.fuse_stages:
                    fusion[3] = e
                seg_on = e
        elif p["role"].startswith("fuse"):
            fusion[int(p["role"][4:])] = e
        else:
            seg_off = e
    return entries, fusion, (seg_on if cfg.ablations.segmentation else None), seg_off


def _objects(root: Path) -> dict:
    from tdof20.benchmark.scoring import DatasetView
    from tdof20.benchmark.tables import models_info_objects

    ds = DatasetView(root)
    return models_info_objects(ds.models_info, {int(o): ds.object_name(int(o)) for o in ds.models_info})


def _header(cfg: ReproduceConfig, root: Path, state: State) -> list[str]:
    d = cfg.data
    src = (f"the given dataset {cfg.dataset}" if cfg.dataset else
           f"simulated: {len(d.scenes)} scenes ({', '.join(d.scenes)}), {d.n_arms} arm positions x {d.steps} steps "
           f"of {d.step_deg:g} deg at {d.width}x{d.height}, oracle labels")
    secs = sum(j.get("seconds", 0.0) for j in state.data["jobs"].values())
    ep = ", ".join(f"{m} {getattr(cfg.epochs, m)}" for m in cfg.methods)
    return [f"# tdof20 reproduce — preset {cfg.preset}", "",
            f"Dataset: {src} ({root}). Training: {cfg.train.image_size[0]}x{cfg.train.image_size[1]}, batch "
            f"{cfg.train.batch_size}, epochs {ep}" + (f", at most {cfg.train.max_steps} optimiser step(s) per run"
                                                     if cfg.train.max_steps else "") + f"; device {cfg.device}.",
            f"Work so far: {secs:.0f} s over {len(state.data['jobs'])} jobs (DIR/reproduce.json)."]


def reproduce(out: str | Path, preset: str | None = None, config: str | Path | dict | None = None,
              dataset: str | Path | None = None, progress: bool = True) -> Path:
    """Run (or resume) the reproduction into ``out``; returns DIR/tables/tables.md. See the module
    docstring for the stages, presets and resume rules."""
    from tdof20.benchmark.tables import write_tables
    from tdof20.formats.io import read_json, write_json

    cfg = make_config(preset, config, dataset)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise TdofError("--out is a file, not a folder", out)
    if cfg.dataset:
        from tdof20.formats.dataset import open_dataset

        open_dataset(cfg.dataset)  # the one "not a dataset" check, before anything is written
    else:
        from tdof20.sim.scenes import normalize_scene_id

        for s in cfg.data.scenes:
            normalize_scene_id(s)  # unknown scene names stop here
    state = State(out, cfg)
    root = Path(cfg.dataset) if cfg.dataset else out / "dataset"
    jobs: list[Job] = []

    def dataset_job() -> dict:
        if cfg.dataset:
            return {"root": str(root), "given": True}
        _sim_dataset(out, cfg, progress)
        return {"root": str(root), "given": False}

    jobs.append(Job("dataset", "dataset", dataset_job))
    for r in _runs(cfg):
        def train_job(r=r) -> dict:
            run = out / "runs" / r["name"]
            train_run(root, r["split"], run, r["method"], cfg, r["epochs"], progress, **r["options"])
            hist = run / "history.json"
            last = (read_json(hist).get("epochs") or [{}])[-1] if hist.exists() else {}
            return {"run": str(run), "last_loss": last.get("loss")}
        jobs.append(Job(f"train/{r['name']}", "train", train_job))
    for p in _predictions(cfg):
        def predict_job(p=p) -> dict:
            csv = out / "results" / f"{p['name']}.csv"
            csv.parent.mkdir(parents=True, exist_ok=True)
            info = predict_run(out / "runs" / p["run"], root, p["split"], csv, cfg, progress, **p["options"])
            return {"results": str(csv), "masks": info.get("masks"), "predictions": info.get("predictions")}

        def score_job(p=p) -> dict:
            csv = out / "results" / f"{p['name']}.csv"
            masks = state.get(f"predict/{p['name']}").get("masks")
            s = score_run(csv, root, p["split"])
            s["oracle_masks"] = masks == "gt"
            s["method"], s["label"], s["split"] = p["method"], p["label"], p["split"]
            if p["options"].get("voting") == "3d":
                s["note"] = ("the paper's pose recovery: 3D voting on the back-projected input depth + least squares, "
                             "trained with vectors from those observed points")
            f = out / "scores" / f"{p['name']}.json"
            f.parent.mkdir(parents=True, exist_ok=True)
            write_json(f, s)
            return {"scores": str(f), "add_s": s["mean"].get("add_s"), "proj2d": s["mean"].get("proj2d"),
                    "oracle_masks": s["oracle_masks"]}
        jobs.append(Job(f"predict/{p['name']}", "predict", predict_job))
        jobs.append(Job(f"score/{p['name']}", "score", score_job))
    if cfg.profile.enabled:
        def profile_job() -> dict:
            recs = profile_methods(tuple(cfg.methods), cfg)
            write_json(out / "profile.json", recs)
            return {"profile": str(out / "profile.json")}
        jobs.append(Job("profile", "profile", profile_job))

    todo = [j for j in jobs if not state.done(j.name)]
    console.print(f"reproduce ({cfg.preset}) -> {out}: {len(jobs)} jobs, {len(jobs) - len(todo)} done already",
                  highlight=False) if progress else None
    with progress_bar(progress, unit="job") as bar:
        task = bar.add_task("reproduce", total=len(jobs), completed=len(jobs) - len(todo))
        for j in todo:
            bar.update(task, description=f"reproduce: {j.name}")
            t0 = time.perf_counter()
            info = j.run()
            state.finish(j.name, time.perf_counter() - t0, stage=j.stage, **info)
            bar.advance(task)

    # tables (always rebuilt from what is on disk: cheap)
    entries, fusion, seg_on, seg_off = _entries(out, cfg, state)
    profiles = read_json(out / "profile.json") if (out / "profile.json").exists() else []
    paths = write_tables(out / "tables", entries, profiles, fusion or None, seg_on, seg_off, _objects(root),
                         header=_header(cfg, root, state))
    if progress:
        console.print(f"tables: {paths['tables.md']}")
    return paths["tables.md"]


__all__ = ["AblationConfig", "DataConfig", "EpochsConfig", "LABELS", "METHODS", "PRESETS", "ProfileConfig",
           "ReproduceConfig", "State", "changed_keys", "config_data", "config_digest", "make_config",
           "predict_run", "profile_methods", "reproduce", "score_run", "train_run", "validation_images"]
