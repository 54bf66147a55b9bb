"""What ``tdof20 reproduce`` runs: its typed config (a preset, a TOML over it) and the presets.

    cfg = make_config("smoke")                                # a preset
    cfg = make_config(config="my.toml", dataset="ROOT")       # a TOML over a preset; a given dataset

A fair benchmark (../shared/design.md): every compared row gets the same training budget —
``train.images``, images seen (optimiser steps x batch) at ``train.image_size``, whatever each
method's batch (``[batch]``) — the same number of prediction-time candidate sets chosen on
validation (or none for all; refused otherwise), the same seeds (``train.seeds``), and no
privileged input (restored depth, ground-truth masks: refused for a compared row, one line naming
the row and the input).

The methods' parts come from their registry records (:class:`~tdof20.methods.contract.ReproduceSettings`):
which methods run and in what order (:data:`METHODS`), their table labels (:data:`LABELS`), the
prediction-time options chosen on validation (:data:`CHOICE_OPTIONS`) and the values tried
(:data:`CANDIDATES`) and a preset's method options (``[method_options.<method>]``). Adding a
method to reproduce is adding its record: nothing here names one, except the paper's ablations of
HFF6DoF ([ablations]) and the separately trained segmentation network of its segmentation
ablation (:data:`SEGNET`), which is no pose method and no row of the tables.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tdof20.config import ConfigError, check_ranges, config_from_data
from tdof20.dataset.naming import normalize_scene_id
from tdof20.errors import TdofError
from tdof20.formats.io import read_toml
from tdof20.methods.base import IMAGE_SIDE
from tdof20.methods.registry import Method, get_method, method_names, methods

#: the segmentation network the segmentation ablation's row without HFF6DoF's head takes its masks
#: from (a registered method trained with the same train entry; predicted with masks = "segnet",
#: seg_run = its run): not a pose method, so no row of the tables
SEGNET = "segnet"


def reproduced_methods() -> list[Method]:
    """The registered pose methods in the tables' order (their records' ``reproduce.rank``, then
    the registration order); the segmentation network (:data:`SEGNET`) is none of them."""
    return sorted((m for m in methods() if m.name != SEGNET), key=lambda m: m.reproduce.rank)


def segnet_available() -> bool:
    """Whether this version has the segmentation network the segmentation ablation needs: the
    registered method :data:`SEGNET` and HFF6DoF's prediction option masks = "segnet" with
    seg_run (imports HFF6DoF's module)."""
    if SEGNET not in method_names(None):
        return False
    return "seg_run" in {f.name for f in dataclasses.fields(get_method("hff6dof").config_class)}


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
    #: the training budget of every run: images seen (optimiser steps x batch), the same for every
    #: compared row whatever its method's batch; epochs follow from it (and the part's size)
    images: int = 24
    num_workers: int = 1
    #: every row is trained (and chosen, predicted, scored) once per seed; tables show the mean and
    #: the spread over them
    seeds: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        self.image_size = tuple(int(v) for v in self.image_size)
        self.seeds = tuple(int(v) for v in self.seeds)
        if len(self.image_size) != 2:
            raise ConfigError(f"train.image_size must be [H, W], got {list(self.image_size)}")
        check_ranges(self, "train", positive=("image_size", "batch_size", "lr", "images"),
                     non_negative=("num_workers", "seeds"))
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"train.seeds names a seed twice: {list(self.seeds)}")
        if not all(IMAGE_SIDE[0] <= v <= IMAGE_SIDE[1] for v in self.image_size):
            raise ConfigError(f"train.image_size must be within {IMAGE_SIDE[1]} pixels a side and at least "
                              f"{IMAGE_SIDE[0]}, got {list(self.image_size)}")


def _batch_post_init(self) -> None:
    check_ranges(self, "batch", non_negative=METHODS)


#: [batch]: images per optimiser step per method (a field per pose method; 0 = train.batch_size)
BatchConfig = dataclasses.make_dataclass(
    "BatchConfig", [(m.name, int, field(default=0)) for m in reproduced_methods()],
    namespace={"__post_init__": _batch_post_init,
               "__doc__": "[batch]: images per optimiser step per method (0 = train.batch_size); the budget "
                          "train.images stays the same for every method."})
