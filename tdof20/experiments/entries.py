"""One scored result as the tables take it (:class:`Entry`), and how the tables print a value.

    e = Entry("PVNet", "pvnet", "hard", score_dict)
    e.value("add_s")            # the mean over objects; e.value("add_s", obj_id) one object's
    pct(0.505)                  # '50.50'
    e = Entry("PVNet", "pvnet", "hard", over_seeds([s0, s1]))   # one row trained with two seeds
    e.value("add_s"), e.spread("add_s")                         # the mean over seeds, its half-range
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

    @property
    def seeds(self) -> list:
        """The seeds the row was trained with (one unnamed seed for a single score dict)."""
        return list(self.scores.get("seeds") or [None])

    def spread(self, key: str, obj_id: int | None = None) -> float | None:
        """The spread over seeds of :meth:`value` (half the range: max - min over 2); None with
        one seed or no value."""
        if len(self.seeds) < 2 or self.value(key, obj_id) is None:
            return None
        sp = self.scores.get("spread") or {}
        d = sp.get("mean") if obj_id is None else (sp.get("objects") or {}).get(str(int(obj_id)))
        v = (d or {}).get(key)
        return None if v is None else float(v)

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


def mean_spread(dicts: Sequence[Mapping]) -> tuple[dict, dict]:
    """Per numeric key of score dicts (one per seed): the mean over the dicts holding a value, and
    the half-range; "n" (targets) the largest."""
    mean, spread = {}, {}
    keys = dict.fromkeys(k for d in dicts for k in d)
    for k in keys:
        vals = [d.get(k) for d in dicts]
        if k == "n":
            mean[k] = max(int(v or 0) for v in vals)
            continue
        num = [float(v) for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)
               and not math.isnan(float(v))]
        if num and len(num) == len([v for v in vals if v is not None]):
            mean[k] = sum(num) / len(num)
            spread[k] = (max(num) - min(num)) / 2
    return mean, spread


def over_seeds(scores: Sequence[Mapping], seeds: Sequence[Any] | None = None) -> dict:
    """One row's score dicts, one per seed, as one score dict: "mean" and "objects" the means over
    the seeds, "spread" ({"mean", "objects"}) their half-ranges, "seeds", "per_seed" (each seed's
    mean ADD(S) and 2D projection), the accuracy curves averaged (where every seed has them on the
    same thresholds), "proj_px" (the 2D projection threshold, where every seed's score names the
    same), "oracle_masks" (any seed's) and the seeds' "budget"s."""
    if not scores:
        raise TdofError("no score to combine over seeds")
    seeds = list(seeds) if seeds is not None else [s.get("seed", i) for i, s in enumerate(scores)]
    mean, spread = mean_spread([s["mean"] for s in scores])
    objs, obj_spread = {}, {}
    for o in dict.fromkeys(k for s in scores for k in s["objects"]):
        present = [s["objects"][o] for s in scores if o in s["objects"]]
        objs[o], obj_spread[o] = mean_spread(present)
    out: dict = {"mean": mean, "objects": objs, "spread": {"mean": spread, "objects": obj_spread},
                 "seeds": seeds, "per_seed": {str(k): {"add_s": s["mean"].get("add_s"),
                                                       "proj2d": s["mean"].get("proj2d")}
                                              for k, s in zip(seeds, scores)},
                 "oracle_masks": any(bool(s.get("oracle_masks")) for s in scores)}
    px = {s.get("proj_px") for s in scores}
    if len(px) == 1 and None not in px:
        out["proj_px"] = px.pop()
    if all(s.get("budget") for s in scores):
        out["budget"] = [s["budget"] for s in scores]
    curves = [s.get("curves") or {} for s in scores]
    avg = {}
    for k in ("add_s", "proj2d"):
        cs = [c.get(k) for c in curves]
        if all(cs) and all(c["x"] == cs[0]["x"] for c in cs):
            avg[k] = {"x": cs[0]["x"], "y": [sum(v) / len(v) for v in zip(*(c["y"] for c in cs))]}
    if avg:
        out["curves"] = avg
    for k in ("note", "method", "label", "split"):
        if k in scores[0]:
            out[k] = scores[0][k]
    return out


def pm(v: float | None, spread: float | None, digits: int = 2) -> str:
    """A fraction as a percentage, with "± half-range" over seeds where there is one."""
    return pct(v, digits) + ("" if spread is None or v is None else f" ± {100 * spread:.{digits}f}")


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
