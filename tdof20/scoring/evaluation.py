"""What a score is made of: the thresholds and summary keys, each object's per-target errors and
decisions (:class:`ObjectEval`), and one results file's evaluation with its summary
(:class:`Evaluation`). :mod:`tdof20.scoring.scorer` computes them, :mod:`tdof20.scoring.report`
turns them into tables and plots.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ADD_THRESHOLD = 0.1  # fraction of the diameter
PROJ_THRESHOLD = 5.0  # pixels at PROJ_WIDTH: the paper's 2D projection threshold
PROJ_WIDTH = 640  # pixels: the image width PROJ_THRESHOLD is for; other widths scale it
PROJ_PLOT_MAX = 20.0  # pixels: the plots' range of 2D projection errors
AUC_MAX = 100.0  # mm
AUC_SE_TARGET = 1.25e-4  # standard error of each object's ADD-S AUC
VISIB_MIN = 0.1  # BOP: ground-truth instances less visible are no targets
KEYS = ("n", "add", "adds", "add_s", "proj2d", "auc_adds", "auc_add_s")
BOP_KEYS = ("ar_vsd", "ar_mssd", "ar_mspd", "ar")
METRICS = ("add", "proj", "vsd", "mssd", "mspd", "ar")  # what --metrics selects
METRIC_KEYS = {"add": ("add", "adds", "add_s", "auc_adds", "auc_add_s"), "proj": ("proj2d",), "vsd": ("ar_vsd",),
               "mssd": ("ar_mssd",), "mspd": ("ar_mspd",), "ar": ("ar",)}
ALL_KEYS = KEYS + BOP_KEYS
THREADS = min(2, os.cpu_count() or 1)  # objects scored in parallel


def proj_threshold(width: int, proj_px: float | None = None) -> float:
    """The 2D projection threshold (px) on images ``width`` pixels wide: ``proj_px`` when given,
    else the paper's 5 px at 640 pixels wide scaled with the width (5 * width / 640), so that a
    threshold means the same share of the image at any resolution (5 px at 160 pixels would be 20
    px at 640)."""
    if proj_px is not None:
        return float(proj_px)
    return PROJ_THRESHOLD * float(width) / PROJ_WIDTH


def format_px(px: Any) -> str:
    """The threshold(s) of :attr:`Evaluation.proj_px` as text: "3.75", or "2.5-5" when scenes differ."""
    if isinstance(px, dict):
        vals = sorted(set(px.values()))
        return f"{vals[0]:g}-{vals[-1]:g}" if len(vals) > 1 else f"{vals[0]:g}"
    return "?" if px is None else f"{px:g}"


@dataclass
class ObjectEval:
    """Per object: one entry per target instance (a target with inst_count k gives k entries).
    Errors are inf where there was no estimate. ``adds`` values are exact where ``adds_exact``
    and control-variate estimates elsewhere; the *_ok decisions are always exact. ``bop`` holds,
    per BOP metric computed, whether each instance is matched (BOP19 matching) at each threshold:
    'mssd' and 'mspd' (n,10), 'vsd' (n,10,10) (tau, threshold); ``scene`` each instance's scene."""

    obj_id: int
    diameter: float
    symmetric: bool
    add: np.ndarray
    adds: np.ndarray
    proj: np.ndarray
    add_ok: np.ndarray
    adds_ok: np.ndarray
    proj_ok: np.ndarray
    adds_exact: np.ndarray
    auc_se: float = 0.0
    stages: dict = field(default_factory=dict)
    scene: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    bop: dict = field(default_factory=dict)
    keys: tuple = KEYS

    @property
    def n(self) -> int:
        return len(self.add)

    @property
    def add_s(self) -> np.ndarray:
        return self.adds if self.symmetric else self.add

    @property
    def add_s_ok(self) -> np.ndarray:
        return self.adds_ok if self.symmetric else self.add_ok

    def values(self, mask: np.ndarray | None = None) -> dict[str, float]:
        """The summary values of the instances in ``mask`` (all by default)."""
        sel = slice(None) if mask is None else mask

        def auc(e):
            e = e[sel]
            return float(np.mean(np.maximum(0.0, 1.0 - e / AUC_MAX))) if len(e) else 0.0

        def acc(ok):
            ok = ok[sel]
            return float(np.mean(ok)) if len(ok) else 0.0

        def ar(name):
            ok = self.bop[name][sel]
            return float(ok.mean()) if ok.size else 0.0

        get = {"add": lambda: acc(self.add_ok), "adds": lambda: acc(self.adds_ok), "add_s": lambda: acc(self.add_s_ok),
               "proj2d": lambda: acc(self.proj_ok), "auc_adds": lambda: auc(self.adds),
               "auc_add_s": lambda: auc(self.add_s), "ar_vsd": lambda: ar("vsd"), "ar_mssd": lambda: ar("mssd"),
               "ar_mspd": lambda: ar("mspd")}
        out: dict[str, float] = {"n": int(np.count_nonzero(np.ones(self.n, bool)[sel]))}
        for k in self.keys[1:]:
            if k == "ar":
                out[k] = (ar("vsd") + ar("mssd") + ar("mspd")) / 3.0
            else:
                out[k] = get[k]()
        return out

    def summary(self) -> dict[str, float]:
        return self.values()


