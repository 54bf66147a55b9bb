"""The method interface and its registry: one :class:`Method` record per pose estimation method.

    from tdof20.methods.registry import get_method, method_names
    method_names()                          # ['hff6dof', 'pvnet', 'densefusion', 'ffb6d']
    m = get_method("pvnet")
    cfg = m.config_class()                  # every option with a working default (TOML: m.config_from)
    meta = MethodMeta.from_catalog(obj_ids, m.default_image_size)
    net = m.build(cfg, meta)
    tf = m.transform(cfg, meta, train=True)          # dataset item -> dict of tensors (picklable)
    total, parts = m.loss(net, collate([tf(i) for i in items]), cfg, meta)
    rows = m.predict_poses(net, batch, cfg, meta)    # [(b, obj_id, score, R (3,3), t (3,) mm)]
    out = m.forward(net, batch)                      # the network alone (profiling)

A method is one module with five pieces — ``<Method>Config`` (a dataclass of plain types),
``build(cfg, meta)``, ``<Method>Transform(cfg, meta, train)``, ``loss(net, batch, cfg, meta)`` and
``predict_poses(net, batch, cfg, meta)`` — plus, optionally, ``example_batch(cfg, meta,
batch_size)`` (network inputs without a dataset, for profiling) and ``config_from_run(config)``
(the method's (cfg, meta) from a run's config.json written before runs recorded them). Registering
it is one :func:`register` call with the module's import path: the module is imported only when a
piece is used, so this file (and ``tdof20 --help``) stays torch-free.

How to add a method: docs/methods.md ("How to add a method").
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tdof20.errors import TdofError

INPUTS = ("rgb", "rgbd")


def _resolve(path: str) -> Any:
    """'package.module:attribute' -> the attribute (the module imported now)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def forward_rgb(net, batch: Mapping):
    """The network of an RGB-only method: ``net(batch["rgb"])`` on the network's device."""
    dev = next(net.parameters()).device
    return net(batch["rgb"].to(dev))


def forward_batch(net, batch: Mapping):
    """A network that takes the whole batch: ``net(batch)`` (the batch already on the device)."""
    return net(batch)


@dataclass(frozen=True)
class Method:
    """One pose estimation method.

    name: what the command line calls it (``tdof20 train NAME``); module: its import path;
    description: one line; inputs: 'rgb' or 'rgbd' (what it reads of a frame: RGB-D methods read
    the transparent sensor's depth, raw or filled; the restored one only with the privileged depth_mode "restored");
    default_image_size: (H, W) the network sees unless a run says otherwise;
    config / transform: the names of its config dataclass and transform class in ``module``;
    forward: 'module:function' (net, batch) -> outputs, the network alone;
    paper: the paper's Table 3 figures for it ({"parameters_M", "macs_G", "fps", "gpu"}, those it
    gives); original: the original implementation's published or counted figures
    ({"parameters_M": ..., "source": ...}); notes: what its profile counts, where that differs
    from the paper's Table 3 or the original (printed under the table).
    """

    name: str
    module: str
    description: str
    inputs: str
    config: str
    transform_class: str
    default_image_size: tuple[int, int] = (240, 320)
    forward_fn: str = "tdof20.methods.registry:forward_batch"
    paper: Mapping[str, Any] = field(default_factory=dict)
    original: Mapping[str, Any] = field(default_factory=dict)
    notes: str = ""

    def __post_init__(self) -> None:
        if self.inputs not in INPUTS:
            raise ValueError(f"method {self.name}: inputs must be one of {INPUTS}, got {self.inputs!r}")

    # ---------------------------------------------------------------------------------------
    @property
    def available(self) -> bool:
        """Whether the method's module exists (found without importing it)."""
        try:
            return importlib.util.find_spec(self.module) is not None
        except (ImportError, ValueError):
            return False

    def load(self):
        """The method's module (imported on first use)."""
        try:
            return importlib.import_module(self.module)
        except ModuleNotFoundError as e:
            if e.name == self.module:
                raise TdofError(f"method '{self.name}': its module {self.module} is not installed") from None
            raise

    @property
    def config_class(self) -> type:
        return getattr(self.load(), self.config)

    def default_config(self):
        return self.config_class()

    def config_from(self, data: Mapping | None, source: str | Path = ""):
        """The method's config from a parsed TOML table / JSON object (strict keys, typed values,
        one-line errors naming ``source``); None or {} = the defaults."""
        from tdof20.config import config_from_data

        return config_from_data(self.config_class, dict(data or {}), source)

    def config_to_data(self, cfg) -> dict:
        """A config as plain JSON/TOML types (tuples as lists), what a run records."""
        import dataclasses

        def plain(v):
            if isinstance(v, (tuple, list)):
                return [plain(x) for x in v]
            if dataclasses.is_dataclass(v):
                return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
            return v

        return plain(cfg)

    def build(self, cfg, meta):
        return self.load().build(cfg, meta)

    def transform(self, cfg, meta, train: bool = False):
        """The method's transform: dataset item -> inputs (+ targets with ``train``)."""
        return getattr(self.load(), self.transform_class)(cfg, meta, train=train)

    def loss(self, net, batch, cfg, meta):
        return self.load().loss(net, batch, cfg, meta)

    def predict_poses(self, net, batch, cfg, meta):
        return self.load().predict_poses(net, batch, cfg, meta)

    def forward(self, net, batch):
        return _resolve(self.forward_fn)(net, batch)

    def example_batch(self, cfg, meta, batch_size: int = 1) -> dict | None:
        """The module's ``example_batch`` (network inputs without a dataset), or None."""
        fn = getattr(self.load(), "example_batch", None)
        return None if fn is None else fn(cfg, meta, batch_size)

    def config_from_run(self, config: Mapping, path: str | Path | None = None):
        """(cfg, meta) of a run from its config.json: the module's ``config_from_run`` when it has
        one (runs written before the interface), else the recorded "method_config" and "meta"."""
        fn = getattr(self.load(), "config_from_run", None)
        if fn is not None:
            return fn(config, path)
        from tdof20.methods.base import MethodMeta

        if "meta" not in config:
            raise TdofError(f"a {self.name} run's config lacks its 'meta' (objects, keypoints, image size)", path)
        return self.config_from(config.get("method_config"), path or ""), MethodMeta.from_json(config["meta"])


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


