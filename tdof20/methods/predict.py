"""Inference with a trained run of any method: poses of the test images of a split, as a BOP
results CSV (``tdof20 predict RUN --dataset ROOT --split simple|hard --out RESULTS.csv``); the run
knows its method (config.json "method"), and the method's ``predict_poses`` gives the poses.

A pose method that predicts with mask source 'segnet' (HFF6DoF without its segmentation head,
``--set masks=segnet --set seg_run=RUN``) takes its object pixels from the segmentation network of
the run ``seg_run`` (``tdof20 train segnet``, :mod:`tdof20.methods.segnet`), run here on the same
images through its own transform; the run must be a segmentation run trained on the pose run's
objects, data (the dataset digest both runs record) and image size (:func:`open_seg_run`). A
segmentation run itself produces masks, not poses: ``predict`` on it refuses in one line (its
segmentation IoU: :func:`segmentation_iou`).

Beside the CSV, ``<stem>_info.json`` records the run's method, its config ("method_config"), the
input depth mode and the input (rgb / rgbd), timings and counts; ``tdof20 benchmark score`` prints
them with the scores.

The time written per image is the method's ``predict_poses`` (network + pose recovery,
device-synchronised; reading and transforming the images is not counted), shared evenly among the
images of a batch (with mask source 'segnet', the segmentation network's forward is counted in both
the time and the network's part). The network's part is measured with forward hooks on the network
and its direct sub-networks (the outermost call counts), so "network_ms_per_image" and
"pose_ms_per_image" are apart for every method.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from tdof20.dataset.reader import open_dataset
from tdof20.dataset.results import write_results_csv
from tdof20.dataset.validation import part_images
from tdof20.errors import TdofError
from tdof20.formats import write_json
from tdof20.formats.io import check_parents, safe_inside
from tdof20.methods.data import SceneImages, TransformedDataset, collate, worker_init
from tdof20.methods.registry import get_method, method_names
from tdof20.methods.runs import CONFIG, Run, depth_mode_of, open_run, read_run_config
from tdof20.methods.train import amp_dtype, select_device, to_device
from tdof20.progress import console, progress as progress_bar

PREDICT_PARTS = ("test", "val")


def check_output_file(path: str | Path, option: str = "--out", if_folder: str | None = None) -> Path:
    """Refuse, before any work, an output file that cannot be written: a folder (``if_folder``: what
    to do then), a path below a file, or a folder without write permission."""
    path = Path(path)
    if path.is_dir():
        raise TdofError(f"{option} is a folder, not a file: "
                        f"{if_folder or 'give a file name, such as ' + str(path / 'results.csv')}", path)
    check_parents(path, option)
    return path


def info_path(out_csv: Path) -> Path:
    """Where predict writes its summary beside the results CSV."""
    return out_csv.with_name(out_csv.stem + "_info.json")


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


class NetworkTimer:
    """Time spent inside a network's forward calls (the network itself and its direct
    sub-networks; only the outermost call counts), device-synchronised: what a method's
    ``predict_poses`` spends in the network, apart from its pose recovery."""

    def __init__(self, net: torch.nn.Module, dev: torch.device):
        self.dev, self.seconds, self._depth, self._t0 = dev, 0.0, 0, 0.0
        mods = [net, *net.children()]
        self._handles = [h for m in mods for h in (m.register_forward_pre_hook(self._pre),
                                                   m.register_forward_hook(self._post))]

    def _pre(self, *_):
        if self._depth == 0:
            _sync(self.dev)
            self._t0 = time.perf_counter()
        self._depth += 1

    def _post(self, *_):
        self._depth -= 1
        if self._depth == 0:
            _sync(self.dev)
            self.seconds += time.perf_counter() - self._t0

    def close(self) -> None:
        for h in self._handles:
            h.remove()


SEG_PREFIX = "seg_input."


class WithSegInput:
    """The pose method's transform of an item plus the segmentation run's own transform of the same
    item, its tensors under ``seg_input.<key>`` (picklable: DataLoader workers)."""

    def __init__(self, pose_transform, seg_transform):
        self.pose_transform, self.seg_transform = pose_transform, seg_transform

    def __call__(self, item) -> dict:
        out = self.pose_transform(item)
        out.update({SEG_PREFIX + k: v for k, v in self.seg_transform(item).items() if isinstance(v, torch.Tensor)})
        return out


def open_seg_run(seg_run: str | Path, pose: Run, device: str | torch.device = "cpu") -> Run:
    """The segmentation run a pose run predicts with (mask source 'segnet'), opened on ``device``
    after one-line refusals naming it: missing, not a run, not a segmentation run (a method whose
    record produces poses), trained on other objects, on other data (the "dataset_sha256" digest both
    runs record, of the dataset's objects, the training images and their labels: train both on the
    same dataset, split and part; runs without digests: their splits) or at another image size (its
    masks must cover the pose network's pixels one to one)."""
    path = Path(seg_run)
    if not str(seg_run).strip() or not path.is_dir():
        raise TdofError("seg_run: no such segmentation run folder (tdof20 train segnet --out makes one)", path)
    if (path / CONFIG).exists():
        m = read_run_config(path).get("method")
        kind = get_method(m).produces
        if kind != "masks":
            raise TdofError(f"seg_run: is a {m} run ({kind}), not a segmentation run: give a run of "
                            f"tdof20 train {', '.join(method_names('masks'))}", path)
    seg = open_run(path, device)
    if seg.method.produces != "masks":
        raise TdofError(f"seg_run: is a {seg.method.name} run, not a segmentation run", path)
    if tuple(seg.meta.obj_ids) != tuple(pose.meta.obj_ids):
        raise TdofError(f"seg_run: was trained on other objects (classes {list(seg.meta.obj_ids)}; the pose run's "
                        f"{list(pose.meta.obj_ids)})", path)
    mine, theirs = seg.config.get("dataset_sha256"), pose.config.get("dataset_sha256")
    if mine is not None and theirs is not None:
        if mine != theirs:
            raise TdofError(f"seg_run: was trained on other data (dataset digest {mine}, the pose run's {theirs}): "
                            "train it on the pose run's dataset, split and part", path)
    elif seg.config.get("split") != pose.config.get("split"):
        raise TdofError(f"seg_run: was trained on split {seg.config.get('split')}, the pose run on "
                        f"{pose.config.get('split')}", path)
    if tuple(seg.meta.image_size) != tuple(pose.meta.image_size):
        raise TdofError("seg_run: its image size {}x{} is not the pose run's {}x{}: train it at the pose run's size"
                        .format(*seg.meta.image_size, *pose.meta.image_size), path)
    return seg


def seg_labels(seg: Run, batch: dict, labels_are_classes: bool, meta) -> torch.Tensor:
    """The segmentation run's classes of a batch (its inputs under ``seg_input.``) in the pose method's
    label convention: class indices (``labels_are_classes``) or object ids (0 = background)."""
    inputs = {k[len(SEG_PREFIX):]: v for k, v in batch.items() if k.startswith(SEG_PREFIX)}
    classes, _ = seg.method.predict_masks(seg.net, inputs, seg.cfg, seg.meta)
    if labels_are_classes:
        return classes
    ids = torch.tensor([0, *meta.obj_ids], dtype=torch.int64, device=classes.device)
    return ids[classes]


def impossible_pose(R, t, diameter: float | None) -> bool:
    """A pose no camera can see: not finite, the object's origin on or behind the camera plane
    (t_z <= 0), or the camera within half the object's diameter of the model's origin (inside the
    object's bounding sphere: the models are centred). A degenerate pose recovery (an untrained
    network's PnP collapsing to t ~ 0) returns such poses; predict writes no row for them (a miss,
    as a wrong pose would be for ADD(S) and 2D projection) and counts them in its summary."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or t[2] <= 0:
        return True
    return bool(diameter) and float(np.linalg.norm(t)) < 0.5 * float(diameter)


def predict(run_dir: str | Path, dataset_root: str | Path, split: str, out_csv: str | Path, *,
            device: str = "auto", batch_size: int = 1, num_workers: int = 2, amp: bool | None = None, seed: int = 0,
            progress: bool = True, method_options: Mapping | None = None, part: str = "test",
            cache_dir: str | Path | None = None, **options) -> Path:
    """Estimate the poses of every test image of ``split`` (``part`` 'val': of its validation part,
    :mod:`tdof20.dataset.validation`, where choices are made) with the run in ``run_dir`` (any method)
    and write the BOP results CSV ``out_csv`` (scene_id,im_id,obj_id,score,R,t,time); returns its
    path. A summary (method, its config, depth mode, timings, counts, options) goes to
    ``<out_csv stem>_info.json`` beside it.

    method_options (a table; nested tables for a nested config) and keyword ``options``: options of
    the run's method config for this prediction (e.g. ``masks="gt"``, ``voting="3d"`` for HFF6DoF;
    None = the run's), checked as a TOML file's (an option the method does not have is refused).
    For HFF6DoF: 'segnet' masks (with ``seg_run``) are a separately trained segmentation network's,
    the paper's ablation for a run trained without the segmentation head; 'gt' masks are the
    dataset's visible masks (an oracle segmentation; not a valid submission). amp: mixed
    precision for the network (None = on for CUDA). batch_size: images per forward pass. seed: the
    pose recovery's generator. cache_dir: where restored depth the dataset lacks is rendered
    (default ROOT/.cache; for a read-only dataset folder), as for training.
    """
    out_csv = check_output_file(out_csv)
    check_output_file(info_path(out_csv), "the summary beside --out",
                      "predict writes it there: move the folder away or choose another --out")
    rows, info = predict_rows(run_dir, dataset_root, split, device=device, batch_size=batch_size,
                              num_workers=num_workers, amp=amp, seed=seed, progress=progress,
                              method_options=method_options, part=part, cache_dir=cache_dir, **options)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    write_results_csv(out_csv, rows)
    write_json(info_path(out_csv), info)
    if progress:
        console.print(f"{info['method']}: {info['predictions']} poses in {info['images']} images ({split}/{part}, "
                      f"masks: {info['masks']}, depth: {info['depth_mode']}); network "
                      f"{info['network_ms_per_image']:.1f} ms + pose {info['pose_ms_per_image']:.1f} ms per image "
                      f"-> {out_csv}", markup=False)
    return out_csv


def prediction_config(method, cfg, options: Mapping, seed: int | None = None):
    """The run's method config with the prediction ``options`` (those not None) applied through the
    method's strict, typed checks (one line naming the option), and ``seed`` where the config has one."""
    changes = {k: v for k, v in options.items() if v is not None}
    if seed is not None and hasattr(cfg, "seed"):
        changes["seed"] = int(seed)
    return method.with_options(cfg, changes, f"{method.name} prediction options")


def predict_rows(run_dir: str | Path, dataset_root: str | Path, split: str, *, device: str = "auto",
                 batch_size: int = 1, num_workers: int = 2, amp: bool | None = None, seed: int = 0,
                 progress: bool = True, images: list[tuple[int, int]] | None = None,
                 method_options: Mapping | None = None, part: str = "test", cache_dir: str | Path | None = None,
                 **options) -> tuple[list[tuple], dict]:
    """What :func:`predict` writes, without writing: (rows (scene_id, im_id, obj_id, score, R (3,3),
    t (3,) mm, time s), summary dict). ``part``: 'test' or 'val' (the validation part of the
    split's train part); ``images`` overrides both."""
    dataset_root = Path(dataset_root)
    ds = open_dataset(dataset_root)  # the one "not a dataset" check
    scene_folder = ds.scene_folder(split)
    if part not in PREDICT_PARTS:
        raise TdofError(f"--part must be one of {', '.join(PREDICT_PARTS)}, got '{part}'")
    if batch_size < 1 or num_workers < 0:
        raise TdofError(f"--batch-size must be >= 1 and --workers >= 0, got {batch_size} and {num_workers}")
    if images is None:
        if part == "val":
            images = part_images(dataset_root, split, "val")
            if not images:
                raise TdofError(f"the {split} split's validation part is empty (too few turntable steps per arm "
                                "position for a validation arc): nothing to predict", dataset_root)
        else:
            images = ds.part_frames(split, "test", "predict")
    if not images:
        raise TdofError("no images to predict")
    dev = select_device(device)
    run = open_run(run_dir, dev)
    method, net, meta = run.method, run.net, run.meta
    if method.produces != "poses":
        raise TdofError(f"is a {method.name} run: it produces {method.produces}, not poses; give it to a pose "
                        f"method's prediction (--set masks=segnet --set seg_run={run_dir})", run_dir)
    cfg = prediction_config(method, run.cfg, {**(method_options or {}), **options}, seed)
    try:
        mask_source = method.mask_source(cfg, net)
    except TdofError as e:
        raise TdofError(str(e), run_dir) from None
    seg = open_seg_run(method.seg_run(cfg), run, dev) if mask_source == "segnet" else None
    labels = method.needs_labels(cfg, net)
    use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        net = net.to(memory_format=torch.channels_last)
    depth_mode = depth_mode_of(cfg)
    if depth_mode == "restored":  # rendered once (cached) where the dataset has none
        if cache_dir is None:  # ROOT/.cache: no symlink out of the dataset
            safe_inside(Path(dataset_root), Path(dataset_root) / ".cache")
        open_dataset(dataset_root, scene_folder, cache_dir=cache_dir).render_restored(images, scene_folder,
                                                                                       show_progress=progress)
    transform = method.transform(cfg, meta, train=False)
    if seg is not None:
        transform = WithSegInput(transform, seg.method.transform(seg.cfg, seg.meta, train=False))
    data = TransformedDataset(SceneImages(dataset_root, images, labels=labels, restored=depth_mode == "restored",
                                          split=scene_folder, cache_dir=cache_dir), transform)
    loader = torch.utils.data.DataLoader(data, batch_size=int(batch_size), shuffle=False,
                                         num_workers=num_workers, collate_fn=collate, worker_init_fn=worker_init,
                                         pin_memory=dev.type == "cuda")
    torch.manual_seed(seed)
    rows = []
    known = set(ds.obj_ids)
    t_all = 0.0
    n_img = n_foreign = n_impossible = 0
    timers = [NetworkTimer(net, dev)] + ([NetworkTimer(seg.net, dev)] if seg is not None else [])
    try:
        with torch.inference_mode(), progress_bar(bool(progress), unit="img") as bar:
            task = bar.add_task(f"predict {split}/{part}", total=len(images))
            for batch in loader:
                batch = to_device(batch, dev)
                _sync(dev)
                t0 = time.perf_counter()
                with torch.autocast(dev.type, dtype=amp_dtype(dev), enabled=use_amp):
                    if seg is not None:  # the segmentation run's masks, where the method reads its labels
                        batch["label"] = seg_labels(seg, batch, method.labels_are_classes, meta)
                    res = method.predict_poses(net, batch, cfg, meta)
                _sync(dev)
                dt = time.perf_counter() - t0
                B = int(batch["rgb"].shape[0])
                t_all += dt
                sids, ims = batch["scene_id"].tolist(), batch["im_id"].tolist()
                for b, obj, score, R, t in res:
                    if int(obj) not in known:  # a class the run has but the dataset does not (the catalog's 20)
                        n_foreign += 1
                        continue
                    if impossible_pose(R, t, meta.diameters.get(int(obj))):
                        n_impossible += 1
                        continue
                    rows.append((int(sids[b]), int(ims[b]), int(obj), float(score), np.asarray(R, np.float64),
                                 np.asarray(t, np.float64), dt / B))
                n_img += B
                bar.advance(task, B)
    finally:
        for timer in timers:
            timer.close()
    t_net = min(sum(timer.seconds for timer in timers), t_all)
    info = {"run": str(Path(run_dir).resolve()), "method": method.name, "input": method.inputs,
            "method_config": method.config_to_data(cfg), "dataset": str(dataset_root.resolve()), "split": split,
            "part": part, "images": n_img, "predictions": len(rows), "masks": mask_source,
            **({"seg_run": str(Path(method.seg_run(cfg)).resolve())} if seg is not None else {}),
            "dropped_objects_not_in_dataset": n_foreign, "dropped_impossible_poses": n_impossible,
            "depth_mode": depth_mode,
            "image_size": list(meta.image_size), "device": str(dev), "amp": use_amp, "batch_size": int(batch_size),
            "seed": int(seed),
            "network_ms_per_image": round(1000 * t_net / max(1, n_img), 3),
            "pose_ms_per_image": round(1000 * (t_all - t_net) / max(1, n_img), 3),
            "fps": round(n_img / max(1e-9, t_all), 2),
            **method.prediction_summary(cfg, meta)}
    return rows, info


def segmentation_iou(run_dir: str | Path, dataset_root: str | Path, split: str, part: str = "test", *,
                     device: str = "auto", batch_size: int = 4, num_workers: int = 0,
                     images: list[tuple[int, int]] | None = None) -> dict:
    """Intersection over union of the run's segmentation with the ground-truth visible labels on
    ``split``/``part``, at the run's image size: {"mean": mean over the object classes present,
    "per_class": {obj_id: IoU}, "pixel_accuracy": fraction of object pixels labelled right}. Pixels and
    unions are pooled over the images. For a method whose network segments the image (HFF6DoF,
    PVNet, DenseFusion's segmentation net; not FFB6D, which segments points)."""
    ds = open_dataset(dataset_root)
    if images is None:
        images = ds.part_frames(split, part, "measure")
    scene_folder = ds.scene_folder(split)
    dev = select_device(device)
    run = open_run(run_dir, dev)
    method, net, cfg, meta = run.method, run.net, run.cfg, run.meta
    if getattr(net, "has_seg_head", True) is False:
        raise TdofError("the run has no segmentation head", run_dir)
    if depth_mode_of(cfg) == "restored":
        ds.render_restored(images, scene_folder, show_progress=False)
    data = TransformedDataset(SceneImages(dataset_root, images, labels=True,
                                          restored=depth_mode_of(cfg) == "restored", split=scene_folder),
                              method.transform(cfg, meta, train=False))
    loader = torch.utils.data.DataLoader(data, batch_size=batch_size, num_workers=num_workers, collate_fn=collate,
                                         worker_init_fn=worker_init)
    n = meta.n_classes
    lut = torch.from_numpy(meta.class_lut())
    inter = torch.zeros(n, dtype=torch.long)
    union = torch.zeros(n, dtype=torch.long)
    present = torch.zeros(n, dtype=torch.bool)
    correct = total = 0
    with torch.inference_mode():
        for batch in loader:
            batch = to_device(batch, dev)
            seg = method.forward(net, batch)["seg"]
            if seg.dim() != 4:
                raise TdofError(f"{method.name} segments points, not the image: no segmentation IoU", run_dir)
            pred = seg.argmax(1).cpu()
            if "label" not in batch:
                raise TdofError(f"{method.name}'s transform keeps no labels: no segmentation IoU", run_dir)
            lab = batch["label"].cpu().long()
            if not method.labels_are_classes:
                lab = torch.where(lab < len(lut), lut[lab.clamp(0, len(lut) - 1)], torch.zeros_like(lab))
            inter += torch.bincount(lab[pred == lab].reshape(-1), minlength=n)[:n]
            union += (torch.bincount(lab.reshape(-1), minlength=n)[:n] + torch.bincount(pred.reshape(-1), minlength=n)[:n])
            present |= torch.bincount(lab.reshape(-1), minlength=n)[:n] > 0
            obj = lab > 0
            correct += int((pred[obj] == lab[obj]).sum())
            total += int(obj.sum())
    union -= inter
    per_class = {meta.obj_of(c): float(inter[c]) / max(1, int(union[c])) for c in range(1, n) if present[c]}
    return {"mean": float(np.mean(list(per_class.values()))) if per_class else 0.0, "per_class": per_class,
            "pixel_accuracy": correct / max(1, total)}
