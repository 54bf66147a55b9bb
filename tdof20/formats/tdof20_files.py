"""The released TDoF20's single files, read and checked (torch-free): the class list, the
intrinsics (depth units detected), the pickled poses (a restricted unpickler), the class-id masks
and image sizes from their headers. The release's layout, lists and units across files:
:mod:`tdof20.formats.tdof20_release`. Every problem is one :class:`TdofError` naming the file."""

from __future__ import annotations

import io
import math
import pickle
import re
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.io import check_image_pixels, read_bytes, read_json, read_text

__all__ = ["read_numbers", "read_classes", "Intrinsics", "depth_scale_mm", "read_intrinsics", "load_pickle", "FramePose",
           "read_pose", "read_class_mask", "image_size"]


def read_numbers(path: Path, what: str) -> np.ndarray:
    """The numbers of a text file (comma- or space-separated, one row a line, "#" comments) as a
    float64 array of equal-length rows; any problem is a TdofError naming the file."""
    text = read_text(path, what)
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append([float(x) for x in re.split(r"[,\s]+", line) if x])
        except ValueError:
            raise TdofError(f"line {n}: not numbers: {line[:60]!r}", path) from None
    if not rows:
        raise TdofError(f"the {what} is empty", path)
    if len({len(r) for r in rows}) != 1:
        raise TdofError(f"rows have different lengths ({sorted({len(r) for r in rows})})", path)
    a = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(a).all():
        raise TdofError("holds NaN or inf", path)
    return a


def read_classes(path: Path) -> list[str]:
    """classes.txt: one name a line (blank lines and '#' comments skipped); ids are 1-based."""
    names = [ln.strip() for ln in read_text(path, "class list").splitlines()]
    names = [n for n in names if n and not n.startswith("#")]
    if not names:
        raise TdofError("lists no classes", path)
    for n in names:
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", n):
            raise TdofError(f"class name {n!r} is not a plain name (letters, digits, _ . -)", path)
    dup = [n for n, c in Counter(names).items() if c > 1]
    if dup:
        raise TdofError(f"class {dup[0]!r} is listed twice", path)
    return names


@dataclass(frozen=True)
class Intrinsics:
    """The camera as found: K (3,3) px, image size, depth in mm per unit, and how it was written."""

    K: np.ndarray
    width: int | None
    height: int | None
    depth_scale_mm: float
    found: str


def depth_scale_mm(value: float, path: Path) -> tuple[float, str]:
    """A released ``depth_scale`` -> (mm per depth unit, the rule used). >= 100: units per metre
    (1000 -> 1 mm); <= 0.01: metres per unit (0.001 -> 1 mm); otherwise mm per unit (BOP's sense)."""
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
        raise TdofError(f"depth_scale must be a number > 0, got {value!r}", path)
    if value >= 100:
        return 1000.0 / value, f"depth_scale {value:g} read as depth units per metre ({1000.0 / value:g} mm per unit)"
    if value <= 0.01:
        return value * 1000.0, f"depth_scale {value:g} read as metres per depth unit ({value * 1000:g} mm per unit)"
    return float(value), f"depth_scale {value:g} read as mm per depth unit (BOP's sense)"


