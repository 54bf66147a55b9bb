"""Pose-estimation results in the BOP CSV format: a strict reader and an atomic writer.

The format (bop_toolkit ``docs/bop_challenge_*``; one row per estimated pose)::

    scene_id,im_id,obj_id,score,R,t,time
    8,0,3,0.97,0.0621 -0.9961 0.0623 -0.6612 0.0059 0.7502 -0.7476 -0.0879 -0.6583,-12.3 40.5 731.0,0.034

``R`` is 9 numbers row-major, ``t`` 3 numbers in millimetres (both space-separated), ``score`` a
confidence (the highest-scored estimate of an object in an image counts), ``time`` the seconds
spent on the whole image (the same on every row of an image; -1 = not measured).

Reading is strict: every problem is a :class:`TdofError` naming the file and the line
(line 1 is the header). What is an error and what only a warning:

* header not exactly ``scene_id,im_id,obj_id,score,R,t,time``                  -> error
* a row without 7 comma-separated fields, R without 9 or t without 3 numbers   -> error
* a number that does not parse, NaN or inf anywhere, negative ids, obj_id 0    -> error
* an id beyond int64 (ID_MAX), a file that is not UTF-8 text                    -> error
* R not a rotation: max |R R^T - I| > 1e-3 (ROTATION_TOLERANCE) or det(R) <= 0  -> error
* the same (scene, image, object, R, t) on two rows (a duplicate)              -> error
* rows of one image with different times (bop_toolkit refuses them too)        -> error
* time -1 (BOP: not measured)                                                   -> warning
* another negative time                                                          -> error
* blank lines                                                                     skipped
Checks against a dataset (:func:`check_against_dataset`): unknown scene, image or object ids
are errors; translations that look like metres (the median |t| of the file 100 or more times
smaller than the median distance of the objects in the dataset) are an error naming a line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from tdof20.errors import TdofError
from tdof20.formats.io import atomic_write_bytes, read_bytes

HEADER = "scene_id,im_id,obj_id,score,R,t,time"
FIELDS = HEADER.split(",")
ROTATION_TOLERANCE = 1e-3  # max |R R^T - I| accepted (rotations printed with ~4 decimals pass)
METRES_RATIO = 100.0  # median GT distance / median |t| of a file at or above this -> metres


@dataclass
class Results:
    """Parsed results: one entry per row, in file order. ``line`` is the 1-based line number of
    each row in its file (rows given in memory count as if written after a header: 2, 3, ...)."""

    scene_id: np.ndarray  # (N,) int64
    im_id: np.ndarray  # (N,) int64
    obj_id: np.ndarray  # (N,) int64
    score: np.ndarray  # (N,) float64
    R: np.ndarray  # (N,3,3)
    t: np.ndarray  # (N,3) mm
    time: np.ndarray  # (N,) seconds, -1 = not measured
    line: np.ndarray  # (N,) int64
    path: Path | None = None
    warnings: list[str] = field(default_factory=list)
    # a file read keeping only the rows that can count (:func:`read_top_results`): the rows the
    # file holds, and how many of them match no key (None, 0: every row of the file is here)
    n_read: int | None = None
    n_unmatched: int = 0

    def __len__(self) -> int:
        return len(self.score)

    @property
    def name(self) -> str:
        """A method name for reports: the file's stem (BOP names files METHOD_DATASET-SPLIT.csv)."""
        return self.path.stem if self.path is not None else "results"

    def where(self, i: int) -> str:
        return f"line {int(self.line[i])}"

    def error(self, i: int | None, message: str) -> TdofError:
        """A TdofError naming the file (if any) and the line of row ``i``."""
        prefix = "" if i is None else (f"line {int(self.line[i])}: " if self.path is not None
                                       else f"row {int(self.line[i]) - 1}: ")
        return TdofError(prefix + message, self.path)

    @classmethod
    def from_rows(cls, rows: Iterable[Sequence], path: str | Path | None = None) -> "Results":
        """Results from (scene_id, im_id, obj_id, score, R (3,3), t (3,) mm, time) tuples
        (time may be None = -1), validated like a file."""
        rows = list(rows)
        n = len(rows)
        sid = np.zeros(n, np.int64)
        iid = np.zeros(n, np.int64)
        oid = np.zeros(n, np.int64)
        score = np.zeros(n)
        R = np.zeros((n, 3, 3))
        t = np.zeros((n, 3))
        tm = np.zeros(n)
        p = None if path is None else Path(path)
        for i, row in enumerate(rows):
            where = f"line {i + 2}: " if p is not None else f"row {i + 1}: "
            if len(row) != 7:
                raise TdofError(f"{where}expected 7 values ({HEADER}), got {len(row)}", p)
            s, im, ob, sc, Ri, ti, ti_me = row
            for name, v in (("scene_id", s), ("im_id", im), ("obj_id", ob)):
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise TdofError(f"{where}{name} must be an integer, got {v!r}", p)
                if int(v) > ID_MAX:
                    raise TdofError(f"{where}{name} {v} is too large for an id (at most {ID_MAX})", p)
            sid[i], iid[i], oid[i] = int(s), int(im), int(ob)
            Ra = np.asarray(Ri, dtype=np.float64)
            ta = np.asarray(ti, dtype=np.float64)
            if Ra.size != 9 or ta.size != 3:
                raise TdofError(f"{where}R must have 9 numbers and t 3, got {Ra.size} and {ta.size}", p)
            R[i] = Ra.reshape(3, 3)
            t[i] = ta.reshape(3)
            score[i] = float(sc)
            tm[i] = -1.0 if ti_me is None else float(ti_me)
        res = cls(sid, iid, oid, score, R, t, tm, np.arange(n, dtype=np.int64) + 2, p)
        _validate(res)
        return res


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
def _fail(path: Path, lineno: int, message: str) -> TdofError:
    return TdofError(f"line {lineno}: {message}", path)


