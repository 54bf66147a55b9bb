"""A training run's folder: its config.json and last.pt, read and checked; the network they
describe, opened; the run's weights digest; the optimiser state dropped once a training is over.

    run = open_run("runs/simple", "cpu")     # Run(method, cfg, net (eval, last weights), meta, config)
    config = read_run_config("runs/simple")  # checked: a registered method, every key predict needs
    ckpt = read_checkpoint("runs/simple/last.pt", needs=("model", "epoch"))   # weights only, no code run

    RUN/config.json       the method, its config ("method_config"), its meta (objects in class order,
                          keypoints, diameters, symmetries, surface samples, image size), the input
                          depth mode, the split, the dataset and the training options, and whatever
                          the method records of its own (:meth:`~tdof20.methods.contract.PoseMethod.run_record`)
    RUN/last.pt           model, optimiser (and AMP scaler) state, epoch and step counters, loss history
                          (the weights, counters and history only once a training is over: drop_optimizer,
                          train's keep_optimizer=False)

Runs written before the interface (HFF6DoF's config.json without "method_config") still open: the
method rebuilds its config from what they recorded (its ``config_from_run``).
"""

from __future__ import annotations

import hashlib
import mmap
import os
import struct
import zipfile
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import torch
from isal import isal_zlib
from torch.overrides import TorchFunctionMode

from tdof20.errors import TdofError
from tdof20.formats import read_json
from tdof20.formats.io import check_parents
from tdof20.methods.data import identity_classes
from tdof20.methods.registry import Method, method_names, run_method

CHECKPOINT = "last.pt"
RUN_VERSION = 2  # config.json's "version": what this tdof20 writes and the newest it reads
CONFIG = "config.json"


RUN_KEYS = ("image_size", "depth_mode", "split", "keypoints")


def depth_mode_of(cfg) -> str:
    """The input depth a method's config reads ('raw' | 'filled' | 'restored'), 'none' for RGB only."""
    return str(getattr(cfg, "depth_mode", "none"))


def read_run_config(run_dir: str | Path, advice: str = "") -> dict:
    """A run's config.json, checked to name a registered method and to hold every key predict and
    resume need (and what its method needs: :meth:`~tdof20.methods.contract.PoseMethod.missing_run_keys`)."""
    path = Path(run_dir) / CONFIG
    if not path.exists():
        raise TdofError(f"missing: the run folder holds {CHECKPOINT} without the {CONFIG} it belongs to{advice}", path)
    config = read_json(path)
    if not isinstance(config, dict) or not isinstance(config.get("method"), str):
        raise TdofError(f"not a training run's {CONFIG} (it names no method){advice}", path)
    method = run_method(config, path)
    version = config.get("version", 1)  # runs from before the field are version 1
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= RUN_VERSION:
        raise TdofError(f"is a run of version {version!r}; this tdof20 reads versions 1..{RUN_VERSION} (a newer "
                        f"tdof20 wrote it: update tdof20){advice}", path)
    missing = [k for k in RUN_KEYS if k not in config] + method.missing_run_keys(config)
    if missing:
        raise TdofError(f"lacks {', '.join(missing)}{advice}", path)
    return config


def build_network(config: dict, path: Path | None = None) -> torch.nn.Module:
    """The network a run's config.json describes (``path``: that file, for the message)."""
    return open_config(config, path)[2]


def open_config(config: dict, path: Path | None = None) -> tuple[Method, Any, torch.nn.Module, Any]:
    """(method, cfg, network with fresh weights, meta) of a run's config.json."""
    method = run_method(config, path)
    cfg, meta = method.config_from_run(config, path)
    return method, cfg, _build(method, cfg, meta, path), meta


def _build(method: Method, cfg: Any, meta: Any, path: Path | None) -> torch.nn.Module:
    """``method``'s network for ``cfg`` with fresh weights; options that make none: one line."""
    try:
        return method.build(cfg, meta)
    except (ValueError, TypeError, RuntimeError) as e:
        raise TdofError(f"its options do not make a {method.name} network ({e})", path) from None


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


_LOCAL_HEADER = struct.Struct("<4s22xHH")  # a zip member's local header: signature .. name and extra lengths


