"""The annotation pipeline: a raw capture session in, a labelled BOP scene out, in six stages.

    annotate(raw_dir, out_dir, models_dir=None, stages=None, cfg=AnnotateConfig())

=============  ===============================================================================
stage          what it does, and what it leaves on disk
=============  ===============================================================================
register       every frame's camera motion to frame (arm 0, step 0) from the opaque depth
               (:func:`tdof20.annotate.registration.register_session`) -> ``work/registration.json``
reconstruct    the usable opaque frames (registration's poses) streamed one by one into a TSDF in
               the reference frame; table top; object clusters
               (:func:`tdof20.annotate.reconstruct.reconstruct`) -> ``work/reconstruction/``:
               ``scene_points.ply``, ``scene_mesh.ply``, ``cluster_000.ply`` ..., ``reconstruction.json``
model          with ``models_dir`` (a BOP models folder in mm: a lab's CAD models, or the models
               the single-object scenes got): each object of ``session.json`` matched to a
               cluster — a shape test (height above the table, footprint radius) picks the
               candidates, a quick upright fit (:func:`tdof20.annotate.models.fit_model`) scores
               them, a one-to-one assignment (scipy ``linear_sum_assignment``) decides;
               without it (single-object scenes): a watertight model built from the cluster
               (:func:`tdof20.annotate.modelbuild.build_model_from_cluster`, screened Poisson) ->
               ``work/fits.json`` (+ ``work/models/`` when built)
place          every object's pose ``T_ref_model`` in the reference frame: the matched fit refined
               with dense samples, set upright on the table (the model's z along the table
               normal, when it is within ``place.upright_max_deg``), checked against the quality
               gate (a bad fit stops the run: no label is written from it) -> ``work/placements.json``
               and the scene's models folder ``models/`` (the built models, or the user's files
               of this scene's objects, copied byte for byte)
label          poses, masks, restored depth of every frame registration did not flag
               (:func:`tdof20.annotate.label.label_scene`; unreadable frames are skipped and
               listed) -> the BOP scene (``rgb/``, ``depth/``, ``depth_opaque/``,
               ``depth_restored/``, ``mask/``, ``mask_visib/``, the JSON files,
               ``scene_info.json``) and ``work/label.json``
qa             overlays, registration plots, HTML report (:func:`tdof20.annotate.qa.write_qa`)
               and, for a simulated session (``truth/``), the evaluation against the truth
               (:func:`tdof20.annotate.evaluate.evaluate_scene`) -> ``qa/``, ``work/evaluation.json``
=============  ===============================================================================

Resuming. ``work/state.json`` records each finished stage: when, how long, the fingerprint of its
inputs (the raw session's ``session.json`` and journal, the stage's options, the outputs of the
stages it reads, a models folder's files) and the signature of its outputs. A rerun skips a stage
whose fingerprint and outputs are unchanged, so an interrupted run resumes after the last finished
stage, and a changed option or input reruns the stages it affects (and, through their outputs,
the ones after). The label stage resumes inside itself too (frames already written are kept).
``stages=[...]`` runs only those stages (skipped when up to date, unless ``force``); a stage whose
inputs are missing stops with one line saying which stage to run first. Every run writes
``work/summary.json``: per-stage status and timing, flagged and skipped frames with their reasons,
the objects' fit scores, the evaluation.

Options (:class:`AnnotateConfig`) come from a TOML file (:func:`load_annotate_config`) with one
table per stage — ``[register]`` (RegistrationConfig), ``[reconstruct]`` (ReconstructionConfig),
``[fit]`` (ModelFitConfig), ``[build]`` (ModelBuildConfig), ``[place]`` (:class:`PlaceConfig`),
``[label]`` (LabelConfig), ``[qa]`` (:class:`QAConfig`) — and top-level ``fuse_max_frames``, ``fuse_crop``, ``fuse_max_height_mm``; an unknown
key is an error naming the file and the key. See ``docs/annotate.md``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import fcntl
import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from tdof20.annotate.label import LabelConfig, label_scene
from tdof20.annotate.models import ModelFitConfig, fit_model
from tdof20.annotate.modelbuild import ModelBuildConfig
from tdof20.annotate.reconstruct import ReconstructionConfig, reconstruct
from tdof20.annotate.registration import RegistrationConfig, RegistrationResult, register_session
from tdof20.config import config_from_data, load_config_file
from tdof20.errors import TdofError
from tdof20.formats import RawSession, atomic_write_bytes, read_json, write_json
from tdof20.formats.bop import read_models_info, write_models_info
from tdof20.o3d import o3d

__all__ = ["STAGES", "AnnotateConfig", "PlaceConfig", "QAConfig", "annotate", "load_annotate_config",
           "annotate_config_from_dict", "parse_stages", "summary_text"]

STAGES = ("register", "reconstruct", "model", "place", "label", "qa")
STATE_FORMAT = "tdof20-annotate-state"
STATE_VERSION = 1
WORK = "work"

# the stages whose outputs each stage reads
_NEEDS = {"register": (), "reconstruct": ("register",), "model": ("reconstruct",),
          "place": ("reconstruct", "model"), "label": ("register", "place"), "qa": ("register", "label")}
# label options that change how the work runs, not what it writes
_LABEL_RUNTIME = ("workers", "executor", "ray_address", "chunk")


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
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
    min_fitness: float = 0.15            # quality gate of the final fit (fraction of cluster points
    max_score_mm: float = 3.0            # within the last ICP distance; truncated mean distance)

    def __post_init__(self) -> None:
        if self.match_samples < 100 or self.fit_samples < 100:
            raise TdofError("place.match_samples and place.fit_samples must be >= 100")
        if self.match_candidates < 1:
            raise TdofError(f"place.match_candidates must be >= 1, got {self.match_candidates}")
        if not self.match_icp_mm or any(d <= 0 for d in self.match_icp_mm) or self.match_voxel_mm <= 0:
            raise TdofError("place.match_icp_mm and place.match_voxel_mm must be > 0")


@dataclass(frozen=True)
class QAConfig:
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
        return {name: _jsonable(dataclasses.asdict(getattr(self, name))) for name in _SECTIONS} | {
            k: getattr(self, k) for k in _SCALARS}


_SECTIONS = ("register", "reconstruct", "fit", "build", "place", "label", "qa")
_SCALARS = ("fuse_max_frames", "fuse_crop", "fuse_max_height_mm")


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def annotate_config_from_dict(data: dict, source: str = "") -> AnnotateConfig:
    """An :class:`AnnotateConfig` from a parsed TOML document (strict: an unknown table or key is
    a TdofError naming ``source`` and the key)."""
    return config_from_data(AnnotateConfig, data, source)


def load_annotate_config(path: str | Path) -> AnnotateConfig:
    """Read and check a TOML annotation config; any problem is one line naming the file."""
    return load_config_file(AnnotateConfig, path)


def parse_stages(spec: str | Iterable[str] | None) -> tuple[str, ...]:
    """Stage names in pipeline order from ``None`` (all), a list, ``"label,qa"`` or a range
    ``"register..model"`` (either end may be left out: ``"place.."``)."""
    if spec is None:
        return STAGES
    items = [spec] if isinstance(spec, str) else list(spec)
    chosen: set[str] = set()
    for item in items:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            if ".." in part:
                a, b = (s.strip() for s in part.split("..", 1))
                for s in (a, b):
                    if s and s not in STAGES:
                        raise TdofError(f"unknown stage '{s}' (stages: {', '.join(STAGES)})")
                i = STAGES.index(a) if a else 0
                j = STAGES.index(b) if b else len(STAGES) - 1
                if i > j:
                    raise TdofError(f"stage range '{part}' runs backwards (order: {' -> '.join(STAGES)})")
                chosen.update(STAGES[i:j + 1])
            elif part in STAGES:
                chosen.add(part)
            else:
                raise TdofError(f"unknown stage '{part}' (stages: {', '.join(STAGES)})")
    if not chosen:
        raise TdofError(f"no stage given (stages: {', '.join(STAGES)})")
    return tuple(s for s in STAGES if s in chosen)


# ---------------------------------------------------------------------------------------------
# fingerprints and the state file
# ---------------------------------------------------------------------------------------------
def _sha_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _sha_obj(obj: Any) -> str:
    return hashlib.sha256(json.dumps(_jsonable(obj), sort_keys=True).encode()).hexdigest()


def _dir_hash(d: Path) -> str:
    """Names and contents of the files directly in ``d``."""
    if not d.is_dir():
        return "absent"
    return _sha_obj({p.name: _sha_file(p) for p in sorted(d.iterdir()) if p.is_file()})


def _count_files(d: Path) -> int:
    try:
        return sum(1 for e in os.scandir(d) if e.is_file())
    except FileNotFoundError:
        return 0


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


class _State:
    """``work/state.json``: {stage: {started, finished, seconds, fingerprint, outputs}}; a stage
    being (re)run has no ``finished``, so an interruption leaves it unfinished."""

    def __init__(self, work: Path, raw: Path):
        self.path = work / "state.json"
        self.data = {"format": STATE_FORMAT, "version": STATE_VERSION, "raw": str(raw), "stages": {}}
        if self.path.exists():
            d = read_json(self.path)
            if not isinstance(d, dict) or d.get("format") != STATE_FORMAT or not isinstance(d.get("stages"), dict):
                raise TdofError(f"not an annotation state file (format must be '{STATE_FORMAT}')", self.path)
            if int(d.get("version", 0)) > STATE_VERSION:
                raise TdofError(f"written by a newer tdof20 (version {d.get('version')}): upgrade tdof20", self.path)
            self.data = d
            self.data["raw"] = str(raw)

    def entry(self, stage: str) -> dict:
        return self.data["stages"].get(stage, {})

    def finished(self, stage: str) -> bool:
        return bool(self.entry(stage).get("finished"))

    def start(self, stage: str) -> None:
        self.data["stages"][stage] = {"started": _now()}
        self.save()

    def finish(self, stage: str, fingerprint: str, seconds: float, outputs: dict) -> None:
        e = self.data["stages"].setdefault(stage, {"started": _now()})
        e.update(finished=_now(), seconds=round(seconds, 3), fingerprint=fingerprint, outputs=outputs)
        self.save()

    def save(self) -> None:
        write_json(self.path, self.data)


# ---------------------------------------------------------------------------------------------
# the run context: paths, inputs, outputs
# ---------------------------------------------------------------------------------------------
class _Missing(Exception):
    """A stage's input is not there (its producing stage has not run)."""

    def __init__(self, stage: str, what: str):
        super().__init__(what)
        self.stage, self.what = stage, what


