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

Train / predict / score / profile go through the small adapter functions below
(:func:`train_run`, :func:`predict_run`, :func:`score_run`, :func:`profile_methods`): the method
registry's loops (:mod:`tdof20.methods.train`, :mod:`tdof20.methods.predict`). :func:`plan` counts
what a config asks for and :func:`estimate` multiplies it by measured unit times
(``benchmarks/methods_profile.py --estimate PRESET``).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from tdof20.dataset.splits import validation_images  # noqa: F401  (re-exported: the rules live in splits)
from tdof20.config import ConfigError, check_ranges, config_from_data
from tdof20.errors import TdofError
from tdof20.progress import console, progress as progress_bar

METHODS = ("pvnet", "densefusion", "ffb6d", "hff6dof")
LABELS = {"pvnet": "PVNet", "densefusion": "DenseFusion", "ffb6d": "FFB6D", "hff6dof": "HFF6DoF (bearing + PnP)",
          "hff6dof-3d": "HFF6DoF (3D voting + LSQ)"}
PROTOCOLS = ("simple", "hard")
SELECT_EPOCHS = ("best", "last")
#: the prediction-time options [candidates.<method>] may list, per method: options that change no
#: weight (the input depth mode a trained network is fed, voting thresholds, sizes of the pose
#: recovery). HFF6DoF's voting is not among them: its two pose recoveries are two rows of the
#: tables, and which one stands for HFF6DoF in the agreement claims is itself chosen on validation.
CHOICE_OPTIONS = {
    "hff6dof": ("depth_mode", "min_pixels", "max_points", "n_hyp", "inlier_cos", "bearing_tol"),
    "pvnet": ("min_pixels", "inlier_cos", "vote_max_pixels", "min_inlier_ratio", "n_hyp", "max_rounds"),
    "densefusion": ("depth_mode", "refine_iterations", "min_points"),
    "ffb6d": ("depth_mode", "bandwidth_mm", "min_points", "max_votes"),
}
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
        check_ranges(self, "data", positive=("steps", "step_deg", "n_arms", "width", "height"),
                     non_negative=("seed",))
        if not self.scenes:
            raise ConfigError("data.scenes must not be empty")
        from tdof20.dataset.naming import normalize_scene_id

        try:
            names = [normalize_scene_id(s) for s in self.scenes]
        except TdofError as e:
            raise ConfigError(f"data.scenes: {e}") from None
        if len(set(names)) != len(names):
            raise ConfigError(f"data.scenes names a scene twice: {list(self.scenes)}")
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
        check_ranges(self, "train", positive=("image_size", "batch_size", "lr"),
                     non_negative=("max_steps", "num_workers", "seed"))
        from tdof20.methods.train import IMAGE_SIDE

        if not all(IMAGE_SIDE[0] <= v <= IMAGE_SIDE[1] for v in self.image_size):
            raise ConfigError(f"train.image_size must be within {IMAGE_SIDE[1]} pixels a side and at least "
                              f"{IMAGE_SIDE[0]}, got {list(self.image_size)}")


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
class SelectConfig:
    """[select]: what is chosen on the validation part (never on the test part).

    epochs: "best" keeps, of each training, the checkpoint of the epoch that scores best on
    validation; "last" keeps the last one (no validation of epochs). every: validate every N-th
    epoch (and the last one). max_images: validate on at most this many validation images of a
    protocol, evenly spaced over the part (0 = all). The score that decides is the mean ADD(S) over
    objects, ties broken by the mean 2D projection accuracy, then by the earlier epoch / the
    candidate listed first."""

    epochs: str = "best"
    every: int = 1
    max_images: int = 0

    def __post_init__(self) -> None:
        if self.epochs not in SELECT_EPOCHS:
            raise ConfigError(f"select.epochs must be one of {', '.join(SELECT_EPOCHS)}, got '{self.epochs}'")
        check_ranges(self, "select", positive=("every",), non_negative=("max_images",))


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
    select: SelectConfig = field(default_factory=SelectConfig)
    #: [method_options.<method>]: options of that method's config (checked by it), e.g. ffb6d n_points
    method_options: dict = field(default_factory=dict)
    #: [candidates.<method>]: option = [values, ...] of the prediction-time options chosen on
    #: validation (:data:`CHOICE_OPTIONS`); the first value of each list is the default
    candidates: dict = field(default_factory=dict)

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