def read_intrinsics(path: Path) -> Intrinsics:
    """intrinsics.json: {fx, fy, cx, cy, [width, height], depth_scale} or a 3x3 (or 9) "K",
    "intrinsic_matrix", "cam_K" or "camera_matrix" with depth_scale (keys case-insensitive)."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise TdofError(f"must hold a JSON object, got {type(data).__name__}", path)
    d = {str(k).lower(): v for k, v in data.items()}
    num = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
    matrix_key = next((k for k in ("k", "intrinsic_matrix", "cam_k", "camera_matrix") if k in d), None)
    if matrix_key is not None:
        try:
            K = np.asarray(d[matrix_key], dtype=np.float64).reshape(3, 3)
        except (TypeError, ValueError):
            raise TdofError(f"'{matrix_key}' must be a 3x3 matrix (or 9 numbers)", path) from None
        found = f"a 3x3 '{matrix_key}'"
    elif all(k in d for k in ("fx", "fy", "cx", "cy")):
        if not all(num(d[k]) for k in ("fx", "fy", "cx", "cy")):
            raise TdofError("fx, fy, cx, cy must be numbers", path)
        K = np.array([[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1]], dtype=np.float64)
        found = "fx, fy, cx, cy"
    else:
        raise TdofError(f"needs fx, fy, cx, cy or a 3x3 'K' / 'intrinsic_matrix'; found keys {sorted(data)}", path)
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise TdofError(f"{found} is not an intrinsic matrix (fx, fy > 0, last row 0 0 1)", path)
    size = [d.get(k, d.get(alt)) for k, alt in (("width", "w"), ("height", "h"))]
    if (size[0] is None) != (size[1] is None):
        raise TdofError("gives only one of width and height", path)
    if size[0] is not None:
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
            raise TdofError(f"width and height must be integers > 0, got {size}", path)
        found += f", width {size[0]}, height {size[1]}"
    else:
        found += ", no image size (taken from the images)"
    if "depth_scale" not in d:
        raise TdofError("has no depth_scale (the README says intrinsics.json holds it): add it", path)
    ds, rule = depth_scale_mm(d["depth_scale"], path)
    return Intrinsics(K, size[0], size[1], ds, f"{found}; {rule}")


class _SafeUnpickler(pickle.Unpickler):
    """Loads plain data (dicts, lists, numpy arrays) only: no other class can be built."""

    _ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
                ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
                ("numpy._core.multiarray", "scalar"), ("numpy.core.numeric", "_frombuffer"),
                ("numpy._core.numeric", "_frombuffer"), ("collections", "OrderedDict"),
                ("copyreg", "_reconstructor"), ("builtins", "object"),
                ("_codecs", "encode")}

    def find_class(self, module, name):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"the pickle wants to build {module}.{name}, which is not plain data")


def load_pickle(path: Path) -> object:
    """A pickle of plain data (Python 3 or Python 2: byte strings are read as latin1)."""
    data = read_bytes(path, "pose file")
    try:
        return _SafeUnpickler(io.BytesIO(data), encoding="latin1").load()
    except Exception as e:  # pickle raises many types on a bad file
        raise TdofError(f"cannot read the pickle ({type(e).__name__}: {e})", path) from None


@dataclass(frozen=True)
class FramePose:
    """One frame's ground truth in the file's units: cls_ids (N,), R (N,3,3), t (N,3), center_3ds (N,3) or None."""

    cls_ids: np.ndarray
    R: np.ndarray
    t: np.ndarray
    center_3ds: np.ndarray | None
    layout: str


def _as_poses(P: np.ndarray, n: int, path: Path) -> tuple[np.ndarray, str]:
    """'poses' in any of (3,4,N), (N,3,4), (N,4,4), (4,4,N), (3,4), (4,4) -> (N,3,4)."""
    cands = []
    if P.shape == (3, 4) or P.shape == (4, 4):
        cands.append((P[None, :3], f"{P.shape[0]}x4 (one instance)"))
    if P.ndim == 3:
        if P.shape[:2] == (3, 4) and P.shape[2] == n:
            cands.append((np.moveaxis(P, 2, 0), "(3,4,N)"))
        if P.shape[:2] == (4, 4) and P.shape[2] == n:
            cands.append((np.moveaxis(P, 2, 0)[:, :3], "(4,4,N)"))
        if P.shape[1:] == (3, 4) and P.shape[0] == n:
            cands.append((P, "(N,3,4)"))
        if P.shape[1:] == (4, 4) and P.shape[0] == n:
            cands.append((P[:, :3], "(N,4,4)"))
        if P.shape[1:] == (4, 4) and P.shape[0] == n and not np.allclose(P[:, 3], [0, 0, 0, 1], atol=1e-6):
            cands = [c for c in cands if c[1] != "(N,4,4)"]
    if P.ndim == 3 and P.shape[:2] == (4, 4) and P.shape[2] == n and not np.allclose(P[3].T, [0, 0, 0, 1], atol=1e-6):
        cands = [c for c in cands if c[1] != "(4,4,N)"]
    if not cands:
        raise TdofError(f"'poses' has shape {P.shape}, which is none of (3,4,N), (N,3,4), (N,4,4) with N = "
                        f"{n} (the length of 'cls_ids')", path)
    return cands[0]


def read_pose(path: Path, n_classes: int) -> FramePose:
    """A pose/*.pkl: a dict with 'poses' (see :func:`_as_poses`), 'cls_ids' (or 'cls_indexes',
    1-based class ids), optionally 'center_3ds' (N,3). Rotations are checked."""
    d = load_pickle(path)
    if not isinstance(d, dict):
        raise TdofError(f"must hold a dict (keys poses, cls_ids, ...), got {type(d).__name__}", path)
    keys = {str(k): k for k in d}
    if "poses" not in keys:
        raise TdofError(f"has no 'poses' (found keys {sorted(keys)})", path)
    ck = next((k for k in ("cls_ids", "cls_indexes", "cls_id") if k in keys), None)
    if ck is None:
        raise TdofError(f"has no 'cls_ids' (found keys {sorted(keys)})", path)
    try:
        cls = np.asarray(d[keys[ck]], dtype=np.float64).reshape(-1)
        P = np.asarray(d[keys["poses"]], dtype=np.float64)
    except (TypeError, ValueError):
        raise TdofError("'poses' and 'cls_ids' must be numeric arrays", path) from None
    if len(cls) == 0:
        raise TdofError("'cls_ids' is empty: a frame needs at least one object", path)
    if not np.isfinite(cls).all() or not np.all(cls == np.round(cls)):
        raise TdofError(f"'{ck}' must hold integer class ids, got {cls.tolist()}", path)
    bad = [c for c in cls.tolist() if not 1 <= c <= n_classes]  # before the cast: 1e40 stays 1e40
    if bad:
        shown = int(bad[0]) if abs(bad[0]) < 1e15 else f"{bad[0]:g}"
        raise TdofError(f"class id {shown} is not in classes.txt (ids 1..{n_classes})", path)
    cls = cls.astype(np.int64)
    if not np.isfinite(P).all():
        raise TdofError("'poses' holds NaN or inf", path)
    Rt, layout = _as_poses(P, len(cls), path)
    R, t = Rt[:, :, :3], Rt[:, :, 3]
    err = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    for i in range(len(cls)):
        if err[i] > 1e-3 or det[i] < 0:
            raise TdofError(f"instance {i}: the rotation of 'poses' {layout} is not a rotation matrix "
                            f"(|R R^T - I| = {err[i]:.2g}, det {det[i]:.3g})", path)
    c3 = None
    if "center_3ds" in keys:
        try:
            c3 = np.asarray(d[keys["center_3ds"]], dtype=np.float64)
        except (TypeError, ValueError):  # a string, a dict, a ragged list
            raise TdofError(f"'center_3ds' must be a numeric (N,3) array with N = {len(cls)}, got "
                            f"{type(d[keys['center_3ds']]).__name__}", path) from None
        if c3.shape == (3, len(cls)) and c3.shape != (len(cls), 3):
            c3 = c3.T
        c3 = c3.reshape(-1, 3) if c3.size == 3 * len(cls) else None
        if c3 is None:
            raise TdofError(f"'center_3ds' must be (N,3) with N = {len(cls)}", path)
    return FramePose(cls, R, t, c3, layout)


def read_class_mask(path: Path) -> np.ndarray:
    """mask/*.png -> (H,W) int32 class ids (grey 8/16-bit, palette indices, or RGB with equal channels)."""
    from PIL import Image

    data = read_bytes(path, "mask file")
    try:
        with warnings.catch_warnings():  # our own size bound below says it in one line
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data))
        mode = im.mode
        check_image_pixels(im.size[1], im.size[0], path)  # from the header, before decoding
        a = np.asarray(im)
    except TdofError:
        raise
    except Exception as e:
        raise TdofError(f"cannot read the mask ({type(e).__name__}: {e})", path) from None
    if a.ndim == 3:
        if not (np.all(a[..., 0] == a[..., 1]) and np.all(a[..., 0] == a[..., 2])):
            raise TdofError(f"the mask is a colour ({mode}) image with unequal channels: it must hold one class "
                            "id per pixel", path)
        a = a[..., 0]
    return a.astype(np.int32)


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(height, width) of a JPEG or PNG from its header."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            w, h = im.size
            fmt = im.format
    except FileNotFoundError:
        raise TdofError(f"{what} not found", path) from None
    except Exception as e:
        raise TdofError(f"cannot read the {what} ({type(e).__name__}: {e})", path) from None
    if what == "colour image" and fmt != "JPEG":
        raise TdofError(f"expected a JPEG colour image, found {fmt}", path)
    check_image_pixels(h, w, path)
    return h, w