def method_names() -> list[str]:
    """The registered methods whose module exists, in registration order."""
    return [n for n, m in _REGISTRY.items() if m.available]


def methods() -> list[Method]:
    return [_REGISTRY[n] for n in method_names()]


def get_method(name: str) -> Method:
    """The method called ``name``; an unknown one is a one-line TdofError listing the known ones."""
    key = str(name).strip().lower()
    m = _REGISTRY.get(key)
    if m is None or not m.available:
        raise TdofError(f"unknown method '{name}' (known: {', '.join(method_names())})")
    return m


def run_method(config: Mapping, path: str | Path | None = None) -> Method:
    """The method a run's config.json names (its "method"; ``path``: the file, for the message)."""
    if not isinstance(config, Mapping) or not isinstance(config.get("method"), str):
        raise TdofError("not a run's config (no \"method\" in it)", path)
    try:
        return get_method(config["method"])
    except TdofError as e:
        raise TdofError(f"the run's method: {e}", path) from None


# --------------------------------------------------------------------------------------------
# the methods (one entry each; the modules load on first use)

register(Method(
    name="hff6dof", module="tdof20.methods.hff6dof_method",
    description="HFF6DoF (the paper): RGB and geometry ResNet34s fused hierarchically, 3D keypoint vectors, "
                "voting + fitting",
    inputs="rgbd", config="HFF6DoFConfig", transform_class="HFF6DoFTransform", default_image_size=(240, 320),
    forward_fn="tdof20.methods.hff6dof_method:forward",
    paper={"parameters_M": 56.82, "macs_G": 85.12, "fps": 29.38, "gpu": "GTX 1080Ti"},
    original={"parameters_M": 56.82, "source": "the paper, Table 3 (no code released)"},
    notes="decoder widths sized to the paper's 56.82 M (the paper leaves the decoder open); the multiply-adds "
          "stay under its 85.12 G"))

register(Method(
    name="pvnet", module="tdof20.methods.pvnet",
    description="PVNet (Peng et al. 2019): RGB only, ResNet18 at stride 8, 2D keypoint vectors, RANSAC voting + PnP",
    inputs="rgb", config="PVNetConfig", transform_class="PVNetTransform", default_image_size=(240, 320),
    forward_fn="tdof20.methods.registry:forward_rgb",
    paper={},
    original={"parameters_M": 12.96, "source": "clean-pvnet's Resnet18 for one object (2 classes): 12,957,748, "
                                             "counted from lib/networks/pvnet/resnet18.py"},
    notes="one network for all objects (the original: one per object): +11,913 parameters for 20 objects in the "
          "segmentation head and the per-class vertex heads, of which one 18-channel head runs per pixel; the "
          "paper's Table 3 gives no PVNet figures"))

register(Method(
    name="densefusion", module="tdof20.methods.densefusion",
    description="DenseFusion (Wang et al. 2019): PSPNet-ResNet18 crop embedding + PointNet, dense fusion, "
                "per-point poses, iterative refiner",
    inputs="rgbd", config="DenseFusionConfig", transform_class="DenseFusionTransform",
    default_image_size=(240, 320), paper={"macs_G": 142.25},
    original={"parameters_M": 23.39, "source": "j96w/DenseFusion lib/network.py for YCB (21 objects), counted "
                                              "from its modules: PoseNet 21.45 M (its PSPNet-ResNet18, no BN, "
                                              "17.46 M) + PoseRefineNet 1.94 M; no segmentation network of its "
                                              "own (PoseCNN's labels)"},
    notes="counts its own PSPNet-ResNet18 segmentation network (17.4 M; the original takes PoseCNN's labels) "
          "and BatchNorm; one forward = segmentation at full size + the estimator on one 160x160 crop of 1,000 "
          "points + one refiner pass: each further object adds the estimator and 2 refiner passes (~17 G)"))

register(Method(
    name="ffb6d", module="tdof20.methods.ffb6d",
    description="FFB6D (He et al. 2021): PSPNet-ResNet34 + RandLA-Net with bidirectional fusion, keypoint "
                "offsets, MeanShift + least squares",
    inputs="rgbd", config="FFB6DConfig", transform_class="FFB6DTransform", default_image_size=(240, 320),
    paper={"macs_G": 215.54},
    original={"parameters_M": 33.8, "source": "published with FFB6D (He et al., CVPR 2021): FFB6D 33.8 M, "
                                             "PVN3D 39.2 M (as issue 14 quotes them)"},
    notes="12,800 points sampled from the depth (the original's 480x640/24); neighbour indices are computed "
          "in the transform (scipy), outside the network's time; the counter skips KNN and MeanShift"))
