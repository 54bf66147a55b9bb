"""The strict checks of an uploaded results file, streamed: the file is read part by part
(:func:`tdof20.dataset.results.iter_rows`, 256 KiB of text at a time), each part gets the
reader's row checks and the dataset's id checks, and what spans parts is kept small — an 8-byte
digest and the line of each row (duplicates), |t| of each row (the metres check's median), one time
per image of the dataset (one time per image). Memory: about 24 bytes a row beyond one part, so a
40 MB file costs the server a few MB, not the gigabytes of parsing it whole. The messages are the
reader's (:func:`~tdof20.dataset.results.read_results`), each naming the line of the first problem
in file order."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tdof20.dataset.results import METRES_RATIO, check_against_dataset, check_rows, iter_rows
from tdof20.errors import TdofError
from tdof20.server.facts import DatasetFacts


PART_BYTES = 256 * 1024  # text parsed at once (~1,000 rows: a few MB of Python objects at the peak)


@dataclass
class Checked:
    """What the checks learnt of a file that passed them."""

    n_rows: int
    warnings: list[str] = field(default_factory=list)


def _keys(part) -> np.ndarray:
    n = len(part)
    return np.ascontiguousarray(np.concatenate([np.stack([part.scene_id, part.im_id, part.obj_id], 1).astype(np.float64),
                                                part.R.reshape(n, 9), part.t], axis=1))


def _digests(keys: np.ndarray) -> np.ndarray:
    return np.array([int.from_bytes(hashlib.blake2b(k.tobytes(), digest_size=8).digest(), "little")
                     for k in keys], dtype=np.uint64)


def check_file(path: Path, facts: DatasetFacts, split: str) -> Checked:
    """Check the results file at ``path`` as :meth:`DatasetFacts.check` does, streamed (see the
    module docstring); a TdofError naming the line of the first problem."""
    del split  # (the ids are the dataset's, whichever protocol: what matches no target is ignored)
    path = Path(path)
    times: dict[tuple[int, int], tuple[float, int]] = {}  # image -> (time, first line); bounded by the dataset
    digests, lines, norms = [], [], []
    first_small = None  # (line, |t|) of the first row whose |t| could be metres
    gt = facts.train_distance_mm
    n = 0
    for part in iter_rows(path, PART_BYTES):
        if not len(part):
            continue
        check_rows(part)
        check_against_dataset(part, facts.scene_ids, lambda s: facts.images[s], facts.obj_ids, None)
        for s, im, t, ln in zip(part.scene_id.tolist(), part.im_id.tolist(), part.time.tolist(), part.line.tolist()):
            seen = times.get((s, im))
            if seen is None:
                times[(s, im)] = (t, ln)
            elif seen[0] != t:
                raise TdofError(f"line {ln}: time {t:g} differs from {seen[0]:g} on line {seen[1]} for scene {s} "
                                f"image {im}: BOP needs one time per image (the time of the whole image on each of "
                                "its rows)", path)
        digests.append(_digests(_keys(part)))
        lines.append(part.line.copy())
        nr = np.linalg.norm(part.t, axis=1)
        norms.append(nr)
        if gt and first_small is None:
            small = np.flatnonzero(nr * METRES_RATIO <= gt)
            if len(small):
                first_small = (int(part.line[small[0]]), float(nr[small[0]]))
        n += len(part)
    if n > 1:
        d = np.concatenate(digests)
        ln = np.concatenate(lines)
        _, first_idx, inv = np.unique(d, return_index=True, return_inverse=True)
        dup = np.flatnonzero(first_idx[inv.reshape(-1)] != np.arange(n))
        if len(dup):
            _duplicate(path, {int(ln[i]): int(ln[first_idx[inv.reshape(-1)[i]]]) for i in dup[:64]})
    if gt and n:
        med = float(np.median(np.concatenate(norms)))
        if med * METRES_RATIO <= gt and first_small is not None:
            raise TdofError(f"line {first_small[0]}: translations look like metres: |t| = {first_small[1]:.4g} here "
                            f"and {med:.4g} in the median over {n} rows, while the dataset's objects are about "
                            f"{gt:.0f} mm from the camera; t must be in millimetres", path)
    warnings = []
    unmeasured = sum(1 for t, _ in times.values() if t == -1)
    if unmeasured:
        warnings.append(f"{unmeasured} image(s) report no time (-1): run times will not be summarised")
    return Checked(n, warnings)


def _duplicate(path: Path, pairs: dict[int, int]) -> None:
    """Raise the duplicate error of the first pair (later line -> earlier line) whose rows are
    really equal (a second pass reads just those rows: digests of 8 bytes may, rarely, collide)."""
    want = set(pairs) | set(pairs.values())
    rows = {}
    for part in iter_rows(path):
        hit = np.flatnonzero(np.isin(part.line, list(want)))
        if len(hit):
            keys = _keys(part)
            rows.update({int(part.line[i]): keys[i] for i in hit})
    for later in sorted(pairs):
        a, b = rows.get(later), rows.get(pairs[later])
        if a is not None and b is not None and a.tobytes() == b.tobytes():
            raise TdofError(f"line {later}: duplicates line {pairs[later]} (scene {int(a[0])}, image {int(a[1])}, "
                            f"object {int(a[2])}, same pose)", path)


__all__ = ["Checked", "check_file"]
