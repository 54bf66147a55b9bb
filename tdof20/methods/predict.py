"""Inference with a trained run of any method: poses of the test images of a split, as a BOP
results CSV (``tdof20 predict RUN --dataset ROOT --split simple|hard --out RESULTS.csv``); the run
knows its method (config.json "method"), and the method's ``predict_poses`` gives the poses.

Beside the CSV, ``<stem>_info.json`` records the run's method, its config ("method_config"), the
input depth mode and the input (rgb / rgbd), timings and counts; ``tdof20 benchmark score`` prints
them with the scores.

The time written per image is the method's ``predict_poses`` (network + pose recovery,
device-synchronised; reading and transforming the images is not counted), shared evenly among the
images of a batch. The network's part is measured with forward hooks on the network and its direct
sub-networks (the outermost call counts), so "network_ms_per_image" and "pose_ms_per_image" are
apart for every method.

HFF6DoF's pose recovery (:func:`recover_poses`, used by ``hff6dof_method.predict_poses``), per image
(paper section 3.5):

1. the network at the run's image size -> segmentation logits and the keypoint vector field;
2. objects: the classes of the segmentation's argmax that cover at least ``min_pixels`` pixels
   (without a segmentation head: the ground-truth visible masks, ``masks = "gt"``);
3. keypoint voting, all objects of a batch at once, in one of two ways (``voting``):

   - ``bearing`` (default): *every* pixel of the object votes, with or without depth. A pixel's
     true 3D point lies on its viewing ray r and its vector v points from that point to the
     keypoint, so the keypoint lies in the plane through the camera centre spanned by r and v,
     whatever the depth: RANSAC over these planes gives each keypoint's bearing (direction from
     the camera), and PnP of the model's keypoints onto the 9 bearings gives R, t. The depth only
     enters through the network's geometry input.
   - ``3d`` (the paper's): the object's pixels *with depth* (the input depth of the run's depth
     mode) are back-projected and vote for 3D keypoints
     (:func:`~tdof20.methods.voting.vote_keypoints_batched`); Kabsch (least squares, weighted by
     each keypoint's inlier count) of the model's keypoints onto them gives R, t.

   On glass most sensor depth is missing or lies behind the surface, which biases ``3d`` voting
   of a run trained with vectors from the true surface points (``vector_origin = "restored"``);
   a run trained with ``vector_origin = "observed"`` (vectors from the input depth's points, none
   where it has no depth) votes from the very points its vectors start at. The comparison is in
   docs/hff6dof.md;
4. score = the mean fraction of the object's voting pixels that are inliers.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from tdof20.errors import TdofError
from tdof20.formats import write_json
from tdof20.formats.io import check_parents
from tdof20.methods.data import SceneImages, TransformedDataset, backproject, collate, split_part_images, \
    worker_init
from tdof20.methods.fitting import kabsch_torch
from tdof20.methods.train import amp_dtype, depth_mode_of, open_run, select_device, to_device
from tdof20.methods.voting import vote_keypoints_batched
from tdof20.progress import console, progress as progress_bar

MASK_SOURCES = ("auto", "network", "gt")
PREDICT_PARTS = ("test", "val")
VOTING = ("3d", "bearing")
DEFAULT_VOTING = "bearing"  # the result of the depth comparison in docs/hff6dof.md


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


def default_min_pixels(image_size) -> int:
    """Smallest segment taken for an object: 0.05 % of the image, at least 10 pixels."""
    return max(10, int(round(5e-4 * image_size[0] * image_size[1])))


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def pixel_rays(K: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(H*W,3) unit viewing rays of the pixels of a camera K (3,3)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32, device=K.device),
                          torch.arange(W, dtype=torch.float32, device=K.device), indexing="ij")
    d = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    return torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)


def vote_bearings_batched(rays: torch.Tensor, vectors: torch.Tensor, valid: torch.Tensor, n_hyp: int = 128,
                          tol: float = 0.02, refine_iters: int = 2, min_sin: float = 1e-2,
                          generator: torch.Generator | None = None, max_elements: int = 1 << 24
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """RANSAC voting of keypoint *bearings* (unit directions from the camera centre), depth-free.

    A pixel's true 3D point lies on its viewing ray r, and its predicted vector v points from that
    point to keypoint k, so the keypoint lies in the plane through the camera centre spanned by r
    and v — whatever the pixel's depth. Each pixel thus constrains the keypoint's bearing b by
    n.b = 0, n = r x v / |r x v|, and b must be a positive combination of r and v. Hypotheses:
    b = n_i x n_j of random pairs; votes: |n.b| < ``tol`` and b between r and v; refinement: the
    smallest eigenvector of sum n n^T over the inliers, ``refine_iters`` times.

    rays (B,N,3) unit; vectors (B,N,K,3) unit; valid (B,N) bool. Returns (bearings (B,K,3),
    n_inliers (B,K) int64); NaN bearings where no hypothesis was acceptable.
    """
    B, N, K, _ = vectors.shape
    dev = rays.device
    dtype = torch.float32
    rays = rays.to(dtype)
    V = torch.nn.functional.normalize(vectors.to(dtype), dim=-1, eps=1e-12).permute(0, 2, 1, 3).contiguous()
    n = torch.cross(rays[:, None].expand_as(V), V, dim=-1)                       # (B,K,N,3)
    norm = n.norm(dim=-1)
    ok_n = valid[:, None] & (norm > 1e-3)
    n = torch.where(ok_n[..., None], n / norm.clamp_min(1e-12)[..., None], torch.zeros_like(n))
    c = (rays[:, None] * V).sum(-1)                                               # (B,K,N) r.v
    rT = rays.transpose(1, 2)[:, None]                                            # (B,1,3,N)
    nT, VT = n.transpose(-1, -2), V.transpose(-1, -2)                             # (B,K,3,N)
    nv = ok_n.sum(-1)                                                             # (B,K)

    def inliers(h: torch.Tensor) -> torch.Tensor:                                 # h (B,K,H,3) -> (B,K,H,N)
        d = torch.matmul(h, nT).abs()
        p = torch.matmul(h, rT)                                                   # b.r
        q = torch.matmul(h, VT)                                                   # b.v
        cc = c[:, :, None]
        return (d < tol) & (p - q * cc > 0) & (q - p * cc > -tol) & ok_n[:, :, None]

    # hypotheses from pairs of valid pixels (per keypoint: pixels whose plane is defined)
    order = torch.argsort((~ok_n).to(torch.int8), dim=-1, stable=True)            # (B,K,N)
    r = torch.rand((B, K, int(n_hyp), 2), generator=generator,
                   device=generator.device if generator is not None else dev).to(dev)
    idx = (r * nv[..., None, None].to(r.dtype)).long().clamp(max=max(N - 1, 0))
    idx = torch.gather(order[:, :, None].expand(B, K, int(n_hyp), N), 3, idx)
    bi = torch.arange(B, device=dev)[:, None, None]
    ki = torch.arange(K, device=dev)[None, :, None]
    h = torch.cross(n[bi, ki, idx[..., 0]], n[bi, ki, idx[..., 1]], dim=-1)     # (B,K,H,3)
    hn = h.norm(dim=-1)
    ok = (hn > min_sin) & (nv[..., None] >= 2)
    h = h / hn.clamp_min(1e-12)[..., None]
    mean_ray = torch.nn.functional.normalize((rays * valid[..., None]).sum(1), dim=-1)
    h = torch.where(((h * mean_ray[:, None, None]).sum(-1) < 0)[..., None], -h, h)
    chunk = max(1, int(max_elements) // max(1, B * K * N))
    score = torch.cat([inliers(h[:, :, i:i + chunk]).sum(-1) for i in range(0, int(n_hyp), chunk)], dim=2)
    score = torch.where(ok, score, torch.full_like(score, -1))
    best = score.argmax(2)
    b = torch.gather(h, 2, best[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
    found = torch.gather(score, 2, best[..., None])[..., 0] > 0
    inl = inliers(b[:, :, None])[:, :, 0]
    for _ in range(max(0, int(refine_iters))):
        w = inl.to(dtype)
        A = torch.einsum("bkn,bkni,bknj->bkij", w, n, n)
        _, evecs = torch.linalg.eigh(A)
        nb = evecs[..., 0]
        nb = torch.where(((nb * b).sum(-1, keepdim=True) < 0), -nb, nb)
        b = torch.where((inl.sum(-1) >= 3)[..., None] & torch.isfinite(nb).all(-1, keepdim=True), nb, b)
        inl = inliers(b[:, :, None])[:, :, 0]
    n_inl = inl.sum(-1)
    b = torch.where(found[..., None], b, torch.full_like(b, float("nan")))
    return b, torch.where(found, n_inl, torch.zeros_like(n_inl))


def pose_from_bearings(model_kp: np.ndarray, bearings: np.ndarray, n_inliers: np.ndarray, n_points: int
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP of model keypoints (K,3) mm onto keypoint bearings (K,3) (OpenCV EPnP, then
    Levenberg-Marquardt); keypoints with few inliers (< max(3, 2 % of the points)) are left out.
    None when fewer than 4 keypoints remain or PnP fails."""
    import cv2

    use = np.isfinite(bearings).all(1) & (bearings[:, 2] > 1e-6) & (n_inliers >= max(3, 0.02 * n_points))
    if use.sum() < 4:
        return None
    obj = np.ascontiguousarray(model_kp[use], dtype=np.float64)
    img = np.ascontiguousarray(bearings[use, :2] / bearings[use, 2:], dtype=np.float64)
    cam = np.eye(3)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, cam, None, flags=cv2.SOLVEPNP_EPNP)
        if ok:
            ok, rvec, tvec = cv2.solvePnP(obj, img, cam, None, rvec, tvec, useExtrinsicGuess=True,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not ok or tvec[2, 0] <= 0:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec[:, 0]


def recover_poses(seg_classes: torch.Tensor, vec: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                  kp_table: torch.Tensor, min_pixels: int, max_points: int = 2000, n_hyp: int = 128,
                  inlier_cos: float = 0.99, generator: torch.Generator | None = None,
                  confidence: torch.Tensor | None = None, voting: str = DEFAULT_VOTING, bearing_tol: float = 0.02
                  ) -> list[list[dict]]:
    """Poses of the objects in a batch of network outputs.

    seg_classes (B,H,W) int64 obj_id per pixel (0 = background); vec (B,3K,H,W) unit vectors;
    depth (B,H,W) mm of the input depth (0 = none); K (B,3,3); kp_table (n_classes,K,3) model
    keypoints in mm; confidence (B,H,W) optional per-pixel class probability.
    voting: '3d' — the object's pixels *with depth* are back-projected and vote for 3D keypoints
    (:func:`~tdof20.methods.voting.vote_keypoints_batched`, inliers within ``inlier_cos``), then
    Kabsch onto the model's keypoints; 'bearing' — *every* pixel of the object votes for the
    keypoints' bearings (:func:`vote_bearings_batched`, depth-free), then PnP.
    Returns per image a list of {"obj_id", "R" (3,3), "t" (3,), "score", "n_points", "confidence"}
    for every object with at least ``min_pixels`` pixels and a successful fit; score = the mean
    fraction of the object's voting pixels that are inliers. At most ``max_points`` random pixels
    of an object vote.
    """
    if voting not in VOTING:
        raise TdofError(f"unknown voting '{voting}' (valid: {', '.join(VOTING)})")
    B, H, W = seg_classes.shape
    dev = vec.device
    nk = vec.shape[1] // 3
    points, vectors, owners = [], [], []
    for b in range(B):
        classes, counts = torch.unique(seg_classes[b], return_counts=True)
        P = None
        for c, cnt in zip(classes.tolist(), counts.tolist()):
            if c <= 0 or c >= kp_table.shape[0] or cnt < min_pixels or not torch.isfinite(kp_table[c]).all():
                continue
            sel = seg_classes[b] == c
            if voting == "3d":
                sel = sel & (depth[b] > 0)
            idx = sel.reshape(-1).nonzero()[:, 0]
            if idx.numel() < 3:
                continue
            if idx.numel() > max_points:
                pick = torch.randperm(idx.numel(), generator=generator, device="cpu" if generator is None
                                      else generator.device)[:max_points].to(idx.device)
                idx = idx[pick]
            if P is None:
                P = backproject(depth[b], K[b]).reshape(-1, 3) if voting == "3d" else pixel_rays(K[b], H, W)
            points.append(P[idx])
            vectors.append(vec[b].reshape(nk, 3, H * W)[:, :, idx].permute(2, 0, 1))
            conf = float(confidence[b].reshape(-1)[idx].mean()) if confidence is not None else 1.0
            owners.append((b, c, int(idx.numel()), conf))
    results: list[list[dict]] = [[] for _ in range(B)]
    if not owners:
        return results
    n = max(p.shape[0] for p in points)
    Pp = torch.zeros(len(points), n, 3, device=dev)
    Vp = torch.zeros(len(points), n, nk, 3, device=dev)
    M = torch.zeros(len(points), n, dtype=torch.bool, device=dev)
    for i, (p, v) in enumerate(zip(points, vectors)):
        Pp[i, :p.shape[0]] = p
        Vp[i, :p.shape[0]] = v.float()
        M[i, :p.shape[0]] = True
    model_kp = kp_table[torch.tensor([o[1] for o in owners], device=kp_table.device)]
    if voting == "3d":
        kps, n_inl = vote_keypoints_batched(Pp, Vp, M, n_hyp=n_hyp, inlier_cos=inlier_cos, generator=generator)
        R, t = kabsch_torch(model_kp.to(dev), kps, weights=n_inl.to(kps.dtype))
        R, t, n_inl = R.cpu().numpy(), t.cpu().numpy(), n_inl.cpu().numpy()
    else:
        bear, n_inl = vote_bearings_batched(Pp, Vp, M, n_hyp=n_hyp, tol=bearing_tol, generator=generator)
        bear, n_inl, mk = bear.cpu().numpy(), n_inl.cpu().numpy(), model_kp.cpu().numpy()
        R = np.full((len(owners), 3, 3), np.nan)
        t = np.full((len(owners), 3), np.nan)
        for i, o in enumerate(owners):
            fit = pose_from_bearings(mk[i], bear[i], n_inl[i], o[2])
            if fit is not None:
                R[i], t[i] = fit
    for i, (b, c, npts, conf) in enumerate(owners):
        if not (np.isfinite(R[i]).all() and np.isfinite(t[i]).all()):
            continue
        results[b].append({"obj_id": int(c), "R": R[i].astype(np.float64), "t": t[i].astype(np.float64),
                           "score": float(n_inl[i].mean() / max(1, npts)), "n_points": npts, "confidence": conf})
    return results


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


#: predict's options that set a field of the method's config (None: as the run's config says)
PREDICT_OPTIONS = ("masks", "voting", "min_pixels", "max_points", "n_hyp", "inlier_cos")


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
            device: str = "auto", batch_size: int = 1, num_workers: int = 2, masks: str | None = None,
            min_pixels: int | None = None, max_points: int | None = None, n_hyp: int | None = None,
            inlier_cos: float | None = None, voting: str | None = None, amp: bool | None = None, seed: int = 0,
            progress: bool = True, method_options: dict | None = None, part: str = "test",
            cache_dir: str | Path | None = None) -> Path:
    """Estimate the poses of every test image of ``split`` (``part`` 'val': of its validation part,
    :mod:`tdof20.dataset.validation`, where choices are made) with the run in ``run_dir`` (any method)
    and write the BOP results CSV ``out_csv`` (scene_id,im_id,obj_id,score,R,t,time); returns its
    path. A summary (method, its config, depth mode, timings, counts, options) goes to
    ``<out_csv stem>_info.json`` beside it.

    masks ('auto' | 'network' | 'gt'), voting ('bearing' | '3d'), min_pixels, max_points, n_hyp,
    inlier_cos, and any option in ``method_options``: prediction options of the run's method config
    (None = the run's; an option the method does not have is refused). For HFF6DoF: 'gt' masks
    are the dataset's visible masks (an oracle segmentation, the only choice for a run trained
    without the segmentation head; not a valid submission). amp: mixed precision for the network
    (None = on for CUDA). batch_size: images per forward pass. seed: the pose recovery's generator.
    cache_dir: where restored depth the dataset lacks is rendered (default ROOT/.cache; for a
    read-only dataset folder), as for training.
    """
    from tdof20.dataset.results import write_results_csv

    out_csv = check_output_file(out_csv)
    check_output_file(info_path(out_csv), "the summary beside --out",
                      "predict writes it there: move the folder away or choose another --out")
    rows, info = predict_rows(run_dir, dataset_root, split, device=device, batch_size=batch_size,
                              num_workers=num_workers, masks=masks, min_pixels=min_pixels, max_points=max_points,
                              n_hyp=n_hyp, inlier_cos=inlier_cos, voting=voting, amp=amp, seed=seed,
                              progress=progress, method_options=method_options, part=part, cache_dir=cache_dir)
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    write_results_csv(out_csv, rows)
    write_json(info_path(out_csv), info)
    if progress:
        console.print(f"{info['method']}: {info['predictions']} poses in {info['images']} images ({split}/{part}, "
                      f"masks: {info['masks']}, depth: {info['depth_mode']}); network "
                      f"{info['network_ms_per_image']:.1f} ms + pose {info['pose_ms_per_image']:.1f} ms per image "
                      f"-> {out_csv}", markup=False)
    return out_csv


