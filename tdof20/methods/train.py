"""Training any registered method on a dataset split (``tdof20 train METHOD``): one loop for all
(device, AMP, DDP, checkpoints, resume, progress, loss curves), the method's pieces from its
contract (:mod:`tdof20.methods.contract`, through the registry).

    from tdof20.methods.train import train
    run = train("ROOT", "simple", "runs/simple", image_size=(240, 320), epochs=20)   # the paper's method
    run = train("ROOT", "simple", "runs/pvnet", method="pvnet", method_config={"n_hyp": 64})
    run = train("ROOT", "simple", "runs/fuse2", fuse_stages=2)      # an option of the method's config

A run folder holds everything needed to resume and to predict (read and checked by
:mod:`tdof20.methods.runs`):

    RUN/config.json       the method, its config ("method_config"), its meta, the input depth mode,
                          the split, the dataset and the training options (what predict rebuilds the
                          network from), and what the method records of its own (``run_record``)
    RUN/last.pt           model, optimiser (and AMP scaler) state, epoch and step counters, loss history
                          (no optimiser state once a run trained with keep_optimizer=False has ended)
    RUN/history.json      per-epoch losses, learning rate, images/s, seconds spent waiting for the
                          loader (data_seconds) and CPU seconds of the process (several processes:
                          each one's weights digest at the end, which must agree)
    RUN/loss.png          loss curves (total and the method's parts) and learning rate
    RUN/data/{split}_train.h5   the packed training shard (made on first use, reused afterwards)

Running ``train`` again on the same RUN resumes from last.pt: the epoch and step counters, the
optimiser's moments and the loss history continue; asking for more ``epochs`` (or a larger
``max_steps``) extends the run. The method's options must not change between calls.

Everything a call refuses (a damaged or foreign last.pt, an --out that is a file, an empty split
part, changed options) is refused before anything is packed or written, and the files found are
left as they are.

Options come from keyword arguments or a TOML file (``--config``, :func:`load_train_config`)::

    [train]                      # TrainOptions: image_size, batch_size, epochs, lr, ...
    batch_size = 4
    [method]                     # the method's config (HFF6DoFConfig, PVNetConfig, ...)
    fuse_stages = 2

and single options over it (``--set fuse_stages=2``, :func:`tdof20.methods.registry.parse_set_options`).

Several processes: ``torchrun --nproc_per_node N -m tdof20 train METHOD ...`` (or any launcher
that sets RANK / LOCAL_RANK / WORLD_SIZE): one process per GPU (NCCL), or per CPU process with
``--device cpu`` (gloo); DistributedDataParallel over the method's loss, a DistributedSampler,
``batch_size`` per process; only rank 0 packs, prints and writes; at the end the processes compare
a digest of their weights (history.json's ``processes``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import resource
import time
import tomllib
from collections.abc import Mapping
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

# torch's OpenMP (libgomp on Linux) spin-waits at every barrier unless told otherwise, read once
# when torch loads: on cores shared with anything else (a loader worker, another process) a
# training step then took 10x the CPU time and wall time (docs in benchmarks/train_throughput.py).
# Effective when this module is the first to import torch; the command line sets it at its start.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from tdof20.config import config_from_data
from tdof20.dataset.reader import open_dataset
from tdof20.dataset.shards import ShardDataset
from tdof20.errors import TdofError
from tdof20.formats import write_json
from tdof20.methods.base import IMAGE_SIDE, MethodMeta
from tdof20.methods.data import (TransformedDataset, check_depth_mode, collate, dataset_classes, dataset_meta,
                                 keypoints_to_json, worker_init)
from tdof20.methods.devices import amp_dtype, distributed, select_device, to_device
from tdof20.methods.history import NOT_LOSSES, plot_losses
from tdof20.methods.registry import DEFAULT_METHOD, Method, get_method
from tdof20.methods.runs import (CHECKPOINT, CONFIG, RUN_VERSION, check_run_folder, check_weights, depth_mode_of,
                                 open_config, parameters_digest, read_checkpoint, read_run_config, run_classes,
                                 save_atomic)
from tdof20.methods.runs import load_run  # noqa: F401  (re-exported: tests/test_dataset_reader.py imports it here)
from tdof20.methods.train_data import dataset_digest, images_digest, shard_for, train_images
from tdof20.progress import console, progress as progress_bar

LR_SCHEDULES = ("cosine", "step")


# --------------------------------------------------------------------------------------------
# options


def lr_factor(step: int, total: int, schedule: str, warmup: int) -> float:
    """Learning-rate multiplier at optimiser step ``step`` of ``total``: a linear warm-up over
    ``warmup`` steps, then 'cosine' (to 1 % at the end) or 'step' (x0.1 at 60 %, x0.01 at 85 %)."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    frac = min(1.0, step / max(1, total))
    if schedule == "cosine":
        return 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * frac))
    if schedule == "step":
        return 1.0 if frac < 0.6 else (0.1 if frac < 0.85 else 0.01)
    raise TdofError(f"unknown learning-rate schedule '{schedule}' (valid: {', '.join(LR_SCHEDULES)})")