@dataclass
class _Ctx:
    raw: Path
    out: Path
    models_dir: Path | None
    cfg: AnnotateConfig
    session: RawSession
    progress: bool
    problems: list = field(default_factory=list)

    @property
    def work(self) -> Path:
        return self.out / WORK

    # file names
    @property
    def reg_file(self) -> Path:
        return self.work / "registration.json"

    @property
    def rec_dir(self) -> Path:
        return self.work / "reconstruction"

    @property
    def fits_file(self) -> Path:
        return self.work / "fits.json"

    @property
    def built_dir(self) -> Path:
        return self.work / "models"

    @property
    def placements_file(self) -> Path:
        return self.work / "placements.json"

    @property
    def label_file(self) -> Path:
        return self.work / "label.json"

    @property
    def eval_file(self) -> Path:
        return self.work / "evaluation.json"

    def raw_fingerprint(self) -> str:
        files = [self.raw / "session.json", self.raw / "journal.jsonl"]
        return _sha_obj([_sha_file(f) if f.exists() else "absent" for f in files])

    def require(self, path: Path, stage: str) -> Path:
        if not path.exists():
            raise _Missing(stage, str(path.relative_to(self.out)) if path.is_relative_to(self.out) else str(path))
        return path

    # --- what each stage wrote (its signature), read back by the stages after it -------------------
    def outputs(self, stage: str) -> dict:
        if stage == "register":
            return {"registration.json": _sha_file(self.require(self.reg_file, stage))}
        if stage == "reconstruct":
            meta = self.require(self.rec_dir / "reconstruction.json", stage)
            d = read_json(meta)
            for c in d.get("clusters", []):
                self.require(self.rec_dir / c["file"], stage)
            return {"reconstruction.json": _sha_file(meta)}
        if stage == "model":
            out = {"fits.json": _sha_file(self.require(self.fits_file, stage))}
            if read_json(self.fits_file).get("source") == "built":
                self.require(self.built_dir / "models_info.json", stage)
                out["models"] = _dir_hash(self.built_dir)
            return out
        if stage == "place":
            self.require(self.out / "models" / "models_info.json", stage)
            return {"placements.json": _sha_file(self.require(self.placements_file, stage)),
                    "models": _dir_hash(self.out / "models")}
        if stage == "label":
            out = {n: _sha_file(self.require(self.out / n, stage))
                   for n in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "scene_info.json")}
            out["label.json"] = _sha_file(self.require(self.label_file, stage))
            for sub in ("rgb", "depth", "depth_opaque", "depth_restored", "mask", "mask_visib"):
                out[sub] = _count_files(self.out / sub)
            return out
        if stage == "qa":
            out = {"qa.json": _sha_file(self.require(self.out / "qa" / "qa.json", stage))}
            self.require(self.out / "qa" / "report.html", stage)
            if self.eval_file.exists():
                out["evaluation.json"] = _sha_file(self.eval_file)
            return out
        raise KeyError(stage)

    def inputs(self, stage: str) -> dict:
        """What a stage's result depends on (hashed into its fingerprint)."""
        c = self.cfg
        d: dict[str, Any] = {"raw": self.raw_fingerprint(),
                             "upstream": {u: self.outputs(u) for u in _NEEDS[stage]}}
        if stage == "register":
            d["cfg"] = c.register.to_dict()
        elif stage == "reconstruct":
            d["cfg"] = [dataclasses.asdict(c.reconstruct), c.fuse_max_frames, c.fuse_crop, c.fuse_max_height_mm]
        elif stage in ("model", "place"):
            d["cfg"] = [dataclasses.asdict(c.fit), dataclasses.asdict(c.place)]
            if stage == "model":
                d["build"] = dataclasses.asdict(c.build) if self.models_dir is None else None
            md = self.models_dir
            if stage == "place" and md is None and self.fits_file.exists():
                rec = read_json(self.fits_file).get("models_dir")
                md = Path(rec) if rec else None
            d["models_dir"] = None if md is None else _dir_hash(md)
        elif stage == "label":
            d["cfg"] = {k: v for k, v in dataclasses.asdict(c.label).items() if k not in _LABEL_RUNTIME}
        elif stage == "qa":
            d["cfg"] = dataclasses.asdict(c.qa)
            t = self.session.truth_dir
            d["truth"] = _sha_file(t / "scene_gt.json") if t is not None and (t / "scene_gt.json").exists() else None
        return d


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _pcd(points: np.ndarray) -> "o3d.geometry.PointCloud":
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64).reshape(-1, 3)))