ID_MAX = int(np.iinfo(np.int64).max)  # ids are int64
_TOO_LARGE = -2


def _id_value(text: str) -> int:
    """A non-negative decimal id; -1 when it is not one, _TOO_LARGE beyond int64."""
    s = text.strip()
    if not (s.isdigit() and s.isascii()):
        return -1
    v = int(s)
    return v if v <= ID_MAX else _TOO_LARGE


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def read_results(path: str | Path) -> Results:
    """Read and check a BOP results CSV; any problem is a TdofError naming the file and line.
    The file is parsed in parts (:func:`iter_rows`): memory beyond the rows' arrays (136 bytes a
    row) is bounded, not the text's size."""
    path = Path(path)
    parts = list(iter_rows(path))
    if len(parts) == 1:
        res = parts[0]
    else:
        res = Results(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                        ("scene_id", "im_id", "obj_id", "score", "R", "t", "time", "line")), path)
    _validate(res)
    return res


STREAM_BYTES = 1 << 20  # a part of a file parsed at once (~4,000 rows)


def _check_header(path: Path, first: str) -> None:
    header = ",".join(f.strip() for f in first.split(","))
    if header != HEADER:
        hint = ""
        if header == "scene_id,im_id,obj_id,score,R,t":
            hint = " (the time column is missing: add ',time' and -1 where not measured)"
        raise _fail(path, 1, f"malformed header {first.strip()[:80]!r}: expected {HEADER!r}{hint}")


