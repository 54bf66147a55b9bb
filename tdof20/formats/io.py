"""Atomic writers and checked readers for the files every stage exchanges (JSON, PNG).

Writes go to a temporary file in the same folder and are renamed into place, so a reader never
sees a half-written file and an interrupted write never damages the file that was there.
Readers turn any problem into a one-line :class:`TdofError` naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
import struct
import tempfile
import tomllib
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from isal import isal_zlib

from tdof20.errors import TdofError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: the largest image (pixels) any reader decodes: checked from the header, before decoding
MAX_IMAGE_PIXELS = 8192 * 8192
# OpenCV prints its own warnings and "[ERROR:0@...] global grfmt_png.cpp ..." lines about a corrupt
# file; our one-line error says it instead (one line, naming the file)
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def atomic_write_bytes(path: str | Path, data: bytes, fsync: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError) and e.filename is None:  # a write into the open file (a full disk): name it
            raise OSError(e.errno, e.strerror or str(e), str(path)) from e
        raise


# the temporary files atomic_write_bytes makes (mkstemp: 8 characters of [a-z0-9_])
TEMP_FILE_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")


def stale_temp_files(dir: str | Path) -> list[Path]:
    """The unfinished atomic writes (``.{name}.<8 random characters>.tmp`` files) anywhere under a
    folder, sorted: what a killed writer left. Only files of exactly that pattern; nothing is
    removed here (the caller does, while it holds the folder)."""
    root = Path(dir)
    return sorted(p for p in root.rglob(".*.tmp") if TEMP_FILE_RE.match(p.name) and p.is_file())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj: Any, indent: int | None = 2) -> str:
    return json.dumps(obj, indent=indent, default=_json_default, allow_nan=False)


def write_json(path: str | Path, obj: Any, indent: int | None = 2, fsync: bool = False) -> None:
    atomic_write_bytes(path, (dumps_json(obj, indent) + "\n").encode(), fsync=fsync)


def read_bytes(path: str | Path, what: str = "file", limit: int | None = None,
               max_size: int | None = None) -> bytes:
    """The bytes of a file (the first ``limit`` bytes when given). The one place files are read
    for the checked readers: a missing file, a folder, a file on a path through a file or a file
    that cannot be read is a one-line :class:`TdofError` naming it; ``what`` names it in the
    message ("results file" -> "results file not found"). Only regular files are read (a link to
    /dev/zero or a FIFO is refused, never read or waited on); ``max_size``: refuse a larger file."""
    path = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO does not wait for a writer; only regular files are read
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        with os.fdopen(fd, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                if stat.S_ISDIR(st.st_mode):
                    raise IsADirectoryError
                raise TdofError(f"is not a regular file (a device, pipe or socket): not a {what}", path)
            if max_size is not None and st.st_size > max_size:
                raise TdofError(f"the {what} is {st.st_size / 1e6:.1f} MB, more than the {max_size / 1e6:.0f} MB "
                                f"a {what} may have", path)
            return f.read() if limit is None else f.read(limit)
    except FileNotFoundError:
        raise TdofError(f"{what} not found", path) from None
    except IsADirectoryError:
        raise TdofError(f"is a folder, not a {what}", path) from None
    except NotADirectoryError:
        raise TdofError(f"{what} not found (a part of its path is a file, not a folder)", path) from None
    except PermissionError:
        raise TdofError(f"cannot read the {what}: permission denied", path) from None
    except OSError as e:
        raise TdofError(f"cannot read the {what} ({e.strerror or type(e).__name__})", path) from None


def read_text(path: str | Path, what: str = "file", max_size: int | None = None) -> str:
    """A UTF-8 text file (a byte-order mark is dropped) as a string; see :func:`read_bytes`.
    Bytes that are not UTF-8 are a TdofError naming the file and the line they are on."""
    data = read_bytes(path, what, max_size=max_size)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise TdofError(f"line {line}: not UTF-8 text", path) from None


def read_json(path: str | Path, what: str = "file") -> Any:
    """A JSON file; a missing, unreadable or malformed file is one TdofError naming it."""
    path = Path(path)
    text = read_text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise TdofError(f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}", path) from None


def read_toml(path: str | Path, what: str = "config file") -> dict:
    """A TOML file as a dict; a missing, unreadable or malformed file is one TdofError naming it."""
    path = Path(path)
    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TdofError(f"malformed TOML: {e}", path) from None


def check_output_file(path: str | Path, option: str, what: str = "file") -> Path:
    """Refuse, before any work, an output file that cannot be written where it is named: a
    folder of that name, or a file on its path where a folder must be. ``option`` names the
    option in the message (``--out``)."""
    path = Path(path)
    if path.is_dir():
        raise TdofError(f"{option} names a folder: give the {what} to write", path)
    check_parents(path, option)
    return path


def check_output_dir(path: str | Path, option: str, what: str = "folder") -> Path:
    """Refuse, before any work, an output folder that is an existing file or lies under one."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise TdofError(f"{option} names a file: give a {what}", path)
    check_parents(path, option)
    return path


