"""The label stage: every frame of a raw session labelled from the registered camera motion and
the placed object models, written as a BOP scene (the layout of :func:`tdof20.sim.truth.oracle_scene`).

Per frame ``(arm, step)`` of the transparent phase, ``im_id = arm * steps + step``:

- ``rgb/``, ``depth/``: the transparent phase's files, copied byte for byte (checked against the
  journal's sha256 first); ``depth_opaque/``: the opaque twin's depth, copied, when captured;
- ``depth_restored/``: the models' rendered depth where a model is seen, the opaque twin's depth
  elsewhere, 0 where neither;
- ``mask/``, ``mask_visib/``: full and visible mask of every placed object (``gt_id`` = its index
  in ``placements``), by exact z-buffer ray casting (``method="raycast"``) or by the paper's
  far-to-near point projection (``method="far_to_near"``);
- ``scene_camera.json`` (cam_K, depth_scale, cam_R_w2c / cam_t_w2c with the reference camera
  (arm 0, step 0) as the world), ``scene_gt.json`` (``inv(T_ref_frame) @ T_ref_model``),
  ``scene_gt_info.json`` (boxes, pixel counts — px_count_valid over the *transparent* depth —
  and visible fraction).

The frames run in chunks on worker processes (or a Ray cluster, see
:mod:`tdof20.annotate.executors`); each worker opens the session and builds its ray caster once.
The workers write the images; the scene's :class:`~tdof20.formats.BopSceneWriter` rewrites the
three JSON files atomically as the chunks come back (merged with the entries already there; at
most every 2 s, and at the end — also of an interrupted run), so a killed run loses at most the
chunks of its last 2 s and those in flight, and a rerun redoes only the frames whose files or
JSON entries are missing or whose poses changed. A frame with a missing or corrupt image is
skipped and reported, never labelled; a frame the caller skips (flagged by registration) gets no
labels, and labels left from an earlier run for it are removed.

The stage writes neither ``models/`` nor ``scene_info.json`` (the pipeline's other stages do).
One writer per scene folder: two runs on the same folder at once are not supported. With worker
processes (the default), a script calling :func:`label_scene` needs the usual
``if __name__ == "__main__":`` guard (workers start by forkserver, see executors).
"""

from __future__ import annotations

import os
import time
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import cv2
import numpy as np

from tdof20.annotate.executors import EXECUTORS, process_cache, resolve_workers, run_chunks
from tdof20.annotate.labels import ModelRaycaster, far_to_near, mask_iou
from tdof20.annotate.pngread import decode_png_fast
from tdof20.config import check_ranges
from tdof20.errors import TdofError
from tdof20.formats import (EMPTY_BBOX, BopSceneWriter, RawSession, atomic_write_bytes, gt_info_from_masks,
                            pose_to_bop, sha256_bytes, write_png)
from tdof20.formats.bop import drop_stale_masks
from tdof20.formats.io import png_header
from tdof20.formats.session import frame_size_problem
from tdof20.geometry import PinholeCamera
from tdof20.geometry.raycast import BoxRender
from tdof20.geometry.sampling import sample_mesh_surface

METHODS = ("raycast", "far_to_near")
IMAGE_DIRS = ("rgb", "depth", "depth_opaque", "depth_restored")
MASK_DIRS = ("mask", "mask_visib")
_POSE_TOL_R = 1e-7     # a stored pose this close to the requested one counts as the same label
_POSE_TOL_T = 1e-4     # mm
_FLUSH_S = 2.0         # the three JSON files are rewritten (and synced) at most this often while the
                       # chunks come in, and once at the end: after every chunk, the full scene's
                       # 100 chunks rewrote ~180 MB with 300 fsyncs