def _damaged_member(path: Path) -> str | None:
    """The first member of the zip archive at ``path`` whose bytes run past the end of the file or
    do not match the CRC-32 its central directory records; None when every member is whole.

    torch.save stores its members uncompressed: each is checksummed where it lies, through a
    memory map, by ISA-L's CRC-32 (about 3x zlib's; zipfile.testzip also copied every byte through
    its reader), so the check costs little more than the one read of the file a load needs anyway,
    and the pages it reads are the ones ``torch.load(mmap=True)`` then maps. A compressed member
    (not torch's) is read through zipfile, which checks its CRC."""
    with open(path, "rb") as f, zipfile.ZipFile(f) as z:
        size = os.fstat(f.fileno()).st_size
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m, memoryview(m) as view:
            for info in z.infolist():
                if info.compress_type != zipfile.ZIP_STORED:
                    try:
                        with z.open(info) as member:
                            while member.read(1 << 24):
                                pass
                    except zipfile.BadZipFile:
                        return info.filename
                    continue
                if info.header_offset + _LOCAL_HEADER.size > size:
                    return info.filename
                magic, n_name, n_extra = _LOCAL_HEADER.unpack_from(view, info.header_offset)
                start = info.header_offset + _LOCAL_HEADER.size + n_name + n_extra
                if magic != b"PK\x03\x04" or start + info.compress_size > size:
                    return info.filename
                if isal_zlib.crc32(view[start:start + info.compress_size]) != info.CRC:
                    return info.filename
    return None


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
    try:  # torch.load does not check the zip's CRCs: a damaged weight would load as garbage
        bad = _damaged_member(path)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, struct.error) as e:
        bad = f"? ({type(e).__name__})"
    if bad is not None:
        raise TdofError(f"cannot be read as a checkpoint ({_size_text(size)}; damaged: its member {bad} fails "
                        f"its CRC check){advice}", path)
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


def check_weights(net: torch.nn.Module, ckpt: dict, config: dict, path: Path, advice: str = "") -> None:
    """A one-line TdofError naming the checkpoint ``path`` when its weights do not fit ``net`` (the
    network ``config``, the run's config.json, describes; it may live on the meta device) or the
    checkpoint was written by a run of other options."""
    why = []
    saved = ckpt.get("config")
    if isinstance(saved, dict):
        if saved.get("method") not in (None, config.get("method")):
            why.append(f"a {saved.get('method')} network here, {config.get('method')} in {CONFIG}")
        old, now = saved.get("network") or {}, config.get("network") or {}  # a method's "network" record
        why += [f"{k} {old.get(k)} here, {now.get(k)} in {CONFIG}" for k in old
                if old.get(k) != now.get(k)]
        old, now = saved.get("method_config") or {}, config.get("method_config") or {}
        why += [f"{k} {old.get(k)} here, {now.get(k)} in {CONFIG}" for k in sorted(set(old) & set(now))
                if old.get(k) != now.get(k) and k not in saved.get("network", {})]
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
    """The object id of each class 1..n of a run (its meta's objects, else config.json's
    "classes"; an HFF6DoF run recorded without either: ids 1..n_classes-1, class = obj_id)."""
    if isinstance(config.get("meta"), dict) and "obj_ids" in config["meta"]:
        return [int(c) for c in config["meta"]["obj_ids"]]
    classes = config.get("classes")
    if classes is None:
        return identity_classes(config["network"]["n_classes"])
    return [int(c) for c in classes]


class _UninitialisedOnMeta(TorchFunctionMode):
    """``torch.empty`` without a device makes its tensor on the meta device (shapes only).

    torch.nn's layers make their parameters with ``torch.empty`` and then initialise them in place
    (kaiming_uniform_, ...): under this mode those parameters live on the meta device and their
    initialisation costs nothing (HFF6DoF's two ResNet-34 encoders, ~43 M weights, took ~3 s of
    random numbers that a loaded checkpoint overwrote). Tensors made with values (``torch.tensor``,
    ``zeros``, ``ones``, ``arange``: the non-persistent buffers such as the ImageNet mean, a class
    look-up table) stay real, unlike under ``with torch.device("meta")``, where their values would
    be lost with no checkpoint to restore them from."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is torch.empty and kwargs.get("device") is None:
            kwargs["device"] = "meta"
        return func(*args, **kwargs)


def _meta_tensors(net: torch.nn.Module) -> list[str]:
    """Names of the network's parameters, buffers and plain tensor attributes on the meta device."""
    found = [k for k, t in [*net.named_parameters(), *net.named_buffers()] if t.is_meta]
    for prefix, module in net.named_modules():
        found += [f"{prefix}.{k}".lstrip(".") for k, v in vars(module).items()
                  if isinstance(v, torch.Tensor) and v.is_meta]
    return found


def network_with_weights(build: Callable[[], torch.nn.Module], state: dict, device: str | torch.device = "cpu",
                         check: Callable[[torch.nn.Module], None] | None = None) -> torch.nn.Module | None:
    """The network ``build()`` makes, with the weights ``state`` (a state dict: every parameter and
    persistent buffer, as check_weights ensures) on ``device``, without computing the random
    initial weights that ``state`` replaces (:class:`_UninitialisedOnMeta`); ``check(net)`` first
    (on the weightless network: a one-line error for weights that do not fit it).

    Each weight is copied into a tensor of the network's own dtype and (contiguous) layout, as
    ``load_state_dict`` copies into a network built for real: the network is the same, bit for bit,
    and owns its memory (not a map of the checkpoint's file, which may be replaced or cut short
    while it is in use). None when a tensor stays on the meta device (a method whose build fills a
    ``torch.empty`` buffer that is no weight): the caller then builds the network for real."""
    try:
        with _UninitialisedOnMeta():
            net = build()
    except Exception:  # noqa: BLE001 - an op without a meta kernel (or bad options: the real build says which)
        return None
    if check is not None:
        check(net)
    device = torch.device(device)
    own = net.state_dict(keep_vars=True)
    weights = OrderedDict()
    for k, v in state.items():
        mine = own.get(k)
        if mine is None:  # check_weights refuses extra weights; without a check, load_state_dict does
            weights[k] = v
            continue
        weights[k] = torch.empty(mine.shape, dtype=mine.dtype, device=device).copy_(v)
    if hasattr(state, "_metadata"):  # the modules' state-dict versions (BatchNorm's num_batches_tracked)
        weights._metadata = state._metadata
    net.load_state_dict(weights, assign=True)
    return None if _meta_tensors(net) else net.to(device)  # the buffers that are no weights move too