def _predict_config(method, cfg, options: dict):
    """The run's method config with predict's options (those not None) applied; refused when the
    method has no such option."""
    import dataclasses

    names = {f.name for f in dataclasses.fields(cfg)}
    changes = {k: v for k, v in options.items() if v is not None}
    bad = [k for k in changes if k not in names]
    if bad:
        raise TdofError(f"--{bad[0].replace('_', '-')} is not an option of {method.name} runs "
                        f"(its options: {', '.join(sorted(names))})")
    return dataclasses.replace(cfg, **changes) if changes else cfg


def _needs_labels(method, cfg, net) -> bool:
    fn = getattr(method.load(), "needs_labels", None)
    return bool(fn(cfg, net)) if fn is not None else False


def predict_rows(run_dir: str | Path, dataset_root: str | Path, split: str, *, device: str = "auto",
                 batch_size: int = 1, num_workers: int = 2, masks: str | None = None, min_pixels: int | None = None,
                 max_points: int | None = None, n_hyp: int | None = None, inlier_cos: float | None = None,
                 voting: str | None = None, amp: bool | None = None, seed: int = 0, progress: bool = True,
                 images: list[tuple[int, int]] | None = None, method_options: dict | None = None,
                 part: str = "test", cache_dir: str | Path | None = None) -> tuple[list[tuple], dict]:
    """What :func:`predict` writes, without writing: (rows (scene_id, im_id, obj_id, score, R (3,3),
    t (3,) mm, time s), summary dict). ``part``: 'test' or 'val' (the validation part of the
    split's train part); ``images`` overrides both."""
    dataset_root = Path(dataset_root)
    if masks is not None and masks not in MASK_SOURCES:
        raise TdofError(f"--masks must be one of {', '.join(MASK_SOURCES)}, got '{masks}'")
    if voting is not None and voting not in VOTING:
        raise TdofError(f"--voting must be one of {', '.join(VOTING)}, got '{voting}'")
    from tdof20.dataset.reader import open_dataset

    ds = open_dataset(dataset_root)  # the one "not a dataset" check
    bop_split = ds.check_split(split) if ds.layout == "bop" else None
    if part not in PREDICT_PARTS:
        raise TdofError(f"--part must be one of {', '.join(PREDICT_PARTS)}, got '{part}'")
    if batch_size < 1 or num_workers < 0:
        raise TdofError(f"--batch-size must be >= 1 and --workers >= 0, got {batch_size} and {num_workers}")
    if images is None:
        if part == "val":
            from tdof20.dataset.validation import part_images

            images = part_images(dataset_root, split, "val")
            if not images:
                raise TdofError(f"the {split} split's validation part is empty (too few turntable steps per arm "
                                "position for a validation arc): nothing to predict", dataset_root)
        else:
            images = split_part_images(dataset_root, split, "test", "predict")
    if not images:
        raise TdofError("no images to predict")
    dev = select_device(device)
    run = open_run(run_dir, dev)
    method, net, meta = run.method, run.net, run.meta
    cfg = _predict_config(method, run.cfg, {**dict(masks=masks, voting=voting, min_pixels=min_pixels,
                                                   max_points=max_points, n_hyp=n_hyp, inlier_cos=inlier_cos),
                                            **(method_options or {})})
    cfg = _predict_config(method, cfg, {"seed": seed} if hasattr(cfg, "seed") else {})
    mask_source = "network"
    if method.name == "hff6dof":
        from tdof20.methods.hff6dof_method import mask_source as hff_masks

        try:
            mask_source = hff_masks(cfg, net)
        except TdofError as e:
            raise TdofError(f"{e}: use --masks gt", run_dir) from None
    labels = _needs_labels(method, cfg, net)
    use_amp = (dev.type == "cuda") if amp is None else (bool(amp) and dev.type == "cuda")
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True
        net = net.to(memory_format=torch.channels_last)
    depth_mode = depth_mode_of(cfg)
    if depth_mode == "restored":  # rendered once (cached) where the dataset has none
        open_dataset(dataset_root, bop_split, cache_dir=cache_dir).render_restored(images, bop_split,
                                                                                    show_progress=progress)
    data = TransformedDataset(SceneImages(dataset_root, images, labels=labels, restored=depth_mode == "restored",
                                          split=bop_split, cache_dir=cache_dir),
                              method.transform(cfg, meta, train=False))
    loader = torch.utils.data.DataLoader(data, batch_size=int(batch_size), shuffle=False,
                                         num_workers=num_workers, collate_fn=collate, worker_init_fn=worker_init,
                                         pin_memory=dev.type == "cuda")
    torch.manual_seed(seed)
    rows = []
    known = set(ds.obj_ids)
    t_all = 0.0
    n_img = n_foreign = n_impossible = 0
    timer = NetworkTimer(net, dev)
    try:
        with torch.inference_mode(), progress_bar(bool(progress), unit="img") as bar:
            task = bar.add_task(f"predict {split}/{part}", total=len(images))
            for batch in loader:
                batch = to_device(batch, dev)
                _sync(dev)
                t0 = time.perf_counter()
                with torch.autocast(dev.type, dtype=amp_dtype(dev), enabled=use_amp):
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
        timer.close()
    t_net = min(timer.seconds, t_all)
    info = {"run": str(Path(run_dir).resolve()), "method": method.name, "input": method.inputs,
            "method_config": method.config_to_data(cfg), "dataset": str(dataset_root.resolve()), "split": split,
            "part": part, "images": n_img, "predictions": len(rows), "masks": mask_source,
            "dropped_objects_not_in_dataset": n_foreign, "dropped_impossible_poses": n_impossible,
            "depth_mode": depth_mode,
            "image_size": list(meta.image_size), "device": str(dev), "amp": use_amp, "batch_size": int(batch_size),
            "seed": int(seed),
            "network_ms_per_image": round(1000 * t_net / max(1, n_img), 3),
            "pose_ms_per_image": round(1000 * (t_all - t_net) / max(1, n_img), 3),
            "fps": round(n_img / max(1e-9, t_all), 2)}
    for k in PREDICT_OPTIONS:  # the options of the older summary, where the method has them
        if hasattr(cfg, k) and k != "masks":
            info[k] = getattr(cfg, k)
    if method.name == "hff6dof":
        info["min_pixels"] = int(cfg.min_pixels) or default_min_pixels(meta.image_size)
    return rows, info


