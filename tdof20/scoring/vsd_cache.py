"""VSD's ground-truth half kept between scorings: ROOT/.cache/vsd/.

Half of VSD's work is the dataset's alone: each ground-truth instance rendered (ray cast in its
footprint, through the toolkit's depth buffer) and compared with its test depth image, which gives
V_g and d_g (:class:`tdof20.scoring.metrics.vsd.VisibleGt`). Every submission on the same targets
needs the very same arrays, so the scorer keeps them on disk, one file per block of a scene's
images (:data:`BLOCK` image ids) and target set, and the next scoring reads them instead of casting
(about half of VSD's rays). What a file is valid for is in its name's and its ``key``'s digest: the
format, VSD's delta, the instances (object, image, ground-truth index, R, t, K), the meshes' bytes,
and per image its depth PNG's bytes and depth_scale — any change and the file is not used (it is
rebuilt). Pixels are stored as their indices in the instances' footprint boxes and their 16-bit
depth-buffer values (the depth is recomputed from them exactly: :meth:`VisibleGt.from_stored`),
both differenced along the pixels and deflated (ISA-L).

The cache holds ground truth: it stays in ROOT/.cache/, which ``dataset publish`` never copies. A
dataset folder the scorer cannot write to is scored without it (computed each time); a file that
cannot be read is recomputed; files are written atomically, so scorers on one dataset can share it.
"""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path

import numpy as np
from isal import isal_zlib

from tdof20.scoring.metrics.vsd import VisibleGt

BLOCK = 128  # image ids per cache file (and per block the scorer reads at once)
FORMAT = "tdof20-vsd-gt-2"


def _blob(a: np.ndarray) -> np.ndarray:
    return np.frombuffer(isal_zlib.compress(np.ascontiguousarray(a).tobytes(), 1), np.uint8)


def _unblob(b: np.ndarray, dtype) -> np.ndarray:
    return np.frombuffer(isal_zlib.decompress(b.tobytes()), dtype)


def encode(gt: VisibleGt) -> dict[str, np.ndarray]:
    """The arrays a cache file holds for ``gt``: boxes, per-pose pixel counts, the V_g pixels (their
    indices on the poses' box rasters laid end to end, differenced) and their depth-buffer values
    (uint16, differenced modulo 2^16), both deflated."""
    boxes = gt.boxes.astype(np.int32)
    area = np.maximum(gt.boxes[:, 1] - gt.boxes[:, 0], 0) * np.maximum(gt.boxes[:, 3] - gt.boxes[:, 2], 0)
    off = np.cumsum(area) - area
    g = np.repeat(off, gt.counts) + gt.idx  # increasing
    if len(g) and g[-1] >= 1 << 32:
        raise ValueError("too many pixels for one file")
    qi = gt.qi.astype(np.uint16)
    return {"boxes": boxes, "counts": gt.counts.astype(np.int64),
            "pixels": _blob(np.diff(g, prepend=0).astype(np.uint32)),
            "qi": _blob(np.diff(qi, prepend=np.uint16(0)))}


def unpack(arrays) -> VisibleGt:
    """:func:`encode`'s arrays as a :class:`VisibleGt` without its depths (``depth`` None: they need
    each pose's clip planes, :meth:`VisibleGt.from_stored`)."""
    boxes = np.asarray(arrays["boxes"], np.int64).reshape(-1, 4)
    counts = np.asarray(arrays["counts"], np.int64)
    area = np.maximum(boxes[:, 1] - boxes[:, 0], 0) * np.maximum(boxes[:, 3] - boxes[:, 2], 0)
    off = np.cumsum(area) - area
    g = np.cumsum(_unblob(arrays["pixels"], np.uint32), dtype=np.int64)
    qi = np.cumsum(_unblob(arrays["qi"], np.uint16), dtype=np.uint16)
    if len(g) != counts.sum() or len(qi) != len(g) or (counts < 0).any():
        raise ValueError("pixels, depths and counts disagree")
    idx = g - np.repeat(off, counts)
    if len(idx) and ((idx < 0).any() or (idx >= np.repeat(area, counts)).any()):
        raise ValueError("a pixel outside its box")
    return VisibleGt(boxes, np.concatenate([[0], np.cumsum(counts)]), idx, None, qi)


class GtCache:
    """The files of ROOT/.cache/vsd/ (``root`` None: no cache)."""

    def __init__(self, root: str | Path | None):
        self.dir = None if root is None else Path(root) / ".cache" / "vsd"
        self.hits = self.misses = 0
        self._writable = None

    def writable(self) -> bool:
        """Whether files can be kept (the folder made or there, and writable)."""
        if self._writable is None:
            ok = False
            if self.dir is not None:
                try:
                    self.dir.mkdir(parents=True, exist_ok=True)
                    ok = os.access(self.dir, os.W_OK | os.X_OK)
                except OSError:
                    ok = False
            self._writable = ok
        return self._writable

    def path(self, scene: int, block: int, name_digest: str) -> Path:
        return self.dir / f"{scene:06d}" / f"{block:05d}-{name_digest[:16]}.npz"

    def load(self, path: Path, key: str) -> dict | None:
        """The arrays of a valid file for ``key``, else None."""
        if self.dir is None or not path.is_file():
            self.misses += 1
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) != key:
                    raise ValueError("stale")
                out = {k: z[k] for k in ("boxes", "counts", "pixels", "qi")}
        except Exception:  # unreadable, truncated or stale: computed again (and rewritten)
            self.misses += 1
            return None
        self.hits += 1
        return out

    def save(self, path: Path, key: str, arrays: dict) -> None:
        """Write a file atomically; a full disk or a read-only folder only leaves it unwritten."""
        if not self.writable():
            return
        buf = io.BytesIO()
        np.savez(buf, key=np.array(key), **arrays)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(buf.getvalue())
            os.replace(tmp, path)
        except OSError:
            try:
                tmp.unlink()
            except OSError:
                pass


def digest(*parts) -> str:
    """sha256 of ``parts`` (str, bytes or arrays), each length-prefixed."""
    h = hashlib.sha256()
    for p in parts:
        b = p.encode() if isinstance(p, str) else (np.ascontiguousarray(p).tobytes() if isinstance(p, np.ndarray)
                                                   else bytes(p))
        h.update(len(b).to_bytes(8, "little"))
        h.update(b)
    return h.hexdigest()


__all__ = ["BLOCK", "FORMAT", "GtCache", "digest", "encode", "unpack"]
