"""Training HFF6DoF on a dataset split (``tdof20 train hff6dof``).

    from tdof20.methods.train import train
    run = train("ROOT", "simple", "runs/simple", image_size=(240, 320), epochs=20)

A run folder holds everything needed to resume and to predict:

    RUN/config.json       network config, keypoints {obj_id: (9,3) mm}, image size, depth mode, and
                          the training options (what predict rebuilds the network from)
    RUN/last.pt           model, optimiser (and AMP scaler) state, epoch and step counters, loss history
    RUN/history.json      per-epoch losses, learning rate, images/s (several processes: each one's
                          weights digest at the end, which must agree)
    RUN/loss.png          loss curves (total, segmentation, vector field) and learning rate
    RUN/data/{split}_train.h5   the packed training shard (made on first use, reused afterwards)

Running ``train`` again on the same RUN resumes from last.pt: the epoch and step counters, the
optimiser's moments and the loss history continue; asking for more ``epochs`` (or a larger
``max_steps``) extends the run. The network options must not change between calls.

Everything a call refuses (a damaged or foreign last.pt, an --out that is a file, an empty split
part, changed options) is refused before anything is packed or written, and the files found are
left as they are.

Several processes: ``torchrun --nproc_per_node N -m tdof20 train hff6dof ...`` (or any launcher
that sets RANK / LOCAL_RANK / WORLD_SIZE): one process per GPU (NCCL), or per CPU process with
``--device cpu`` (gloo); DistributedDataParallel, a DistributedSampler, ``batch_size`` per
process; only rank 0 packs, prints and writes; at the end the processes compare a digest of
their weights (history.json's ``processes``).
"""

from __future__ import annotations

import hashlib
import math
import os
import time
import zipfile
from contextlib import nullcontext
from datetime import timedelta
from pathlib import Path

import torch

from tdof20.errors import TdofError
from tdof20.formats import read_json, write_json
from tdof20.formats.io import check_parents
from tdof20.methods.data import (DEFAULT_DEPTH_MODE, N_KEYPOINTS, HFFTransform, TransformedDataset,
                                 check_depth_mode, collate, dataset_classes, identity_classes, keypoints_from_json,
                                 keypoints_to_json, split_part_images, worker_init)
from tdof20.methods.hff6dof import HFF6DoF
from tdof20.methods.losses import hff_loss
from tdof20.progress import console, progress as progress_bar

LR_SCHEDULES = ("cosine", "step")
CHECKPOINT = "last.pt"
CONFIG = "config.json"


# --------------------------------------------------------------------------------------------
# devices and processes


