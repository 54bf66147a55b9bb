"""The method contract: what every pose estimation method implements (:class:`PoseMethod`), and
what ``tdof20 reproduce`` runs of it (:class:`ReproduceSettings`).

A method is one module (its network, transform, loss and pose recovery) with one class that
implements :class:`PoseMethod`; its registry record (:mod:`tdof20.methods.registry`) names it,
describes it and loads that class on first use, so that the registry, the contract and
``tdof20 --help`` import no torch::

    class PVNetMethod(PoseMethod):
        config_class = PVNetConfig                       # a dataclass of plain types, TOML-settable
        def build(self, cfg, meta): ...                  # -> torch.nn.Module
        def transform(self, cfg, meta, train=False): ... # dataset item -> dict of tensors (picklable)
        def loss(self, net, batch, cfg, meta): ...       # -> (total, {"loss": ..., parts})
        def predict_poses(self, net, batch, cfg, meta): ...   # -> [(b, obj_id, score, R (3,3), t (3,) mm)]
        def forward(self, net, batch): ...               # the network alone (profiling, segmentation IoU)

The optional members have defaults here: :meth:`example_batch` (network inputs without a dataset,
for profiling), :meth:`config_from_run` (runs recorded before the interface) and the hooks the
shared training and prediction loops ask instead of testing a method's name:
:attr:`ddp_find_unused_parameters`, :attr:`labels_are_classes`, :meth:`missing_run_keys`,
:meth:`run_record`, :meth:`mask_source`, :meth:`needs_labels`, :meth:`prediction_summary` and
:meth:`predict_masks`.

Not every registered method estimates poses: a record's ``produces`` (:mod:`tdof20.methods.registry`)
says 'poses' (a compared method: reproduce's rows, ``tdof20 predict``) or 'masks' (a segmentation
network trained by the same loop, whose :meth:`predict_masks` gives a pose method its object pixels
when that method predicts with ``masks = 'segnet'``: :mod:`tdof20.methods.segnet`).

torch-free: the type hints name torch only for checkers.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from tdof20.errors import TdofError

if TYPE_CHECKING:  # pragma: no cover - type hints only
    import torch

    from tdof20.methods.base import MethodMeta

#: a prediction's rows: (index in the batch, obj_id, score, R (3,3), t (3,) mm)
PoseRows = list[tuple[int, int, float, Any, Any]]

#: what a registered method gives: poses (a compared pose estimation method) or masks (a segmentation
#: network that only serves a pose method's ``masks = 'segnet'``)
PRODUCES = ("poses", "masks")
#: where a prediction takes the object pixels from (:meth:`PoseMethod.mask_source`): the method's own
#: network, a separately trained segmentation network's run (``seg_run``), or the dataset's visible
#: masks (an oracle: never a compared row)
MASK_SOURCES = ("network", "segnet", "gt")

#: options the prediction summary (``<stem>_info.json``) has always listed where a method's config has them
SUMMARY_OPTIONS = ("voting", "min_pixels", "max_points", "n_hyp", "inlier_cos")


def forward_rgb(net, batch: Mapping):
    """The network of an RGB-only method: ``net(batch["rgb"])`` on the network's device."""
    dev = next(net.parameters()).device
    return net(batch["rgb"].to(dev))


def forward_batch(net, batch: Mapping):
    """A network that takes the whole batch: ``net(batch)`` (the batch already on the device)."""
    return net(batch)


def _no_unused_choices(options: Mapping) -> tuple[str, ...]:
    return ()


@dataclass(frozen=True)
class ReproduceSettings:
    """What ``tdof20 reproduce`` (:mod:`tdof20.experiments.reproduce`) runs of a method.

    label: the method's row in the tables; variant_labels: rows of the method's variants, by
    suffix ({"3d": ...} labels the row ``<name>-3d``); rank: where its rows stand (ascending, ties in
    registration order: the rivals 0, the paper's own method after them);
    preset_options: the method's config options per preset (``[method_options.<name>]``);
    choice_options: the prediction-time options ``[candidates.<name>]`` may list (options that
    change no weight); candidates: the values the presets that choose on validation try (the
    first of each list is the default); unused_choices: (a row's own prediction options) -> the
    candidate options that do not act on that row (left out of its grid).
    """

    label: str
    choice_options: tuple[str, ...] = ()
    candidates: Mapping[str, list] = field(default_factory=dict)
    preset_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    variant_labels: Mapping[str, str] = field(default_factory=dict)
    rank: int = 0
    unused_choices: Callable[[Mapping], tuple[str, ...]] = _no_unused_choices

    def __post_init__(self) -> None:
        bad = sorted(set(self.candidates) - set(self.choice_options))
        if bad:
            raise ValueError(f"reproduce candidates {bad} are not among the choice options {self.choice_options}")


