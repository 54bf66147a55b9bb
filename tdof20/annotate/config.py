"""The options of ``tdof20 annotate``: one dataclass per stage and :class:`AnnotateConfig` over them.

``[register]`` :class:`~tdof20.annotate.registration_config.RegistrationConfig`, ``[reconstruct]``
:class:`~tdof20.annotate.reconstruct.ReconstructionConfig`, ``[fit]``
:class:`~tdof20.annotate.models.ModelFitConfig`, ``[build]``
:class:`~tdof20.annotate.modelbuild_config.ModelBuildConfig`, ``[place]`` :class:`PlaceConfig` (the model
and place stages), ``[label]`` :class:`~tdof20.annotate.label.LabelConfig`, ``[qa]``
:class:`QAConfig`; top-level ``fuse_max_frames``, ``fuse_crop``, ``fuse_max_height_mm`` (the
reconstruct stage's choice of frames and crop). :func:`load_annotate_config` reads a TOML file
(strict: an unknown table or key, or a value of the wrong type, is one line naming the file and
the key); every default works on the simulator. See ``docs/annotate.md``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tdof20.annotate.label import LabelConfig
from tdof20.annotate.models import ModelFitConfig
from tdof20.annotate.modelbuild_config import ModelBuildConfig
from tdof20.annotate.reconstruct import ReconstructionConfig
from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.annotate.uncertainty import UncertaintyConfig
from tdof20.config import check_ranges, config_from_data, load_config_file
from tdof20.errors import TdofError

__all__ = ["AnnotateConfig", "PlaceConfig", "QAConfig", "annotate_config_from_dict", "jsonable",
           "load_annotate_config"]


@dataclass(frozen=True)
class PlaceConfig:
    """Matching the models to the clusters (model stage) and placing them (place stage)."""

    match_samples: int = 3000            # model surface samples of the quick matching fits
    match_voxel_mm: float = 3.0          # the clusters thinned to this for the matching fits
    match_icp_mm: tuple[float, ...] = (8.0, 4.0)   # ICP distances of the matching fits
    match_candidates: int = 3            # clusters fitted per object (the best by shape first) ...
    match_shape_margin: float = 0.5      # ... if within this of the best shape cost (relative units)
    fit_samples: int = 20000             # model surface samples of the final fit
    upright: bool = True                 # objects stand on the table: model z along the table normal
    upright_max_deg: float = 3.0         # ... when the fit's tilt is below this (else kept as fitted)
    contact: bool = True                 # ... and set down onto the table (its lowest point on it) ...
    contact_max_mm: float = 6.0          # ... when within this of it (refine_placement)
    min_fitness: float = 0.15            # quality gate of the final fit (fraction of cluster points
    max_score_mm: float = 3.0            # within the last ICP distance; truncated mean distance)
    # the twin check (tdof20.annotate.twins): the transparent phase's glass returns against the twin's pose
    twin_check: bool = True
    twin_frames: int = 96                # transparent frames read (spread over arms and steps)
    twin_groups: int = 12                # interleaved groups of them the 95 % bound comes from
    twin_rounds: int = 3                 # fits, each choosing the returns at the last one's pose
    twin_margin_mm: float = 15.0         # returns within the object's footprint + this ...
    twin_min_height_mm: float = 6.0      # ... and this far above the table top are its evidence
    twin_scale_mm: float = 4.0           # Cauchy scale of the fit (glass returns are noisy)
    twin_trunc_mm: float = 15.0          # returns farther from the model are not its evidence
    twin_min_points: int = 200           # fewer returns: not checked (flagged)
    twin_max_ci95_mm: float = 0.6        # strong evidence: bounds at most these ...
    twin_max_ci95_deg: float = 0.6
    twin_max_mm: float = 5.0             # ... and an offset within these: the pose corrected
    twin_max_deg: float = 5.0
    twin_within_mm: float = 1.0          # weak evidence bounding the offset within these: kept
    twin_within_deg: float = 1.0
    twin_min_ci95_mm: float = 0.05       # floors of the bounds
    twin_min_ci95_deg: float = 0.05

    def __post_init__(self) -> None:
        if self.match_samples < 100 or self.fit_samples < 100:
            raise TdofError("place.match_samples and place.fit_samples must be >= 100")
        if self.match_candidates < 1:
            raise TdofError(f"place.match_candidates must be >= 1, got {self.match_candidates}")
        if not self.match_icp_mm or any(d <= 0 for d in self.match_icp_mm) or self.match_voxel_mm <= 0:
            raise TdofError("place.match_icp_mm and place.match_voxel_mm must be > 0")
        check_ranges(self, "place", positive=("twin_frames", "twin_groups", "twin_rounds", "twin_scale_mm", "twin_trunc_mm",
                                              "twin_min_points", "twin_max_ci95_mm", "twin_max_ci95_deg",
                                              "twin_max_mm", "twin_max_deg", "twin_within_mm", "twin_within_deg",
                                              "twin_min_ci95_mm", "twin_min_ci95_deg"),
                     non_negative=("twin_margin_mm", "twin_min_height_mm", "contact_max_mm"))


@dataclass(frozen=True)
class QAConfig:
    """The qa stage: the overlays drawn and the evaluation against a simulated session's truth."""

    sample: int = 12                     # overlays of this many labelled frames (+ every flagged one)
    evaluate: bool = True                # evaluate against truth/ when the session has one
    evaluate_max_frames: int = 0         # 0 = every frame
    evaluate_points: int = 2000          # Monte-Carlo samples per model of the surface distance

    def __post_init__(self) -> None:
        if self.sample < 0 or self.evaluate_max_frames < 0 or self.evaluate_points < 10:
            raise TdofError("qa.sample and qa.evaluate_max_frames must be >= 0, qa.evaluate_points >= 10")