#: the prediction-time choices of the cpu, gpu and full presets (the first value is the default)
CANDIDATES = {"hff6dof": {"depth_mode": ["filled", "raw"], "bearing_tol": [0.02, 0.04]},
              "pvnet": {"inlier_cos": [0.99, 0.97]},
              "densefusion": {"refine_iterations": [2, 0]},
              "ffb6d": {"bandwidth_mm": [40.0, 20.0]}}

#: the presets, as TOML-like data over the defaults
PRESETS: dict[str, dict] = {
    "smoke": {"data": {"scenes": ["single/juice_cup_340", "single/handle_cup_280", "multi/08", "multi/01"],
                       "steps": 6, "step_deg": 5.0, "n_arms": 4, "width": 80, "height": 60},
              "train": {"image_size": [32, 48], "batch_size": 4, "lr": 2e-3, "max_steps": 6},
              "epochs": {m: 1 for m in METHODS},
              "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
              "profile": {"height": 120, "width": 160, "repeats": 1},
              "method_options": {"ffb6d": {"n_points": 512, "meanshift_iters": 30, "max_votes": 500},
                                 "densefusion": {"n_points": 128, "crop_size": 48}}},
    "cpu": {"data": {"scenes": list(ALL_SCENES), "steps": 12, "step_deg": 30.0, "n_arms": 4, "width": 160,
                     "height": 120},
            "train": {"image_size": [96, 128], "batch_size": 4, "lr": 1e-3},
            "epochs": {"hff6dof": 8, "pvnet": 8, "densefusion": 4, "ffb6d": 4},
            "method_options": {"ffb6d": {"n_points": 2048}, "densefusion": {"n_points": 500, "crop_size": 64}},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 240, "width": 320, "repeats": 3},
            "select": {"epochs": "best", "every": 2, "max_images": 200},
            "candidates": CANDIDATES},
    "gpu": {"data": {"scenes": list(ALL_SCENES), "steps": 60, "step_deg": 6.0, "n_arms": 4, "width": 640,
                     "height": 480},
            "train": {"image_size": [240, 320], "batch_size": 8, "lr": 1e-3, "num_workers": 8},
            "epochs": {"hff6dof": 20, "pvnet": 20, "densefusion": 10, "ffb6d": 10},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 480, "width": 640, "repeats": 20},
            "select": {"epochs": "best", "every": 5, "max_images": 300},
            "candidates": CANDIDATES},
    "full": {"data": {"scenes": list(ALL_SCENES), "steps": 400, "step_deg": 0.9, "n_arms": 4, "width": 640,
                      "height": 480},
             "train": {"image_size": [480, 640], "batch_size": 8, "lr": 1e-3, "num_workers": 8},
             "epochs": {"hff6dof": 100, "pvnet": 100, "densefusion": 50, "ffb6d": 50},
             "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
             "profile": {"height": 480, "width": 640, "repeats": 50},
             "select": {"epochs": "best", "every": 10, "max_images": 1000},
             "candidates": CANDIDATES},
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
    candidates = merged.pop("candidates", {})
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
    cfg.candidates = check_candidates(candidates, src)
    return cfg