@dataclass
class Evaluation:
    """One results file scored: per object its :class:`ObjectEval`, the warnings and notes, the
    timings of the stages, the rows read, the keys computed and the dataset's scene and object names."""

    method: str
    objects: dict[int, ObjectEval]
    warnings: list[str]
    timings: dict[str, float]
    n_rows: int = 0
    keys: tuple = KEYS  # "n" and the metric keys computed, in report order
    scene_labels: dict = field(default_factory=dict)  # scene id -> its name ("multi/08")
    object_labels: dict = field(default_factory=dict)  # obj_id -> the dataset's name for it
    # the 2D projection threshold used (px): one number, or {"<scene_id>": px} where image widths differ
    proj_px: Any = None

    def summary(self) -> dict[str, Any]:
        """{"objects": {"<obj_id>": {...}}, "mean": {...} (over objects), "all": {...} (pooled over
        target instances), "scenes": {"<scene_id>": {...}} (pooled over each scene's instances)}."""
        keys = self.keys
        objs = {str(k): v.summary() for k, v in sorted(self.objects.items())}
        per = [v for v in objs.values() if v["n"] > 0]
        mean = {k: (float(np.mean([o[k] for o in per])) if per else 0.0) for k in keys[1:]}
        mean = {"n": len(per), **mean}
        allv: dict[str, Any] = {"n": int(sum(o["n"] for o in per))}
        for k in keys[1:]:
            allv[k] = float(sum(o[k] * o["n"] for o in per) / allv["n"]) if allv["n"] else 0.0
        scenes = {}
        ids = sorted({int(x) for o in self.objects.values() for x in np.unique(o.scene)})
        for sid in ids:
            parts = [o.values(o.scene == sid) for o in self.objects.values()]
            parts = [p for p in parts if p["n"] > 0]
            n = sum(p["n"] for p in parts)
            scenes[str(sid)] = {"n": n, **{k: float(sum(p[k] * p["n"] for p in parts) / n) for k in keys[1:]}}
        out = {"objects": objs, "mean": mean, "all": allv, "scenes": scenes}
        if "proj2d" in keys and self.proj_px is not None:
            out["proj_px"] = self.proj_px
        return _rounded(out)


def _rounded(d: Any) -> Any:
    """Floats to 10 decimals (float32 kernels leave ~1e-12 noise: 0.99999999999 -> 1.0)."""
    if isinstance(d, dict):
        return {k: _rounded(v) for k, v in d.items()}
    return round(d, 10) if isinstance(d, float) else d


__all__ = ["ADD_THRESHOLD", "ALL_KEYS", "AUC_MAX", "AUC_SE_TARGET", "BOP_KEYS", "Evaluation", "KEYS", "METRICS",
           "METRIC_KEYS", "ObjectEval", "PROJ_PLOT_MAX", "PROJ_THRESHOLD", "PROJ_WIDTH", "THREADS", "VISIB_MIN",
           "format_px", "proj_threshold"]
