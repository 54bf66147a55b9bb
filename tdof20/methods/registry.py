"""The registry of pose estimation methods: one :class:`Method` record per method, each an object
of the method contract (:class:`~tdof20.methods.contract.PoseMethod`) whose implementation loads on
first use.

    from tdof20.methods.registry import get_method, method_names
    method_names()                          # ['hff6dof', 'pvnet', 'densefusion', 'ffb6d']: the pose methods
    method_names(None)                      # every registered one, 'segnet' (masks, not poses) too
    m = get_method("pvnet")
    cfg = m.config_class()                  # every option with a working default (TOML: m.config_from)
    cfg = m.with_options(cfg, parse_set_options(["n_hyp=64"]), "--set")   # strict keys, typed values
    meta = MethodMeta.from_catalog(obj_ids, m.default_image_size)
    net = m.build(cfg, meta)
    tf = m.transform(cfg, meta, train=True)          # dataset item -> dict of tensors (picklable)
    total, parts = m.loss(net, collate([tf(i) for i in items]), cfg, meta)
    rows = m.predict_poses(net, batch, cfg, meta)    # [(b, obj_id, score, R (3,3), t (3,) mm)]
    out = m.forward(net, batch)                      # the network alone (profiling)

A record holds what is known without importing the method (its name, description, input, default
image size, the paper's and the original's figures, what ``tdof20 reproduce`` runs of it) and a
loader of its implementation class: the method's module, which imports torch, is imported only
when a piece is used, so this file (and ``tdof20 --help``) stays torch-free.

A record's ``produces`` says what the method gives: 'poses' (a compared pose estimation method:
:func:`methods` and :func:`method_names` list these, so reproduce's tables, the profile table and
every loop over "the methods" see only them) or 'masks' ('segnet', :mod:`tdof20.methods.segnet`: a
segmentation network trained by the same ``tdof20 train`` loop, whose run a pose method's
``masks = 'segnet'``, ``seg_run = RUN`` reads at prediction time; ``tdof20 predict`` refuses it).
:func:`get_method` finds either kind.

How to add a method: docs/methods.md ("How to add a method").
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from tdof20.config import config_from_data
from tdof20.errors import TdofError
from tdof20.methods.base import MethodMeta
from tdof20.methods.contract import PRODUCES, PoseMethod, ReproduceSettings

INPUTS = ("rgb", "rgbd")
#: the method ``tdof20 train`` and :func:`tdof20.methods.train.train` take unless told otherwise (the paper's)
DEFAULT_METHOD = "hff6dof"


def _plain(v: Any) -> Any:
    """A config value as plain JSON/TOML types (tuples as lists, nested dataclasses as tables)."""
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if dataclasses.is_dataclass(v):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    return v


def _deep_merge(base: dict, changes: Mapping) -> dict:
    out = dict(base)
    for k, v in changes.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


@dataclass(frozen=True, eq=False)
class Method(PoseMethod):
    """One pose estimation method's record; the contract's members forward to its implementation.

    name: what the command line calls it (``tdof20 train NAME``); description: one line;
    inputs: 'rgb' or 'rgbd' (what it reads of a frame: RGB-D methods read the transparent sensor's
    depth, raw or filled; the restored one only with the privileged depth_mode "restored");
    implementation: () -> the method's :class:`~tdof20.methods.contract.PoseMethod` class (imports
    its module); reproduce: what ``tdof20 reproduce`` runs of it;
    default_image_size: (H, W) the network sees unless a run says otherwise; image_multiple: both
    sides of the image size must be a multiple of it (FFB6D's stride-8 encoder: 8);
    paper: the paper's Table 3 figures for it ({"parameters_M", "macs_G", "fps", "gpu"}, those it
    gives); original: the original implementation's published or counted figures
    ({"parameters_M": ..., "source": ...}); notes: what its profile counts, where that differs
    from the paper's Table 3 or the original (printed under the table); produces: 'poses' (a
    compared pose method) or 'masks' (a segmentation network serving a pose method's
    ``masks = 'segnet'``; not a row of any table).
    """

    name: str
    description: str
    inputs: str
    implementation: Callable[[], type[PoseMethod]]
    reproduce: ReproduceSettings
    default_image_size: tuple[int, int] = (240, 320)
    image_multiple: int = 1
    paper: Mapping[str, Any] = field(default_factory=dict)
    original: Mapping[str, Any] = field(default_factory=dict)
    notes: str = ""
    produces: str = "poses"

    def __post_init__(self) -> None:
        if self.inputs not in INPUTS:
            raise ValueError(f"method {self.name}: inputs must be one of {INPUTS}, got {self.inputs!r}")
        if self.produces not in PRODUCES:
            raise ValueError(f"method {self.name}: produces must be one of {PRODUCES}, got {self.produces!r}")

    @cached_property
    def impl(self) -> PoseMethod:
        """The method's implementation (its module imported now)."""
        return self.implementation()()

    # ----------------------------------------------------------------------- config
    @property
    def config_class(self) -> type:
        return self.impl.config_class

    def default_config(self):
        return self.config_class()

    def config_from(self, data: Mapping | None, source: str | Path = ""):
        """The method's config from a parsed TOML table / JSON object (strict keys, typed values,
        one-line errors naming ``source``); None or {} = the defaults."""
        return config_from_data(self.config_class, dict(data or {}), source)

    def config_to_data(self, cfg) -> dict:
        """A config as plain JSON/TOML types (tuples as lists), what a run records."""
        return _plain(cfg)

    def with_options(self, cfg, changes: Mapping, source: str | Path = ""):
        """``cfg`` with ``changes`` applied (a nested config: nested tables), through the same strict,
        typed checks as a TOML file (one-line errors naming ``source`` and the key)."""
        if not changes:
            return cfg
        return self.config_from(_deep_merge(self.config_to_data(cfg), changes), source)

    # ----------------------------------------------------------------------- the contract
    @property
    def ddp_find_unused_parameters(self) -> bool:
        return self.impl.ddp_find_unused_parameters

    @property
    def labels_are_classes(self) -> bool:
        return self.impl.labels_are_classes

    def build(self, cfg, meta):
        return self.impl.build(cfg, meta)

    def transform(self, cfg, meta, train: bool = False):
        return self.impl.transform(cfg, meta, train=train)

    def loss(self, net, batch, cfg, meta):
        return self.impl.loss(net, batch, cfg, meta)

    def predict_poses(self, net, batch, cfg, meta):
        return self.impl.predict_poses(net, batch, cfg, meta)

    def forward(self, net, batch):
        return self.impl.forward(net, batch)

    def example_batch(self, cfg, meta, batch_size: int = 1) -> dict | None:
        return self.impl.example_batch(cfg, meta, batch_size)

    def config_from_run(self, config: Mapping, path: str | Path | None = None):
        """(cfg, meta) of a run from its config.json: the implementation's reading (runs written
        before the interface), else the recorded "method_config" and "meta"."""
        own = self.impl.config_from_run(config, path)
        if own is not None:
            return own
        if "meta" not in config:
            raise TdofError(f"a {self.name} run's config lacks its 'meta' (objects, keypoints, image size)", path)
        return self.config_from(config.get("method_config"), path or ""), MethodMeta.from_json(config["meta"])

    def missing_run_keys(self, config: Mapping) -> list[str]:
        return self.impl.missing_run_keys(config)

    def run_record(self, net) -> dict:
        return self.impl.run_record(net)

    def mask_source(self, cfg, net) -> str:
        return self.impl.mask_source(cfg, net)

    def needs_labels(self, cfg, net) -> bool:
        return self.impl.needs_labels(cfg, net)

    def seg_run(self, cfg) -> str:
        return self.impl.seg_run(cfg)

    def predict_masks(self, net, batch, cfg, meta):
        return self.impl.predict_masks(net, batch, cfg, meta)

    def prediction_summary(self, cfg, meta) -> dict:
        return self.impl.prediction_summary(cfg, meta)