class PoseMethod(ABC):
    """One pose estimation method's pieces (see the module docstring). ``cfg`` is an instance of
    :attr:`config_class`; ``meta`` a :class:`~tdof20.methods.base.MethodMeta` (the dataset's
    objects, keypoints, sizes and the network input size)."""

    #: the method's config dataclass (plain types; every option with a working default)
    config_class: ClassVar[type]
    #: whether DistributedDataParallel must look for parameters a step leaves without gradient
    #: (a loss that skips sub-networks, e.g. a refiner trained on some steps only)
    ddp_find_unused_parameters: ClassVar[bool] = True
    #: whether the transform's ``label`` holds class indices 0..n already (else object ids)
    labels_are_classes: ClassVar[bool] = False

    @abstractmethod
    def build(self, cfg, meta: MethodMeta) -> torch.nn.Module:
        """The network for ``meta``'s objects, with fresh weights."""

    @abstractmethod
    def transform(self, cfg, meta: MethodMeta, train: bool = False) -> Callable[[Mapping], dict]:
        """Dataset item -> network inputs (+ training targets with ``train``); picklable."""

    @abstractmethod
    def loss(self, net, batch: Mapping, cfg, meta: MethodMeta) -> tuple[torch.Tensor, dict]:
        """(total loss, {"loss": float, part: float, ...}) of a batch of transformed items."""

    @abstractmethod
    def predict_poses(self, net, batch: Mapping, cfg, meta: MethodMeta) -> PoseRows:
        """The poses found in a batch: [(b, obj_id, score, R (3,3), t (3,) mm)]."""

    @abstractmethod
    def forward(self, net, batch: Mapping) -> Any:
        """The network alone on a batch (profiling; ``["seg"]`` for the segmentation IoU)."""

    def example_batch(self, cfg, meta: MethodMeta, batch_size: int = 1) -> dict | None:
        """Network inputs made without a dataset (profiling), or None: the profiler then transforms a
        synthetic item."""
        return None

    def config_from_run(self, config: Mapping, path=None) -> tuple[Any, MethodMeta] | None:
        """(cfg, meta) of a run from its config.json when the method reads runs recorded before the
        interface; None = the recorded "method_config" and "meta" (what every run records now)."""
        return None

    def missing_run_keys(self, config: Mapping) -> list[str]:
        """What a run's config.json lacks for this method's :meth:`config_from_run` (by default its
        "method_config")."""
        return [] if "method_config" in config else ["method_config"]

    def run_record(self, net) -> dict:
        """Entries a run's config.json records beside the shared ones (built from the network); a
        resumed run must record the same."""
        return {}

    def mask_source(self, cfg, net) -> str:
        """Where prediction takes the object pixels from (one of :data:`MASK_SOURCES`): 'network' (its
        own segmentation), 'segnet' (a separately trained segmentation network's run, the config's
        ``seg_run``: the shared prediction loop runs it on the same images and puts its classes in
        the batch's ``label``, in the method's label convention, see :attr:`labels_are_classes`) or
        'gt' (the dataset's visible masks, an oracle); a TdofError when the config asks for what the
        network cannot give."""
        return "network"

    def seg_run(self, cfg) -> str:
        """The segmentation run a prediction with mask source 'segnet' takes its masks from (the
        config's ``seg_run``; "" when it has none)."""
        return str(getattr(cfg, "seg_run", "") or "")

    def predict_masks(self, net, batch: Mapping, cfg, meta: MethodMeta):
        """(classes (B,H,W) int64 class indices 0..n of ``meta``, confidence (B,H,W) float) of a batch:
        what a method that produces masks gives (its record's ``produces = 'masks'``)."""
        raise TdofError(f"{type(self).__name__} produces poses, not masks")

    def needs_labels(self, cfg, net) -> bool:
        """Whether prediction reads the dataset's labels (ground-truth masks)."""
        return self.mask_source(cfg, net) == "gt"

    def prediction_summary(self, cfg, meta: MethodMeta) -> dict:
        """Options the prediction summary lists beside the method's config (those of
        :data:`SUMMARY_OPTIONS` the config has)."""
        return {k: getattr(cfg, k) for k in SUMMARY_OPTIONS if hasattr(cfg, k)}


__all__ = ["MASK_SOURCES", "PRODUCES", "PoseMethod", "PoseRows", "ReproduceSettings", "SUMMARY_OPTIONS",
           "forward_batch", "forward_rgb"]