@dataclass(frozen=True)
class AnnotateConfig:
    """Every option of ``tdof20 annotate``; the defaults work on the simulator."""

    register: RegistrationConfig = field(default_factory=RegistrationConfig)
    reconstruct: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    fit: ModelFitConfig = field(default_factory=ModelFitConfig)
    build: ModelBuildConfig = field(default_factory=ModelBuildConfig)
    place: PlaceConfig = field(default_factory=PlaceConfig)
    label: LabelConfig = field(default_factory=LabelConfig)
    qa: QAConfig = field(default_factory=QAConfig)
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    fuse_max_frames: int = 240           # at most this many usable opaque frames go into the TSDF,
                                         # spread evenly over each arm's turn (0 = all)
    fuse_crop: bool = True               # fuse only the turntable volume (depth outside it dropped
    fuse_max_height_mm: float = 500.0    # first: up to this above the table, within
                                         # reconstruct.crop_radius_mm + 20 mm of the axis)
    source: str = ""                     # the file it was read from ("" = built in code)

    def __post_init__(self) -> None:
        if self.fuse_max_frames < 0:
            raise TdofError(f"fuse_max_frames must be >= 0 (0 = all), got {self.fuse_max_frames}", self.source or None)

    def with_label_options(self, executor: str | None = None, ray_address: str | None = None,
                           workers: int | None = None) -> "AnnotateConfig":
        """A copy with the label stage's executor options replaced where given (the CLI's
        ``--executor``, ``--ray-address``, ``--workers``); they do not change what is written."""
        kw = {k: v for k, v in (("executor", executor), ("ray_address", ray_address), ("workers", workers))
              if v is not None}
        return dataclasses.replace(self, label=dataclasses.replace(self.label, **kw)) if kw else self

    def to_dict(self) -> dict:
        return {name: jsonable(dataclasses.asdict(getattr(self, name))) for name in _SECTIONS} | {
            k: getattr(self, k) for k in _SCALARS}


_SECTIONS = ("register", "reconstruct", "fit", "build", "place", "label", "qa", "uncertainty")
_SCALARS = ("fuse_max_frames", "fuse_crop", "fuse_max_height_mm")


def jsonable(x: Any) -> Any:
    """``x`` as plain JSON types (arrays as lists, anything else unknown as its string): what the
    config's ``to_dict`` and the state file's fingerprints are made of."""
    return json.loads(json.dumps(x, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def annotate_config_from_dict(data: dict, source: str = "") -> AnnotateConfig:
    """An :class:`AnnotateConfig` from a parsed TOML document (strict: an unknown table or key is
    a TdofError naming ``source`` and the key)."""
    return config_from_data(AnnotateConfig, data, source)


def load_annotate_config(path: str | Path) -> AnnotateConfig:
    """Read and check a TOML annotation config; any problem is one line naming the file."""
    return load_config_file(AnnotateConfig, path)