_REGISTRY: dict[str, Method] = {}


def register(method: Method, replace: bool = False) -> Method:
    """Add ``method`` to the registry (``replace``: over a method of the same name)."""
    name = method.name.strip().lower()
    if not name or name == "all" or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"a method name is a plain word other than 'all', got {method.name!r}")
    if name in _REGISTRY and not replace:
        raise ValueError(f"method '{name}' is registered already")
    _REGISTRY[name] = method
    return method


def methods(produces: str | None = "poses") -> list[Method]:
    """The registered methods that produce ``produces`` ('poses': the compared pose estimation
    methods; 'masks': the segmentation networks; None: every one), in registration order."""
    return [m for m in _REGISTRY.values() if produces is None or m.produces == produces]


def method_names(produces: str | None = "poses") -> list[str]:
    """The names of :func:`methods` (by default the pose methods; None: every registered one)."""
    return [m.name for m in methods(produces)]


def get_method(name: str) -> Method:
    """The method called ``name`` (either kind); an unknown one is a one-line TdofError listing the
    known ones."""
    m = _REGISTRY.get(str(name).strip().lower())
    if m is None:
        raise TdofError(f"unknown method '{name}' (known: {', '.join(method_names(None))})")
    return m


def run_method(config: Mapping, path: str | Path | None = None) -> Method:
    """The method a run's config.json names (its "method"; ``path``: the file, for the message)."""
    if not isinstance(config, Mapping) or not isinstance(config.get("method"), str):
        raise TdofError("not a run's config (no \"method\" in it)", path)
    try:
        return get_method(config["method"])
    except TdofError as e:
        raise TdofError(f"the run's method: {e}", path) from None