BatchConfig.__module__ = __name__

#: the segmentation ablation's masks for the row without HFF6DoF's head
SEG_MASKS = ("segnet", "gt")


@dataclass
class AblationConfig:
    """[ablations]: fuse_stages (HFF6DoF trained on hard with each number of fused stages; () =
    no fusion ablation; 3 is the main run), segmentation (HFF6DoF on hard without its head: the
    segmentation module's ablation), segmentation_masks (where that row's object pixels come from:
    "segnet" = a segmentation network trained separately on the same split (:data:`SEGNET`), the
    paper's ablation; "gt" = ground-truth masks, an oracle row marked as such and outside every
    claim), segnet_share (the part of the row's budget train.images the segmentation network
    spends; HFF6DoF without its head spends the rest, so that the row's two trainings together
    see as many images as every other row), voting_3d (the paper's 3D voting + least squares as a
    row beside the default bearing + PnP: a second row of its own, not a choice)."""

    fuse_stages: tuple[int, ...] = ()
    segmentation: bool = False
    segmentation_masks: str = "segnet"
    segnet_share: float = 0.25
    voting_3d: bool = True

    def __post_init__(self) -> None:
        self.fuse_stages = tuple(sorted({int(v) for v in self.fuse_stages}))
        if any(not 1 <= v <= 5 for v in self.fuse_stages):
            raise ConfigError(f"ablations.fuse_stages must be in 1..5, got {list(self.fuse_stages)}")
        if self.segmentation_masks not in SEG_MASKS:
            raise ConfigError(f"ablations.segmentation_masks must be one of {', '.join(SEG_MASKS)}, got "
                              f"'{self.segmentation_masks}'")
        if not 0.0 < self.segnet_share < 1.0:
            raise ConfigError(f"ablations.segnet_share must be between 0 and 1 (exclusive), got {self.segnet_share}")


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
    batch: BatchConfig = field(default_factory=BatchConfig)
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
        bad = [f"{m} {self.batch_of(m)}" for m in self.methods if self.train.images % self.batch_of(m)]
        if bad:
            raise ConfigError(f"train.images ({self.train.images}) must be a multiple of every method's batch, so "
                              f"that each sees the same images: not of {', '.join(bad)}")
        if self.ablations.segmentation and self.ablations.segmentation_masks == "segnet" \
                and self.segnet_images() >= self.train.images:
            raise ConfigError(f"train.images ({self.train.images}) leaves nothing of the segmentation ablation's budget "
                              f"to HFF6DoF after the segmentation network's {self.segnet_images()}: give more images")

    def batch_of(self, method: str) -> int:
        """Images per optimiser step of ``method`` ([batch], else train.batch_size)."""
        return getattr(self.batch, method, 0) or self.train.batch_size

    def segnet_images(self) -> int:
        """The segmentation network's part of the segmentation ablation's budget: segnet_share x
        train.images, down to a multiple of both its batch and HFF6DoF's (so both parts are
        whole steps), at least one such multiple."""
        unit = math.lcm(self.train.batch_size, self.batch_of("hff6dof"))
        return max(unit, int(self.ablations.segnet_share * self.train.images) // unit * unit)


ALL_SCENES = tuple([f"single/{i:02d}" for i in range(1, 21)] + [f"multi/{i:02d}" for i in range(20)])

#: the presets that choose prediction-time options on validation (each method's candidates)
CHOOSING_PRESETS = ("cpu", "gpu", "full")


def candidate_table(candidates: dict, method: str, options: dict) -> dict:
    """The candidate lists ([candidates.<method>]) that act on a row of ``method`` predicted with
    its own ``options``: without those the method's record leaves out for such a row
    (``unused_choices``: HFF6DoF's bearing_tol acts only with bearing voting, inlier_cos only with
    3D voting) and without those the row fixes itself."""
    table = dict(candidates.get(method, {}))
    for k in list(get_method(method).reproduce.unused_choices(options)) + list(options):
        table.pop(k, None)
    return table


def grid_size(table: dict) -> int:
    """The number of candidate sets a table of lists makes (their product)."""
    return math.prod(len(v) for v in table.values())


#: the compared rows' own prediction options, per row kind: (method, options) for every main row
def main_rows(methods_: tuple[str, ...], voting_3d: bool) -> list[tuple[str, dict]]:
    rows = [(m, {}) for m in methods_]
    if "hff6dof" in methods_ and voting_3d:
        rows.append(("hff6dof", {"voting": "3d"}))
    return rows


def _equal_candidates(candidates: dict) -> dict:
    """Every method's candidates (its record's) cut to the same number of candidate sets: the
    smallest grid among the main rows; a record with more drops its later option lists (its first
    ones, the record's order, are kept), so no method gets more choices on validation than another."""
    out = copy.deepcopy(candidates)
    rows = main_rows(METHODS, True)
    k = min(grid_size(candidate_table(out, m, o)) for m, o in rows)
    for m in out:
        while max(grid_size(candidate_table(out, m, o)) for mm, o in rows if mm == m) > k and len(out[m]) > 1:
            out[m].pop(list(out[m])[-1])
    return out


#: the prediction-time choices of the presets that choose (the first value is the default): the
#: records' candidates, cut to the same number of candidate sets for every method
CANDIDATES = _equal_candidates({m.name: {k: list(v) for k, v in m.reproduce.candidates.items()}
                                for m in reproduced_methods() if m.reproduce.candidates})

#: the presets' shared settings, as TOML-like data over the defaults (the methods' parts: :func:`_preset`).
#: train.images, the budget of every training run (images seen), is the same for every method: smoke
#: 6 steps of 4; cpu 800 steps of 4 (5 epochs of simple's 640 train-val images, 2.4 of hard's 1,360);
#: gpu 8,000 steps of 8 (19 / 9.2 epochs); full 280,000 steps of 8 (100 epochs of simple's 22,400).
PRESET_SETTINGS: dict[str, dict] = {
    "smoke": {"data": {"scenes": ["single/juice_cup_340", "single/handle_cup_280", "multi/08", "multi/01"],
                       "steps": 6, "step_deg": 5.0, "n_arms": 4, "width": 80, "height": 60},
              "train": {"image_size": [32, 48], "batch_size": 4, "lr": 2e-3, "images": 24, "seeds": [0]},
              "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
              "profile": {"height": 120, "width": 160, "repeats": 1}},
    "cpu": {"data": {"scenes": list(ALL_SCENES), "steps": 12, "step_deg": 30.0, "n_arms": 4, "width": 160,
                     "height": 120},
            "train": {"image_size": [96, 128], "batch_size": 4, "lr": 1e-3, "images": 3200, "seeds": [0, 1]},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 240, "width": 320, "repeats": 3},
            "select": {"epochs": "best", "every": 1, "max_images": 200}},
    "gpu": {"data": {"scenes": list(ALL_SCENES), "steps": 60, "step_deg": 6.0, "n_arms": 4, "width": 640,
                     "height": 480},
            "train": {"image_size": [240, 320], "batch_size": 8, "lr": 1e-3, "num_workers": 8, "images": 64000,
                      "seeds": [0, 1, 2]},
            "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
            "profile": {"height": 480, "width": 640, "repeats": 20},
            "select": {"epochs": "best", "every": 4, "max_images": 300}},
    "full": {"data": {"scenes": list(ALL_SCENES), "steps": 400, "step_deg": 0.9, "n_arms": 4, "width": 640,
                      "height": 480},
             "train": {"image_size": [480, 640], "batch_size": 8, "lr": 1e-3, "num_workers": 8, "images": 2240000,
                       "seeds": [0, 1, 2]},
             "ablations": {"fuse_stages": [1, 2, 3, 4, 5], "segmentation": True},
             "profile": {"height": 480, "width": 640, "repeats": 50},
             "select": {"epochs": "best", "every": 10, "max_images": 1000}},
}


