"""The BOP JSON files' layout and their checked values, shared by the scene files
(:mod:`tdof20.formats.bop`) and ``models_info.json`` (:mod:`tdof20.formats.bop_models`).

Layout: one line per top-level key, keys sorted numerically, compact values — as the BOP
toolkit writes them. Checks: a problem is one TdofError naming the file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.io import atomic_write_bytes, dumps_json

ROT_TOL = 1e-3   # |R R^T - I| above this is not a rotation


def flat(a: Any) -> list[float]:
    """An array's values as a flat list of Python floats (row-major), as the files hold them."""
    return [float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


def bop_json_line(key: Any, entry: Any) -> str:
    """One top-level line of :func:`dumps_bop_json` (without its separator)."""
    return f"  {json.dumps(str(key))}: {dumps_json(entry, indent=None)}"


def join_bop_json(lines: list[str]) -> str:
    """The file text of already sorted :func:`bop_json_line` lines."""
    return "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}\n"


def dumps_bop_json(content: dict) -> str:
    """BOP toolkit layout: one line per top-level key (sorted numerically), compact values."""
    keys = sorted(content, key=lambda k: (0, int(k)) if str(k).lstrip("-").isdigit() else (1, str(k)))
    return join_bop_json([bop_json_line(k, content[k]) for k in keys])


def write_bop_text(path: Path, text: str) -> None:
    """Write a BOP JSON file's text atomically, synced to disk."""
    atomic_write_bytes(path, text.encode(), fsync=True)


def write_bop_json(path: Path, content: dict) -> None:
    """Write ``content`` as a BOP JSON file (:func:`dumps_bop_json`) atomically, synced to disk."""
    write_bop_text(path, dumps_bop_json(content))


def is_num(v: Any) -> bool:
    """A finite JSON number (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


#: the largest image or object id (BOP's ids are int32; the shards store them so)
MAX_ID = 2**31 - 1


def is_int(v: Any) -> bool:
    """A JSON integer (not a bool)."""
    return isinstance(v, int) and not isinstance(v, bool)


def check_nums(path: Path, v: Any, n: int, where: str) -> np.ndarray:
    """``v`` as (n,) float64, or a TdofError unless it is a list of ``n`` finite numbers."""
    if not isinstance(v, list) or len(v) != n:
        got = len(v) if isinstance(v, list) else type(v).__name__
        raise TdofError(f"{where} must be {n} numbers, got {got}", path)
    if not all(is_num(x) for x in v):
        raise TdofError(f"{where} must hold finite numbers only", path)
    return np.asarray(v, dtype=np.float64)


def check_rotation(path: Path, v: Any, where: str) -> np.ndarray:
    """``v`` (9 numbers, row-major) as a (3,3) rotation, or a TdofError."""
    R = check_nums(path, v, 9, where).reshape(3, 3)
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > ROT_TOL or np.linalg.det(R) < 0:
        raise TdofError(f"{where} is not a rotation matrix (|R R^T - I| = {err:.2g}, det {np.linalg.det(R):.3g})", path)
    return R


def by_image_id(path: Path, data: Any) -> dict[int, Any]:
    """A scene file's object keyed by image id -> {im_id: entry}; a TdofError unless it is an
    object whose keys are non-negative integers."""
    if not isinstance(data, dict):
        raise TdofError(f"must hold a JSON object keyed by image id, got {type(data).__name__}", path)
    out = {}
    for k, v in data.items():
        try:
            i = int(k)
        except ValueError:
            raise TdofError(f"key {k!r} is not an integer id", path) from None
        if i < 0 or str(i) != str(k).strip():
            raise TdofError(f"key {k!r} is not a non-negative integer id", path)
        if i > MAX_ID:
            raise TdofError(f"key {k!r}: image ids are at most {MAX_ID} (BOP's ids are 32-bit)", path)
        out[i] = v
    return out