def iter_rows(path: str | Path, part_bytes: int = STREAM_BYTES):
    """The rows of a results CSV, parsed part by part (each a :class:`Results` of about
    ``part_bytes`` of text, its rows not yet checked as a whole): the header is checked first;
    lines are split as :meth:`str.splitlines` splits the whole text (a part ends after a "\\n");
    bytes that are not UTF-8 are a TdofError naming their line. At least one part is yielded."""
    import codecs

    path = Path(path)
    read_bytes(path, "results file", limit=0)  # (the checked readers' one-line errors: missing, a folder, ...)
    dec = codecs.getincrementaldecoder("utf-8-sig")()
    try:
        f = open(path, "rb")
    except OSError as e:
        raise TdofError(f"cannot read the results file: {e.strerror or e}", path) from None
    with f:
        carry, lineno, newlines, header_seen, yielded, done = "", 1, 0, False, False, False
        while not done:
            try:
                data = f.read(part_bytes)
            except OSError as e:
                raise TdofError(f"cannot read the results file: {e.strerror or e}", path) from None
            done = not data
            try:
                text = carry + dec.decode(data, final=done)
            except UnicodeDecodeError as e:
                line = newlines + data[: max(0, e.start)].count(b"\n") + 1
                raise TdofError(f"line {line}: not UTF-8 text", path) from None
            newlines += data.count(b"\n")
            cut = len(text) if done else text.rfind("\n") + 1
            text, carry = text[:cut], text[cut:]
            lines = text.splitlines()
            if not header_seen:
                if not lines:
                    if done:
                        raise _fail(path, 1, f"empty file: expected the header {HEADER!r}")
                    continue
                _check_header(path, lines[0])
                header_seen = True
                lines = lines[1:]
                lineno += 1
            res = parse_rows(lines, path, lineno)
            lineno += len(lines)
            if len(res) or (done and not yielded):
                yielded = True
                yield res


def _row_keys(part: Results) -> np.ndarray:
    """(n, 15) float64: what makes two rows duplicates (scene, image, object, R, t)."""
    n = len(part)
    return np.ascontiguousarray(np.concatenate([np.stack([part.scene_id, part.im_id, part.obj_id], 1).astype(np.float64),
                                                part.R.reshape(n, 9), part.t], axis=1))


def _row_digests(keys: np.ndarray) -> np.ndarray:
    """A 64-bit digest of each row of ``keys`` (vectorised multiply-xorshift over its bytes; equal
    rows, equal digests; a collision is possible, so a digest match is confirmed on the rows)."""
    words = np.ascontiguousarray(keys).view(np.uint64)
    h = np.full(len(words), 0x9E3779B97F4A7C15, np.uint64)
    with np.errstate(over="ignore"):
        for j in range(words.shape[1]):
            h ^= words[:, j]
            h *= np.uint64(0xBF58476D1CE4E5B9)
            h ^= h >> np.uint64(31)
    return h


_FIELDS_OF = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time", "line")


def _cat(parts: list[Results], path: Path | None) -> Results:
    return Results(*(np.concatenate([getattr(p, k) for p in parts]) for k in _FIELDS_OF), path)


def _take(res: Results, idx: np.ndarray) -> Results:
    return Results(*(getattr(res, k)[idx] for k in _FIELDS_OF), res.path)


