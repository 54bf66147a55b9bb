"""One scored result as the tables take it (:class:`Entry`), and how the tables print a value.

    e = Entry("PVNet", "pvnet", "hard", score_dict)
    e.value("add_s")            # the mean over objects; e.value("add_s", obj_id) one object's
    pct(0.505)                  # '50.50'
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from tdof20.errors import TdofError

SPLITS = ("simple", "hard")
MISSING = "—"
ORACLE = "oracle masks"


@dataclass(frozen=True)
class Entry:
    """One scored result. label: the column title ("HFF6DoF", "HFF6DoF 3D voting + LSQ"); method:
    the registry's name ('hff6dof', 'pvnet', ...); split: 'simple' | 'hard'; scores: the dict of
    :func:`~tdof20.scoring.scoring.score`; oracle_masks: ground-truth masks picked the object
    pixels; note: a short remark printed under the table."""

    label: str
    method: str
    split: str
    scores: Mapping[str, Any]
    oracle_masks: bool = False
    note: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise TdofError(f"result '{self.label}': split must be simple or hard, got '{self.split}'")
        if not isinstance(self.scores, Mapping) or "objects" not in self.scores or "mean" not in self.scores:
            raise TdofError(f"result '{self.label}' ({self.split}): not a score dict (needs 'objects' and 'mean')")

    def value(self, key: str, obj_id: int | None = None) -> float | None:
        """The score ``key`` of one object (None: the mean over objects); None where absent."""
        d = self.scores["mean"] if obj_id is None else self.scores["objects"].get(str(int(obj_id)))
        if not d or d.get("n", 1) == 0:
            return None
        v = d.get(key)
        return None if v is None else float(v)

    @property
    def title(self) -> str:
        return f"{self.label} · {self.split}" + (f" ({ORACLE})" if self.oracle_masks else "")


def pct(v: float | None, digits: int = 2) -> str:
    """A fraction as a percentage with ``digits`` decimals; "—" for none."""
    return MISSING if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.{digits}f}"


def csv_text(rows: Sequence[Sequence[Any]]) -> str:
    """Rows as CSV text."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for r in rows:
        w.writerow(["" if v is None else v for v in r])
    return buf.getvalue()


def signed(v: float | None) -> str:
    """A difference of fractions in percentage points, with its sign; "—" for none."""
    return MISSING if v is None else f"{100 * v:+.2f}"
