"""Strict checks of parsed JSON for the raw session's files: every failure is one line naming
the file and the field path (and, for the journal, the line)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError

RIGID_TOL = 1e-4   # |R R^T - I| above this is not a rotation


def json_type(v: Any) -> str:
    """How an error message names the JSON type of ``v`` ("a number", "an object", ...)."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, dict):
        return "an object"
    return type(v).__name__


def is_number(v: Any) -> bool:
    """A number (Python or numpy), not a bool."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def is_int(v: Any) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


class Checker:
    """Raises :class:`TdofError` naming ``path`` (and, for the journal, the line)."""

    def __init__(self, path: str | Path | None, prefix: str = ""):
        self.path = path
        self.prefix = prefix

    def fail(self, msg: str) -> None:
        raise TdofError(self.prefix + msg, self.path)

    def obj(self, v: Any, where: str) -> dict:
        if not isinstance(v, dict):
            self.fail(f"{where} must be an object {{...}}, got {json_type(v)}")
        return v

    def get(self, d: dict, key: str, where: str) -> Any:
        if key not in d:
            self.fail(f"missing field '{where + '.' if where else ''}{key}'")
        return d[key]

    def number(self, v: Any, where: str, gt: float | None = None) -> float:
        if not is_number(v):
            self.fail(f"{where} must be a number, got {json_type(v)}")
        x = float(v)
        if not math.isfinite(x):
            self.fail(f"{where} must be finite, got {x}")
        if gt is not None and not x > gt:
            self.fail(f"{where} must be > {gt:g}, got {x:g}")
        return x

    def integer(self, v: Any, where: str, lo: int | None = None, hi: int | None = None) -> int:
        if not is_int(v):
            got = repr(v) if isinstance(v, float) else json_type(v)
            self.fail(f"{where} must be an integer, got {got}")
        i = int(v)
        if (lo is not None and i < lo) or (hi is not None and i > hi):
            rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            self.fail(f"{where} must be {rng}, got {i}")
        return i

    def string(self, v: Any, where: str) -> str:
        if not isinstance(v, str):
            self.fail(f"{where} must be a string, got {json_type(v)}")
        return v

    def numbers(self, v: Any, n: int, where: str, what: str = "numbers") -> np.ndarray:
        if not isinstance(v, (list, tuple, np.ndarray)):
            self.fail(f"{where} must be {n} {what}, got {json_type(v)}")
        if len(v) != n:
            self.fail(f"{where} must be {n} {what}, got {len(v)}")
        for i, x in enumerate(v):
            if not is_number(x):
                self.fail(f"{where}[{i}] must be a number, got {json_type(x)}")
            if not math.isfinite(float(x)):
                self.fail(f"{where}[{i}] must be finite, got {float(x)}")
        return np.asarray(v, dtype=np.float64)

    def rigid(self, v: Any, where: str, metres_below: float | None = None, zero_ok: bool = False) -> np.ndarray:
        """A row-major 4x4 rigid transform in mm. ``metres_below``: a translation shorter than this
        (mm) looks like metres and is refused; ``zero_ok`` lets an exactly zero translation pass."""
        T = self.numbers(v, 16, where, "numbers (a row-major 4x4 rigid transform, mm)").reshape(4, 4)
        if np.max(np.abs(T[3] - [0, 0, 0, 1])) > 1e-9:
            self.fail(f"{where} is not a rigid transform: last row must be 0 0 0 1, "
                      f"got {' '.join(f'{x:g}' for x in T[3])}")
        R = T[:3, :3]
        err = float(np.max(np.abs(R @ R.T - np.eye(3))))
        if err > RIGID_TOL:
            self.fail(f"{where} is not a rigid transform: its rotation is not orthonormal "
                      f"(|R R^T - I| = {err:.2g} > {RIGID_TOL:g})")
        if np.linalg.det(R) < 0:
            self.fail(f"{where} is not a rigid transform: its rotation is a reflection (det -1)")
        if metres_below is not None:
            norm = float(np.linalg.norm(T[:3, 3]))
            if norm < metres_below and not (zero_ok and norm == 0.0):
                self.fail(f"{where} translation has length {norm:.4g}: looks like metres, millimetres expected")
        return T


__all__ = ["Checker", "RIGID_TOL", "is_int", "is_number", "json_type"]