def _top_k(res: Results, k: np.ndarray) -> np.ndarray:
    """Indices (in file order) of each (scene, image, object)'s ``k`` (per row: its key's k) best
    rows: decreasing score, ties the earlier line (the scorer's order)."""
    order = np.lexsort((res.line, -res.score, res.obj_id, res.im_id, res.scene_id))
    keys = np.stack([res.scene_id[order], res.im_id[order], res.obj_id[order]], axis=1)
    new = np.ones(len(order), bool)
    new[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    start = np.maximum.accumulate(np.where(new, np.arange(len(order)), 0))
    rank = np.arange(len(order)) - start
    return np.sort(order[rank < k[order]])


def read_top_results(path: str | Path, keep: Callable[[Results], np.ndarray],
                     check_ids: Callable[[Results], None] | None = None, gt_distance_mm: float | None = None,
                     part_bytes: int | None = None) -> Results:
    """Read and check a results CSV as :func:`read_results` does (every row checked, duplicates and
    one time per image across the whole file, the metres check's median over every row), but
    keep in memory only the rows that can count: ``keep(part)`` gives each row of a part the
    number k of its (scene, image, object)'s rows that count (a target's inst_count; 0: it matches
    no target), and only each key's top k rows by score (ties: the earlier line) are kept, so the
    memory is bounded by the targets, not the file: beyond them about 24 bytes a row (an 8-byte
    digest for the duplicates, the line, |t| for the median). ``check_ids(part)``: the dataset's id
    checks (:func:`check_against_dataset` without the distance), ``gt_distance_mm`` its metres
    check; ``part_bytes`` the text parsed at once (default :data:`STREAM_BYTES`). The rows come
    back in file order with ``n_read`` (the file's rows) and ``n_unmatched`` (those with k = 0),
    and the -1 time warning counted over the whole file. A file of one part gets exactly :func:`read_results`' checks and messages;
    a longer one names the first problem found part by part (within a part in the reader's order,
    duplicates and the metres check across parts after the last part)."""
    path = Path(path)
    times: dict[tuple[int, int], tuple[float, int]] = {}  # image -> (time, first line); bounded by the dataset
    digests, lines, norms = [], [], []
    first_small = None  # (line, |t|) of the first row whose |t| could be metres
    pool: Results | None = None
    n = n_unmatched = 0
    for part in iter_rows(path, STREAM_BYTES if part_bytes is None else part_bytes):
        if not len(part):
            continue
        check_rows(part)
        if check_ids is not None:
            check_ids(part)
        for s, im, t, ln in zip(part.scene_id.tolist(), part.im_id.tolist(), part.time.tolist(), part.line.tolist()):
            seen = times.get((s, im))
            if seen is None:
                times[(s, im)] = (t, ln)
            elif seen[0] != t:
                raise TdofError(f"line {ln}: time {t:g} differs from {seen[0]:g} on line {seen[1]} for scene {s} "
                                f"image {im}: BOP needs one time per image (the time of the whole image on each of "
                                "its rows)", path)
        digests.append(_row_digests(_row_keys(part)))
        lines.append(part.line.copy())
        nr = np.linalg.norm(part.t, axis=1)
        norms.append(nr)
        if gt_distance_mm and first_small is None:
            small = np.flatnonzero(nr * METRES_RATIO <= gt_distance_mm)
            if len(small):
                first_small = (int(part.line[small[0]]), float(nr[small[0]]))
        n += len(part)
        k = np.asarray(keep(part), np.int64)
        n_unmatched += int((k <= 0).sum())
        part = _take(part, np.flatnonzero(k > 0))
        pool = part if pool is None else _cat([pool, part], path)
        pool = _take(pool, _top_k(pool, np.asarray(keep(pool), np.int64)))
    if n > 1:
        d = np.concatenate(digests)
        ln = np.concatenate(lines)
        _, first_idx, inv = np.unique(d, return_index=True, return_inverse=True)
        dup = np.flatnonzero(first_idx[inv.reshape(-1)] != np.arange(n))
        if len(dup):
            _duplicate(path, {int(ln[i]): int(ln[first_idx[inv.reshape(-1)[i]]]) for i in dup[:64]})
    if gt_distance_mm and n:
        med = float(np.median(np.concatenate(norms)))
        if med * METRES_RATIO <= gt_distance_mm and first_small is not None:
            raise TdofError(f"line {first_small[0]}: translations look like metres: |t| = {first_small[1]:.4g} here "
                            f"and {med:.4g} in the median over {n} rows, while the dataset's objects are about "
                            f"{gt_distance_mm:.0f} mm from the camera; t must be in millimetres", path)
    out = pool if pool is not None else Results(*(np.zeros((0,) + s_, dt) for s_, dt in (
        ((), np.int64), ((), np.int64), ((), np.int64), ((), np.float64), ((3, 3), np.float64), ((3,), np.float64),
        ((), np.float64), ((), np.int64))), path)
    unmeasured = sum(1 for t, _ in times.values() if t == -1)
    if unmeasured:
        out.warnings.append(f"{unmeasured} image(s) report no time (-1): run times will not be summarised")
    out.n_read, out.n_unmatched = n, n_unmatched
    return out


def _duplicate(path: Path, pairs: dict[int, int]) -> None:
    """Raise the duplicate error of the first pair (later line -> earlier line) whose rows are
    really equal (a second pass reads just those rows: digests of 8 bytes may, rarely, collide)."""
    want = set(pairs) | set(pairs.values())
    rows = {}
    for part in iter_rows(path):
        hit = np.flatnonzero(np.isin(part.line, list(want)))
        if len(hit):
            keys = _row_keys(part)
            rows.update({int(part.line[i]): keys[i] for i in hit})
    for later in sorted(pairs):
        a, b = rows.get(later), rows.get(pairs[later])
        if a is not None and b is not None and a.tobytes() == b.tobytes():
            raise TdofError(f"line {later}: duplicates line {pairs[later]} (scene {int(a[0])}, image {int(a[1])}, "
                            f"object {int(a[2])}, same pose)", path)


def parse_rows(lines: Sequence[str], path: Path, first_line: int) -> Results:
    """The rows of ``lines`` (the file's lines from line ``first_line`` on; blank ones skipped)
    parsed, not yet checked as a whole (:func:`read_results` checks them; a reader that streams a
    file in parts checks each part). A TdofError naming the line on a malformed row."""
    ids: list[str] = []
    toks: list[str] = []
    ln: list[int] = []
    counts = (("score", 1), ("R", 9), ("t", 3), ("time", 1))
    for k, raw in enumerate(lines, first_line):
        f = raw.split(",")
        if len(f) != 7:
            if not raw.strip():
                continue
            raise _fail(path, k, f"expected 7 comma-separated fields ({HEADER}), found {len(f)}")
        parts = [f[3].split(), f[4].split(), f[5].split(), f[6].split()]
        if len(parts[0]) != 1 or len(parts[1]) != 9 or len(parts[2]) != 3 or len(parts[3]) != 1:
            name, n = next((nm, c) for (nm, c), p in zip(counts, parts) if len(p) != c)
            got = len(parts[[c[0] for c in counts].index(name)])
            raise _fail(path, k, f"{name} must hold {n} space-separated number{'s' if n > 1 else ''}, found {got}")
        ids += f[:3]
        for p in parts:
            toks += p
        ln.append(k)
    n = len(ln)
    line = np.asarray(ln, np.int64)
    ints = np.array([_id_value(x) for x in ids], dtype=np.int64).reshape(n, 3)
    if (ints < 0).any():
        r, c = np.argwhere(ints < 0)[0]
        got = ids[3 * r + c].strip()
        if ints[r, c] == _TOO_LARGE:
            raise _fail(path, int(line[r]), f"{FIELDS[c]} {got[:30]}{'...' if len(got) > 30 else ''} is too large "
                                            f"for an id (at most {ID_MAX})")
        raise _fail(path, int(line[r]), f"{FIELDS[c]} must be a non-negative integer, got {got!r}")
    try:
        nums = np.array(toks, dtype=np.float64).reshape(n, 14)
    except ValueError:
        for j, x in enumerate(toks):
            if not _is_float(x):
                r, c = divmod(j, 14)
                name = "score" if c == 0 else "R" if c < 10 else "t" if c < 13 else "time"
                raise _fail(path, int(line[r]), f"{name}: {x!r} is not a number") from None
        raise
    bad = ~np.isfinite(nums)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        name = "score" if c == 0 else "R" if c < 10 else "t" if c < 13 else "time"
        raise _fail(path, int(line[r]), f"{name} holds NaN or inf")
    return Results(ints[:, 0].copy(), ints[:, 1].copy(), ints[:, 2].copy(), nums[:, 0].copy(),
                   nums[:, 1:10].reshape(n, 3, 3).copy(), nums[:, 10:13].copy(), nums[:, 13].copy(), line, path)


def _first(mask: np.ndarray) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if len(idx) else None


def check_rows(res: Results) -> None:
    """The row-level checks of a file (numbers, ids, rotations, times, duplicates) on ``res``
    alone: a reader that streams a file checks each part so, and what spans parts itself."""
    _validate(res)


def _validate(res: Results) -> None:
    """Row-level checks shared by files and in-memory rows (see the module docstring)."""
    n = len(res)
    # numbers (rows given in memory have not been checked yet)
    for name, arr in (("score", res.score), ("R", res.R.reshape(n, 9)), ("t", res.t), ("time", res.time)):
        bad = ~np.isfinite(arr.reshape(n, -1)).all(axis=1) if n else np.zeros(0, bool)
        if (i := _first(bad)) is not None:
            raise res.error(i, f"{name} holds NaN or inf")
    for name, arr in (("scene_id", res.scene_id), ("im_id", res.im_id)):
        if (i := _first(arr < 0)) is not None:
            raise res.error(i, f"{name} must be >= 0, got {arr[i]}")
    if (i := _first(res.obj_id < 1)) is not None:
        raise res.error(i, f"obj_id must be >= 1, got {res.obj_id[i]}")
    # rotations
    if n:
        E = np.abs(np.einsum("nij,nkj->nik", res.R, res.R) - np.eye(3)).reshape(n, 9).max(axis=1)
        det = np.linalg.det(res.R)
        if (i := _first((E > ROTATION_TOLERANCE) | (det <= 0))) is not None:
            raise res.error(i, f"R is not a rotation matrix (max |R R^T - I| = {E[i]:.3g}, det = {det[i]:.4g}; "
                               f"tolerance {ROTATION_TOLERANCE:g}, det > 0)")
    # times: -1 = not measured (warning), other negatives are errors, one time per image
    if (i := _first((res.time < 0) & (res.time != -1))) is not None:
        raise res.error(i, f"time must be >= 0 seconds, or -1 when not measured; got {res.time[i]:g}")
    if n:
        img = np.stack([res.scene_id, res.im_id], axis=1)
        _, inv = np.unique(img, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        first = np.full(inv.max() + 1, -1, np.int64)
        order = np.arange(n)
        first[inv[::-1]] = order[::-1]  # first row of each image
        ref = res.time[first[inv]]
        if (i := _first(res.time != ref)) is not None:
            j = first[inv[i]]
            raise res.error(i, f"time {res.time[i]:g} differs from {res.time[j]:g} on line {res.line[j]} for scene "
                               f"{res.scene_id[i]} image {res.im_id[i]}: BOP needs one time per image "
                               f"(the time of the whole image on each of its rows)")
        n_unmeasured = len(np.unique(inv[res.time == -1]))
        if n_unmeasured:
            res.warnings.append(f"{n_unmeasured} image(s) report no time (-1): run times will not be summarised")
    # duplicates: the same object pose twice in one image
    if n > 1:
        key = np.concatenate([np.stack([res.scene_id, res.im_id, res.obj_id], 1).astype(np.float64),
                              res.R.reshape(n, 9), res.t], axis=1)
        key = np.ascontiguousarray(key).view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel()
        _, first_idx, inv = np.unique(key, return_index=True, return_inverse=True)
        dup = first_idx[inv.reshape(-1)] != np.arange(n)
        if (i := _first(dup)) is not None:
            j = first_idx[inv.reshape(-1)[i]]
            raise res.error(i, f"duplicates line {res.line[j]} (scene {res.scene_id[i]}, image {res.im_id[i]}, "
                               f"object {res.obj_id[i]}, same pose)")


def check_against_dataset(res: Results, scene_ids: set[int], images_of: Callable[[int], set[int]],
                          obj_ids: set[int], gt_distance_mm: float | None = None) -> None:
    """Refuse ids the dataset does not have (``scene_ids``: its scenes; ``images_of(scene_id)``:
    the image ids of a scene; ``obj_ids``: its objects) and translations that look like metres
    (``gt_distance_mm``: the median distance of the ground-truth objects from the camera)."""
    scenes = np.array(sorted(scene_ids), dtype=np.int64)
    if (i := _first(~np.isin(res.scene_id, scenes))) is not None:
        raise res.error(i, f"unknown scene_id {res.scene_id[i]} (the dataset's scenes: {_ranges(scenes)})")
    objs = np.array(sorted(obj_ids), dtype=np.int64)
    if (i := _first(~np.isin(res.obj_id, objs))) is not None:
        raise res.error(i, f"unknown obj_id {res.obj_id[i]} (the dataset's objects: {_ranges(objs)})")
    bad_rows = []
    for s in np.unique(res.scene_id):
        rows = np.flatnonzero(res.scene_id == s)
        known = np.fromiter(images_of(int(s)), dtype=np.int64)
        bad = ~np.isin(res.im_id[rows], known)
        if bad.any():
            bad_rows.append(int(rows[np.argmax(bad)]))
    if bad_rows:
        i = min(bad_rows, key=lambda r: res.line[r])
        raise res.error(i, f"scene {res.scene_id[i]} has no image {res.im_id[i]}")
    if gt_distance_mm and len(res):
        norms = np.linalg.norm(res.t, axis=1)
        med = float(np.median(norms))
        if med * METRES_RATIO <= gt_distance_mm:
            i = _first(norms * METRES_RATIO <= gt_distance_mm)
            raise res.error(i, f"translations look like metres: |t| = {norms[i]:.4g} here and {med:.4g} in the median "
                               f"over {len(res)} rows, while the dataset's objects are about {gt_distance_mm:.0f} mm "
                               f"from the camera; t must be in millimetres")


def _ranges(ids: np.ndarray) -> str:
    ids = sorted(int(i) for i in ids)
    if not ids:
        return "none"
    out, start, prev = [], ids[0], ids[0]
    for i in ids[1:] + [None]:
        if i is not None and i == prev + 1:
            prev = i
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if i is not None:
            start = prev = i
    return ", ".join(out)


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------
def _num(x: float) -> str:
    return repr(float(x))


def format_results_csv(rows: Iterable[Sequence]) -> str:
    """The CSV text of (scene_id, im_id, obj_id, score, R (3,3), t (3,) mm, time s) rows
    (time None -> -1); numbers at full precision."""
    out = [HEADER]
    for row in rows:
        if len(row) != 7:
            raise ValueError(f"a results row has 7 values ({HEADER}), got {len(row)}")
        s, im, ob, sc, R, t, tm = row
        R = np.asarray(R, dtype=np.float64).reshape(-1)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if R.size != 9 or t.size != 3:
            raise ValueError(f"R must be (3,3) and t (3,), got {R.size} and {t.size} numbers")
        if not (np.isfinite(R).all() and np.isfinite(t).all() and math.isfinite(float(sc))):
            raise ValueError(f"scene {s} image {im} object {ob}: R, t and score must be finite")
        tm = -1.0 if tm is None else float(tm)
        out.append(f"{int(s)},{int(im)},{int(ob)},{_num(sc)},{' '.join(map(_num, R))},"
                   f"{' '.join(map(_num, t))},{_num(tm)}")
    return "\n".join(out) + "\n"


def write_results_csv(path: str | Path, rows: Iterable[Sequence]) -> Path:
    """Atomically write a BOP results CSV from (scene_id, im_id, obj_id, score, R (3,3),
    t (3,) mm, time s or None) rows. Returns the path."""
    path = Path(path)
    atomic_write_bytes(path, format_results_csv(rows).encode())
    return path


__all__ = ["HEADER", "ID_MAX", "ROTATION_TOLERANCE", "METRES_RATIO", "Results", "check_rows", "iter_rows", "parse_rows", "read_results", "read_top_results", "check_against_dataset",
           "format_results_csv", "write_results_csv"]