def check_candidates(candidates: Any, src: str = "") -> dict:
    """[candidates.<method>] option = [values]: each option one of :data:`CHOICE_OPTIONS`, each list
    non-empty without repeats, each value one the method's config accepts (restored depth, derived
    from the ground truth, is no candidate). Returns the tables as plain JSON types."""
    from tdof20.methods.registry import get_method

    where = src or None
    if not isinstance(candidates, dict) or any(not isinstance(v, dict) for v in candidates.values()):
        raise TdofError("candidates must hold one table per method ([candidates.hff6dof] ...)", where)
    bad = sorted(set(candidates) - set(METHODS))
    if bad:
        raise TdofError(f"unknown candidates.{bad[0]} (known: {', '.join(METHODS)})", where)
    out: dict = {}
    for m, table in candidates.items():
        for opt, values in table.items():
            key = f"candidates.{m}.{opt}"
            if opt not in CHOICE_OPTIONS[m]:
                raise TdofError(f"{key}: not an option chosen on validation (for {m}: "
                                f"{', '.join(CHOICE_OPTIONS[m])})", where)
            if not isinstance(values, list) or not values:
                raise TdofError(f"{key} must be a non-empty list of values, got {values!r}", where)
            if len({json.dumps(v) for v in values}) != len(values):
                raise TdofError(f"{key} lists a value twice: {values}", where)
            if opt == "depth_mode" and "restored" in values:
                raise TdofError(f"{key}: 'restored' depth is derived from the ground truth (an upper bound, never "
                                "a submission): it is no candidate", where)
            for v in values:
                try:
                    get_method(m).config_from({opt: v}, "")
                except TdofError as e:
                    raise TdofError(f"{key}: {e}", where) from None
            out.setdefault(m, {})[opt] = json.loads(json.dumps(values))
    return out


def config_data(cfg: ReproduceConfig) -> dict:
    """The config as plain JSON types (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def config_digest(cfg: ReproduceConfig) -> str:
    """sha256 of the config's canonical JSON (the device left out: it changes no result's meaning;
    with a given dataset, the simulated scenes' settings too: they are not used)."""
    d = config_data(cfg)
    d.pop("device", None)
    if d.get("dataset"):
        d.pop("data", None)
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
              show: bool, stop_epoch: int | None = None, **options) -> Path:
    """Train (or continue) ``run`` on the train part minus the validation part of ``split``, for
    ``epochs`` epochs in all; with ``stop_epoch`` the call ends after that epoch (the schedule still
    spans ``epochs``)."""
    from tdof20.methods.train import train

    t = cfg.train
    mcfg = cfg.method_options.get(method)
    if "vector_origin" in options:  # a method option, not a shortcut of train()
        mcfg = {**(mcfg or {}), "vector_origin": options.pop("vector_origin")}
    return train(root, split, run, method=method, method_config=mcfg, image_size=tuple(t.image_size), batch_size=t.batch_size,
                 epochs=int(epochs), lr=t.lr, max_steps=t.max_steps or None, num_workers=t.num_workers, seed=t.seed,
                 device=cfg.device, progress=show, part="train-val", stop_epoch=stop_epoch, **options)