def parse_set_options(items: Iterable[str], option: str = "--set") -> dict:
    """``key=value`` strings (the command line's repeatable ``--set``) -> a nested table of options:
    the value is read as a TOML value (a number, true/false, a quoted string, an array), else taken as
    a bare string (``masks=gt``); a dotted key sets an option of a nested table (``a.b=1``).
    One-line errors naming the item."""
    out: dict = {}
    for item in items:
        key, eq, text = item.partition("=")
        key = key.strip()
        parts = key.split(".")
        if not eq or not all(p.strip() for p in parts):
            raise TdofError(f"{option} {item!r}: give key=value (e.g. {option} fuse_stages=2)")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        table = out
        for p in parts[:-1]:
            table = table.setdefault(p.strip(), {})
            if not isinstance(table, dict):
                raise TdofError(f"{option} {item!r}: {p} is set as a value and as a table")
        if isinstance(table.get(parts[-1].strip()), dict):
            raise TdofError(f"{option} {item!r}: {key} is set as a value and as a table")
        table[parts[-1].strip()] = value
    return out


# --------------------------------------------------------------------------------------------
# the methods (one record each; each loader imports its module, which imports torch, on first use)


def _hff6dof() -> type[PoseMethod]:
    from tdof20.methods.hff6dof_method import HFF6DoFMethod  # imports torch

    return HFF6DoFMethod


def _pvnet() -> type[PoseMethod]:
    from tdof20.methods.pvnet import PVNetMethod  # imports torch

    return PVNetMethod


def _densefusion() -> type[PoseMethod]:
    from tdof20.methods.densefusion import DenseFusionMethod  # imports torch

    return DenseFusionMethod


def _ffb6d() -> type[PoseMethod]:
    from tdof20.methods.ffb6d import FFB6DMethod  # imports torch

    return FFB6DMethod


def _segnet() -> type[PoseMethod]:
    from tdof20.methods.segnet import SegNetMethod  # imports torch

    return SegNetMethod


def _hff6dof_unused_choices(options: Mapping) -> tuple[str, ...]:
    """HFF6DoF's bearing_tol acts only with bearing voting, inlier_cos only with 3D voting."""
    return ("bearing_tol",) if options.get("voting") == "3d" else ("inlier_cos",)


register(Method(
    name="hff6dof", implementation=_hff6dof,
    description="HFF6DoF (the paper): RGB and geometry ResNet34s fused hierarchically, 3D keypoint vectors, "
                "voting + fitting",
    inputs="rgbd", default_image_size=(240, 320),
    paper={"parameters_M": 56.82, "macs_G": 85.12, "fps": 29.38, "gpu": "GTX 1080Ti"},
    original={"parameters_M": 56.82, "source": "the paper, Table 3 (no code released)"},
    notes="decoder widths sized to the paper's 56.82 M (the paper leaves the decoder open); the multiply-adds "
          "stay under its 85.12 G",
    reproduce=ReproduceSettings(
        label="HFF6DoF (bearing + PnP)", variant_labels={"3d": "HFF6DoF (3D voting + LSQ)"}, rank=1,
        choice_options=("depth_mode", "min_pixels", "max_points", "n_hyp", "inlier_cos", "bearing_tol"),
        candidates={"depth_mode": ["filled", "raw"]},  # as many candidate sets as each rival (issue 23)
        unused_choices=_hff6dof_unused_choices)))