@dataclass
class TrainOptions:
    """The shared training options (TOML table ``[train]``); every default works.

    image_size: (H, W) the images are resized to; () = the method's default size; (0, 0) = the
    dataset's own size. max_steps: 0 = no limit (the epochs decide)."""

    image_size: tuple[int, ...] = ()
    batch_size: int = 8
    epochs: int = 20
    lr: float = 1e-3
    lr_schedule: str = "cosine"
    weight_decay: float = 1e-4
    num_workers: int = 2
    max_steps: int = 0
    seed: int = 0
    save_every_s: float = 600.0

    def __post_init__(self) -> None:
        self.image_size = tuple(int(v) for v in self.image_size)
        if self.image_size and len(self.image_size) != 2:
            raise TdofError(f"image_size must be [H, W], got {list(self.image_size)}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise TdofError(f"lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got '{self.lr_schedule}'")


def load_train_config(path: str | Path, method: Method) -> tuple[TrainOptions, Any]:
    """(TrainOptions, the method's config) from a TOML file with the tables [train] and [method]
    (either may be left out); strict keys, one-line errors naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise TdofError("no such config file", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise TdofError(f"cannot be read ({e})", path) from None
    except tomllib.TOMLDecodeError as e:
        raise TdofError(f"is not valid TOML ({e})", path) from None
    extra = sorted(set(data) - {"train", "method"})
    if extra:
        raise TdofError(f"unknown table(s) {', '.join(extra)} (known: train, method)", path)
    return config_from_data(TrainOptions, data.get("train", {}), path), method.config_from(data.get("method"), path)


def _replace(cfg, changes: Mapping[str, Any], method: Method):
    """``cfg`` with the fields in ``changes`` replaced (checked by its __post_init__); a change to
    a field the method's config lacks is a one-line error naming the option."""
    names = {f.name for f in dataclasses.fields(cfg)}
    for k in changes:
        if k not in names:
            raise TdofError(f"--{k.replace('_', '-')} is not an option of {method.name} "
                            f"(its options: {', '.join(sorted(names))})")
    return dataclasses.replace(cfg, **changes) if changes else cfg


def make_method_config(method: Method, given=None, options: Mapping | None = None, **changes):
    """The method's config: ``given`` (a config, a dict of its options, or None = defaults) with
    ``options`` (a table of its options, nested tables for a nested config: checked as a TOML
    file's, one line naming the option) and then the ``changes`` of the command line's shortcuts
    (``depth_mode``, ``backbone_weights``: refused naming the option where the method lacks it)
    applied; None values are left out."""
    if given is None or isinstance(given, Mapping):
        cfg = method.config_from(given or {}, "method options")
    elif isinstance(given, method.config_class):
        cfg = given
    else:
        raise TdofError(f"method_config for {method.name} must be a {method.config_class.__name__} or a dict, "
                        f"got {type(given).__name__}")
    cfg = method.with_options(cfg, {k: v for k, v in (options or {}).items() if v is not None}, "method options")
    return _replace(cfg, {k: v for k, v in changes.items() if v is not None}, method)


def _check_same(saved: dict, new: dict, path: Path) -> None:
    """Refuse to resume a run with other method, network, data or batch options."""
    pairs = [("method", saved.get("method"), new.get("method"))]
    if "method_config" in saved and "method_config" in new:
        old_m, new_m = dict(saved["method_config"]), new["method_config"]
        try:  # an option added since the run was made: the run had its default
            defaults = get_method(str(new.get("method"))).config_to_data(get_method(str(new.get("method"))).default_config())
        except TdofError:
            defaults = {}
        old_m.update({k: v for k, v in defaults.items() if k not in old_m})
        pairs += [(f"{new['method']} option {k}", old_m.get(k), new_m.get(k)) for k in sorted(set(old_m) | set(new_m))]
    old_net, new_net = saved.get("network") or {}, new.get("network") or {}
    pairs += [(f"network {k}", old_net.get(k), new_net.get(k)) for k in sorted(set(old_net) | set(new_net))
              if old_net and new_net]
    pairs += [(key, saved.get(key), new.get(key)) for key in ("image_size", "depth_mode", "split")]
    pairs += [("part", saved.get("part", "train"), new.get("part", "train")),
              ("the list of training images", saved.get("images_sha256"), new.get("images_sha256"))]
    if saved.get("dataset_sha256") is not None:  # a run from before issue 22 recorded none
        pairs.append(("the dataset's content (digest of its models_info, images and labels)",
                      saved.get("dataset_sha256"), new.get("dataset_sha256")))
    pairs.append(("classes (object ids)", run_classes(saved), run_classes(new)))
    pairs.append(("batch_size", saved.get("train", {}).get("batch_size"), new["train"]["batch_size"]))
    for key, old, now in pairs:
        if old != now:
            raise TdofError(f"the run was started with {key} = {old}, now {now}: use another --out for "
                            "other network or data options", path)


# --------------------------------------------------------------------------------------------
# training


class LossModule(torch.nn.Module):
    """The method's loss as a module, ``forward(batch) -> total``, so that DistributedDataParallel
    sees every network call of the loss (a method's loss may call sub-networks directly); the
    parts of the last call are in ``parts``."""

    def __init__(self, method: Method, net: torch.nn.Module, cfg, meta):
        super().__init__()
        self.net = net
        self.method, self.cfg, self.meta = method, cfg, meta
        self.parts: dict[str, float] = {}

    def forward(self, batch: dict) -> torch.Tensor:
        total, self.parts = self.method.loss(self.net, batch, self.cfg, self.meta)
        return total


class EpochIndices(torch.utils.data.Sampler):
    """The image indices of the current epoch (set before each pass): one DataLoader with
    persistent workers serves every epoch, so workers are forked once per call rather than once per
    epoch (each fork made the next steps copy the network's and AdamW's written pages)."""

    def __init__(self) -> None:
        self.indices: list[int] = []

    def __iter__(self):
        return iter(self.indices)

    def __len__(self) -> int:
        return len(self.indices)


def _cpu_seconds() -> float:
    """CPU seconds of this process (user + system): beside an epoch's wall time it tells starved
    (wall >> CPU) from busy (CPU grew: spinning threads, page faults)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _meta_json(meta) -> dict:
    d = meta.to_json()
    d["model_points"] = {k: [[round(float(x), 3) for x in p] for p in v] for k, v in d["model_points"].items()}
    return d


_METHOD_DEFAULT = "method"
_WEIGHTS_ONLY = ("holds the weights only (its training ended and its optimiser state was dropped, as reproduce "
                 "does): train into another --out")


def train(dataset_root: str | Path, split: str, out_run: str | Path, *, method: str = DEFAULT_METHOD,
          method_config=None, image_size: tuple[int, int] | None | str = _METHOD_DEFAULT, batch_size: int = 8,
          epochs: int = 20, lr: float = 1e-3, lr_schedule: str = "cosine", weight_decay: float = 1e-4,
          depth_mode: str | None = None, device: str = "auto", amp: bool | None = None, num_workers: int = 2,
          max_steps: int | None = None, seed: int = 0, backbone_weights: str | Path | None = None,
          shard: str | Path | None = None,
          save_every_s: float = 600.0, progress: bool = True, cache_dir: str | Path | None = None,
          part: str = "train", images: list[tuple[int, int]] | None = None,
          stop_epoch: int | None = None, keep_optimizer: bool = True, method_options: Mapping | None = None,
          **options) -> Path:
    """Train (or resume training) ``method`` on the train part of ``split`` of the dataset at
    ``dataset_root``; returns the run folder ``out_run``.

    method: a registered method (tdof20.methods.registry; default the paper's). method_config: its
    config (a dataclass, a dict of its options, or None = its defaults); method_options (a table,
    nested tables for a nested config) and keyword ``options`` (e.g. ``fuse_stages=2``): options
    of that config over it, checked as a TOML file's; depth_mode ('raw' | 'filled' | 'restored',
    the last privileged) and backbone_weights (a torchvision checkpoint for the method's ResNet)
    are shortcuts for options of that config (None: as the config says; an option the method
    lacks is refused).
    image_size: (H, W) the images are resized to (colour by area, depth and labels by nearest
    neighbour, K scaled); 'method' = the method's default size; None = the dataset's own size.
    batch_size: images per optimiser step per process. epochs: passes over the training images in
    all (counting earlier calls on this run). lr, lr_schedule ('cosine' | 'step'), weight_decay:
    AdamW with a short linear warm-up. device: 'auto' | 'cpu' | 'cuda' | 'cuda:N' | 'mps'. amp:
    mixed precision (None = on for CUDA; bf16 where supported, else fp16 with loss scaling).
    max_steps: stop after this many optimiser steps in all (the schedule then spans them). shard:
    an HDF5 file from `tdof20 dataset pack` to train on instead of packing into RUN/data/.
    save_every_s: checkpoint at the end of an epoch when the last checkpoint is older than this many
    seconds (0 = after every epoch), and always when the run ends.
    part: 'train' (default: the split's whole train part) or 'train-val' (the train part minus its
    validation part, :mod:`tdof20.dataset.validation`, so that choices can be made on
    validation); images: an explicit list of (scene_id, im_id) of the train part instead. The run
    records its part ("part", and "images_sha256" of the list) and refuses to resume on another.
    stop_epoch: end this call once this many epochs are done in all (or at the run's end, if that
    comes first), with a checkpoint; the learning-rate schedule still spans ``epochs`` (or
    ``max_steps``), so calling again with a larger ``stop_epoch`` continues the very same run: how a
    caller validates each epoch's checkpoint (``tdof20 reproduce`` keeps the validation-best one).
    keep_optimizer: False = the checkpoint written when the run reaches its end (the last step of
    ``epochs`` or ``max_steps``) leaves out the optimiser's (and AMP scaler's) state, two thirds of
    the file, as :func:`~tdof20.methods.runs.drop_optimizer` would, without reading and writing the
    file again (``tdof20 reproduce``'s runs): the run is then predicted and scored, and calling
    train on it again is a no-op while it asks for no further step, refused once it does.

    Any dataset layout (tdof20's, BOP's: ``split`` is then a split folder such as 'train_pbr') and
    any object ids: classes 1..n map to the dataset's objects (the run's meta; a tdof20 dataset
    within ids 1..20 keeps the catalog's 20). Restored depth the dataset lacks is rendered once
    into ROOT/.cache/ (or ``cache_dir``) when the shard is packed (training targets use it; the
    input depth of every method is the sensor's, raw or filled, unless depth_mode says 'restored').
    """
    rank, local_rank, world = distributed()
    try:  # the checks before any work
        m = get_method(method)
        dataset_root = Path(dataset_root)
        out_run = Path(out_run)
        ds = open_dataset(dataset_root)  # the one "not a dataset" check
        split = ds.check_train_split(split)
        if depth_mode is not None:
            check_depth_mode(depth_mode)
        if lr_schedule not in LR_SCHEDULES:
            raise TdofError(f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got '{lr_schedule}'")
        if batch_size < 1 or epochs < 1 or not 0 < lr < float("inf"):
            raise TdofError(f"--batch-size and --epochs must be >= 1 and --lr a number > 0, got {batch_size}, "
                            f"{epochs} and {lr}")
        if num_workers < 0 or seed < 0:
            raise TdofError(f"--workers and --seed must be >= 0, got {num_workers} and {seed}")
        if image_size is not None and not isinstance(image_size, str) and not all(
                IMAGE_SIDE[0] <= int(v) <= IMAGE_SIDE[1] for v in image_size):
            raise TdofError(f"--image-size must be within {IMAGE_SIDE[0]}..{IMAGE_SIDE[1]} pixels a side, "
                            f"got {image_size}")
        if stop_epoch is not None and int(stop_epoch) < 1:
            raise TdofError(f"stop_epoch must be >= 1, got {stop_epoch}")
        cfg = make_method_config(m, method_config, {**(method_options or {}), **options}, depth_mode=depth_mode,
                                 backbone_weights=None if backbone_weights is None else str(backbone_weights))
        if isinstance(image_size, str):
            if image_size != _METHOD_DEFAULT:
                raise TdofError(f"image_size must be (H, W), None or '{_METHOD_DEFAULT}', got '{image_size}'")
            image_size = tuple(m.default_image_size)

        check_run_folder(out_run, dataset_root)
        if shard is not None and (part != "train" or images is not None):
            raise TdofError("--shard decides the training images: give it without --part or an image list", shard)
        if shard is None:
            ds.part_frames(split, "train", "train on")
        subset, part = train_images(dataset_root, split, part, images) if shard is None else (None, "train")
        # what the run's data is made from (a --shard's own objects are checked against the dataset)
        data_digest = dataset_digest(dataset_root, split, subset) if shard is None else None

        dev = select_device(device)
        if world > 1:
            if dev.type == "cuda":
                dev = torch.device("cuda", local_rank)
                torch.cuda.set_device(dev)
            elif dev.type != "cpu":
                raise TdofError(f"--device {device}: training in {world} processes runs on CUDA (NCCL) or the CPU "
                                "(gloo), not on this device")
        main = rank == 0
        show = bool(progress) and main
        use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")

        # the run to resume, read and checked before anything is written or packed
        ckpt_path = out_run / CHECKPOINT
        resume = ckpt_path.exists()
        ckpt = saved = saved_meta = None
        if resume:
            advice = (f": move {CHECKPOINT} out of the run folder to start the run afresh, or train into another "
                      "--out")
            saved = read_run_config(out_run, advice)
            ckpt = read_checkpoint(ckpt_path, needs=("model", "epoch", "step", "history"), advice=advice)
            try:
                ckpt_epoch, ckpt_step = int(ckpt["epoch"]), int(ckpt["step"])
                ckpt_history = list(ckpt["history"])
            except (TypeError, ValueError):
                raise TdofError(f"its epoch, step or history is not what train writes{advice}", ckpt_path) from None
            # a run whose optimiser state was dropped at its end trains no further; a call that asks for
            # no further step (its epochs, max_steps or stop_epoch already reached) is the no-op it
            # was before the drop (a resumed tdof20 reproduce makes such calls)
            if "optimizer" not in ckpt and not (
                    ckpt_epoch >= epochs or (max_steps is not None and ckpt_step >= int(max_steps))
                    or (stop_epoch is not None and ckpt_epoch >= int(stop_epoch))):
                raise TdofError(_WEIGHTS_ONLY, ckpt_path)
            with torch.device("meta"):  # shapes only: nothing is allocated
                saved_m, _, saved_net, saved_meta = open_config(saved, out_run / CONFIG)
                check_weights(saved_net, ckpt, saved, ckpt_path, advice)
            if saved_m.name != m.name:
                raise TdofError(f"the run was started with method = {saved_m.name}, now {m.name}: use another --out "
                                "for another method", out_run / CONFIG)
            # the options that must not change, before the work (a native image size is known later)
            early = {"method": m.name, "image_size": saved.get("image_size") if image_size is None else
                     [int(image_size[0]), int(image_size[1])], "depth_mode": depth_mode_of(cfg), "split": split,
                     "part": part, "images_sha256": images_digest(subset), "dataset_sha256": data_digest,
                     "classes": run_classes(saved), "train": {"batch_size": batch_size},
                     "method_config": m.config_to_data(cfg)}
            with torch.device("meta"):
                early.update(m.run_record(m.build(cfg, saved_meta)))
            _check_same(saved, early, out_run / CONFIG)
    except TdofError as e:
        # each process of a launch meets the same refusal here, before the processes meet: the
        # command line lets process 0 alone print it
        e.same_in_every_process = world > 1
        raise

    dist = wait_group = None
    try:
        if world > 1:
            import torch.distributed as dist
            if not dist.is_initialized():
                dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
            # packing the shard can take long: the other processes wait for it on a group without
            # the default collective timeout
            wait_group = dist.new_group(backend="gloo", timeout=timedelta(days=7))
        if amp and dev.type != "cuda" and show:
            console.print("[yellow]mixed precision is for CUDA devices; training in float32")
        if main:
            out_run.mkdir(parents=True, exist_ok=True)
        shard_path = shard_for(dataset_root, split, out_run, shard, rank, show, cache_dir, subset, part,
                               data_digest)
        if dist is not None:
            dist.barrier(group=wait_group)
        data = ShardDataset(shard_path)
        if image_size is None:
            import h5py
            with h5py.File(shard_path, "r") as f:
                image_size = tuple(int(v) for v in f["rgb"].shape[1:3])
        image_size = (int(image_size[0]), int(image_size[1]))
        if min(image_size) < 32:
            raise TdofError(f"--image-size {image_size[0]}x{image_size[1]} is too small (32 pixels at least)")
        if len(data) < world:
            raise TdofError(f"{len(data)} training image{'s' if len(data) != 1 else ''} cannot be shared among "
                            f"{world} processes: use fewer processes", shard_path)

        if resume:
            meta = MethodMeta(obj_ids=saved_meta.obj_ids, keypoints=saved_meta.keypoints,
                              diameters=saved_meta.diameters, symmetric=saved_meta.symmetric,
                              model_points=saved_meta.model_points, image_size=image_size)
            if "meta" not in saved and set(meta.obj_ids) <= set(ds.obj_ids):
                # a run from before the interface recorded no model samples: take them from the dataset
                meta = dataset_meta(ds, meta.obj_ids, image_size)
                meta = MethodMeta(obj_ids=meta.obj_ids, keypoints=saved_meta.keypoints, diameters=meta.diameters,
                                  symmetric=meta.symmetric, model_points=meta.model_points, image_size=image_size)
        else:
            meta = dataset_meta(ds, dataset_classes(ds.obj_ids, ds.uses_catalog_ids), image_size)
        torch.manual_seed(seed)
        net = m.build(cfg, meta)
        train_options = dict(batch_size=batch_size, epochs=epochs, lr=lr, lr_schedule=lr_schedule,
                       weight_decay=weight_decay, amp=use_amp, num_workers=num_workers, max_steps=max_steps,
                       seed=seed, backbone_weights=None if backbone_weights is None else str(backbone_weights),
                       world_size=world, device=str(dev))
        config = {"method": m.name, "version": RUN_VERSION, "method_config": m.config_to_data(cfg), "meta": _meta_json(meta),
                  "input": m.inputs, "image_size": list(image_size), "depth_mode": depth_mode_of(cfg), "split": split,
                  "part": part, "images_sha256": images_digest(subset), "dataset_sha256": data_digest,
                  "dataset": str(dataset_root.resolve()), "shard": str(Path(shard_path).resolve()),
                  "keypoints": keypoints_to_json(meta.keypoints), "classes": list(meta.obj_ids),
                  "objects": {str(o): ds.object_name(o) for o in meta.obj_ids if o in ds.models_info},
                  "layout": ds.layout, "train": train_options, **m.run_record(net)}
        if resume:
            _check_same(saved, config, out_run / CONFIG)
            net.load_state_dict(ckpt["model"])
        net = net.to(dev)
        if dev.type == "cuda":
            net = net.to(memory_format=torch.channels_last)
            torch.backends.cudnn.benchmark = True
        # fused: one kernel over all parameters instead of a dozen element-wise passes each; on the
        # CPU that is 5x less optimiser time (HFF6DoF's 57 M parameters: 0.38 -> 0.075 s a step,
        # a third of a 48x64 batch-4 step), the same update to float rounding (~1e-8)
        opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay,
                                fused=dev.type in ("cpu", "cuda"))
        scaler = torch.amp.GradScaler("cuda", enabled=use_amp and amp_dtype(dev) == torch.float16)
        epoch, step, history, epochs_log = 0, 0, [], []
        weights_only = False  # resumed from a checkpoint without the optimiser's state
        if resume:
            try:  # moves AdamW's moments to the parameters' device (a run over has none: it trains no more)
                if "optimizer" in ckpt:
                    opt.load_state_dict(ckpt["optimizer"])
                if ckpt.get("scaler") and scaler.is_enabled():
                    scaler.load_state_dict(ckpt["scaler"])
            except (ValueError, KeyError, TypeError, RuntimeError) as e:
                raise TdofError(f"its optimiser state does not fit the network ({type(e).__name__}: "
                                f"{(str(e).splitlines() or [''])[0][:80]}){advice}", ckpt_path) from None
            weights_only = "optimizer" not in ckpt
            epoch, step, history = ckpt_epoch, ckpt_step, ckpt_history
            epochs_log = list(ckpt.get("epochs") or [])
            for g in opt.param_groups:  # the options of this call win (lr, weight decay)
                g["weight_decay"] = weight_decay
            ckpt = None  # the weights now live in the network and the optimiser
        if main:  # written once the run's state is known to load
            write_json(out_run / CONFIG, config)
        loss_module = LossModule(m, net, cfg, meta)
        model = loss_module
        if world > 1:
            if dev.type == "cuda":
                model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            model = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[local_rank] if dev.type == "cuda" else None,
                find_unused_parameters=m.ddp_find_unused_parameters)

        transform = m.transform(cfg, meta, train=True)
        # a transform whose dense per-pixel part can run batched on the training device
        # (``defer_to_device() -> stage``; HFF6DoF's): there on a GPU, so that CPU loader workers do
        # not starve it (on the CPU the workers keep it, overlapped with the step)
        defer = getattr(transform, "defer_to_device", None)
        device_stage = defer() if defer is not None and dev.type != "cpu" else None
        tdata = TransformedDataset(data, transform)
        n = len(tdata)
        per_rank = n // world
        bs = min(batch_size, max(1, per_rank))
        steps_per_epoch = max(1, per_rank // bs)
        total = epochs * steps_per_epoch
        if max_steps is not None:
            total = min(total, int(max_steps))
        warmup = min(200, total // 20)
        # where this call ends: the run's end, or the end of epoch stop_epoch (the schedule spans total)
        limit = total if stop_epoch is None else min(total, int(stop_epoch) * steps_per_epoch)
        if weights_only and step < limit:  # the early check's counters disagree (another number of processes)
            raise TdofError(_WEIGHTS_ONLY, ckpt_path)
        sampler = torch.utils.data.DistributedSampler(tdata, num_replicas=world, rank=rank, shuffle=True,
                                                      seed=seed, drop_last=True)
        if main and show:
            console.print(f"{m.name} on {split}/{part}: {n} images at {image_size[0]}x{image_size[1]}, depth "
                          f"{depth_mode_of(cfg)}, batch {bs} x {world} process(es), {steps_per_epoch} steps/epoch, "
                          f"device {dev}{' (AMP ' + str(amp_dtype(dev)).split('.')[-1] + ')' if use_amp else ''}"
                          + (f", resuming at epoch {epoch}, step {step}" if resume else ""), markup=False)

        last_save = [time.perf_counter()]
        # what check_weights compares (method, options, image size, depth, keypoints), without the
        # meta's model samples (config.json keeps them): a third of a megabyte of pickle that every
        # reader of last.pt unpickled in pure Python (weights_only), more than its weights cost
        ckpt_config = {k: v for k, v in config.items() if k != "meta"}

        def save(processes: dict | None = None) -> None:
            last_save[0] = time.perf_counter()
            if not main:
                return
            # the run's end without keep_optimizer: the weights, counters and history only
            over = weights_only or (not keep_optimizer and step >= total)
            save_atomic({"model": net.state_dict(),
                         **({} if over else {"optimizer": opt.state_dict(),
                                             "scaler": scaler.state_dict() if scaler.is_enabled() else None}),
                         "epoch": epoch, "step": step, "history": history, "epochs": epochs_log,
                         "config": ckpt_config}, ckpt_path)
            write_json(out_run / "history.json", {"epochs": epochs_log, "steps": step, "total_steps": total,
                                                   "steps_per_epoch": steps_per_epoch,
                                                   **({"processes": processes} if processes else {})})
            if history:
                plot_losses(history, out_run / "loss.png", f"{m.name} training")

        global_bs = bs * world
        start_step = step
        epoch_idx = EpochIndices()
        loader = torch.utils.data.DataLoader(
            tdata, batch_size=bs, sampler=epoch_idx, num_workers=num_workers, collate_fn=collate,
            worker_init_fn=worker_init, drop_last=True, pin_memory=dev.type == "cuda",
            persistent_workers=num_workers > 0)
        with progress_bar(show, unit="img") as bar:
            task = bar.add_task("training", total=limit * global_bs, completed=min(step, limit) * global_bs)
            while step < limit:
                sampler.set_epoch(epoch)
                skip = step - epoch * steps_per_epoch  # steps of this epoch done before a resume
                epoch_idx.indices = list(sampler)[max(0, skip) * bs: steps_per_epoch * bs]
                model.train()
                t0, n_img, sums, counts = time.perf_counter(), 0, {}, {}
                c0, data_s, n_steps = _cpu_seconds(), 0.0, 0
                batches = iter(loader)
                while True:
                    t_wait = time.perf_counter()
                    batch = next(batches, None)
                    data_s += time.perf_counter() - t_wait
                    if batch is None or step >= limit:
                        break
                    batch = to_device(batch, dev)
                    if device_stage is not None:  # the input side too: counted with the loader's wait
                        t_wait = time.perf_counter()
                        batch = device_stage(batch)
                        data_s += time.perf_counter() - t_wait
                    lr_now = lr * lr_factor(step, total, lr_schedule, warmup)
                    for g in opt.param_groups:
                        g["lr"] = lr_now
                    ctx = torch.autocast(dev.type, dtype=amp_dtype(dev)) if use_amp else nullcontext()
                    with ctx:
                        loss = model(batch)
                    opt.zero_grad(set_to_none=True)
                    scaler.scale(loss).backward()
                    scaler.step(opt)
                    scaler.update()
                    step += 1
                    n_steps += 1
                    n_img += batch["rgb"].shape[0] * world
                    parts = {k: float(v) for k, v in loss_module.parts.items() if k != "loss"}
                    rec = {"step": step, "epoch": epoch, "loss": float(loss.detach()), **parts, "lr": lr_now}
                    if not math.isfinite(rec["loss"]):
                        raise TdofError(f"the loss became {rec['loss']} at step {step}: lower --lr "
                                        "(the last good checkpoint is kept)", out_run)
                    history.append(rec)
                    for k, v in rec.items():
                        if k not in NOT_LOSSES and math.isfinite(v):
                            sums[k] = sums.get(k, 0.0) + v
                            counts[k] = counts.get(k, 0) + 1
                    bar.update(task, advance=global_bs,
                               description=f"epoch {epoch + 1}/{epochs} loss {rec['loss']:.3f}")
                dt = time.perf_counter() - t0
                cpu_s = _cpu_seconds() - c0
                if step >= (epoch + 1) * steps_per_epoch or step >= total:
                    if n_steps:
                        # data_seconds: waiting for the loader (the input side's share of the epoch);
                        # cpu_seconds: this process's CPU time (wall >> CPU x threads: starved by others)
                        epochs_log.append({"epoch": epoch + 1, "steps": step,
                                           **{k: v / counts[k] for k, v in sums.items()},
                                           "lr": history[-1]["lr"], "seconds": round(dt, 2),
                                           "images_per_s": round(n_img / dt, 2) if dt > 0 else None,
                                           "data_seconds": round(data_s, 3), "cpu_seconds": round(cpu_s, 2),
                                           "threads": torch.get_num_threads()})
                    if step >= (epoch + 1) * steps_per_epoch:
                        epoch += 1
                if step < limit and time.perf_counter() - last_save[0] >= save_every_s:
                    save()
                if show and epochs_log:
                    e = epochs_log[-1]
                    others = ", ".join(f"{k} {v:.4f}" for k, v in e.items()
                                       if k not in ("epoch", "steps", "loss", "lr", "seconds", "images_per_s",
                                                    "data_seconds", "cpu_seconds", "threads"))
                    console.print(f"epoch {e['epoch']}: loss {e['loss']:.4f}" + (f" ({others})" if others else "")
                                  + f", {e['images_per_s']} images/s")
        processes = None
        if dist is not None:
            processes = {"world_size": world, "backend": dist.get_backend(),
                         "weights_sha256": [None] * world}
            dist.all_gather_object(processes["weights_sha256"], parameters_digest(net))
            processes["in_sync"] = len(set(processes["weights_sha256"])) == 1
            if not processes["in_sync"] and show:
                console.print("[bold red]the processes ended with different weights: the checkpoint holds "
                              "process 0's")
        if step > start_step or not ckpt_path.exists():  # max_steps=0: the untrained network (a baseline)
            save(processes)
        if dist is not None:
            dist.barrier(group=wait_group)  # the others end when process 0 has written the checkpoint
        if show:
            console.print(f"run: {out_run} (last.pt, config.json, loss.png)", markup=False)
    finally:
        # no barrier on the way out of an error: the other processes may be inside a collective;
        # the launcher (torchrun) ends them when this one exits non-zero
        if dist is not None and dist.is_initialized():
            dist.destroy_process_group()
    return out_run