def _write_ply_points(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> None:
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    pc = _pcd(points)
    if normals is not None and len(normals) == len(points):
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64).reshape(-1, 3))
    if not o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False):
        raise TdofError("cannot write the point cloud", path)
    os.replace(tmp, path)


def _read_ply_points(path: Path, with_normals: bool = False):
    """(N,3) points of a PLY cloud; with ``with_normals`` also its (N,3) normals or None."""
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, np.float64)
    if len(pts) == 0:
        raise TdofError("empty or unreadable point cloud (rerun the reconstruct stage)", path)
    if not with_normals:
        return pts
    return pts, (np.asarray(pc.normals, np.float64) if pc.has_normals() else None)


def _meshes(models_dir: Path, obj_ids: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{obj_id: (V, F)} of a models folder, checked by :func:`~tdof20.annotate.modelbuild.load_models`."""
    from tdof20.annotate.modelbuild import load_models

    return {o: (V, F) for o, (V, F, _) in load_models(models_dir, obj_ids).items()}


def _T_list(T: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(T, float).reshape(16)]


def _T_arr(x: Any) -> np.ndarray:
    return np.asarray(x, float).reshape(4, 4)


def _shape(points: np.ndarray, up: np.ndarray, d: float) -> tuple[float, float]:
    """(height above the table, footprint radius) of points standing on the plane up.x + d = 0:
    the 99.5th percentile of the heights, and the 99th percentile of the horizontal distances
    from the median horizontal position."""
    h = points @ up + d
    flat = points - np.outer(points @ up, up)
    r = np.linalg.norm(flat - np.median(flat, axis=0), axis=1)
    return float(np.percentile(h, 99.5)), float(np.percentile(r, 99))


def _thin(points: np.ndarray, voxel: float) -> np.ndarray:
    return np.asarray(_pcd(points).voxel_down_sample(voxel).points)


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    from tdof20.geometry import rotation_matrix

    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    ang = math.atan2(s, float(a @ b))
    if s < 1e-12:
        return np.eye(3)
    return rotation_matrix(axis / s, ang)


def _upright(T: np.ndarray, up: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, float]:
    """T with the model's z axis turned onto ``up`` about the model point ``centre``; and the tilt
    removed (deg)."""
    R = T[:3, :3]
    tilt = math.degrees(math.acos(float(np.clip(R[:, 2] @ up / np.linalg.norm(up), -1, 1))))
    Rn = _rot_between(R[:, 2], up) @ R
    c = R @ centre + T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = Rn
    out[:3, 3] = c - Rn @ centre
    return out, tilt


def _model_samples(models: dict, n: int) -> dict[int, np.ndarray]:
    from tdof20.annotate.modelbuild import sample_points

    return {o: sample_points(v[0], v[1], n, seed=0) for o, v in models.items()}


def _copy_file(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(dst, src.read_bytes())


# ---------------------------------------------------------------------------------------------
# the stages
# ---------------------------------------------------------------------------------------------
def _stage_register(ctx: _Ctx) -> dict:
    info = ctx.session.info
    if ctx.cfg.register.phase not in info.phases:
        raise TdofError(f"the session has no {ctx.cfg.register.phase} phase (phases: {', '.join(info.phases)}): "
                        f"annotation registers the opaque twins' depth; capture the opaque phase first",
                        ctx.raw / "session.json")
    reg = register_session(ctx.raw, ctx.cfg.register, progress=ctx.progress, workers=ctx.cfg.label.workers)
    reg.save(ctx.reg_file)
    return {"flagged": len(reg.flagged_frames())}


def _stage_reconstruct(ctx: _Ctx) -> dict:
    reg = RegistrationResult.load(ctx.reg_file)
    s = ctx.session
    todo = _fuse_selection([f for f in reg.frames if reg.usable(f.arm, f.step)], ctx.cfg.fuse_max_frames)
    used: list[list[int]] = []
    problems: list[dict] = []

    def frames():
        # one depth image at a time: the TSDF integrates each and drops it
        from tdof20.progress import progress as _progress

        with _progress(ctx.progress, unit="fr") as bar:
            task = bar.add_task("fuse (TSDF)", total=len(todo))
            for f in todo:
                bar.advance(task)
                if not s.has_frame("opaque", f.arm, f.step):
                    continue
                try:
                    z = s.load_depth_mm("opaque", f.arm, f.step, verify=True)
                except TdofError as e:
                    problems.append({"arm": f.arm, "step": f.step, "problem": str(e)})
                    continue
                if not np.any(z):
                    problems.append({"arm": f.arm, "step": f.step, "problem": "the opaque depth is all zero"})
                    continue
                used.append([f.arm, f.step])
                if ctx.cfg.fuse_crop:
                    z = _crop_depth(z, s.info.camera, f.T_ref_frame, a0.axis_point, up,
                                    ctx.cfg.reconstruct.crop_radius_mm + 20.0, ctx.cfg.fuse_max_height_mm)
                yield z, f.T_ref_frame

    a0 = reg.arms[0]
    up = np.asarray(a0.axis_dir, float) / np.linalg.norm(a0.axis_dir)
    if up @ (np.zeros(3) - a0.axis_point) < 0:   # from the table towards the reference camera
        up = -up
    rec = reconstruct(frames(), s.info.camera, a0.axis_point, a0.axis_dir, ctx.cfg.reconstruct)
    if not used:
        reasons = sorted({f.reason for f in reg.frames if f.flagged and f.reason})
        why = f" (registration: {'; '.join(reasons[:2])})" if reasons else ""
        raise TdofError(f"no usable opaque frame to fuse: registration flagged them all or they are unreadable"
                        f"{why}; see work/registration.json", ctx.reg_file)
    if not rec.clusters:
        raise TdofError(f"the reconstruction holds no object on the turntable ({len(used)} frames fused, "
                        f"{len(rec.points)} surface points): see work/reconstruction/scene_points.ply",
                        ctx.rec_dir)
    d = ctx.rec_dir
    d.mkdir(parents=True, exist_ok=True)
    for old in d.glob("cluster_*.ply"):
        old.unlink()
    _write_ply_points(d / "scene_points.ply", rec.points)
    if rec.mesh is not None and len(rec.mesh.triangles):
        tmp = d / "scene_mesh.tmp.ply"
        o3d.io.write_triangle_mesh(str(tmp), rec.mesh, write_ascii=False)
        os.replace(tmp, d / "scene_mesh.ply")
    up, off = rec.plane[:3], float(rec.plane[3])
    clusters = []
    for i, c in enumerate(rec.clusters):
        name = f"cluster_{i:03d}.ply"
        _write_ply_points(d / name, c, rec.cluster_normals[i] if i < len(rec.cluster_normals) else None)
        h, r = _shape(c, up, off)
        clusters.append({"file": name, "n_points": int(len(c)), "centroid": [float(x) for x in c.mean(0)],
                         "height_mm": round(h, 3), "radius_mm": round(r, 3), "sha256": _sha_file(d / name)})
    meta = {"format": "tdof20-reconstruction", "plane": [float(x) for x in rec.plane],
            "axis_point": [float(x) for x in a0.axis_point], "axis_dir": [float(x) for x in a0.axis_dir],
            "frames_fused": len(used), "fuse_max_frames": ctx.cfg.fuse_max_frames, "n_points": int(len(rec.points)),
            "points": "scene_points.ply", "mesh": "scene_mesh.ply" if (d / "scene_mesh.ply").exists() else None,
            "clusters": clusters, "problems": problems,
            "viewpoints": [[float(x) for x in f.T_ref_frame[:3, 3]] for f in todo[:: max(1, len(todo) // 64)]]}
    write_json(d / "reconstruction.json", meta)
    return {"clusters": len(clusters), "frames_fused": len(used), "problems": len(problems)}


def _fuse_selection(frames: list, max_frames: int) -> list:
    """At most ``max_frames`` of the frames (0 = all), the same share of each arm position,
    spread evenly over its steps."""
    if not max_frames or len(frames) <= max_frames:
        return list(frames)
    arms = sorted({f.arm for f in frames})
    per = max(1, max_frames // len(arms))
    out = []
    for a in arms:
        fa = [f for f in frames if f.arm == a]
        idx = np.unique(np.linspace(0, len(fa) - 1, min(per, len(fa))).round().astype(int))
        out += [fa[i] for i in idx]
    return out


def _crop_depth(z: np.ndarray, cam, T_ref_frame: np.ndarray, axis_point: np.ndarray, up: np.ndarray,
                radius: float, max_height: float, below: float = 20.0) -> np.ndarray:
    """Depth (mm) with every pixel outside the turntable volume set to 0: a cylinder of
    ``radius`` about the axis, from ``below`` under the table top to ``max_height`` above it
    (the axis moved into the frame's camera)."""
    R, t = T_ref_frame[:3, :3], T_ref_frame[:3, 3]
    p = R.T @ (np.asarray(axis_point, float) - t)
    a = R.T @ up
    rel = cam.backproject(z) - p.astype(np.float32)
    h = rel @ a.astype(np.float32)
    r2 = np.einsum("hwc,hwc->hw", rel, rel) - h * h
    keep = (z > 0) & (h > -below) & (h < max_height) & (r2 < radius * radius)
    return np.where(keep, z, 0.0).astype(np.float32)


def _load_rec(ctx: _Ctx) -> tuple[dict, list[np.ndarray]]:
    meta = read_json(ctx.rec_dir / "reconstruction.json")
    return meta, [_read_ply_points(ctx.rec_dir / c["file"]) for c in meta["clusters"]]


def _match(models: dict, objects: list[int], clusters: list[np.ndarray], plane: np.ndarray,
           cfg: AnnotateConfig, progress: bool) -> tuple[list[dict], list[int]]:
    """Assign each object (an obj_id of session.json) to a cluster, one to one.

    Shape costs (relative differences of the height above the table and of the footprint radius)
    choose up to ``match_candidates`` clusters per object; each is scored by a quick upright fit
    (truncated mean distance of the cluster to the posed model); the Hungarian assignment on those
    scores (untried pairs cost more than any tried one) decides."""
    from scipy.optimize import linear_sum_assignment

    from tdof20.progress import progress as _progress

    pc = cfg.place
    up, off = plane[:3] / np.linalg.norm(plane[:3]), float(plane[3])
    n_o, n_c = len(objects), len(clusters)
    samples = _model_samples({o: models[o] for o in set(objects)}, pc.match_samples)
    shape_m = {}
    for o in set(objects):
        V = models[o][0]
        P = samples[o]
        h = P[:, 2] - V[:, 2].min()
        r = np.linalg.norm(P[:, :2] - np.median(P[:, :2], axis=0), axis=1)
        shape_m[o] = (float(np.percentile(h, 99.5)), float(np.percentile(r, 99)))
    shape_c = [_shape(c, up, off) for c in clusters]
    S = np.array([[abs(hc - shape_m[o][0]) / shape_m[o][0] + abs(rc - shape_m[o][1]) / shape_m[o][1]
                   for hc, rc in shape_c] for o in objects]).reshape(n_o, n_c)
    thin = {}
    quick = dataclasses.replace(cfg.fit, icp_mm=tuple(pc.match_icp_mm))
    fits: dict[tuple[int, int], Any] = {}

    def fit(i: int, j: int):
        if j not in thin:
            thin[j] = _thin(clusters[j], pc.match_voxel_mm)
        o = objects[i]
        fits[(i, j)] = fit_model(samples[o], thin[j], quick, up=up, model_z_min=float(models[o][0][:, 2].min()),
                                 table_plane=plane)
        return fits[(i, j)]

    pairs = []
    for i in range(n_o):
        order = np.argsort(S[i])
        pairs += [(i, int(j)) for j in order[:pc.match_candidates] if S[i, j] <= S[i, order[0]] + pc.match_shape_margin]
    C = np.full((n_o, n_c), 0.0)
    with _progress(progress, unit="fit") as bar:
        task = bar.add_task("match models to clusters", total=len(pairs))
        for i, j in pairs:
            fit(i, j)
            bar.advance(task)
    big = 10.0 + max([f.score for f in fits.values()], default=0.0)
    for i in range(n_o):
        for j in range(n_c):
            C[i, j] = fits[(i, j)].score if (i, j) in fits else big + S[i, j]
    rows, cols = linear_sum_assignment(C)
    out = []
    for i, j in zip(rows.tolist(), cols.tolist()):
        f = fits.get((i, j)) or fit(i, j)
        out.append({"index": i, "obj_id": int(objects[i]), "cluster": j, "T_ref_model": _T_list(f.T_ref_model),
                    "match_score_mm": float(f.score), "match_fitness": float(f.fitness), "shape_cost": float(S[i, j]),
                    "tried": {int(jj): round(float(ff.score), 4) for (ii, jj), ff in fits.items() if ii == i}})
    out.sort(key=lambda e: e["index"])
    unused = sorted(set(range(n_c)) - set(cols.tolist()))
    return out, unused


def _stage_model(ctx: _Ctx) -> dict:
    meta, clusters = _load_rec(ctx)
    plane = np.asarray(meta["plane"], float)
    objects = ctx.session.info.obj_ids
    if ctx.models_dir is not None:
        models = _meshes(ctx.models_dir, sorted(set(objects)))
        if len(clusters) < len(objects):
            raise TdofError(f"{len(objects)} objects in session.json but the reconstruction split the scene into "
                            f"{len(clusters)} clusters (objects touching? try a smaller reconstruct.cluster_eps_mm)",
                            ctx.rec_dir / "reconstruction.json")
        matched, unused = _match(models, objects, clusters, plane, ctx.cfg, ctx.progress)
        fits = {"format": "tdof20-fits", "source": "models", "models_dir": str(Path(ctx.models_dir).resolve()),
                "models_fingerprint": _dir_hash(Path(ctx.models_dir)), "objects": matched,
                "unused_clusters": unused}
    else:
        from tdof20.annotate.modelbuild import build_model_from_cluster, write_models

        if len(objects) != 1:
            raise TdofError(f"a scene with {len(objects)} objects needs their models (--models: the models folder "
                            f"of the lab's CAD models or of the single-object scenes); only single-object scenes "
                            f"build their model from the reconstruction", ctx.raw / "session.json")
        view = np.asarray(meta.get("viewpoints") or [], float).reshape(-1, 3)
        # the TSDF's normals tell the two sides of a thin glass wall apart, estimated ones cannot
        _, normals = _read_ply_points(ctx.rec_dir / meta["clusters"][0]["file"], with_normals=True)
        built = build_model_from_cluster(clusters[0], plane, ctx.cfg.build, viewpoints=view if len(view) else None,
                                         normals=normals)
        if ctx.built_dir.exists():
            shutil.rmtree(ctx.built_dir)
        write_models({int(objects[0]): built}, ctx.built_dir)
        fits = {"format": "tdof20-fits", "source": "built", "models_dir": None,
                "objects": [{"index": 0, "obj_id": int(objects[0]), "cluster": 0,
                             "T_ref_model": _T_list(built.T_ref_model), "watertight": bool(built.watertight),
                             "symmetries": built.symmetries}],
                "unused_clusters": list(range(1, len(clusters)))}
        if not built.watertight:
            ctx.problems.append(f"object {objects[0]}: the built model is not watertight (see work/models/)")
    write_json(ctx.fits_file, fits)
    return {"source": fits["source"], "objects": len(fits["objects"]), "unused_clusters": fits["unused_clusters"]}


def _stage_place(ctx: _Ctx) -> dict:
    fits = read_json(ctx.fits_file)
    meta, clusters = _load_rec(ctx)
    plane = np.asarray(meta["plane"], float)
    up = plane[:3] / np.linalg.norm(plane[:3])
    pc = ctx.cfg.place
    dst = ctx.out / "models"
    placements = []
    if fits["source"] == "models":
        md = ctx.models_dir if ctx.models_dir is not None else (Path(fits["models_dir"]) if fits.get("models_dir") else None)
        if md is None or not Path(md).is_dir():
            raise TdofError("the model stage used a models folder that is not there now: pass --models", ctx.fits_file)
        md = Path(md)
        obj_ids = sorted({int(e["obj_id"]) for e in fits["objects"]})
        meshes = _meshes(md, obj_ids)
        samples = _model_samples(meshes, pc.fit_samples)
        for e in fits["objects"]:
            o, j = int(e["obj_id"]), int(e["cluster"])
            V = meshes[o][0]
            f = fit_model(samples[o], clusters[j], ctx.cfg.fit, init=_T_arr(e["T_ref_model"]))
            T, tilt = f.T_ref_model, None
            note = ""
            if pc.upright:
                Tu, tilt = _upright(f.T_ref_model, up, 0.5 * (V.min(0) + V.max(0)))
                if tilt <= pc.upright_max_deg:
                    T = Tu
                else:
                    note = f"tilted {tilt:.1f} deg from the table normal (> place.upright_max_deg): kept as fitted"
            bad = []
            if f.fitness < pc.min_fitness:
                bad.append(f"fitness {f.fitness:.2f} < {pc.min_fitness}")
            if f.score > pc.max_score_mm:
                bad.append(f"mean distance {f.score:.2f} mm > {pc.max_score_mm}")
            if bad:
                raise TdofError(f"object {o} fits its cluster badly ({', '.join(bad)}; work/reconstruction/"
                                f"{meta['clusters'][j]['file']}): the wrong model, a model in other units, or a "
                                f"bad reconstruction; no labels are written from it", ctx.fits_file)
            placements.append({"gt_id": len(placements), "obj_id": o, "cluster": j, "T_ref_model": _T_list(T),
                               "fitness": float(f.fitness), "rmse_mm": float(f.rmse), "score_mm": float(f.score),
                               "upright_correction_deg": None if tilt is None or note else round(float(tilt), 4),
                               "source": "models", "note": note})
        # the scene's models folder: the user's files of these objects, byte for byte
        if dst.exists():
            shutil.rmtree(dst)
        infos = read_models_info(md)
        for o in obj_ids:
            _copy_file(md / f"obj_{o:06d}.ply", dst / f"obj_{o:06d}.ply")
            for extra in (f"obj_{o:06d}_samples.npy",):
                if (md / extra).exists():
                    _copy_file(md / extra, dst / extra)
        write_models_info(dst, {o: infos[o] for o in obj_ids})
        kp = md / "keypoints.json"
        if kp.exists():
            k = read_json(kp)
            if isinstance(k, dict):
                write_json(dst / "keypoints.json", {str(o): k[str(o)] for o in obj_ids if str(o) in k})
    else:
        for e in fits["objects"]:
            placements.append({"gt_id": len(placements), "obj_id": int(e["obj_id"]), "cluster": int(e["cluster"]),
                               "T_ref_model": e["T_ref_model"], "fitness": None, "rmse_mm": None, "score_mm": None,
                               "upright_correction_deg": None, "source": "built",
                               "watertight": e.get("watertight"), "note": ""})
        if dst.exists():
            shutil.rmtree(dst)
        for p in sorted(ctx.built_dir.iterdir()):
            if p.is_file():
                _copy_file(p, dst / p.name)
    write_json(ctx.placements_file, {"format": "tdof20-placements", "plane": meta["plane"],
                                     "placements": placements})
    return {"objects": len(placements)}


def _stage_label(ctx: _Ctx) -> dict:
    reg = RegistrationResult.load(ctx.reg_file)
    pl = read_json(ctx.placements_file)["placements"]
    obj_ids = sorted({int(p["obj_id"]) for p in pl})
    models = _meshes(ctx.out / "models", obj_ids)
    info = ctx.session.info
    write_json(ctx.out / "scene_info.json", {
        "scene_id": info.scene_id, "n_arms": info.n_arms, "steps": info.steps, "step_deg": info.step_deg,
        "labels": "tdof20 annotate (registered opaque depth, placed models)",
        "source_session": str(ctx.raw.resolve()), "label_method": ctx.cfg.label.method,
        "objects": [{"gt_id": p["gt_id"], "obj_id": p["obj_id"], "source": p["source"]} for p in pl]})
    T_ref_frames = {(f.arm, f.step): f.T_ref_frame for f in reg.frames}
    summary = label_scene(ctx.raw, ctx.out, T_ref_frames, [(int(p["obj_id"]), _T_arr(p["T_ref_model"])) for p in pl],
                          models, ctx.cfg.label, skip=reg.flagged_frames(), progress=ctx.progress)
    write_json(ctx.label_file, summary)
    if summary["labelled"] + summary["already_done"] == 0:
        first = "; ".join(sorted({s["reason"] for s in summary["skipped"]})[:3])
        raise TdofError(f"no frame could be labelled ({len(summary['skipped'])} skipped: {first})", ctx.label_file)
    return {k: summary[k] for k in ("labelled", "already_done", "frames_per_s")} | {"skipped": len(summary["skipped"])}


def _stage_qa(ctx: _Ctx) -> dict:
    from tdof20.annotate.evaluate import evaluate_scene
    from tdof20.annotate.qa import write_qa

    reg = RegistrationResult.load(ctx.reg_file)
    lab = read_json(ctx.label_file)
    flagged = [(s["arm"], s["step"], s["reason"]) for s in lab.get("skipped", [])]
    evaluation = None
    truth = ctx.session.truth_dir
    if ctx.cfg.qa.evaluate and truth is not None and (truth / "scene_gt.json").exists():
        evaluation = evaluate_scene(ctx.out, truth, max_frames=ctx.cfg.qa.evaluate_max_frames or None,
                                    n_points=ctx.cfg.qa.evaluate_points)
        write_json(ctx.eval_file, evaluation)
    else:
        ctx.eval_file.unlink(missing_ok=True)
    kw = dict(registration=reg, sample=ctx.cfg.qa.sample, evaluation=evaluation, progress=ctx.progress,
              session_dir=ctx.raw)
    try:
        report = write_qa(ctx.out, flagged=flagged, **kw)
    except TdofError:
        # write_qa draws every flagged frame on its colour image and stops on one it cannot read;
        # leave those out of its list (they stay listed, with reasons, in work/summary.json)
        keep, gone = [], []
        for a, k, r in flagged:
            try:
                ctx.session.load_rgb("transparent", a, k)
                keep.append((a, k, r))
            except TdofError:
                gone.append((a, k, r))
        if not gone:
            raise
        for a, k, r in gone:
            ctx.problems.append(f"qa: arm {a} step {k} not drawn (its colour image is unreadable): {r}")
        report = write_qa(ctx.out, flagged=keep, **kw)
    return {"report": str(report), "evaluated": evaluation is not None}


_RUN: dict[str, Callable[[_Ctx], dict]] = {
    "register": _stage_register, "reconstruct": _stage_reconstruct, "model": _stage_model,
    "place": _stage_place, "label": _stage_label, "qa": _stage_qa}


# ---------------------------------------------------------------------------------------------
# the summary
# ---------------------------------------------------------------------------------------------
def _summary(ctx: _Ctx, state: _State, run: dict, warnings: list[str]) -> dict:
    info = ctx.session.info
    s: dict[str, Any] = {
        "scene_id": info.scene_id, "raw": str(ctx.raw.resolve()), "out": str(ctx.out.resolve()),
        "frames_planned": info.n_arms * info.steps, "stages": run,
        "timing_s": {st: state.entry(st).get("seconds") for st in STAGES if state.finished(st)},
        "problems": list(ctx.problems), "warnings": warnings}
    missing = ctx.session.missing_frames()
    if missing:
        s["missing_frames"] = [{"phase": p, "arm": a, "step": k} for p, a, k in missing]
    if ctx.reg_file.exists():
        try:
            reg = RegistrationResult.load(ctx.reg_file)
            s["registration"] = {"flagged": [{"arm": a, "step": k, "reason": r} for a, k, r in reg.flagged_frames()],
                                 "arms": [{"arm": a.arm, "flagged": a.flagged, "reason": a.reason,
                                           "correction_deg": a.correction_deg, "correction_mm": a.correction_mm}
                                          for a in reg.arms]}
        except TdofError as e:
            s["problems"].append(str(e))
    rec = ctx.rec_dir / "reconstruction.json"
    if rec.exists():
        m = read_json(rec)
        s["reconstruction"] = {"frames_fused": m.get("frames_fused"), "clusters": len(m.get("clusters", [])),
                               "problems": m.get("problems", [])}
    if ctx.placements_file.exists():
        s["objects"] = read_json(ctx.placements_file)["placements"]
    if ctx.label_file.exists():
        lab = read_json(ctx.label_file)
        s["label"] = {k: lab.get(k) for k in ("frames", "labelled", "already_done", "skipped", "removed", "no_opaque",
                                              "seconds", "frames_per_s", "method", "executor", "workers")}
    if ctx.eval_file.exists():
        ev = read_json(ctx.eval_file)
        s["evaluation"] = {"all": ev.get("all"), "objects": ev.get("objects"),
                           "wrong_labels": len(ev.get("wrong_labels") or [])}
    report = ctx.out / "qa" / "report.html"
    if report.exists():
        s["report"] = str(report)
    return s


# ---------------------------------------------------------------------------------------------
# the pipeline
# ---------------------------------------------------------------------------------------------
class _Lock:
    """``work/.lock``: one annotate run per scene folder at a time. An exclusive ``flock`` on the
    file is the lock (atomic, and released by the kernel when the holder dies, however it dies);
    the pid written into it only serves the message a second run prints. The file is never
    deleted: a run that unlinked it could let a third run lock a new file beside a live holder."""

    def __init__(self, work: Path):
        self.path = work / ".lock"
        self.fd: int | None = None

    def __enter__(self) -> "_Lock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
            finally:
                os.close(fd)
            who = f" (pid {pid})" if pid.isdigit() else ""
            raise TdofError(f"another annotate run{who} is writing this folder; wait for it to finish",
                            self.path) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self.fd = fd
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            os.close(self.fd)   # closing releases the flock
            self.fd = None


def _session_identity(session: RawSession) -> dict:
    """What makes a raw session this one capture: its scene and the checksums of its first
    journalled frame (a resumed capture, an edited session.json or a moved folder keep it)."""
    entries = sorted(session.entries, key=lambda e: e.t) if session.entries else []
    first = entries[0] if entries else None
    return {"scene_id": session.info.scene_id,
            "first_frame": None if first is None else {"key": list(first.key), **dict(first.sha256)}}


def _clear_scene(out: Path) -> None:
    """Remove everything an annotate run wrote into ``out`` (for ``--force`` over another session's
    annotation), keeping ``work/.lock`` (held by this run)."""
    for p in out.iterdir():
        if p.name == WORK and p.is_dir():
            for q in p.iterdir():
                if q.name != ".lock":
                    shutil.rmtree(q) if q.is_dir() and not q.is_symlink() else q.unlink()
        elif p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def _remove_stale_temp_files(out: Path) -> int:
    """Delete the temporary files an interrupted run left in ``out`` (atomic writes' ``.NAME.*.tmp``,
    the mesh's ``*.tmp.ply``); only called while this run holds the folder's lock."""
    n = 0
    for root, _dirs, files in os.walk(out):
        for name in files:
            if (name.startswith(".") and name.endswith(".tmp")) or name.endswith(".tmp.ply"):
                Path(root, name).unlink(missing_ok=True)
                n += 1
    return n


def annotate(raw_dir: str | Path, out_dir: str | Path, models_dir: str | Path | None = None,
             stages: str | Iterable[str] | None = None, cfg: AnnotateConfig = AnnotateConfig(),
             force: bool = False, progress: bool = True) -> dict:
    """Annotate a raw session into the BOP scene ``out_dir`` (see the module docstring).

    raw_dir: the raw session (``tdof20 capture``'s folder); out_dir: the scene folder (created; a
    non-empty folder must hold an earlier annotate run's ``work/state.json``); models_dir: a BOP
    models folder (mm) holding every object of the session (None: single-object scenes build
    their model); stages: the stages to run (None = all; a list, ``"label,qa"`` or
    ``"register..model"``); force: rerun the chosen stages even when up to date.

    Returns the summary (also written to ``out_dir/work/summary.json``): ``stages`` {stage:
    {status: "ran" | "up to date" | "not requested", seconds}}, ``timing_s`` (the seconds of the
    run that made each stage's current results), ``registration`` (flagged frames with reasons),
    ``reconstruction``, ``objects`` (placements with fitness / RMSE / score), ``label`` (labelled,
    skipped frames with reasons, frames/s), ``evaluation`` (simulated sessions), ``report``,
    ``problems`` and ``warnings``. Raises :class:`TdofError` (one line) on bad input."""
    raw = Path(raw_dir)
    out = Path(out_dir)
    session = RawSession.open(raw)
    chosen = parse_stages(stages)
    md = None if models_dir is None else Path(models_dir)
    if md is not None and not md.is_dir():
        raise TdofError("no such models folder (--models: a BOP models folder in mm)", md)
    if out.exists() and not out.is_dir():
        raise TdofError("is not a folder", out)
    if out.exists() and any(out.iterdir()) and not (out / WORK / "state.json").exists():
        raise TdofError("folder is not empty and holds no annotate run (no work/state.json); choose another --out", out)
    if out.resolve() == raw.resolve() or raw.resolve() in out.resolve().parents:
        raise TdofError("--out must not be the raw session or inside it", out)
    ctx = _Ctx(raw, out, md, cfg, session, progress)
    ctx.work.mkdir(parents=True, exist_ok=True)
    run: dict[str, dict] = {}
    warnings: list[str] = []
    with _Lock(ctx.work):
        state = _State(ctx.work, raw.resolve())
        identity = _session_identity(session)
        recorded = state.data.get("session")
        if recorded is not None and recorded != identity:
            if not force:
                raise TdofError(f"holds the annotation of another session ({recorded.get('scene_id')} from "
                                f"{state.data.get('raw_recorded', 'elsewhere')}); choose another --out, or give "
                                f"--force to replace it", out)
            _clear_scene(out)
            state = _State(ctx.work, raw.resolve())
        state.data["session"] = identity
        state.data["raw_recorded"] = str(raw.resolve())
        removed = _remove_stale_temp_files(out)
        if removed:
            warnings.append(f"removed {removed} temporary file(s) left by an interrupted run")
        for stage in STAGES:
            if stage not in chosen:
                run[stage] = {"status": "not requested"}
                continue
            for u in _NEEDS[stage]:
                if not state.finished(u):
                    raise TdofError(f"stage '{stage}' needs the results of stage '{u}', which has not finished: "
                                    f"run stage '{u}' first", ctx.work / "state.json")
                try:
                    sig = ctx.outputs(u)
                except _Missing as m:
                    raise TdofError(f"stage '{stage}' needs {m.what}, which is missing: run stage '{u}' first",
                                    ctx.out) from None
                if sig != state.entry(u).get("outputs"):
                    raise TdofError(f"the results of stage '{u}' changed since it finished: run stage '{u}' "
                                    f"again first", ctx.work / "state.json")
                if u not in chosen:
                    try:
                        fp_u = _sha_obj(ctx.inputs(u))
                    except _Missing:
                        fp_u = None
                    if fp_u != state.entry(u).get("fingerprint"):
                        warnings.append(f"stage '{u}' is out of date with the current inputs or options; "
                                        f"'{stage}' used its results as they are")
            fp = _sha_obj(ctx.inputs(stage))
            if not force and state.finished(stage) and state.entry(stage).get("fingerprint") == fp:
                try:
                    fresh = ctx.outputs(stage) == state.entry(stage).get("outputs")
                except _Missing:
                    fresh = False
                if fresh:
                    run[stage] = {"status": "up to date", "seconds": 0.0}
                    continue
            state.start(stage)
            t0 = time.perf_counter()
            try:
                result = _RUN[stage](ctx)
            except TdofError as e:
                # the stage stays unfinished; the summary says why
                run[stage] = {"status": "failed", "seconds": round(time.perf_counter() - t0, 3), "error": str(e)}
                write_json(ctx.work / "summary.json", _summary(ctx, state, run, warnings))
                raise
            seconds = time.perf_counter() - t0
            state.finish(stage, fp, seconds, ctx.outputs(stage))
            run[stage] = {"status": "ran", "seconds": round(seconds, 3), **result}
        summary = _summary(ctx, state, run, warnings)
        write_json(ctx.work / "summary.json", summary)
    return summary


def summary_text(summary: dict) -> str:
    """A few lines for a person (what ``tdof20 annotate`` prints): per stage its status and
    seconds, the objects' fits, flagged and skipped frames, the evaluation's medians, the report."""
    lines = [f"{summary['scene_id']}: {summary['out']}"]
    for st in STAGES:
        e = summary["stages"].get(st, {})
        sec = f" {e['seconds']:.1f} s" if e.get("status") == "ran" else ""
        lines.append(f"  {st:<12} {e.get('status', '-')}{sec}" + (f": {e['error']}" if e.get("error") else ""))
    for p in summary.get("objects") or []:
        fit = (f"fitness {p['fitness']:.2f}, mean distance {p['score_mm']:.2f} mm" if p.get("fitness") is not None
               else "model built from the reconstruction")
        lines.append(f"  object {p['obj_id']}: {fit}")
    flagged = (summary.get("registration") or {}).get("flagged") or []
    lab = summary.get("label") or {}
    if lab:
        lines.append(f"  labelled {lab.get('labelled', 0) + lab.get('already_done', 0)} of {lab.get('frames')} frames"
                     f" ({len(flagged)} flagged by registration, {len(lab.get('skipped') or [])} skipped in all)")
        for sk in (lab.get("skipped") or [])[:10]:
            lines.append(f"    skipped arm {sk['arm']} step {sk['step']}: {sk['reason']}")
        if len(lab.get("skipped") or []) > 10:
            lines.append(f"    ... {len(lab['skipped']) - 10} more in work/summary.json")
    ev = (summary.get("evaluation") or {}).get("all") or {}
    if ev:
        def med(k):
            v = (ev.get(k) or {}).get("median")
            return "-" if v is None else f"{v:.3f}"
        lines.append(f"  vs truth (median): motion {med('motion_rot_deg')} deg / {med('motion_trans_mm')} mm, "
                     f"surface {med('surface_mm')} mm, visible IoU {med('iou_visib')}; "
                     f"{summary['evaluation'].get('wrong_labels', 0)} wrong labels")
    for w in summary.get("warnings") or []:
        lines.append(f"  warning: {w}")
    for p in summary.get("problems") or []:
        lines.append(f"  problem: {p}")
    if summary.get("report"):
        lines.append(f"  report: {summary['report']}")
    return "\n".join(lines)