def select_device(device: str = "auto") -> torch.device:
    """'auto' -> the first CUDA GPU, else Apple MPS, else the CPU; anything else as torch reads it."""
    if device in (None, "", "auto"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except RuntimeError as e:
        raise TdofError(f"--device: {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise TdofError(f"--device {device}: this torch has no CUDA device")
    return dev


def _distributed() -> tuple[int, int, int]:
    """(rank, local_rank, world_size) from the launcher's environment (1 process without one)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 0, 1
    return int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")), world


def is_main_process() -> bool:
    """True in a single process and in process 0 of a launch (torchrun): the one that writes and prints."""
    return _distributed()[0] == 0


def amp_dtype(dev: torch.device) -> torch.dtype:
    return torch.bfloat16 if dev.type == "cuda" and torch.cuda.is_bf16_supported() else torch.float16


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


# --------------------------------------------------------------------------------------------
# run folder


NETWORK_KEYS = ("n_classes", "n_keypoints", "fuse_stages", "seg_head", "decoder_channels", "head_channels",
                "geo_channels")
RUN_KEYS = ("network", "image_size", "depth_mode", "split", "keypoints")


def build_network(config: dict, path: Path | None = None) -> HFF6DoF:
    """The network described by a run's config.json (``path``: that file, for the error message)."""
    net = config["network"]
    try:
        return HFF6DoF(n_classes=net["n_classes"], n_keypoints=net["n_keypoints"], fuse_stages=net["fuse_stages"],
                       seg_head=net["seg_head"], decoder_channels=net["decoder_channels"],
                       head_channels=net["head_channels"], geo_channels=net["geo_channels"])
    except (ValueError, TypeError, RuntimeError) as e:
        raise TdofError(f"its network options do not make a network ({e})", path) from None


def read_run_config(run_dir: str | Path, advice: str = "") -> dict:
    """A run's config.json, checked to be an HFF6DoF run's with every key predict and resume need."""
    path = Path(run_dir) / CONFIG
    if not path.exists():
        raise TdofError(f"missing: the run folder holds {CHECKPOINT} without the {CONFIG} it belongs to{advice}", path)
    config = read_json(path)
    if not isinstance(config, dict) or config.get("method") != "hff6dof":
        raise TdofError(f"not an HFF6DoF run's {CONFIG}{advice}", path)
    missing = [k for k in RUN_KEYS if k not in config]
    if isinstance(config.get("network"), dict):
        missing += [f"network.{k}" for k in NETWORK_KEYS if k not in config["network"]]
    elif "network" in config:
        missing.append("network (not a table)")
    if missing:
        raise TdofError(f"lacks {', '.join(missing)}{advice}", path)
    return config


def _size_text(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 100_000 else f"{n} bytes"


def _load_failure(e: BaseException) -> str:
    """What torch.load's exception says about a file, in a few words."""
    text = (str(e).strip().splitlines() or [""])[0]
    if isinstance(e, EOFError):
        return "the file ends early: it is cut short"
    if "zip archive" in text or "central directory" in text:
        return "its zip archive is damaged"
    if text.startswith("Weights only load failed"):
        return "it holds objects other than tensors and plain data"
    text = text.split(". ")[0]
    return f"damaged or not a torch checkpoint ({type(e).__name__}: {text[:80]})"


def read_checkpoint(path: str | Path, needs: tuple[str, ...] = ("model",), advice: str = "",
                    mmap: bool = False) -> dict:
    """The dict a run's last.pt holds, loaded on the CPU without running any code from the file
    (``weights_only``); a one-line TdofError naming the file when it is truncated, random bytes, or
    lacks one of ``needs``. The file itself is left as it is. ``mmap``: map the file instead of
    reading it (only the tensors used are read: predict reads the weights, not AdamW's moments)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as e:
        raise TdofError(f"cannot be read ({e.strerror}){advice}", path) from None
    if path.is_dir():
        raise TdofError(f"is a folder, not a checkpoint{advice}", path)
    if size == 0:
        raise TdofError(f"cannot be read as a checkpoint (the file is empty){advice}", path)
    if not zipfile.is_zipfile(path):
        with open(path, "rb") as f:
            truncated = f.read(4) == b"PK\x03\x04"
        why = ("truncated: it begins like a torch checkpoint but its end is missing" if truncated else
               "not a torch checkpoint: not the zip archive torch.save writes")
        raise TdofError(f"cannot be read as a checkpoint ({_size_text(size)}; {why}){advice}", path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as e:  # a damaged file can make the unpickler fail in any way
        raise TdofError(f"cannot be read as a checkpoint ({_size_text(size)}; {_load_failure(e)}){advice}",
                        path) from None
    if not isinstance(ckpt, dict):
        raise TdofError(f"is not an HFF6DoF checkpoint (it holds a {type(ckpt).__name__}, not a dict with "
                        f"the network's weights){advice}", path)
    missing = [k for k in needs if k not in ckpt]
    if missing:
        raise TdofError(f"is not an HFF6DoF checkpoint (no {', '.join(missing)} in it){advice}", path)
    model = ckpt["model"]
    if not isinstance(model, dict) or not all(isinstance(v, torch.Tensor) for v in model.values()):
        raise TdofError(f"is not an HFF6DoF checkpoint ('model' is not a dict of tensors){advice}", path)
    return ckpt


def _weights(keys: list[str]) -> str:
    return f"{len(keys)} weight{'s' if len(keys) != 1 else ''}"


def _examples(keys: list[str]) -> str:
    return ", ".join(keys[:2]) + (", ..." if len(keys) > 2 else "")


def check_weights(net: HFF6DoF, ckpt: dict, config: dict, path: Path, advice: str = "") -> None:
    """A one-line TdofError naming the checkpoint ``path`` when its weights do not fit ``net`` (the
    network ``config``, the run's config.json, describes; it may live on the meta device) or the
    checkpoint was written by a run of other options."""
    why = []
    saved = ckpt.get("config")
    if isinstance(saved, dict):
        old, now = saved.get("network") or {}, config.get("network") or {}
        why += [f"{k} {old.get(k)} here, {now.get(k)} in {CONFIG}" for k in NETWORK_KEYS
                if k in old and old.get(k) != now.get(k)]
        why += [f"{k} {saved.get(k)} here, {config.get(k)} in {CONFIG}" for k in ("image_size", "depth_mode")
                if k in saved and saved.get(k) != config.get(k)]
        if "keypoints" in saved and saved["keypoints"] != config.get("keypoints"):
            why.append(f"other keypoints than {CONFIG}'s")
    own, state = net.state_dict(), ckpt["model"]
    missing = [k for k in own if k not in state]
    extra = [k for k in state if k not in own]
    shape = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing:
        why.append(f"{_weights(missing)} missing ({_examples(missing)})")
    if extra:
        why.append(f"{_weights(extra)} the network does not have ({_examples(extra)})")
    if shape:
        k = shape[0]
        why.append(f"{_weights(shape)} of another shape ({k} {list(state[k].shape)}, the network's "
                   f"{list(own[k].shape)})")
    if why:
        raise TdofError(f"holds another network than the run's {CONFIG} describes: {'; '.join(why)}{advice}", path)


def run_classes(config: dict) -> list[int]:
    """The object id of each class 1..n of a run (config.json's "classes"; a run recorded without
    one: ids 1..n_classes-1, class = obj_id)."""
    classes = config.get("classes")
    if classes is None:
        return identity_classes(config["network"]["n_classes"])
    return [int(c) for c in classes]


def load_run(run_dir: str | Path, device: str | torch.device = "cpu") -> tuple[HFF6DoF, dict]:
    """(network with the run's last weights, in eval mode, on ``device``; the run's config)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise TdofError("is a file, not a run folder (tdof20 train hff6dof --out makes one)", run_dir)
    if not (run_dir / CONFIG).exists() or not (run_dir / CHECKPOINT).exists():
        raise TdofError(f"not an HFF6DoF run (needs {CONFIG} and {CHECKPOINT}; train one first)", run_dir)
    advice = ": restore it from a copy, or train a new run into another --out"
    config = read_run_config(run_dir)
    ckpt = read_checkpoint(run_dir / CHECKPOINT, advice=advice, mmap=True)
    net = build_network(config, run_dir / CONFIG)
    check_weights(net, ckpt, config, run_dir / CHECKPOINT, advice)
    net.load_state_dict(ckpt["model"])
    return net.to(device).eval(), config


def check_run_folder(out_run: Path, dataset_root: Path) -> None:
    """Refuse, before any work, a --out that cannot be (or must not be made) a run folder."""
    if out_run.exists() and not out_run.is_dir():
        raise TdofError("--out is a file, not a run folder: give a folder (created) or an existing run to resume",
                        out_run)
    check_parents(out_run, "--out")
    if (out_run / "dataset_info.json").exists() or out_run.resolve() == dataset_root.resolve():
        raise TdofError("--out is a dataset root (it is only read): give a run folder of its own", out_run)
    cfg = out_run / CONFIG
    if cfg.exists() and not (out_run / CHECKPOINT).exists():
        try:
            foreign = read_json(cfg).get("method") != "hff6dof"
        except (TdofError, AttributeError):
            foreign = True
        if foreign:
            raise TdofError(f"--out holds a {CONFIG} that is not an HFF6DoF run's (training would overwrite it): "
                            "give another --out", out_run)


def parameters_digest(net: torch.nn.Module) -> str:
    """SHA-256 of the network's parameters (bytes, in order): equal digests = identical weights."""
    h = hashlib.sha256()
    for name, p in net.named_parameters():
        h.update(name.encode())
        h.update(p.detach().float().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def plot_losses(history: list[dict], path: Path) -> Path:
    """Loss curves (per step, with a moving average) and the learning rate, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    steps = np.array([h["step"] for h in history])
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    w = max(1, len(history) // 50)
    for key, colour in (("loss", "black"), ("seg", "tab:blue"), ("vec", "tab:orange")):
        y = np.array([h[key] for h in history], dtype=float)
        ax.plot(steps, y, color=colour, alpha=0.25, lw=0.8)
        if len(y) >= w:
            ys = np.convolve(y, np.ones(w) / w, mode="valid")
            ax.plot(steps[w - 1:], ys, color=colour, lw=1.6, label={"loss": "total", "seg": "segmentation (CE)",
                                                                     "vec": "vector field (L1)"}[key])
    ax.set_yscale("log")
    ax.set_xlabel("optimiser step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3, which="both")
    ax2 = ax.twinx()
    ax2.plot(steps, [h["lr"] for h in history], color="tab:green", lw=1, ls="--", label="learning rate")
    ax2.set_ylabel("learning rate")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
    ax.set_title("HFF6DoF training")
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def _check_same(saved: dict, new: dict, path: Path) -> None:
    old_net, new_net = saved.get("network") or {}, new.get("network") or {}
    pairs = [(f"network {k}", old_net.get(k), new_net.get(k)) for k in sorted(set(old_net) | set(new_net))]
    pairs += [(key, saved.get(key), new.get(key)) for key in ("image_size", "depth_mode", "split")]
    pairs.append(("classes (object ids)", run_classes(saved), run_classes(new)))
    pairs.append(("batch_size", saved.get("train", {}).get("batch_size"), new["train"]["batch_size"]))
    for key, old, now in pairs:
        if old != now:
            raise TdofError(f"the run was started with {key} = {old}, now {now}: use another --out for "
                            "other network or data options", path)


def _shard_for(dataset_root: Path, split: str, out_run: Path, shard: str | Path | None, rank: int,
               show: bool, cache_dir: str | Path | None = None) -> Path:
    from tdof20.benchmark.dataset import pack

    if shard is not None:
        path = Path(shard)
        if not path.exists():
            raise TdofError("no such shard (write one with `tdof20 dataset pack`)", path)
        return path
    path = out_run / "data" / f"{split}_train.h5"
    if rank == 0 and not path.exists():
        pack(dataset_root, split, "train", path, show_progress=show, cache_dir=cache_dir)
    return path


# --------------------------------------------------------------------------------------------
# training


def train(dataset_root: str | Path, split: str, out_run: str | Path, *,
          image_size: tuple[int, int] | None = (240, 320), batch_size: int = 8, epochs: int = 20,
          lr: float = 1e-3, lr_schedule: str = "cosine", weight_decay: float = 1e-4,
          depth_mode: str = DEFAULT_DEPTH_MODE, fuse_stages: int = 3, seg_head: bool = True,
          device: str = "auto", amp: bool | None = None, num_workers: int = 2, max_steps: int | None = None,
          seed: int = 0, backbone_weights: str | Path | None = None, shard: str | Path | None = None,
          save_every_s: float = 600.0, progress: bool = True, cache_dir: str | Path | None = None) -> Path:
    """Train (or resume training) HFF6DoF on the train part of ``split`` of the dataset at
    ``dataset_root``; returns the run folder ``out_run``.

    image_size: (H, W) the images are resized to (colour by area, depth and labels by nearest
    neighbour, K scaled); None = the dataset's own size. batch_size: images per optimiser step per
    process. epochs: passes over the training images in all (counting earlier calls on this run).
    lr, lr_schedule ('cosine' | 'step'), weight_decay: AdamW with a short linear warm-up.
    depth_mode: 'raw' | 'filled' | 'restored' (tdof20.methods.data; 'restored' is privileged).
    fuse_stages (1-5), seg_head: the network's ablation options. device: 'auto' | 'cpu' | 'cuda' |
    'cuda:N' | 'mps'. amp: mixed precision (None = on for CUDA; bf16 where supported, else fp16 with
    loss scaling). max_steps: stop after this many optimiser steps in all (the schedule then spans
    them). backbone_weights: a torchvision resnet34 state dict (.pth) for both encoders. shard: an
    HDF5 file from `tdof20 dataset pack` to train on instead of packing into RUN/data/.
    save_every_s: checkpoint at the end of an epoch when the last checkpoint is older than this many
    seconds (0 = after every epoch), and always when the run ends (a checkpoint holds the model and
    AdamW's two moments: about 680 MB for the default network).

    Any dataset layout (tdof20's, BOP's: ``split`` is then a split folder such as 'train_pbr') and
    any object ids: classes 1..n map to the dataset's objects (config.json "classes"; a tdof20
    dataset within ids 1..20 keeps the catalog's 20). Restored depth the dataset lacks is rendered
    once into ROOT/.cache/ (or ``cache_dir``) when the shard is packed.
    """
    from tdof20.formats.shards import ShardDataset

    rank, local_rank, world = _distributed()
    try:  # the checks before any work
        dataset_root = Path(dataset_root)
        out_run = Path(out_run)
        from tdof20.formats.dataset import open_dataset
        ds = open_dataset(dataset_root)  # the one "not a dataset" check
        if ds.layout == "tdof20":
            from tdof20.benchmark.splits import SPLITS
            if split not in SPLITS:
                raise TdofError(f"--split must be one of {', '.join(SPLITS)}, got '{split}'")
        else:
            split = ds.check_split(split)
        check_depth_mode(depth_mode)
        if lr_schedule not in LR_SCHEDULES:
            raise TdofError(f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got '{lr_schedule}'")
        if batch_size < 1 or epochs < 1 or lr <= 0:
            raise TdofError("--batch-size and --epochs must be >= 1 and --lr > 0")
        if not 1 <= int(fuse_stages) <= 5:
            raise TdofError(f"--fuse-stages must be in 1..5, got {fuse_stages}")

        check_run_folder(out_run, dataset_root)
        if shard is None:
            split_part_images(dataset_root, split, "train", "train on")

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
        ckpt = saved = None
        if resume:
            advice = (f": move {CHECKPOINT} out of the run folder to start the run afresh, or train into another "
                      "--out")
            saved = read_run_config(out_run, advice)
            ckpt = read_checkpoint(ckpt_path, needs=("model", "optimizer", "epoch", "step", "history"), advice=advice)
            with torch.device("meta"):  # shapes only: nothing is allocated
                check_weights(build_network(saved, out_run / CONFIG), ckpt, saved, ckpt_path, advice)
                asked = HFF6DoF(n_classes=len(run_classes(saved)) + 1, n_keypoints=N_KEYPOINTS,
                                fuse_stages=fuse_stages, seg_head=seg_head).config
            # the options that must not change, before the work (a native image size is known later)
            _check_same(saved, {"network": {k: list(v) if isinstance(v, tuple) else v for k, v in asked.items()},
                                "image_size": saved.get("image_size") if image_size is None else
                                [int(image_size[0]), int(image_size[1])],
                                "depth_mode": depth_mode, "split": split, "train": {"batch_size": batch_size}},
                        out_run / CONFIG)
            try:
                ckpt_epoch, ckpt_step = int(ckpt["epoch"]), int(ckpt["step"])
                ckpt_history = list(ckpt["history"])
            except (TypeError, ValueError):
                raise TdofError(f"its epoch, step or history is not what train writes{advice}", ckpt_path) from None
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
        shard_path = _shard_for(dataset_root, split, out_run, shard, rank, show, cache_dir)
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
            keypoints = keypoints_from_json(saved["keypoints"])
            classes = run_classes(saved)
        else:
            keypoints = ds.keypoints()
            classes = dataset_classes(ds.obj_ids, ds.layout)
        torch.manual_seed(seed)
        net = HFF6DoF(n_classes=len(classes) + 1, n_keypoints=N_KEYPOINTS, fuse_stages=fuse_stages, seg_head=seg_head)
        options = dict(batch_size=batch_size, epochs=epochs, lr=lr, lr_schedule=lr_schedule,
                       weight_decay=weight_decay, amp=use_amp, num_workers=num_workers, max_steps=max_steps,
                       seed=seed, backbone_weights=None if backbone_weights is None else str(backbone_weights),
                       world_size=world, device=str(dev))
        config = {"method": "hff6dof", "version": 1,
                  "network": {k: list(v) if isinstance(v, tuple) else v for k, v in net.config.items()},
                  "image_size": list(image_size), "depth_mode": depth_mode, "split": split,
                  "dataset": str(dataset_root.resolve()), "shard": str(Path(shard_path).resolve()),
                  "keypoints": keypoints_to_json(keypoints), "classes": classes,
                  "objects": {str(o): ds.object_name(o) for o in classes if o in ds.models_info},
                  "layout": ds.layout, "train": options}
        if resume:
            _check_same(saved, config, out_run / CONFIG)
            net.load_state_dict(ckpt["model"])
        elif backbone_weights is not None:
            net.load_backbone_weights(backbone_weights)
        net = net.to(dev)
        if dev.type == "cuda":
            net = net.to(memory_format=torch.channels_last)
            torch.backends.cudnn.benchmark = True
        opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
        scaler = torch.amp.GradScaler("cuda", enabled=use_amp and amp_dtype(dev) == torch.float16)
        epoch, step, history, epochs_log = 0, 0, [], []
        if resume:
            try:  # moves AdamW's moments to the parameters' device
                opt.load_state_dict(ckpt["optimizer"])
                if ckpt.get("scaler") and scaler.is_enabled():
                    scaler.load_state_dict(ckpt["scaler"])
            except (ValueError, KeyError, TypeError, RuntimeError) as e:
                raise TdofError(f"its optimiser state does not fit the network ({type(e).__name__}: "
                                f"{(str(e).splitlines() or [''])[0][:80]}){advice}", ckpt_path) from None
            epoch, step, history = ckpt_epoch, ckpt_step, ckpt_history
            epochs_log = list(ckpt.get("epochs") or [])
            for g in opt.param_groups:  # the options of this call win (lr, weight decay)
                g["weight_decay"] = weight_decay
            ckpt = None  # the weights now live in the network and the optimiser
        if main:  # written once the run's state is known to load
            write_json(out_run / CONFIG, config)
        model = net
        if world > 1:
            if dev.type == "cuda":
                model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            model = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[local_rank] if dev.type == "cuda" else None)

        transform = HFFTransform(keypoints, image_size, depth_mode, targets=True, classes=classes)
        tdata = TransformedDataset(data, transform)
        n = len(tdata)
        per_rank = n // world
        bs = min(batch_size, max(1, per_rank))
        steps_per_epoch = max(1, per_rank // bs)
        total = epochs * steps_per_epoch
        if max_steps is not None:
            total = min(total, int(max_steps))
        warmup = min(200, total // 20)
        sampler = torch.utils.data.DistributedSampler(tdata, num_replicas=world, rank=rank, shuffle=True,
                                                      seed=seed, drop_last=True)
        if main and show:
            console.print(f"HFF6DoF on {split}/train: {n} images at {image_size[0]}x{image_size[1]}, depth "
                          f"{depth_mode}, batch {bs} x {world} process(es), {steps_per_epoch} steps/epoch, "
                          f"device {dev}{' (AMP ' + str(amp_dtype(dev)).split('.')[-1] + ')' if use_amp else ''}"
                          + (f", resuming at epoch {epoch}, step {step}" if resume else ""))

        last_save = [time.perf_counter()]

        def save(processes: dict | None = None) -> None:
            last_save[0] = time.perf_counter()
            if not main:
                return
            _save_atomic({"model": net.state_dict(), "optimizer": opt.state_dict(),
                          "scaler": scaler.state_dict() if scaler.is_enabled() else None,
                          "epoch": epoch, "step": step, "history": history, "epochs": epochs_log,
                          "config": config}, ckpt_path)
            write_json(out_run / "history.json", {"epochs": epochs_log, "steps": step,
                                                   **({"processes": processes} if processes else {})})
            if history:
                plot_losses(history, out_run / "loss.png")

        global_bs = bs * world
        start_step = step
        with progress_bar(show, unit="img") as bar:
            task = bar.add_task("training", total=total * global_bs, completed=min(step, total) * global_bs)
            while step < total:
                sampler.set_epoch(epoch)
                skip = step - epoch * steps_per_epoch  # steps of this epoch done before a resume
                idx = list(sampler)[max(0, skip) * bs: steps_per_epoch * bs]
                loader = torch.utils.data.DataLoader(
                    tdata, batch_size=bs, sampler=idx, num_workers=num_workers, collate_fn=collate,
                    worker_init_fn=worker_init,
                    drop_last=True, pin_memory=dev.type == "cuda", persistent_workers=False)
                model.train()
                t0, n_img, sums = time.perf_counter(), 0, {"loss": 0.0, "seg": 0.0, "vec": 0.0}
                n_steps = 0
                for batch in loader:
                    if step >= total:
                        break
                    rgb = batch["rgb"].to(dev, non_blocking=True)
                    geo = batch["geo"].to(dev, non_blocking=True)
                    if dev.type == "cuda":
                        rgb = rgb.contiguous(memory_format=torch.channels_last)
                        geo = geo.contiguous(memory_format=torch.channels_last)
                    lr_now = lr * lr_factor(step, total, lr_schedule, warmup)
                    for g in opt.param_groups:
                        g["lr"] = lr_now
                    ctx = torch.autocast(dev.type, dtype=amp_dtype(dev)) if use_amp else nullcontext()
                    with ctx:
                        out = model(rgb, geo)
                    seg = out["seg"].float() if out["seg"] is not None else None
                    loss, parts = hff_loss(seg, out["vec"].float(), batch["seg"].to(dev), batch["vec"].to(dev),
                                           batch["mask"].to(dev), return_parts=True)
                    opt.zero_grad(set_to_none=True)
                    scaler.scale(loss).backward()
                    scaler.step(opt)
                    scaler.update()
                    step += 1
                    n_steps += 1
                    n_img += rgb.shape[0] * world
                    rec = {"step": step, "epoch": epoch, "loss": float(loss.detach()), "seg": float(parts["seg"]),
                           "vec": float(parts["vec"]), "lr": lr_now}
                    if not math.isfinite(rec["loss"]):
                        raise TdofError(f"the loss became {rec['loss']} at step {step}: lower --lr "
                                        "(the last good checkpoint is kept)", out_run)
                    history.append(rec)
                    for k in sums:
                        sums[k] += rec[k]
                    bar.update(task, advance=global_bs,
                               description=f"epoch {epoch + 1}/{epochs} loss {rec['loss']:.3f}")
                dt = time.perf_counter() - t0
                if step >= (epoch + 1) * steps_per_epoch or step >= total:
                    if n_steps:
                        epochs_log.append({"epoch": epoch + 1, "steps": step,
                                           **{k: v / n_steps for k, v in sums.items()},
                                           "lr": history[-1]["lr"], "seconds": round(dt, 2),
                                           "images_per_s": round(n_img / dt, 2) if dt > 0 else None})
                    if step >= (epoch + 1) * steps_per_epoch:
                        epoch += 1
                if step < total and time.perf_counter() - last_save[0] >= save_every_s:
                    save()
                if show and epochs_log:
                    e = epochs_log[-1]
                    console.print(f"epoch {e['epoch']}: loss {e['loss']:.4f} (seg {e['seg']:.4f}, vec {e['vec']:.4f}), "
                                  f"{e['images_per_s']} images/s")
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
            console.print(f"run: {out_run} (last.pt, config.json, loss.png)")
    finally:
        # no barrier on the way out of an error: the other processes may be inside a collective;
        # the launcher (torchrun) ends them when this one exits non-zero
        if dist is not None and dist.is_initialized():
            dist.destroy_process_group()
    return out_run