register(Method(
    name="pvnet", implementation=_pvnet,
    description="PVNet (Peng et al. 2019): RGB only, ResNet18 at stride 8, 2D keypoint vectors, RANSAC voting + PnP",
    inputs="rgb", default_image_size=(240, 320),
    paper={},
    original={"parameters_M": 12.96, "source": "clean-pvnet's Resnet18 for one object (2 classes): 12,957,748, "
                                             "counted from lib/networks/pvnet/resnet18.py"},
    notes="one network for all objects (the original: one per object): +11,913 parameters for 20 objects in the "
          "segmentation head and the per-class vertex heads, of which one 18-channel head runs per pixel; the "
          "paper's Table 3 gives no PVNet figures",
    reproduce=ReproduceSettings(
        label="PVNet",
        choice_options=("min_pixels", "inlier_cos", "vote_max_pixels", "min_inlier_ratio", "n_hyp", "max_rounds"),
        candidates={"inlier_cos": [0.99, 0.97]})))

register(Method(
    name="densefusion", implementation=_densefusion,
    description="DenseFusion (Wang et al. 2019): PSPNet-ResNet18 crop embedding + PointNet, dense fusion, "
                "per-point poses, iterative refiner",
    inputs="rgbd", default_image_size=(240, 320), paper={"macs_G": 142.25},
    original={"parameters_M": 23.39, "source": "j96w/DenseFusion lib/network.py for YCB (21 objects), counted "
                                              "from its modules: PoseNet 21.45 M (its PSPNet-ResNet18, no BN, "
                                              "17.46 M) + PoseRefineNet 1.94 M; no segmentation network of its "
                                              "own (PoseCNN's labels)"},
    notes="counts its own PSPNet-ResNet18 segmentation network (17.4 M; the original takes PoseCNN's labels) "
          "and BatchNorm; one forward = segmentation at full size + the estimator on one 160x160 crop of 1,000 "
          "points + one refiner pass: each further object adds the estimator and 2 refiner passes (~17 G)",
    reproduce=ReproduceSettings(
        label="DenseFusion",
        choice_options=("depth_mode", "refine_iterations", "min_points"),
        candidates={"refine_iterations": [2, 0]},
        preset_options={"smoke": {"n_points": 128, "crop_size": 48}, "cpu": {"n_points": 500, "crop_size": 64}})))

register(Method(
    name="ffb6d", implementation=_ffb6d,
    description="FFB6D (He et al. 2021): PSPNet-ResNet34 + RandLA-Net with bidirectional fusion, keypoint "
                "offsets, MeanShift + least squares",
    inputs="rgbd", default_image_size=(240, 320), image_multiple=8,
    paper={"macs_G": 215.54},
    original={"parameters_M": 33.8, "source": "published with FFB6D (He et al., CVPR 2021): FFB6D 33.8 M, "
                                             "PVN3D 39.2 M (as issue 14 quotes them)"},
    notes="12,800 points sampled from the depth (the original's 480x640/24); neighbour indices are computed "
          "in the transform (scipy), outside the network's time; the counter skips KNN and MeanShift",
    reproduce=ReproduceSettings(
        label="FFB6D",
        choice_options=("depth_mode", "bandwidth_mm", "min_points", "max_votes"),
        candidates={"bandwidth_mm": [40.0, 20.0]},
        preset_options={"smoke": {"n_points": 512, "meanshift_iters": 30, "max_votes": 500},
                        "cpu": {"n_points": 2048}})))

register(Method(
    name="segnet", implementation=_segnet, produces="masks",
    description="segmentation network (DenseFusion's PSPNet-ResNet18), not a pose method: object masks for a pose "
                "method's masks='segnet' seg_run=RUN (HFF6DoF without its segmentation head)",
    inputs="rgb", default_image_size=(240, 320),
    original={"parameters_M": 17.46, "source": "j96w/DenseFusion vanilla_segmentation: its PSPNet-ResNet18 "
                                              "(no BN), as counted for DenseFusion's record"},
    notes="DenseFusion's segmentation network alone (tdof20.methods.segnet.SegNet, the same module DenseFusion "
          "builds), with BatchNorm; trained with pixel-wise cross-entropy",
    reproduce=ReproduceSettings(label="segmentation network (PSPNet-ResNet18)", rank=99)))