def _preset(name: str) -> dict:
    """A preset: its shared settings, each method's options for it (its registry record), and, in
    a preset that chooses, every method's candidates (:data:`CANDIDATES`)."""
    ms = reproduced_methods()
    out = copy.deepcopy(PRESET_SETTINGS[name])
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
    check_image_size(cfg, src)
    check_fair(cfg, src)
    return cfg


def check_image_size(cfg: ReproduceConfig, src: str = "") -> None:
    """Refuse, before any job runs, a train.image_size a method cannot take (its record's
    ``image_multiple``: FFB6D's stride-8 encoder needs both sides divisible by 8)."""
    h, w = cfg.train.image_size
    for m in cfg.methods:
        k = get_method(m).image_multiple
        if h % k or w % k:
            raise TdofError(f"train.image_size {h}x{w}: {LABELS[m]} needs both sides divisible by {k} "
                            f"(e.g. {h // k * k or k}x{w // k * k or k})", src or None)


def row_label(cfg: ReproduceConfig, method: str, own: dict | None = None) -> str:
    """A main row's label: the method's, or its variant's where the row's options (the config's
    [method_options.<method>] under the row's own) select one (HFF6DoF with voting = "3d" is
    "HFF6DoF (3D voting + LSQ)", whether as the 3D-voting row or as its only row)."""
    options = {**cfg.method_options.get(method, {}), **(own or {})}
    for suffix in get_method(method).reproduce.variant_labels:
        if suffix in options.values():
            return LABELS[f"{method}-{suffix}"]
    return LABELS[method]