class Run(NamedTuple):
    """A trained run, opened: its method, the method's config, the network (last weights, eval
    mode), the meta and the run's config.json."""
    method: Method
    cfg: Any
    net: torch.nn.Module
    meta: Any
    config: dict


def open_run(run_dir: str | Path, device: str | torch.device = "cpu") -> Run:
    """The run in ``run_dir`` with its last weights on ``device`` (any registered method; HFF6DoF
    runs written before the interface too)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise TdofError("is a file, not a run folder (tdof20 train METHOD --out makes one)", run_dir)
    if not (run_dir / CONFIG).exists() or not (run_dir / CHECKPOINT).exists():
        raise TdofError(f"not an HFF6DoF run nor another method's (a run folder holds {CONFIG} and {CHECKPOINT}; "
                        f"train one first: tdof20 train METHOD)", run_dir)
    advice = ": restore it from a copy, or train a new run into another --out"
    config = read_run_config(run_dir)
    ckpt = read_checkpoint(run_dir / CHECKPOINT, advice=advice, mmap=True)
    method = run_method(config, run_dir / CONFIG)
    cfg, meta = method.config_from_run(config, run_dir / CONFIG)

    def check(net: torch.nn.Module) -> None:
        check_weights(net, ckpt, config, run_dir / CHECKPOINT, advice)

    net = network_with_weights(lambda: method.build(cfg, meta), ckpt["model"], device, check)
    if net is None:  # the method's network does not build without its initial weights: as it was
        net = _build(method, cfg, meta, run_dir / CONFIG)
        check(net)
        net.load_state_dict(ckpt["model"])
        net = net.to(device)
    return Run(method, cfg, net.eval(), meta, config)


def load_run(run_dir: str | Path, device: str | torch.device = "cpu") -> tuple[torch.nn.Module, dict]:
    """(network with the run's last weights, in eval mode, on ``device``; the run's config)."""
    r = open_run(run_dir, device)
    return r.net, r.config


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
            foreign = read_json(cfg).get("method") not in method_names()
        except (TdofError, AttributeError):
            foreign = True
        if foreign:
            raise TdofError(f"--out holds a {CONFIG} that is not a training run's (training would overwrite it): "
                            "give another --out", out_run)


def parameters_digest(net: torch.nn.Module) -> str:
    """SHA-256 of the network's parameters (bytes, in order): equal digests = identical weights."""
    h = hashlib.sha256()
    for name, p in net.named_parameters():
        h.update(name.encode())
        h.update(p.detach().float().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def save_atomic(obj, path: Path) -> None:
    """torch.save into a temporary file beside ``path``, then rename: a failed write (disk full)
    removes the temporary file, keeps the previous ``path`` and is a one-line TdofError."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, (OSError, RuntimeError)):
            why = e.strerror if isinstance(e, OSError) and e.strerror else (str(e).strip().splitlines() or [""])[0][:80]
            if "unexpected pos" in why or "file write failed" in why:
                why = "the write failed: is the disk full?"
            kept = f"the previous {path.name} is kept" if path.exists() else "nothing was written"
            raise TdofError(f"cannot be written ({why}); {kept}", path) from None
        raise


def drop_optimizer(run: str | Path) -> int:
    """Rewrite RUN/last.pt without the optimiser's (and AMP scaler's) state, for a run whose training
    is over: the weights, counters, history and config stay, so predict, score and the tables read
    it as before, while AdamW's two moments per weight (two thirds of the file: HFF6DoF's 650 MB
    become 220 MB) go. Such a run cannot be trained on. Returns the bytes saved (0 when there was
    nothing to drop).

    A run trained with ``keep_optimizer=False`` (reproduce's) has no optimiser state left at its
    end: the file is then checked and mapped, its tensors not loaded, and nothing is written."""
    path = Path(run) / CHECKPOINT
    ckpt = read_checkpoint(path, needs=("model", "epoch", "step"), mmap=True)
    if "optimizer" not in ckpt and "scaler" not in ckpt:
        return 0
    before = path.stat().st_size
    save_atomic({k: v for k, v in ckpt.items() if k not in ("optimizer", "scaler")}, path)
    return before - path.stat().st_size
