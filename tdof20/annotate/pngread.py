"""A fast path for reading the PNGs that tdof20 writes itself (:func:`tdof20.formats.encode_png`:
IHDR, one IDAT, IEND; every row with the Sub filter): the label stage decodes two 16-bit depth
images a frame, the evaluation two masks per labelled instance and image (19,200 for the full
3,200-frame scene).

Such a PNG is undone by ISA-L's inflate and one running sum per row (the Sub filter adds each byte
to the byte one pixel to its left, modulo 256: ``np.cumsum(..., dtype=np.uint8)``), about twice as
fast as OpenCV's libpng for a 640x480 depth image and four times for a mask. Anything else —
another filter, interlacing, several IDAT chunks, a bad CRC or checksum, a short or long stream,
a colour type other than grey 8/16-bit or RGB 8-bit — gives None, and the caller decodes the file
the usual way (:func:`tdof20.formats.decode_png`), which also words the errors. The result is the
array OpenCV gives (RGB order for colour, as ``decode_png`` returns it), bit for bit.

(This belongs beside ``decode_png`` in ``tdof20/formats/io.py``; it lives here until that
module's owners take it.)
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from isal import isal_zlib

from tdof20.formats import decode_png, read_bytes
from tdof20.formats.io import PNG_SIGNATURE

__all__ = ["decode_png_fast", "mask_rows", "mask_rows_iou", "read_png_fast"]

# (colour type, bit depth) -> bytes per pixel
_BPP = {(0, 8): 1, (0, 16): 2, (2, 8): 3}
_KIND = {"depth": ((0, 16),), "mask": ((0, 8),), "rgb": ((2, 8),), "any": tuple(_BPP)}


def _filtered_rows(data: bytes, kind: str = "any") -> tuple[np.ndarray, int, int, int] | None:
    """(rows (H, 1 + W*bpp) uint8, W, bpp, bit depth) of a PNG in the layout encode_png writes,
    with every row's filter byte 1 (Sub); None for anything else."""
    if len(data) < 57 or not data.startswith(PNG_SIGNATURE):
        return None
    n, tag = struct.unpack_from(">I4s", data, 8)
    if tag != b"IHDR" or n != 13:
        return None
    w, h, bit_depth, colour, comp, filt, interlace = struct.unpack_from(">IIBBBBB", data, 16)
    if (colour, bit_depth) not in _KIND.get(kind, ()) or comp or filt or interlace or w == 0 or h == 0:
        return None
    if struct.unpack_from(">I", data, 29)[0] != isal_zlib.crc32(data[12:29]):
        return None
    n, tag = struct.unpack_from(">I4s", data, 33)
    end = 41 + n
    if tag != b"IDAT" or len(data) != end + 16 or data[end + 4:] != b"\x00\x00\x00\x00IEND\xaeB`\x82":
        return None
    if struct.unpack_from(">I", data, end)[0] != isal_zlib.crc32(data[37:end]):
        return None
    bpp = _BPP[(colour, bit_depth)]
    try:
        raw = isal_zlib.decompress(memoryview(data)[41:end])
    except Exception:  # isal raises its own error types on a corrupt stream
        return None
    if len(raw) != h * (1 + w * bpp):
        return None
    rows = np.frombuffer(raw, np.uint8).reshape(h, 1 + w * bpp)
    if np.any(rows[:, 0] != 1):
        return None
    return rows, w, bpp, bit_depth


def decode_png_fast(data: bytes, path: str | Path = "<bytes>", kind: str = "any") -> np.ndarray:
    """:func:`tdof20.formats.decode_png` (the same array, the same errors), faster on the PNGs
    tdof20 writes."""
    got = _filtered_rows(data, kind)
    if got is None:
        return decode_png(data, path, kind)
    rows, w, bpp, bit_depth = got
    h = rows.shape[0]
    img = np.cumsum(rows[:, 1:].reshape(h, w, bpp), axis=1, dtype=np.uint8)
    if bit_depth == 16:
        return img.view(">u2").reshape(h, w).astype(np.uint16)
    return img.reshape(h, w) if bpp == 1 else img


def read_png_fast(path: str | Path, kind: str = "any") -> np.ndarray:
    """:func:`tdof20.formats.read_png` with :func:`decode_png_fast`."""
    return decode_png_fast(read_bytes(path), Path(path), kind)


def mask_rows(path: str | Path) -> tuple[int, int, np.ndarray, tuple[int, int]]:
    """A mask PNG (8-bit grey) as (v0, u0, block, (H, W)): ``block`` (n, m) bool holds every
    non-zero pixel, its top-left pixel is (v0, u0) — what an IoU needs, without decoding the
    empty rows and columns around an object. Any PNG the fast path does not take is read whole
    (:func:`tdof20.formats.read_png`, its errors)."""
    data = read_bytes(path)
    got = _filtered_rows(data, "mask")
    if got is None:
        m = decode_png(data, Path(path), "mask") > 0
        return 0, 0, m, m.shape
    rows, w, _, _ = got
    h = rows.shape[0]
    body = rows[:, 1:]
    # Sub filter: a row is all zero exactly when its filtered bytes are, and left of a row's first
    # non-zero filtered byte every pixel is 0; right of its last one every pixel repeats it
    nz = np.flatnonzero(body.any(axis=1))
    if not len(nz):
        return 0, 0, np.zeros((0, 0), bool), (h, w)
    r0, r1 = int(nz[0]), int(nz[-1]) + 1
    cols = np.flatnonzero(body[r0:r1].any(axis=0))
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    block = np.cumsum(body[r0:r1, c0:c1], axis=1, dtype=np.uint8)
    if c1 < w and block[:, -1].any():     # a row still on at its last change: on to the border
        block = np.cumsum(body[r0:r1, c0:], axis=1, dtype=np.uint8)
    return r0, c0, block > 0, (h, w)


def mask_rows_iou(a: tuple[int, int, np.ndarray, tuple[int, int]],
                  b: tuple[int, int, np.ndarray, tuple[int, int]]) -> float:
    """IoU of two :func:`mask_rows` of one image size (1.0 when both are empty)."""
    (va, ua, ma, _), (vb, ub, mb, _) = a, b
    na, nb = int(np.count_nonzero(ma)), int(np.count_nonzero(mb))
    v0, v1 = max(va, vb), min(va + ma.shape[0], vb + mb.shape[0])
    u0, u1 = max(ua, ub), min(ua + ma.shape[1], ub + mb.shape[1])
    inter = 0
    if v1 > v0 and u1 > u0:
        inter = int(np.count_nonzero(ma[v0 - va:v1 - va, u0 - ua:u1 - ua] & mb[v0 - vb:v1 - vb, u0 - ub:u1 - ub]))
    union = na + nb - inter
    return 1.0 if union == 0 else inter / union