#: privileged inputs, by option and value: derived from the ground truth, never a submission
PRIVILEGED = {"depth_mode": {"restored": "restored depth (derived from the ground truth)"},
              "masks": {"gt": "ground-truth masks"},
              "boxes": {"gt": "ground-truth boxes"}}


def privileged_inputs(options: dict) -> list[str]:
    """The privileged inputs a row's options give it (:data:`PRIVILEGED`): restored depth,
    ground-truth masks or boxes."""
    return [PRIVILEGED[k][v] for k, v in options.items() if isinstance(v, str) and v in PRIVILEGED.get(k, {})]


def check_fair(cfg: ReproduceConfig, src: str = "") -> None:
    """Refuse what would make the compared rows unequal: a privileged input for any compared row
    (through [method_options.<method>]; one line naming the row and the input), or candidate
    lists that give the compared rows different numbers of candidate sets chosen on validation.
    (The budget is one number, train.images, for every row; :class:`ReproduceConfig` checks it
    divides into whole steps of each method's batch.)"""
    where = src or None
    sizes = {}
    labels = [row_label(cfg, m, own) for m, own in main_rows(cfg.methods, cfg.ablations.voting_3d)]
    twice = sorted({x for x in labels if labels.count(x) > 1})
    if twice:
        raise TdofError(f"two compared rows would be the same '{twice[0]}' (ablations.voting_3d adds HFF6DoF's 3D "
                        "voting row, and method_options.hff6dof.voting = \"3d\" makes its main row that too): set "
                        "one of them", where)
    for (m, own), row in zip(main_rows(cfg.methods, cfg.ablations.voting_3d), labels):
        bad = privileged_inputs(cfg.method_options.get(m, {}))
        if bad:
            key = next(k for k, v in cfg.method_options[m].items() if k in PRIVILEGED and v in PRIVILEGED[k])
            raise TdofError(f"method_options.{m}.{key}: the compared row '{row}' would predict with {bad[0]}, a "
                            "privileged input: refused (an oracle belongs only in a row marked as such, e.g. "
                            "ablations.segmentation_masks = \"gt\")", where)
        sizes[row] = grid_size(candidate_table(cfg.candidates, m, own))
    if len(set(sizes.values())) > 1:
        shown = ", ".join(f"{r} {n}" for r, n in sizes.items())
        raise TdofError(f"the compared rows get different numbers of candidate sets chosen on validation ({shown}): "
                        "give every method's [candidates.<method>] the same number of sets, or none to any", where)


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