def check_parents(path: str | Path, option: str) -> None:
    """Refuse an output path under a file, or in a folder this user cannot write (the nearest
    existing folder above it is the one that counts: the rest is created)."""
    path = Path(path)
    for up in path.absolute().parents:
        if up.exists():
            if not up.is_dir():
                raise TdofError(f"{option}: {up} is a file, so nothing can be written under it", path)
            if not os.access(up, os.W_OK | os.X_OK):
                raise TdofError(f"{option}: no permission to write in {up}", path)
            return


def safe_inside(root: Path, path: Path) -> Path:
    """``path`` after checking that writing there stays inside the input folder ``root``: it lies
    under ``root`` (no ``..`` out of it) and no existing component of it below ``root`` (``root``
    itself excluded: a dataset may be reached through a link) is a symbolic link. A dataset
    someone else made could point its ``.cache/`` (or any folder tdof20 writes into) at the
    user's own folders; such a write is a one-line TdofError naming the link instead."""
    root, path = Path(root), Path(path)
    base = Path(os.path.normpath(root.absolute()))
    full = Path(os.path.normpath(path.absolute()))
    try:
        rel = full.relative_to(base)
    except ValueError:
        raise TdofError(f"tdof20 does not write outside the dataset folder {root}", path) from None
    cur = base
    for part in rel.parts:
        cur = cur / part
        if cur.is_symlink():
            raise TdofError("is a symbolic link inside the dataset: tdof20 does not write through a symlink "
                            "inside a dataset (give --cache-dir to write elsewhere)", cur)
        if not cur.exists():
            break
    return path


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def encode_png(image: np.ndarray, compression: int = 1) -> bytes:
    """Encode an 8-bit colour (H,W,3 RGB), 8-bit grey (H,W) or uint16 (H,W) image as PNG bytes.

    Written by hand over ISA-L's deflate (``isal``), because libpng's zlib deflate is the whole
    cost of PNG writing and runs 4-7x slower at the same size. The container is plain PNG
    (IHDR, one IDAT, IEND; every row with the Sub filter) that every decoder reads.
    ``compression``: ISA-L level 0-3.
    """
    img = np.ascontiguousarray(image)
    if img.ndim == 3:
        if img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"colour images must be (H,W,3) uint8, got {img.shape} {img.dtype}")
        rows, bpp, bit_depth, colour_type = img.reshape(img.shape[0], -1), 3, 8, 2
    elif img.ndim == 2 and img.dtype == np.uint8:
        rows, bpp, bit_depth, colour_type = img, 1, 8, 0
    elif img.ndim == 2 and img.dtype == np.uint16:
        rows = img.astype(">u2").view(np.uint8).reshape(img.shape[0], -1)
        bpp, bit_depth, colour_type = 2, 16, 0
    else:
        raise ValueError(f"single-channel images must be (H,W) uint8 or uint16, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    if h == 0 or w == 0:
        raise ValueError("cannot encode an empty image")
    data = np.empty((h, rows.shape[1] + 1), np.uint8)
    data[:, 0] = 1  # filter type Sub: each byte minus the byte one pixel to its left
    data[:, 1:1 + bpp] = rows[:, :bpp]
    np.subtract(rows[:, bpp:], rows[:, :-bpp], out=data[:, 1 + bpp:])
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    idat = isal_zlib.compress(data.tobytes(), int(np.clip(compression, 0, 3)))
    return PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


def write_png(path: str | Path, image: np.ndarray, compression: int = 1) -> bytes:
    """Atomically write a PNG (see :func:`encode_png`); returns the bytes written."""
    data = encode_png(image, compression)
    atomic_write_bytes(path, data)
    return data


def decode_png(data: bytes, path: str | Path = "<bytes>", kind: str = "any") -> np.ndarray:
    """Decode PNG bytes. kind: 'rgb' (H,W,3 uint8), 'depth' (H,W uint16), 'mask' (H,W uint8) or 'any'."""
    if not data.startswith(PNG_SIGNATURE):
        raise _not_png(data, path)
    png_header(path, "any", data)  # a sane header (and image size) before decoding
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise TdofError("corrupt PNG: cannot be decoded", path)
    if kind == "rgb":
        if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.dtype != np.uint8:
            raise TdofError(f"expected an 8-bit colour PNG, found {arr.dtype} with shape {arr.shape}", path)
        arr = np.ascontiguousarray(arr[..., 2::-1])
    elif kind == "depth":
        if arr.ndim != 2 or arr.dtype != np.uint16:
            raise TdofError(f"expected a 16-bit single-channel depth PNG, found {arr.dtype} with shape {arr.shape}", path)
    elif kind == "mask":
        if arr.ndim != 2 or arr.dtype != np.uint8:
            raise TdofError(f"expected an 8-bit single-channel mask PNG, found {arr.dtype} with shape {arr.shape}", path)
    elif arr.ndim == 3:
        arr = np.ascontiguousarray(arr[..., 2::-1])
    return arr


_OTHER_FORMATS = ((b"\xff\xd8\xff", "JPEG"), (b"BM", "BMP"), (b"GIF8", "GIF"), (b"II*\x00", "TIFF"),
                  (b"MM\x00*", "TIFF"), (b"RIFF", "WebP"))
PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


def _not_png(data: bytes, path: str | Path) -> TdofError:
    fmt = next((name for sig, name in _OTHER_FORMATS if data.startswith(sig)), None)
    if fmt is not None:
        return TdofError(f"not a PNG file (bad signature): it holds a {fmt} image, whatever its name says", path)
    return TdofError("not a PNG file (bad signature)", path)


def check_image_pixels(h: int, w: int, path: str | Path) -> None:
    """Refuse an image larger than :data:`MAX_IMAGE_PIXELS` (from its header, before decoding)."""
    if int(h) * int(w) > MAX_IMAGE_PIXELS:
        raise TdofError(f"the image is {w}x{h} ({int(w) * int(h) / 1e6:.0f} megapixels), more than the "
                        f"{MAX_IMAGE_PIXELS / 1e6:.0f} megapixels tdof20 reads", path)


def png_header(path: str | Path, kind: str = "any", data: bytes | None = None) -> tuple[int, int]:
    """(height, width) of a PNG from its header alone (the first 33 bytes; nothing is decoded),
    checked against ``kind`` as :func:`decode_png` would: 'rgb' an 8-bit RGB(A) image, 'depth' a
    16-bit grey image, 'mask' a grey image of at most 8 bits. A file that is not a PNG (a JPEG
    named .png), has no image header or holds another kind of image is a TdofError naming it.
    ``data``: the file's bytes when they are read already (``path`` then only names it)."""
    path = Path(path)
    data = read_bytes(path, "image file", limit=33) if data is None else data[:33]
    if not data.startswith(PNG_SIGNATURE):
        raise _not_png(data, path)
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise TdofError("corrupt PNG: no image header (IHDR) after the signature", path)
    w, h, bits, colour = struct.unpack(">IIBB", data[16:26])
    if w == 0 or h == 0:
        raise TdofError(f"corrupt PNG: its header gives a {w}x{h} image", path)
    check_image_pixels(h, w, path)
    found = f"a {PNG_COLOUR_TYPES.get(colour, f'colour type {colour}')} PNG of {bits} bits per sample"
    if kind == "rgb" and not (bits == 8 and colour in (2, 6)):
        raise TdofError(f"expected an 8-bit colour PNG, found {found}", path)
    if kind == "depth" and not (bits == 16 and colour == 0):
        raise TdofError(f"expected a 16-bit single-channel depth PNG, found {found}", path)
    if kind == "mask" and not (bits <= 8 and colour == 0):
        raise TdofError(f"expected an 8-bit single-channel mask PNG, found {found}", path)
    return h, w


def read_png(path: str | Path, kind: str = "any") -> np.ndarray:
    """Read and check a PNG (see :func:`decode_png`); any problem is a one-line TdofError."""
    return decode_png(read_bytes(path), Path(path), kind)


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
