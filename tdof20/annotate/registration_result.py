"""The registration's results: per frame (:class:`FrameRegistration`), per arm position
(:class:`ArmRegistration`) and per session (:class:`RegistrationResult`), saved as JSON
(format ``tdof20-registration``) and read back by the later stages.

Frames and conventions as in :mod:`~tdof20.annotate.registration`: mm, ``T_a_b`` maps points
from frame b to frame a, ``T_ref_frame`` maps cam(arm, step) to cam(0, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.io import read_json, write_json
from tdof20.formats.session import RawSession

__all__ = ["FrameRegistration", "ArmRegistration", "RegistrationResult", "RESULT_FORMAT", "RESULT_VERSION",
           "depth_scale_text"]

RESULT_FORMAT = "tdof20-registration"
RESULT_VERSION = 1


@dataclass
class FrameRegistration:
    arm: int
    step: int
    T_ref_frame: np.ndarray                   # (4,4) cam(arm, step) -> cam(0, 0), mm
    fitness: float = 0.0
    rmse: float = float("nan")                # inlier RMSE, mm
    residual_deg: float = float("nan")        # vs the turntable prior
    residual_mm: float = float("nan")         # displacement of the axis point vs the prior
    flagged: bool = False
    reason: str = ""

    def to_dict(self) -> dict:
        return {"arm": self.arm, "step": self.step, "T_ref_frame": _T_list(self.T_ref_frame),
                "fitness": _f(self.fitness), "rmse": _f(self.rmse), "residual_deg": _f(self.residual_deg),
                "residual_mm": _f(self.residual_mm), "flagged": bool(self.flagged), "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict) -> "FrameRegistration":
        return cls(int(d["arm"]), int(d["step"]), _T_arr(d["T_ref_frame"]), _uf(d["fitness"]), _uf(d["rmse"]),
                   _uf(d["residual_deg"]), _uf(d["residual_mm"]), bool(d["flagged"]), str(d.get("reason", "")))


@dataclass
class ArmRegistration:
    arm: int
    axis_dir: np.ndarray                      # (3,) unit, camera frame of (arm, step 0)
    axis_point: np.ndarray                    # (3,) mm, where the axis meets the table top
    plane_normal: np.ndarray                  # (3,) table top normal (towards the camera)
    plane_d: float                            # plane: n . x + d = 0 (mm)
    crop_radius: float                        # mm
    T_ref_arm: np.ndarray                     # (4,4) cam(arm, 0) -> cam(0, 0)
    T_ref_arm_prior: np.ndarray               # (4,4) the robot's (hand-eye) prior
    fitness: float = float("nan")             # arm-to-arm ICP (nan for arm 0)
    rmse: float = float("nan")
    correction_deg: float = 0.0               # refined vs prior
    correction_mm: float = 0.0
    flagged: bool = False
    reason: str = ""
    association: str = ""                     # the frame-to-frame correspondences used (projective / closest)

    def to_dict(self) -> dict:
        return {"arm": self.arm, "association": self.association, "axis_dir": _v(self.axis_dir), "axis_point": _v(self.axis_point),
                "plane_normal": _v(self.plane_normal), "plane_d": float(self.plane_d),
                "crop_radius": float(self.crop_radius), "T_ref_arm": _T_list(self.T_ref_arm),
                "T_ref_arm_prior": _T_list(self.T_ref_arm_prior), "fitness": _f(self.fitness),
                "rmse": _f(self.rmse), "correction_deg": float(self.correction_deg),
                "correction_mm": float(self.correction_mm), "flagged": bool(self.flagged), "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict) -> "ArmRegistration":
        return cls(int(d["arm"]), np.asarray(d["axis_dir"], float), np.asarray(d["axis_point"], float),
                   np.asarray(d["plane_normal"], float), float(d["plane_d"]), float(d["crop_radius"]),
                   _T_arr(d["T_ref_arm"]), _T_arr(d["T_ref_arm_prior"]), _uf(d["fitness"]), _uf(d["rmse"]),
                   float(d["correction_deg"]), float(d["correction_mm"]), bool(d["flagged"]),
                   str(d.get("reason", "")), str(d.get("association", "")))


@dataclass
class RegistrationResult:
    scene_id: str
    steps: int
    step_deg: float
    n_arms: int
    frames: list[FrameRegistration]
    arms: list[ArmRegistration]
    config: dict = field(default_factory=dict)
    timing_s: dict = field(default_factory=dict)
    turntable: dict = field(default_factory=dict)   # direction used and where it came from
    depth_scale: dict = field(default_factory=dict)  # registration.DepthScale.to_dict(); {} = not estimated

    @property
    def depth_factor(self) -> float:
        """Reported / true depth as estimated (1.0 when not estimated): the later stages divide
        every depth of the session by it (:meth:`corrected`)."""
        return float(self.depth_scale.get("factor", 1.0) or 1.0)

    def corrected(self, session: RawSession) -> RawSession:
        """``session`` with its camera's ``depth_scale`` divided by :attr:`depth_factor`: every depth
        it loads is then in true millimetres, and the labels' scene_camera.json says so."""
        return session.with_depth_factor(1.0 / self.depth_factor)

    def frame(self, arm: int, step: int) -> FrameRegistration:
        for f in self.frames:
            if f.arm == arm and f.step == step:
                return f
        raise KeyError(f"no registration for arm {arm} step {step}")

    def poses(self) -> np.ndarray:
        """(n_arms, steps, 4, 4) T_ref_frame (NaN where a frame has none)."""
        out = np.full((self.n_arms, self.steps, 4, 4), np.nan)
        for f in self.frames:
            out[f.arm, f.step] = f.T_ref_frame
        return out

    def flagged_frames(self) -> list[tuple[int, int, str]]:
        """(arm, step, reason) of every flagged frame (also every frame of a flagged arm)."""
        bad_arms = {a.arm: a.reason for a in self.arms if a.flagged}
        out = []
        for f in self.frames:
            if f.flagged:
                out.append((f.arm, f.step, f.reason))
            elif f.arm in bad_arms:
                out.append((f.arm, f.step, f"arm {f.arm} flagged: {bad_arms[f.arm]}"))
        return out

    def usable(self, arm: int, step: int) -> bool:
        """True when the frame's pose may be used for labels."""
        f = self.frame(arm, step)
        return not f.flagged and not self.arms[arm].flagged

    def to_dict(self) -> dict:
        return {"format": RESULT_FORMAT, "version": RESULT_VERSION, "scene_id": self.scene_id,
                "steps": self.steps, "step_deg": self.step_deg, "n_arms": self.n_arms,
                "config": self.config, "timing_s": self.timing_s, "turntable": self.turntable,
                "depth_scale": self.depth_scale,
                "arms": [a.to_dict() for a in self.arms], "frames": [f.to_dict() for f in self.frames]}

    @classmethod
    def from_dict(cls, d: dict, path: str | Path | None = None) -> "RegistrationResult":
        if not isinstance(d, dict) or d.get("format") != RESULT_FORMAT:
            raise TdofError(f"not a registration result (format must be '{RESULT_FORMAT}')", path)
        if int(d.get("version", 0)) > RESULT_VERSION:
            raise TdofError(f"registration result version {d.get('version')} is newer than this tdof20 "
                            f"reads ({RESULT_VERSION}): upgrade tdof20", path)
        try:
            return cls(str(d["scene_id"]), int(d["steps"]), float(d["step_deg"]), int(d["n_arms"]),
                       [FrameRegistration.from_dict(f) for f in d["frames"]],
                       [ArmRegistration.from_dict(a) for a in d["arms"]], dict(d.get("config", {})),
                       dict(d.get("timing_s", {})), dict(d.get("turntable", {})), dict(d.get("depth_scale") or {}))
        except (KeyError, TypeError, ValueError) as e:
            raise TdofError(f"malformed registration result ({type(e).__name__}: {e})", path) from None

    def save(self, path: str | Path) -> Path:
        """Write atomically as JSON."""
        path = Path(path)
        write_json(path, self.to_dict())
        return path

    @classmethod
    def load(cls, path: str | Path) -> "RegistrationResult":
        return cls.from_dict(read_json(path), path)


def depth_scale_text(ds: dict) -> str:
    """One phrase for the registration's depth-scale estimate (``RegistrationResult.depth_scale``)."""
    if not ds.get("arms"):
        return ds.get("note") or "not estimated"
    m, f, ci = ds["measured"], ds["factor"], ds.get("ci95")
    bound = f" +- {100 * ci:.2f} %" if ci is not None else ""
    what = (f"corrected (depth divided by {f:.4f})" if f != 1.0 else "not corrected")
    return (f"{m:.4f}{bound} (95 %; the depth read {100 * (m - 1):+.2f} % against the robot's poses, "
            f"{ds['arms']} arm pair(s)): {what}")


def _f(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _uf(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _v(x: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(x).reshape(-1)]


def _T_list(T: np.ndarray) -> list[float]:
    return _v(np.asarray(T, float).reshape(16))


def _T_arr(x: list) -> np.ndarray:
    a = np.asarray(x, float)
    if a.size != 16:
        raise ValueError("a transform must be 16 numbers")
    return a.reshape(4, 4)

