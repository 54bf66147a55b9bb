"""What ``tdof20 reproduce`` runs: its typed config (a preset, a TOML over it) and the presets.

    cfg = make_config("smoke")                                # a preset
    cfg = make_config(config="my.toml", dataset="ROOT")       # a TOML over a preset; a given dataset

The methods' parts come from their registry records (:class:`~tdof20.methods.contract.ReproduceSettings`):
which methods run and in what order (:data:`METHODS`), their table labels (:data:`LABELS`), the
prediction-time options chosen on validation (:data:`CHOICE_OPTIONS`) and the values tried
(:data:`CANDIDATES`), the epochs of each preset (:class:`EpochsConfig`, ``[epochs]``) and a
preset's method options (``[method_options.<method>]``). Adding a method to reproduce is adding
its record: nothing here names one, except the paper's ablations of HFF6DoF ([ablations]).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tdof20.config import ConfigError, check_ranges, config_from_data
from tdof20.dataset.naming import normalize_scene_id
from tdof20.errors import TdofError
from tdof20.formats.io import read_toml
from tdof20.methods.base import IMAGE_SIDE
from tdof20.methods.registry import Method, get_method, methods


def reproduced_methods() -> list[Method]:
    """The registered methods in the tables' order (their records' ``reproduce.rank``, then the
    registration order)."""
    return sorted(methods(), key=lambda m: m.reproduce.rank)


METHODS = tuple(m.name for m in reproduced_methods())
#: each result row's label: a method's, and its variants' (``<method>-<suffix>``)
LABELS = {k: v for m in reproduced_methods()
          for k, v in [(m.name, m.reproduce.label)] + [(f"{m.name}-{s}", lab)
                                                       for s, lab in m.reproduce.variant_labels.items()]}
PROTOCOLS = ("simple", "hard")
SELECT_EPOCHS = ("best", "last")
#: the prediction-time options [candidates.<method>] may list, per method: options that change no
#: weight (the input depth mode a trained network is fed, voting thresholds, sizes of the pose
#: recovery). HFF6DoF's voting is not among them: its two pose recoveries are two rows of the
#: tables, and which one stands for HFF6DoF in the agreement claims is itself chosen on validation.
CHOICE_OPTIONS = {m.name: tuple(m.reproduce.choice_options) for m in reproduced_methods()}


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
        if not all(IMAGE_SIDE[0] <= v <= IMAGE_SIDE[1] for v in self.image_size):
            raise ConfigError(f"train.image_size must be within {IMAGE_SIDE[1]} pixels a side and at least "
                              f"{IMAGE_SIDE[0]}, got {list(self.image_size)}")


def _epochs_post_init(self) -> None:
    check_ranges(self, "epochs", positive=METHODS)


#: [epochs]: training epochs per method (a field per registered method, default 1)
EpochsConfig = dataclasses.make_dataclass(
    "EpochsConfig", [(m.name, int, field(default=1)) for m in methods()],
    namespace={"__post_init__": _epochs_post_init, "__doc__": "[epochs]: training epochs per method."})
EpochsConfig.__module__ = __name__


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

#: the presets that choose prediction-time options on validation (each method's candidates)
CHOOSING_PRESETS = ("cpu", "gpu", "full")

#: the prediction-time choices of the presets that choose (the first value is the default)
CANDIDATES = {m.name: {k: list(v) for k, v in m.reproduce.candidates.items()}
              for m in reproduced_methods() if m.reproduce.candidates}

#: the presets' shared settings, as TOML-like data over the defaults (the methods' parts: :func:`_preset`)
PRESET_SETTINGS: dict[str, dict] = {
    "smoke": {"data": {"scenes": ["single/juice_cup_340", "single/handle_cup_280", "multi/08", "multi/01"],
                       "steps": 6, "step_deg": 5.0, "n_arms": 4, "width": 80, "height": 60},
              "train": {"image_size": [32, 48], "batch_size": 4, "lr": 2e-3, "max_steps": 6},
              "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
              "profile": {"height": 120, "width": 160, "repeats": 1}},
    "cpu": {"data": {"scenes": list(ALL_SCENES), "steps": 12, "step_deg": 30.0, "n_arms": 4, "width": 160,
                     "height": 120},
            "train": {"image_size": [96, 128], "batch_size": 4, "lr": 1e-3},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 240, "width": 320, "repeats": 3},
            "select": {"epochs": "best", "every": 2, "max_images": 200}},
    "gpu": {"data": {"scenes": list(ALL_SCENES), "steps": 60, "step_deg": 6.0, "n_arms": 4, "width": 640,
                     "height": 480},
            "train": {"image_size": [240, 320], "batch_size": 8, "lr": 1e-3, "num_workers": 8},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 480, "width": 640, "repeats": 20},
            "select": {"epochs": "best", "every": 5, "max_images": 300}},
    "full": {"data": {"scenes": list(ALL_SCENES), "steps": 400, "step_deg": 0.9, "n_arms": 4, "width": 640,
                      "height": 480},
             "train": {"image_size": [480, 640], "batch_size": 8, "lr": 1e-3, "num_workers": 8},
             "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
             "profile": {"height": 480, "width": 640, "repeats": 50},
             "select": {"epochs": "best", "every": 10, "max_images": 1000}},
}


def _preset(name: str) -> dict:
    """A preset: its shared settings, each method's epochs and options for it (its registry record),
    and, in a preset that chooses, every method's candidates."""
    ms = reproduced_methods()
    out = copy.deepcopy(PRESET_SETTINGS[name])
    out["epochs"] = {m.name: int(m.reproduce.epochs.get(name, 1)) for m in ms}
    options = {m.name: dict(m.reproduce.preset_options[name]) for m in ms if name in m.reproduce.preset_options}
    if options:
        out["method_options"] = options
    if name in CHOOSING_PRESETS:
        out["candidates"] = copy.deepcopy(CANDIDATES)
    return out


#: the presets, as TOML-like data over the defaults
PRESETS: dict[str, dict] = {name: _preset(name) for name in PRESET_SETTINGS}


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def make_config(preset: str | None = None, config: str | Path | dict | None = None,
                dataset: str | Path | None = None) -> ReproduceConfig:
    """The config: ``preset`` (or the TOML's ``preset``), the TOML file or dict ``config`` over it,
    and ``dataset`` (a root to use instead of simulating). Strict keys, one-line errors naming the file."""
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


def flat_keys(d: Any, prefix: str = "") -> dict:
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(flat_keys(v, f"{prefix}.{k}" if prefix else k))
        return out
    return {prefix: d}


def changed_keys(old: dict, new: dict) -> list[str]:
    """The dotted option names whose values differ between two configs' data (device ignored)."""
    a, b = flat_keys(old), flat_keys(new)
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k) and k != "device")