def predict_run(run: Path, root: Path, split: str, out_csv: Path, cfg: ReproduceConfig, show: bool,
                part: str = "test", images: list[tuple[int, int]] | None = None, **options) -> dict:
    """Predict ``part`` ('test' or 'val'; ``images``: these validation images only) of ``split`` with
    the run folder ``run`` into ``out_csv`` (+ ``_info.json``); ``options``: the method's prediction
    options (its config's names). Returns the summary."""
    from tdof20.dataset.results import write_results_csv
    from tdof20.formats.io import read_json, write_json
    from tdof20.methods.predict import info_path, predict, predict_rows

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
    from tdof20.scoring.scoring import evaluate
    from tdof20.experiments.tables import curves_from_evaluation

    if part == "val":
        if targets is None:
            raise TdofError("scoring the validation part needs its targets file")
        ev = evaluate(results_csv, root, None, targets=targets, metrics="add,proj")
    else:
        ev = evaluate(results_csv, root, split, metrics="add,proj")
    return {**ev.summary(), "curves": curves_from_evaluation(ev), "warnings": list(ev.warnings), "part": part}


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


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (data-loader workers): a job's work on
    a machine shared with other jobs, where its wall time says little."""
    import resource

    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


@dataclass
class Job:
    name: str            # "train/pvnet/simple"
    stage: str           # dataset | train | predict | score | profile | tables
    run: Callable[[], dict]


def _sim_dataset(out: Path, cfg: ReproduceConfig, show: bool) -> Path:
    from tdof20.dataset.build import build_dataset
    from tdof20.capture import run_capture, sim_config
    from tdof20.dataset.naming import normalize_scene_id
    from tdof20.sim.truth import oracle_scene

    d = cfg.data
    scenes = [normalize_scene_id(s) for s in d.scenes]  # known and distinct: DataConfig checked them
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


def _grid(cfg: ReproduceConfig, p: dict) -> list[dict]:
    """The candidate option sets of a main prediction ``p`` ([candidates.<method>], the product of
    its lists in the order given; the first set is the default), without the options that do not
    act on the row (HFF6DoF: bearing_tol only with bearing voting, inlier_cos only with 3D voting).
    [{}] when nothing is listed."""
    table = dict(cfg.candidates.get(p["method"], {}))
    if p["method"] == "hff6dof":
        table.pop("bearing_tol" if p["options"].get("voting") == "3d" else "inlier_cos", None)
    keys = list(table)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(table[k] for k in keys))]


def _source(cfg: ReproduceConfig, p: dict) -> dict:
    """The main prediction whose chosen options ``p`` uses: itself, or for the ablations' runs
    HFF6DoF's main run on hard (the ablations change only the fusion or the head)."""
    if p["role"] == "main":
        return p
    return next(q for q in _predictions(cfg) if q["name"] == "hff6dof_hard")


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
            from tdof20.dataset.validation import part_images

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
        from tdof20.dataset.validation import val_targets
        from tdof20.formats.io import write_json

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
    from tdof20.formats.io import read_json

    h = read_json(run / "history.json")
    ep = h.get("epochs") or [{}]
    return {"step": int(h.get("steps", 0)), "epoch": int(ep[-1].get("epoch", 0)),
            "ended": int(h.get("steps", 0)) >= int(h.get("total_steps", h.get("steps", 0))),
            "loss": ep[-1].get("loss")}


KEPT = "kept"


def _keep(run: Path, step: int) -> Path:
    """Copy the run's current weights (at ``step``) into RUN/kept/ (config.json + last.pt with the
    weights only): a run folder predict reads. Refused when the checkpoint is not at ``step``."""
    import shutil

    import torch

    from tdof20.formats.io import read_json, write_json
    from tdof20.methods.train import read_checkpoint

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


def _validated_epochs(cfg: ReproduceConfig, epochs: int) -> list[int]:
    if cfg.select.epochs != "best" or epochs < 2:
        return [epochs]
    every = cfg.select.every
    return sorted(set(range(every, epochs + 1, every)) | {epochs})


def _train_and_keep(out: Path, root: Path, cfg: ReproduceConfig, r: dict, default_options: dict,
                    val: Validation, show: bool) -> dict:
    """Train run ``r`` on train minus val, epoch by epoch where epochs are chosen: after each
    validated epoch its checkpoint is predicted and scored on validation (with ``default_options``)
    and the best one is copied to RUN/kept/. Resumable at any point."""
    run = out / "runs" / r["name"]
    marks = _validated_epochs(cfg, r["epochs"])
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


# --------------------------------------------------------------------------------------------
# what a config costs: counted (plan) and multiplied out from measured unit times (estimate)