def segmentation_iou(run_dir: str | Path, dataset_root: str | Path, split: str, part: str = "test", *,
                     device: str = "auto", batch_size: int = 4, num_workers: int = 0,
                     images: list[tuple[int, int]] | None = None) -> dict:
    """Intersection over union of the run's segmentation with the ground-truth visible labels on
    ``split``/``part``, at the run's image size: {"mean": mean over the object classes present,
    "per_class": {obj_id: IoU}, "pixel_accuracy": fraction of object pixels labelled right}. Pixels and
    unions are pooled over the images. For a method whose network segments the image (HFF6DoF,
    PVNet, DenseFusion's segmentation net; not FFB6D, which segments points)."""
    if images is None:
        images = split_part_images(dataset_root, split, part, "measure")
    from tdof20.dataset.reader import open_dataset

    ds = open_dataset(dataset_root)
    bop_split = ds.check_split(split) if ds.layout == "bop" else None
    dev = select_device(device)
    run = open_run(run_dir, dev)
    method, net, cfg, meta = run.method, run.net, run.cfg, run.meta
    if getattr(net, "has_seg_head", True) is False:
        raise TdofError("the run has no segmentation head", run_dir)
    if depth_mode_of(cfg) == "restored":
        ds.render_restored(images, bop_split, show_progress=False)
    data = TransformedDataset(SceneImages(dataset_root, images, labels=True,
                                          restored=depth_mode_of(cfg) == "restored", split=bop_split),
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
            if method.name != "hff6dof":  # the HFF6DoF transform gives class indices already
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