@dataclass(frozen=True)
class LabelConfig:
    """Options of the label stage (every default works on the simulator).

    method: "raycast" (exact z-buffer, default) or "far_to_near" (the paper's point projection).
    compare_every: also run the other method on every N-th frame (``im_id % N == 0``) and report
        the IoU of the two visible masks (0 = never).
    png_compression: ISA-L level 0-3 of the masks and depth_restored (copied files keep theirs).
    chunk: frames per task sent to a worker (the JSON files are rewritten at most every 2 s as they come back).
    workers: worker processes (None = os.cpu_count(); 1 = in this process).
    executor: "local" (worker processes) or "ray"; ray_address: the cluster (None = a new local
        Ray instance).
    samples: Monte-Carlo surface samples per model for far_to_near when none are given; None =
        by image size: 200,000 at 640x480 (scaled with the pixel count, at least 20,000) — dense
        enough that single-pixel points cover the surface (measured visible-mask IoU against
        raycast: median 0.975 at 640x480, 0.92 at 160x120, where edge pixels weigh more).
    splat_px: far_to_near splats each point over a (2 splat_px + 1)^2 square (0: dense samples
        instead; a 1-pixel splat grows every silhouette by a pixel: IoU 0.93 at 640x480).
    verify: check each copied file against the journal's sha256 (a colour image is then not
        decoded: the checksum proves it is the file the capture wrote); False decodes it instead.
    gate: check every label against the frame's own opaque depth before it is written (independent
        of the registration and placement that made it): per object, on its visible pixels (eroded
        by one pixel) with opaque depth, the share within ``gate_tol_mm`` of the model's surface
        must be at least ``gate_min_agree`` and the share where the opaque depth lies more than
        ``gate_tol_mm`` behind the model ("see-through": nothing stands where the label puts the
        object) at most ``gate_max_see_through``; an object with fewer than ``gate_min_pixels``
        such pixels is not judged. A frame with an object that fails is not written (skipped,
        with the figures in its reason); a frame without an opaque twin is written unchecked.
    """

    method: str = "raycast"
    compare_every: int = 0
    png_compression: int = 1
    chunk: int = 16
    workers: int | None = None
    executor: str = "local"
    ray_address: str | None = None
    samples: int | None = None
    splat_px: int = 0
    verify: bool = True
    gate: bool = True
    gate_tol_mm: float = 6.0
    gate_min_pixels: int = 30
    gate_min_agree: float = 0.6
    gate_max_see_through: float = 0.2

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise TdofError(f"label method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.executor not in EXECUTORS:
            raise TdofError(f"executor must be one of {', '.join(EXECUTORS)}, got {self.executor!r}")
        if int(self.compare_every) < 0:
            raise TdofError(f"compare_every must be >= 0 (0 = never), got {self.compare_every}")
        if not 0 <= int(self.png_compression) <= 3:
            raise TdofError(f"png_compression must be 0..3, got {self.png_compression}")
        if int(self.chunk) < 1:
            raise TdofError(f"chunk must be >= 1 frame, got {self.chunk}")
        if self.workers is not None and int(self.workers) < 1:
            raise TdofError(f"workers must be >= 1 (or None = all cores), got {self.workers}")
        if self.samples is not None and int(self.samples) < 1:
            raise TdofError(f"samples must be >= 1, got {self.samples}")
        if int(self.splat_px) < 0:
            raise TdofError(f"splat_px must be >= 0, got {self.splat_px}")
        check_ranges(self, "label", positive=("gate_tol_mm", "gate_min_pixels"),
                     fraction=("gate_min_agree", "gate_max_see_through"))

    def to_dict(self) -> dict:
        return asdict(self)


def auto_samples(camera: PinholeCamera) -> int:
    """Monte-Carlo samples per model that far_to_near needs at this image size (see LabelConfig)."""
    return int(max(20_000, round(200_000 * camera.width * camera.height / (640 * 480))))


# ---------------------------------------------------------------------------------------------
# the work of one frame (runs in a worker)
# ---------------------------------------------------------------------------------------------
@dataclass
class _WorkerState:
    session: RawSession
    camera: PinholeCamera
    raycaster: Any
    samples: dict | None = None


@dataclass(frozen=True)
class _LabelJob:
    """Everything a worker needs, pickled once per worker; ``key`` names its per-process state."""

    session_dir: str
    out_dir: str
    placements: tuple                 # ((obj_id, T_ref_model (4,4)), ...)
    models: dict                      # {obj_id: (V (V,3), F (F,3))}
    samples: dict | None              # {obj_id: (N,3)} or None: sampled in the worker when needed
    cfg: LabelConfig
    depth_factor: float = 1.0         # multiplies the camera's depth_scale (the registration's correction)
    key: str = field(default_factory=lambda: uuid.uuid4().hex)

    def state(self) -> _WorkerState:
        return process_cache(("label", self.key), self._build)

    def _build(self) -> _WorkerState:
        session = RawSession.open(self.session_dir).with_depth_factor(self.depth_factor)
        cam = session.info.camera
        return _WorkerState(session, cam, ModelRaycaster(self.models, cam))

    def samples_of(self, st: _WorkerState) -> dict:
        if st.samples is None:
            if self.samples is not None:
                st.samples = {int(k): np.asarray(v, np.float64) for k, v in self.samples.items()}
            else:
                n = self.cfg.samples or auto_samples(st.camera)
                st.samples = {o: sample_mesh_surface(v, f, n, seed=0) for o, (v, f) in self.models.items()}
        return st.samples

    def render(self, st: _WorkerState, method: str, poses: list):
        if method == "raycast":
            return st.raycaster.render(poses)
        return far_to_near(self.samples_of(st), poses, st.camera, splat_px=self.cfg.splat_px)

    def __call__(self, chunk: list) -> list[dict]:
        st = self.state()
        return [self.label_frame(st, spec) for spec in chunk]

    # --- one frame ------------------------------------------------------------------------------
    def _read(self, st: _WorkerState, phase: str, arm: int, step: int, kind: str,
              decode: bool) -> tuple[bytes, np.ndarray | None]:
        s = st.session
        e = s.entry(phase, arm, step)
        p = s.path / (e.rgb if kind == "rgb" else e.depth)
        try:
            data = p.read_bytes()
        except FileNotFoundError:
            raise TdofError(f"missing {kind} file of {phase} arm {arm} step {step} (the journal lists it)", p) from None
        except OSError as ex:
            raise TdofError(f"cannot read ({type(ex).__name__})", p) from None
        if self.cfg.verify and sha256_bytes(data) != e.sha256.get(kind):
            raise TdofError(f"checksum mismatch: the {kind} file of {phase} arm {arm} step {step} differs "
                            f"from what the journal recorded", p)
        img = None
        if decode or not self.cfg.verify:
            img = decode_png_fast(data, p, kind)   # decode_png's array and errors, faster on our PNGs
            h, w = img.shape[:2]
        else:   # copied as it is: its header must still say what the scene's readers expect
            h, w = png_header(p, kind, data)
        problem = frame_size_problem((h, w), st.camera, kind)
        if problem:
            raise TdofError(problem, p)
        return data, img

    def label_frame(self, st: _WorkerState, spec: tuple) -> dict:
        im_id, arm, step, T_ref_frame, compare = spec[:5]
        drop = spec[5] if len(spec) > 5 else frozenset()   # obj_ids labelled out of this frame (still rendered)
        res: dict = {"im_id": im_id, "arm": arm, "step": step}
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            rgb_bytes, _ = self._read(st, "transparent", arm, step, "rgb", decode=False)
            depth_bytes, depth = self._read(st, "transparent", arm, step, "depth", decode=True)
            opaque_bytes = opaque = None
            if st.session.has_frame("opaque", arm, step):
                opaque_bytes, opaque = self._read(st, "opaque", arm, step, "depth", decode=True)
        except TdofError as e:
            res.update(status="skipped", reason=str(e))
            return res
        t1 = time.perf_counter()

        T_frame_ref = np.linalg.inv(np.asarray(T_ref_frame, np.float64))
        poses = [(obj_id, T_frame_ref @ T_ref_model) for obj_id, T_ref_model in self.placements]
        cam = st.camera
        h, w = cam.height, cam.width
        # the labels of a frame are worked on in the box around the objects (outside it nothing is
        # seen): the same numbers as over the whole image, for a fraction of its pixels
        if self.cfg.method == "raycast":
            lab = st.raycaster.render_box(poses)
        else:
            whole = self.render(st, self.cfg.method, poses)
            lab = BoxRender((0, h, 0, w), (h, w), whole.full, whole.visible, whole.depth)
        cmp = None
        if compare:
            other = "far_to_near" if self.cfg.method == "raycast" else "raycast"
            lab2 = self.render(st, other, poses)
            exact, painter = (lab.whole(), lab2) if self.cfg.method == "raycast" else (lab2, lab.whole())
            cmp = _compare(exact, painter, len(poses))
        t2 = time.perf_counter()

        gate = None
        if self.cfg.gate and opaque is not None:
            exact = lab if self.cfg.method == "raycast" else st.raycaster.render_box(poses)
            ev0, ev1, eu0, eu1 = exact.box
            gate = gate_check(exact, opaque[ev0:ev1, eu0:eu1].astype(np.float32) * np.float32(cam.depth_scale),
                              self.cfg)
            failed = [(g, poses[g][0], c) for g, c in enumerate(gate) if c["ok"] is False and poses[g][0] not in drop]
            if failed:
                res.update(status="skipped", gate=gate, reason="label gate: " + "; ".join(
                    f"object {o} (gt {g}) disagrees with the opaque depth: {c['agree']:.0%} of {c['pixels']} "
                    f"pixels within {self.cfg.gate_tol_mm:g} mm, {c['see_through']:.0%} see through it"
                    for g, o, c in failed))
                return res
        v0, v1, u0, u1 = lab.box
        hit = lab.visible >= 0
        restored = np.zeros((h, w), np.uint16) if opaque is None else opaque.copy()
        restored[v0:v1, u0:u1][hit] = cam.mm_to_depth(lab.depth[hit])
        visib = [(lab.visible == i) & full for i, full in enumerate(lab.full)]
        kept = [g for g, (o, _) in enumerate(poses) if o not in drop]
        full_k, visib = [lab.full[g] for g in kept], [visib[g] for g in kept]
        gt, gt_info = [], []
        depth_box = depth[v0:v1, u0:u1]
        for (obj_id, T), full, vis in zip([poses[g] for g in kept], full_k, visib):
            gt.append(pose_to_bop(T[:3, :3], T[:3, 3], obj_id=int(obj_id)))
            gt_info.append(_gt_info(full, vis, depth_box, offset=(u0, v0)))
        T_w2c = T_frame_ref
        camera = {"cam_K": [float(x) for x in cam.K.reshape(-1)], "depth_scale": float(cam.depth_scale),
                  "cam_R_w2c": [float(x) for x in T_w2c[:3, :3].reshape(-1)],
                  "cam_t_w2c": [float(x) for x in T_w2c[:3, 3]]}
        t3 = time.perf_counter()

        out = Path(self.out_dir)
        name = f"{im_id:06d}.png"
        c = self.cfg.png_compression
        atomic_write_bytes(out / "rgb" / name, rgb_bytes)
        atomic_write_bytes(out / "depth" / name, depth_bytes)
        if opaque_bytes is not None:
            atomic_write_bytes(out / "depth_opaque" / name, opaque_bytes)
        else:
            (out / "depth_opaque" / name).unlink(missing_ok=True)
        write_png(out / "depth_restored" / name, restored, c)
        for g, (full, vis) in enumerate(zip(full_k, visib)):
            for sub, m in (("mask", full), ("mask_visib", vis)):
                img = np.zeros((h, w), np.uint8)
                img[v0:v1, u0:u1] = m.view(np.uint8) * np.uint8(255)
                write_png(out / sub / f"{im_id:06d}_{g:06d}.png", img, c)
        drop_stale_masks(out, im_id, len(kept))  # a frame written before with more instances
        t4 = time.perf_counter()
        res.update(status="labelled", camera=camera, gt=gt, gt_info=gt_info, compare=cmp,
                   opaque=opaque_bytes is not None, gate=gate,
                   times={"read": t1 - t0, "render": t2 - t1, "labels": t3 - t2, "write": t4 - t3,
                          "cpu": time.process_time() - c0})
        return res


def gate_check(lab, opaque_mm: np.ndarray, cfg: LabelConfig) -> list[dict]:
    """The label gate's figures per instance (see :class:`LabelConfig`): ``pixels`` (visible,
    eroded by one pixel, with opaque depth), ``agree`` (share within ``gate_tol_mm`` of the
    model's ray-cast depth), ``see_through`` (share where the opaque depth is more than
    ``gate_tol_mm`` behind it), ``median_mm`` (median |difference|) and ``ok`` (True, False, or
    None when too few pixels to judge). ``lab``: a LabelRender with ``opaque_mm`` (H,W), or a
    BoxRender with ``opaque_mm`` cut to its box (its margin makes the erosion the same)."""
    out = []
    kernel = np.ones((3, 3), np.uint8)
    tol = float(cfg.gate_tol_mm)
    for i in range(len(lab.full)):
        if lab.visible.size == 0:   # an empty box: nothing seen
            out.append({"pixels": 0, "agree": None, "see_through": None, "median_mm": None, "ok": None})
            continue
        vis = cv2.erode((lab.visible == i).view(np.uint8), kernel).view(bool)
        pix = vis & (opaque_mm > 0)
        n = int(np.count_nonzero(pix))
        if n < cfg.gate_min_pixels:
            out.append({"pixels": n, "agree": None, "see_through": None, "median_mm": None, "ok": None})
            continue
        dz = opaque_mm[pix] - lab.depth[pix]
        agree = float(np.mean(np.abs(dz) <= tol))
        see = float(np.mean(dz > tol))
        out.append({"pixels": n, "agree": round(agree, 4), "see_through": round(see, 4),
                    "median_mm": round(float(np.median(np.abs(dz))), 3),
                    "ok": agree >= cfg.gate_min_agree and see <= cfg.gate_max_see_through})
    return out


def _gt_info(full: np.ndarray, vis: np.ndarray, depth: np.ndarray, offset: tuple[int, int] = (0, 0)) -> dict:
    """:func:`gt_info_from_masks` of an instance computed on the bounding box of its masks (the
    same numbers, without several passes over the whole image). The arrays may be a box of the
    image whose top-left pixel is ``offset`` (u, v): the boxes are given in the whole image."""
    x, y, w, h = cv2.boundingRect(full.view(np.uint8)) if full.size else (0, 0, 0, 0)
    if w == 0 or h == 0:   # no silhouette: every count 0, both boxes empty, whatever the pixel
        return gt_info_from_masks(np.zeros((1, 1), bool), np.zeros((1, 1), bool), np.zeros((1, 1), np.uint16))
    info = gt_info_from_masks(full[y:y + h, x:x + w], vis[y:y + h, x:x + w], depth[y:y + h, x:x + w])
    for k in ("bbox_obj", "bbox_visib"):
        if info[k] != EMPTY_BBOX:
            info[k] = [info[k][0] + x + offset[0], info[k][1] + y + offset[1], info[k][2], info[k][3]]
    return info


def _compare(exact, painter, n: int) -> list[dict]:
    """Per instance seen by either method: IoU of the visible and of the full masks."""
    out = []
    for i in range(n):
        ve, vp = exact.visible == i, painter.visible == i
        if not (ve.any() or vp.any()):
            continue
        out.append({"gt_id": i, "visible_iou": mask_iou(ve, vp), "full_iou": mask_iou(exact.full[i], painter.full[i]),
                    "px_visib": int(ve.sum())})
    return out


# ---------------------------------------------------------------------------------------------
# the stage
# ---------------------------------------------------------------------------------------------
def _check_T(T: Any, where: str) -> np.ndarray | None:
    a = np.asarray(T, dtype=np.float64)
    if a.shape != (4, 4):
        raise TdofError(f"{where} must be a (4,4) transform, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        return None
    return a


def _frame_transforms(T_ref_frames: Any, n_arms: int, steps: int) -> dict[tuple[int, int], np.ndarray]:
    """{(arm, step): (4,4)} from a dict, or from an (n_arms, steps, 4, 4) array (NaN = none)."""
    out = {}
    if isinstance(T_ref_frames, Mapping):
        for key, T in T_ref_frames.items():
            a, k = (int(x) for x in key)
            t = _check_T(T, f"T_ref_frames[{a}, {k}]")
            if t is not None:
                out[(a, k)] = t
        return out
    arr = np.asarray(T_ref_frames, dtype=np.float64)
    if arr.ndim != 4 or arr.shape[2:] != (4, 4):
        raise TdofError(f"T_ref_frames must be a dict {{(arm, step): (4,4)}} or an (arms, steps, 4, 4) array, "
                        f"got shape {arr.shape}")
    for a in range(min(n_arms, arr.shape[0])):
        for k in range(min(steps, arr.shape[1])):
            if np.all(np.isfinite(arr[a, k])):
                out[(a, k)] = arr[a, k]
    return out


def _skip_reasons(skip: Any) -> dict[tuple[int, int], str]:
    if isinstance(skip, Mapping):
        return {(int(a), int(k)): str(r) for (a, k), r in skip.items()}
    out = {}
    for item in skip or ():
        if len(item) == 4:  # (arm, step, reason, obj_ids): only those objects left out (_object_skips)
            continue
        if len(item) == 3:  # (arm, step, reason), as RegistrationResult.flagged_frames() gives
            a, k, r = item
            out[(int(a), int(k))] = str(r)
        else:
            a, k = item
            out[(int(a), int(k))] = "skipped by the caller (flagged)"
    return out


def _object_skips(skip: Any) -> dict[tuple[int, int], tuple[frozenset, str]]:
    """{(arm, step): (obj_ids, reason)} of ``skip``'s (arm, step, reason, obj_ids) items."""
    if isinstance(skip, Mapping):
        return {}
    return {(int(it[0]), int(it[1])): (frozenset(int(o) for o in it[3]), str(it[2]))
            for it in skip or () if len(it) == 4}


def _listing(d: Path) -> set[str]:
    try:
        return {e.name for e in os.scandir(d)}
    except FileNotFoundError:
        return set()


def _same_labels(writer: BopSceneWriter, im_id: int, cam: dict, gt: list[tuple[int, np.ndarray]]) -> bool:
    """Whether the stored entries of a frame are the ones these inputs give (so it is not redone)."""
    try:
        c = writer.camera[im_id]
        if not np.allclose(c["cam_K"], cam["cam_K"], rtol=0, atol=1e-9) or c["depth_scale"] != cam["depth_scale"]:
            return False
        if not (np.allclose(c["cam_R_w2c"], cam["cam_R_w2c"], rtol=0, atol=_POSE_TOL_R)
                and np.allclose(c["cam_t_w2c"], cam["cam_t_w2c"], rtol=0, atol=_POSE_TOL_T)):
            return False
        stored = writer.gt[im_id]
        if len(stored) != len(gt) or len(writer.gt_info[im_id]) != len(gt):
            return False
        for e, (obj_id, T) in zip(stored, gt):
            if int(e["obj_id"]) != int(obj_id):
                return False
            if not (np.allclose(e["cam_R_m2c"], T[:3, :3].reshape(-1), rtol=0, atol=_POSE_TOL_R)
                    and np.allclose(e["cam_t_m2c"], T[:3, 3], rtol=0, atol=_POSE_TOL_T)):
                return False
    except (KeyError, TypeError, ValueError):
        return False
    return True


def _remove_frame_files(out: Path, im_id: int, listing: dict[str, set[str]] | None) -> None:
    """Delete a frame's images and masks (``listing``: the folders' names, or None to look)."""
    name, prefix = f"{im_id:06d}.png", f"{im_id:06d}_"
    for sub in IMAGE_DIRS:
        if listing is None or name in listing[sub]:
            (out / sub / name).unlink(missing_ok=True)
    for sub in MASK_DIRS:
        for n in (listing[sub] if listing is not None else _listing(out / sub)):
            if n.startswith(prefix):
                (out / sub / n).unlink(missing_ok=True)


def _stats(x: list[float]) -> dict:
    if not x:
        return {"median": None, "min": None, "p5": None, "mean": None}
    a = np.asarray(x, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "p5": float(np.percentile(a, 5)),
            "mean": float(a.mean())}


def label_scene(session_dir: str | Path, out_dir: str | Path, T_ref_frames: Any,
                placements: Iterable[tuple[int, np.ndarray]], models: Mapping[int, tuple[np.ndarray, np.ndarray]],
                cfg: LabelConfig = LabelConfig(), skip: Any = (), progress: bool = True,
                samples: Mapping[int, np.ndarray] | None = None, reuse: bool = True,
                depth_factor: float = 1.0) -> dict:
    """Label every frame of the transparent phase of a raw session into the BOP scene ``out_dir``.

    T_ref_frames: {(arm, step): (4,4)} camera of frame (arm, step) -> reference camera (arm 0,
        step 0), e.g. ``RegistrationResult.frame(a, k).T_ref_frame``; an (arms, steps, 4, 4)
        array (NaN = none, as ``truth_T_ref_frame`` gives) is accepted too. A frame without one is
        skipped ("no registration").
    placements: [(obj_id, T_ref_model (4,4))], the model pose of each object instance in the
        reference camera; gt_id = index in this list.
    models: {obj_id: (vertices (V,3) mm, faces (F,3))} in the model frames.
    skip: frames not to label: [(arm, step)], [(arm, step, reason)] (as
        ``RegistrationResult.flagged_frames()`` lists them) or {(arm, step): reason}; an item
        (arm, step, reason, obj_ids) labels that frame without those objects (no gt entry, no
        masks, not judged by the gate; still rendered, so they hide what they stand in front of).
    samples: {obj_id: (N,3) mm} Monte-Carlo surface samples for far_to_near; None = ``cfg.samples``
        area-uniform samples of each mesh (seed 0), drawn in each worker when needed.
    reuse: keep a frame whose files and labels on disk are already the ones this run would write
        (False: label every frame again, e.g. when the label gate's options changed since).
    depth_factor: multiplies session.json's ``camera.depth_scale`` (the registration's depth-scale
        correction, ``1 / RegistrationResult.depth_factor``): the gate reads true millimetres and
        scene_camera.json's ``depth_scale`` says what the depth images really mean.

    Returns a summary: ``frames`` (planned), ``labelled``, ``already_done``, ``skipped``
    ([{im_id, arm, step, reason}]), ``removed`` (im_ids whose earlier labels were removed because
    the frame is now skipped), ``no_opaque`` (labelled im_ids without an opaque twin),
    ``seconds``, ``run_seconds`` (the labelling, worker start included), ``frames_per_s``
    (labelled / run_seconds), ``first_chunk_seconds`` (until the first chunk came back: worker
    start and set-up), ``steady_frames_per_s`` (the rate after it),
    ``worker_seconds`` (wall time per part — read, render, labels, write — and ``cpu``, the
    workers' CPU time, summed over the frames), ``main_cpu_seconds`` (this process's CPU time
    while the workers ran: collecting results, writing the JSON files) and
    ``comparison`` (raycast vs far_to_near IoUs over the compared frames, or None).
    """
    t_start = time.perf_counter()
    session = RawSession.open(session_dir).with_depth_factor(depth_factor)
    info = session.info
    cam = info.camera
    steps, n_arms = info.steps, info.n_arms
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise TdofError("is not a folder", out)

    # --- inputs ---------------------------------------------------------------------------------
    model_map = {}
    for obj_id, vf in dict(models).items():
        try:
            v, f = vf
        except (TypeError, ValueError):
            raise TdofError(f"models[{obj_id}] must be (vertices (V,3), faces (F,3))") from None
        v, f = np.asarray(v, np.float64), np.asarray(f)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(v) == 0 or len(f) == 0:
            raise TdofError(f"models[{obj_id}] must be (vertices (V,3), faces (F,3)), got {v.shape} and {f.shape}")
        model_map[int(obj_id)] = (v, f.astype(np.int64))
    places = []
    for i, (obj_id, T) in enumerate(placements):
        if int(obj_id) not in model_map:
            raise TdofError(f"placement {i}: no model for object {obj_id}")
        t = _check_T(T, f"placement {i} T_ref_model")
        if t is None:
            raise TdofError(f"placement {i} T_ref_model holds NaN or inf")
        places.append((int(obj_id), t))
    if not places:
        raise TdofError("nothing to label: no object placements")
    if samples is not None:
        missing = {o for o, _ in places} - {int(k) for k in samples}
        if missing:
            raise TdofError(f"samples given, but none for object(s) {sorted(missing)}")
        samples = {int(k): np.asarray(v, np.float64).reshape(-1, 3) for k, v in samples.items()}
    Ts = _frame_transforms(T_ref_frames, n_arms, steps)
    skips = _skip_reasons(skip)
    drops = _object_skips(skip)

    # --- plan: what is done, what to do, what to skip ------------------------------------------
    writer = BopSceneWriter(out)
    listing = {d: _listing(out / d) for d in IMAGE_DIRS + MASK_DIRS}
    K_flat = [float(x) for x in cam.K.reshape(-1)]
    skipped, done, todo = [], [], []
    for arm in range(n_arms):
        for step in range(steps):
            im_id = arm * steps + step
            reason = skips.get((arm, step))
            if reason is None and (arm, step) not in Ts:
                reason = "no registration for this frame (no T_ref_frame)"
            if reason is None and not session.has_frame("transparent", arm, step):
                reason = "missing frame: the journal does not list it (never captured)"
            drop, drop_reason = drops.get((arm, step), (frozenset(), ""))
            kept = [(o, Tm) for o, Tm in places if o not in drop]
            if reason is None and not kept:
                reason = drop_reason
            if reason is not None:
                skipped.append({"im_id": im_id, "arm": arm, "step": step, "reason": reason})
                continue
            T = Ts[(arm, step)]
            T_frame_ref = np.linalg.inv(T)
            name = f"{im_id:06d}.png"
            has_opaque = session.has_frame("opaque", arm, step)
            files_ok = (all(name in listing[d] for d in ("rgb", "depth", "depth_restored"))
                        and (not has_opaque or name in listing["depth_opaque"])
                        and all(f"{im_id:06d}_{g:06d}.png" in listing[d] for d in MASK_DIRS for g in range(len(kept))))
            if reuse and files_ok and writer.has(im_id):
                camd = {"cam_K": K_flat, "depth_scale": float(cam.depth_scale),
                        "cam_R_w2c": T_frame_ref[:3, :3].reshape(-1), "cam_t_w2c": T_frame_ref[:3, 3]}
                if _same_labels(writer, im_id, camd, [(o, T_frame_ref @ Tm) for o, Tm in kept]):
                    done.append(im_id)
                    continue
            compare = cfg.compare_every > 0 and im_id % cfg.compare_every == 0
            todo.append((im_id, arm, step, T, compare) + ((drop,) if drop else ()))
    removed = []
    for s in skipped:  # labels of an earlier run for a frame that must not be labelled now
        im_id = s["im_id"]
        name = f"{im_id:06d}.png"
        if writer.has_any(im_id) or any(name in listing[d] for d in IMAGE_DIRS):
            writer.drop(im_id)
            _remove_frame_files(out, im_id, listing)
            removed.append(im_id)
    for d in IMAGE_DIRS + MASK_DIRS:
        (out / d).mkdir(parents=True, exist_ok=True)
    writer.flush()

    # --- run ------------------------------------------------------------------------------------
    job = _LabelJob(str(session.path), str(out), tuple(places), model_map, samples, cfg, depth_factor)
    chunks = [todo[i:i + cfg.chunk] for i in range(0, len(todo), cfg.chunk)]
    labelled, no_opaque, comparisons = [], [], []
    times: dict[str, float] = {}
    t_run, cpu_run = time.perf_counter(), time.process_time()
    t_first, n_first = None, 0
    t_flush = time.perf_counter()
    gate_agree: list[float] = []
    gate_failed = gate_unjudged = 0
    try:
        for results in run_chunks(job, chunks, executor=cfg.executor, workers=cfg.workers,
                                  ray_address=cfg.ray_address, progress=progress, description="labels",
                                  size=len, unit="fr"):
            for r in results:
                for c in r.get("gate") or ():
                    if c["ok"] is not None:
                        gate_agree.append(c["agree"])
                        gate_failed += c["ok"] is False
                    else:
                        gate_unjudged += 1
                if r["status"] != "labelled":
                    skipped.append({k: r[k] for k in ("im_id", "arm", "step", "reason")})
                    if writer.has_any(r["im_id"]):  # an earlier run's labels of a frame now unreadable
                        writer.drop(r["im_id"])
                        _remove_frame_files(out, r["im_id"], None)
                        removed.append(r["im_id"])
                    continue
                writer.put(r["im_id"], r["camera"], r["gt"], r["gt_info"])
                labelled.append(r["im_id"])
                if not r["opaque"]:
                    no_opaque.append(r["im_id"])
                for c in r["compare"] or ():
                    comparisons.append({"im_id": r["im_id"], **c})
                for k, v in r["times"].items():
                    times[k] = times.get(k, 0.0) + v
            if time.perf_counter() - t_flush >= _FLUSH_S:
                writer.flush()
                t_flush = time.perf_counter()
            if t_first is None:
                t_first, n_first = time.perf_counter(), len(labelled)
    finally:
        writer.flush()
    t_end, cpu_main = time.perf_counter(), time.process_time() - cpu_run
    if cfg.executor == "local" and min(resolve_workers(cfg.workers), len(chunks)) <= 1:
        cpu_main -= times.get("cpu", 0.0)  # the frames ran in this process: count their CPU once

    skipped.sort(key=lambda s: s["im_id"])
    run_s = t_end - t_run
    comparison = None
    if comparisons:
        comparison = {"methods": ["raycast", "far_to_near"], "every": cfg.compare_every,
                      "frames": len({c["im_id"] for c in comparisons}), "instances": len(comparisons),
                      "visible_iou": _stats([c["visible_iou"] for c in comparisons]),
                      "full_iou": _stats([c["full_iou"] for c in comparisons]),
                      "per_instance": comparisons}
    return {
        "frames": n_arms * steps, "labelled": len(labelled), "already_done": len(done), "skipped": skipped,
        "removed": removed, "no_opaque": sorted(no_opaque), "method": cfg.method, "executor": cfg.executor,
        "workers": min(resolve_workers(cfg.workers), max(len(chunks), 1)) if cfg.executor == "local" else cfg.workers,
        "seconds": t_end - t_start, "run_seconds": run_s,
        "frames_per_s": len(labelled) / run_s if labelled and run_s > 0 else 0.0,
        "first_chunk_seconds": None if t_first is None else t_first - t_run,
        "steady_frames_per_s": (len(labelled) - n_first) / (t_end - t_first)
        if t_first is not None and len(labelled) > n_first and t_end > t_first else None,
        "worker_seconds": {k: round(v, 3) for k, v in times.items()},
        "main_cpu_seconds": round(cpu_main, 3),
        "comparison": comparison,
        "gate": {"enabled": cfg.gate, "instances_checked": len(gate_agree), "instances_failed": gate_failed,
                 "instances_unjudged": gate_unjudged, "agree": _stats(gate_agree),
                 "frames_refused": sum(1 for sk in skipped if sk["reason"].startswith("label gate:"))},
    }


__all__ = ["LabelConfig", "label_scene", "METHODS"]