def _part_counts(cfg: ReproduceConfig) -> dict:
    """{split: {"train-val", "val", "test"}} image counts of the config's data, from the split rules
    (simulated scenes) or the given dataset, without building anything."""
    from tdof20.dataset.splits import VAL_PART, part_of
    from tdof20.dataset.naming import normalize_scene_id, scene_number

    out = {p: {"train-val": 0, "val": 0, "test": 0} for p in cfg.protocols}
    if cfg.dataset:
        from tdof20.dataset.validation import part_images

        for p in cfg.protocols:
            for part in out[p]:
                out[p][part] = len(part_images(cfg.dataset, p, part))
        return out
    d = cfg.data
    for s in d.scenes:
        sid = scene_number(normalize_scene_id(s))
        for im in range(d.n_arms * d.steps):
            for p in cfg.protocols:
                part = part_of(p, sid, im, d.steps, d.n_arms, with_val=True)
                if part is not None:
                    out[p][{"train": "train-val", VAL_PART: "val"}.get(part, part)] += 1
    return out


def plan(cfg: ReproduceConfig) -> dict:
    """What ``cfg`` asks for, counted without running anything: {"frames" (simulated RGB-D pairs,
    both phases), "parts" (:func:`_part_counts`), "runs": [{"name", "method", "split", "images",
    "steps", "epochs", "val_predictions", "val_images", "test_images"}]}. Validation predictions are
    an upper bound (figures shared between the choices are counted once each)."""
    parts = _part_counts(cfg)
    preds = {p["run"]: p for p in _predictions(cfg)}
    runs = []
    for r in _runs(cfg):
        n = parts[r["split"]]["train-val"]
        bs = min(cfg.train.batch_size, max(1, n))
        spe = max(1, n // bs)
        steps = r["epochs"] * spe
        if cfg.train.max_steps:
            steps = min(steps, cfg.train.max_steps)
        p = preds[r["name"]]
        marks = _validated_epochs(cfg, r["epochs"])
        n_val = (len(marks) if len(marks) > 1 and steps > spe else 0)
        grid = _grid(cfg, p) if p["role"] == "main" else [{}]
        n_val += len(grid) if len(grid) > 1 else 0
        if p["method"] == "hff6dof" and p["role"] == "main" and cfg.ablations.voting_3d:
            n_val += 1  # the formulation's figure (usually shared with the choices above)
        vi = parts[r["split"]]["val"]
        runs.append({"name": r["name"], "method": r["method"], "split": r["split"], "images": n, "steps": steps,
                     "epochs": r["epochs"], "val_predictions": n_val,
                     "val_images": min(vi, cfg.select.max_images) if cfg.select.max_images else vi,
                     "test_images": parts[r["split"]]["test"]})
    d = cfg.data
    frames = 0 if cfg.dataset else 2 * len(d.scenes) * d.n_arms * d.steps
    return {"frames": frames, "parts": parts, "runs": runs}


def estimate(cfg: ReproduceConfig, step_s: dict, image_s: dict, frame_s: float = 0.0,
             profile_s: float = 0.0) -> dict:
    """Multiply :func:`plan` out: ``step_s`` {method: seconds per optimiser step at the config's
    image size and batch}, ``image_s`` {method: seconds per predicted image (input + network + pose
    recovery)}, ``frame_s`` seconds per simulated frame (capture + labels + dataset build),
    ``profile_s`` seconds for Table 3. Returns {"total_s", "dataset_s", "train_s", "val_s", "test_s",
    "profile_s", "per_run": [...], "plan"}."""
    pl = plan(cfg)
    per_run, tr, va, te = [], 0.0, 0.0, 0.0
    for r in pl["runs"]:
        t = r["steps"] * step_s[r["method"]]
        v = r["val_predictions"] * r["val_images"] * image_s[r["method"]]
        x = r["test_images"] * image_s[r["method"]]
        tr, va, te = tr + t, va + v, te + x
        per_run.append({**r, "train_s": round(t, 1), "val_s": round(v, 1), "test_s": round(x, 1)})
    ds = pl["frames"] * frame_s
    return {"total_s": round(ds + tr + va + te + profile_s, 1), "dataset_s": round(ds, 1), "train_s": round(tr, 1),
            "val_s": round(va, 1), "test_s": round(te, 1), "profile_s": round(profile_s, 1), "per_run": per_run,
            "plan": pl}


def _entries(out: Path, cfg: ReproduceConfig, state: State):
    """The tables' inputs from the scores written: (entries, fusion, seg_on, seg_off); the HFF6DoF
    row chosen on validation to stand for HFF6DoF in the agreement claims carries extra["primary"]."""
    from tdof20.experiments.tables import Entry
    from tdof20.formats.io import read_json

    entries, fusion, seg_on, seg_off = [], {}, None, None
    for p in _predictions(cfg):
        f = out / "scores" / f"{p['name']}.json"
        if not f.exists():
            continue
        s = read_json(f)
        form = f"choose/formulation/{p['split']}"
        primary = state.done(form) and state.get(form).get("primary") == p["name"]
        e = Entry(p["label"], p["method"], p["split"], s, oracle_masks=bool(s.get("oracle_masks")),
                  note=s.get("note", ""), extra={"primary": True} if primary else {})
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
    from tdof20.scoring.scoring import DatasetView
    from tdof20.experiments.tables import models_info_objects

    ds = DatasetView(root)
    return models_info_objects(ds.models_info, {int(o): ds.object_name(int(o)) for o in ds.models_info})


def _pcts(f: dict) -> str:
    a, b = f.get("add_s"), f.get("proj2d")
    return f"{'—' if a is None else f'{100 * a:.1f}'} / {'—' if b is None else f'{100 * b:.1f}'} %"


def _opts_text(options: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in options.items()) or "defaults"


def choices(cfg: ReproduceConfig, state: State) -> list[dict]:
    """What was chosen on validation, per result (and the HFF6DoF formulation per protocol), with
    the validation figures behind each choice: [{"result", "choice", "chosen", "validation"}]."""
    rows = []
    for p in _predictions(cfg):
        t = f"train/{p['run']}"
        if state.done(t):
            j = state.get(t)
            val = j.get("validation") or []
            if val:
                rows.append({"result": p["name"], "choice": "epoch",
                             "chosen": f"epoch {j['kept_epoch']} of {j['epochs']} (step {j['kept_step']})",
                             "validation": "; ".join(f"epoch {f['epoch']}: {_pcts(f)}" for f in val)})
        c = f"choose/{_source(cfg, p)['name']}"
        if state.done(c) and state.get(c).get("validation"):
            j = state.get(c)
            fixed = set(p["options"])
            rows.append({"result": p["name"], "choice": "options" if p["role"] == "main" else
                         f"options (those of {_source(cfg, p)['name']})",
                         "chosen": _opts_text({k: v for k, v in j["options"].items() if k not in fixed}),
                         "validation": "; ".join(_opts_text({k: v for k, v in f["options"].items() if k not in fixed})
                                                 + f": {_pcts(f)}" for f in j["validation"])})
    for split in cfg.protocols:
        c = f"choose/formulation/{split}"
        if state.done(c):
            j = state.get(c)
            rows.append({"result": f"HFF6DoF · {split}", "choice": "pose recovery standing for HFF6DoF "
                         "(agreement claims)", "chosen": LABELS[j["primary"].split("_")[0]],
                         "validation": "; ".join(f"{LABELS[n.split('_')[0]]}: {_pcts(f)}"
                                                 for n, f in j["validation"].items())})
    return rows


def _given_source(root: Path) -> str:
    """What a given dataset is, from its dataset_info.json: e.g. 'the given dataset, imported from
    the TDoF20 release at /data/TDoF20: 5 scenes, 3 objects'."""
    from tdof20.formats.io import read_json

    try:
        info = read_json(root / "dataset_info.json")
    except TdofError:
        return "the given dataset"
    origin = {"tdof20-release": "imported from the TDoF20 release"}
    src = origin.get(info.get("source"), "")
    src += f" at {info['source_path']}" if src and info.get("source_path") else ""
    counts = f"{len(info.get('scenes') or {})} scenes, {len(info.get('objects') or {})} objects"
    return f"the given dataset, {src}: {counts}" if src else f"the given dataset: {counts}"


def _header(cfg: ReproduceConfig, root: Path, state: State) -> list[str]:
    d = cfg.data
    src = (_given_source(root) if cfg.dataset else
           f"simulated: {len(d.scenes)} scenes ({', '.join(d.scenes)}), {d.n_arms} arm positions x {d.steps} steps "
           f"of {d.step_deg:g} deg at {d.width}x{d.height}, oracle labels")
    secs = sum(j.get("seconds", 0.0) for j in state.data["jobs"].values())
    cpu = sum(j.get("cpu_seconds", 0.0) for j in state.data["jobs"].values())
    ep = ", ".join(f"{m} {getattr(cfg.epochs, m)}" for m in cfg.methods)
    sel = cfg.select
    return [f"# tdof20 reproduce — preset {cfg.preset}", "",
            f"Dataset: {src} ({root}). Training: on each protocol's train part minus its validation part, "
            f"{cfg.train.image_size[0]}x{cfg.train.image_size[1]}, batch "
            f"{cfg.train.batch_size}, epochs {ep}" + (f", at most {cfg.train.max_steps} optimiser step(s) per run"
                                                     if cfg.train.max_steps else "") + f"; device {cfg.device}.",
            f"Choices on the validation part only (the test part is predicted once, with what was chosen): "
            f"epochs {'the validation-best' if sel.epochs == 'best' else 'the last'}"
            + (f" (every {sel.every} epochs)" if sel.epochs == "best" and sel.every > 1 else "")
            + f"; candidates {json.dumps(cfg.candidates) if cfg.candidates else 'none'}"
            + (f"; at most {sel.max_images} validation images per protocol" if sel.max_images else "") + ".",
            f"Work so far: {secs:.0f} s of wall time, {cpu:.0f} s of CPU, over {len(state.data['jobs'])} jobs "
            "(DIR/reproduce.json)."]


def reproduce(out: str | Path, preset: str | None = None, config: str | Path | dict | None = None,
              dataset: str | Path | None = None, progress: bool = True) -> Path:
    """Run (or resume) the reproduction into ``out``; returns DIR/tables/tables.md. See the module
    docstring for the stages, presets and resume rules."""
    from tdof20.experiments.tables import write_tables
    from tdof20.formats.io import read_json, write_json

    cfg = make_config(preset, config, dataset)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise TdofError("--out is a file, not a folder", out)
    if cfg.dataset:
        from tdof20.dataset.reader import open_dataset

        open_dataset(cfg.dataset)  # the one "not a dataset" check, before anything is written
    from tdof20.methods.train import select_device

    try:
        select_device(cfg.device)  # a device this machine lacks stops here, not after the dataset
    except TdofError as e:
        raise TdofError(str(e).replace("--device", "device", 1), config if isinstance(config, (str, Path)) else None) \
            from None
    state = State(out, cfg)
    root = Path(cfg.dataset) if cfg.dataset else out / "dataset"
    val = Validation(out, root, cfg, state, progress)
    preds = _predictions(cfg)
    by_run = {p["run"]: p for p in preds}
    jobs: list[Job] = []

    def dataset_job() -> dict:
        if cfg.dataset:
            return {"root": str(root), "given": True}
        _sim_dataset(out, cfg, progress)
        return {"root": str(root), "given": False}

    def kept(p: dict) -> dict:
        return state.get(f"train/{p['run']}")

    def options_of(p: dict) -> dict:
        """The options the test prediction of ``p`` uses: the row's own, and those chosen on validation."""
        src = _source(cfg, p)
        c = f"choose/{src['name']}"
        chosen = state.get(c)["options"] if state.done(c) else _grid(cfg, src)[0]
        return {**{k: v for k, v in chosen.items() if k not in p["options"]}, **p["options"]}

    def val_figure(p: dict) -> dict:
        """p's kept checkpoint with its chosen options, on validation (cached)."""
        k = kept(p)
        return val.figure(p["run"], Path(k["kept"]), p["split"], k["kept_step"], k["kept_epoch"], options_of(p))

    jobs.append(Job("dataset", "dataset", dataset_job))
    for r in _runs(cfg):
        def train_job(r=r) -> dict:
            p = by_run[r["name"]]
            src = _source(cfg, p)
            default = {**_grid(cfg, src)[0], **p["options"]}
            return _train_and_keep(out, root, cfg, r, default, val, progress)
        jobs.append(Job(f"train/{r['name']}", "train", train_job))
    for p in preds:
        grid = _grid(cfg, p) if p["role"] == "main" else [{}]
        if len(grid) > 1:
            def choose_job(p=p, grid=grid) -> dict:
                k = kept(p)
                figs, best = [], None
                for combo in grid:
                    f = val.figure(p["run"], Path(k["kept"]), p["split"], k["kept_step"], k["kept_epoch"],
                                   {**combo, **p["options"]})
                    figs.append({"options": f["options"], "add_s": f["add_s"], "proj2d": f["proj2d"]})
                    if _better(f, best):
                        best, chosen = f, combo
                return {"options": chosen, "validation": figs, "epoch": k["kept_epoch"]}
            jobs.append(Job(f"choose/{p['name']}", "choose", choose_job))
    for split in cfg.protocols:
        pair = [p for p in preds if p["name"] in (f"hff6dof_{split}", f"hff6dof-3d_{split}")]
        if len(pair) == 2:
            def formulation_job(pair=pair) -> dict:
                figs = {p["name"]: val_figure(p) for p in pair}
                best = None
                for name, f in figs.items():  # the default (bearing + PnP) first: it wins ties
                    if _better(f, best):
                        best, primary = f, name
                return {"primary": primary,
                        "validation": {n: {"add_s": f["add_s"], "proj2d": f["proj2d"]} for n, f in figs.items()}}
            jobs.append(Job(f"choose/formulation/{split}", "choose", formulation_job))
    for p in preds:
        def predict_job(p=p) -> dict:
            csv = out / "results" / f"{p['name']}.csv"
            csv.parent.mkdir(parents=True, exist_ok=True)
            opts = options_of(p)
            info = predict_run(Path(kept(p)["kept"]), root, p["split"], csv, cfg, progress, part="test", **opts)
            return {"results": str(csv), "masks": info.get("masks"), "predictions": info.get("predictions"),
                    "dropped_impossible_poses": info.get("dropped_impossible_poses", 0),
                    "run": kept(p)["kept"], "epoch": kept(p)["kept_epoch"], "options": opts}

        def score_job(p=p) -> dict:
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
                from tdof20.methods.train import drop_optimizer

                drop_optimizer(info["run"])
            bar.advance(task)

    # tables (always rebuilt from what is on disk: cheap)
    entries, fusion, seg_on, seg_off = _entries(out, cfg, state)
    profiles = read_json(out / "profile.json") if (out / "profile.json").exists() else []
    paths = write_tables(out / "tables", entries, profiles, fusion or None, seg_on, seg_off, _objects(root),
                         header=_header(cfg, root, state), choices=choices(cfg, state))
    if progress:
        console.print(f"tables: {paths['tables.md']}", markup=False)
    return paths["tables.md"]


__all__ = ["AblationConfig", "CANDIDATES", "CHOICE_OPTIONS", "DataConfig", "EpochsConfig", "LABELS", "METHODS",
           "PRESETS", "ProfileConfig", "ReproduceConfig", "SelectConfig", "State", "Validation", "changed_keys",
           "check_candidates", "choices", "estimate", "plan", "config_data", "config_digest", "make_config",
           "predict_run", "profile_methods", "reproduce", "score_run", "train_run", "validation_images"]
