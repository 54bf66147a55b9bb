"""What a scored submission's result may show, to its owner, to the public and on the leaderboard.

The worker stores the scorer's full summary (every cell to 10 decimals). Shown as stored, one
estimate for one target of a test part gives that target's exact error: with every other target
left without an estimate, an object's ADD(S) AUC is ``(1 - e / 100 mm) / n``. :func:`disclose` is
the one function that turns the stored result into what may leave the server; the submissions
module applies it to every result it returns (API and pages), the leaderboard ranks by what it
shows, and the results page's figures are drawn from its output alone (:mod:`tdof20.server.figures`).

The rule for a test part (docs/server.md, "What the scores can tell"):

- A shown cell (an object, a scene, all targets pooled, the mean over objects) of ``n`` targets is
  given at a step ``q`` of :data:`STEPS` (0.1 % ... 5 %), the finest with ``n * q >= K`` (:data:`K`
  = 10): changing one target's estimate, whatever it is, moves the exact value by at most ``1 / n
  <= q / K``, a tenth of a step. The mean over ``N`` objects counts as ``N * min(n_o)`` targets (one
  target moves it by ``1 / (N n_o)``). A cell with fewer than :data:`MIN_TARGETS` (``K / 5 %`` =
  200) targets is withheld, with the reason.
- Each shown value is rounded with a dither: ``q * round(x / q + v)``, ``v`` uniform in
  [-1/2, 1/2), drawn from a keyed hash (HMAC-SHA256 with the server's secret key, the
  submission's uid, the cell and the metric). Without it a deterministic rounding tells one bit per
  cell per submission exactly where the attacker can bring the rest of the cell to a rounding
  boundary; with it a value is the upper step with probability ``frac(x / q)`` (unbiased: its mean
  is ``x``), so one target, moving ``x`` by at most ``q / K``, moves that probability by at most
  ``1 / K``: a noisy, small fraction of a bit per cell and submission that only many submissions
  average out. The same submission always shows the same values (the key and uid are fixed); the
  key never leaves the server (the database's ``meta`` table, :func:`server_key`).
- Exact 0 and 1 stay exact (a value on the grid is never moved).

The same rule covers the condition cells (occlusion level, distance, symmetric or not: each a set
of targets pooled, shown by its own count). Where a protocol has a held-back part, only the public
part's cells are shown until the operator reveals the private part's; the whole test set's never
before (with the public part's, it would give the private part's by subtraction).

A validation part (public labels) is shown whole, per-image errors included.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
import weakref
from typing import Any

STEPS = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05)  # fractions: 0.1 % ... 5 %
K = 10  # a cell's step is at least K / n: one target moves its exact value by at most q / K
MIN_TARGETS = math.ceil(K / STEPS[-1])  # 200: fewer targets and even the coarsest step is too fine
KEY_NAME = "disclosure_key"  # the row of the meta table holding the server's secret (hex)
RULE = (f"test part: each cell at a step of 0.1-5 % (at least {K} / its targets: one target moves it by "
        f"at most a tenth of a step), rounded with a secret dither; cells under {MIN_TARGETS} targets "
        "withheld (docs/server.md)")
VAL_RULE = "validation part: its labels are public, so every figure is shown in full"


def step_for(n: int) -> float | None:
    """The step a cell of ``n`` targets is shown at, None when it is withheld."""
    for q in STEPS:
        if n * q >= K - 1e-9:
            return q
    return None


def _dither(key: bytes, uid: str, cell: str, metric: str) -> float:
    """A value in [-1/2, 1/2) that only the key's holder can compute (HMAC-SHA256)."""
    h = hmac.new(key, f"{uid}\x00{cell}\x00{metric}".encode(), hashlib.sha256).digest()
    return int.from_bytes(h[:8], "big") / 2.0**64 - 0.5


def _shown(x: Any, q: float, v: float) -> float | None:
    if not isinstance(x, (int, float)) or not math.isfinite(x):
        return None
    k = round(float(x) / q + v)
    return round(min(1.0, max(0.0, k * q)), 6)


def _cell(stored: dict, n_eff: int, key: bytes, uid: str, cell: str, reason: str) -> dict:
    """One cell as shown: its count, its step and its values (or None and why it is withheld)."""
    n = stored.get("n")
    out: dict[str, Any] = {"n": n}
    q = step_for(n_eff)
    metrics = [k for k in stored if k != "n"]
    if q is None:
        out.update({k: None for k in metrics})
        out["withheld"] = reason
        return out
    out.update({k: _shown(stored[k], q, _dither(key, uid, cell, k)) for k in metrics})
    out["step"] = q
    return out


def _summary(sm: dict, key: bytes, uid: str, prefix: str = "") -> dict[str, Any]:
    """A stored summary ({"objects", "scenes", "all", "mean", "proj_px"}) as the rule shows it."""
    objects = {o: c for o, c in (sm.get("objects") or {}).items() if isinstance(c, dict)}
    small = f"fewer than {MIN_TARGETS} targets"
    shown: dict[str, Any] = {}
    shown["objects"] = {o: _cell(c, int(c.get("n") or 0), key, uid, f"{prefix}object:{o}", small)
                        for o, c in objects.items()}
    shown["scenes"] = {s: _cell(c, int(c.get("n") or 0), key, uid, f"{prefix}scene:{s}", small)
                       for s, c in (sm.get("scenes") or {}).items() if isinstance(c, dict)}
    if isinstance(sm.get("all"), dict):
        shown["all"] = _cell(sm["all"], int(sm["all"].get("n") or 0), key, uid, f"{prefix}all", small)
    if isinstance(sm.get("mean"), dict):
        counts = [int(c.get("n") or 0) for c in objects.values() if (c.get("n") or 0) > 0]
        n_eff = len(counts) * min(counts) if counts else 0  # one target moves the mean by 1 / (N n_o)
        why = small + " in its smallest object times the objects" if counts else \
            "its objects' target counts are not stored (scored by an older server)"
        shown["mean"] = _cell(sm["mean"], n_eff, key, uid, f"{prefix}mean", why)
    if "proj_px" in sm:
        shown["proj_px"] = sm["proj_px"]  # the 2D threshold: the dataset's, public
    return shown


def _conditions(cond: Any, key: bytes, uid: str, prefix: str = "") -> dict[str, dict]:
    """Condition cells ({kind: {bin: cell}}: occlusion, distance, symmetry), each by its own target
    count like an object's or a scene's (a bin is a set of targets, pooled)."""
    small = f"fewer than {MIN_TARGETS} targets"
    return {kind: {b: _cell(c, int(c.get("n") or 0), key, uid, f"{prefix}cond:{kind}:{b}", small)
                   for b, c in bins.items() if isinstance(c, dict)}
            for kind, bins in (cond or {}).items() if isinstance(bins, dict)}


def disclose(result: dict | None, part: str, key: bytes, uid: str, held: dict | None = None) -> dict | None:
    """What may be shown of a stored ``result`` (the worker's: ``summary``, ``conditions``,
    ``parts``, ``warnings``, names, and ``per_image`` for a validation part) of submission ``uid`` on
    ``part`` (test or val).

    A validation result comes back whole. A test result keeps its warnings and names, loses any
    per-image data, and its summary and condition cells are the rule's (module docstring): every
    cell keeps its target count ``n`` and gets ``step`` and its metrics at that step, or
    ``withheld`` (the reason) and None for each metric. ``result["disclosure"]`` says which rule applied.

    ``held``: the protocol's held-back part ({"revealed": when, or None}) where it has one. Then the
    summary and conditions shown are the public part's alone (no cell of the whole test set: with
    the public part's it would give the private part's); the private part's (``private``) only once
    the operator revealed it, else only that it exists. A result scored before the part was chosen
    (no ``parts``) shows no figure until it is scored again."""
    if result is None:
        return None
    if part == "val":
        return {**result, "disclosure": {"part": "val", "rule": VAL_RULE}}
    out = {k: v for k, v in result.items() if k not in ("summary", "per_image", "plots", "conditions", "parts")}
    disc: dict[str, Any] = {"part": "test", "rule": RULE, "steps": list(STEPS), "k": K, "min_targets": MIN_TARGETS}
    if held is None:
        out["summary"] = _summary(result.get("summary") or {}, key, uid)
        out["conditions"] = _conditions(result.get("conditions"), key, uid)
    else:
        parts = result.get("parts") if isinstance(result.get("parts"), dict) else None
        disc["held_back"] = True
        disc["revealed"] = bool(held.get("revealed"))
        if parts is None:
            out["summary"] = {"withheld": "scored before this protocol's test images were split into a public and "
                                          "a held-back part: shown once it is scored again"}
            out["conditions"] = {}
        else:
            pub = parts.get("public") or {}
            out["summary"] = _summary(pub.get("summary") or {}, key, uid, "public:")
            out["conditions"] = _conditions(pub.get("conditions"), key, uid, "public:")
            if held.get("revealed"):
                priv = parts.get("private") or {}
                out["private"] = {"summary": _summary(priv.get("summary") or {}, key, uid, "private:"),
                                  "conditions": _conditions(priv.get("conditions"), key, uid, "private:")}
    out["disclosure"] = disc
    return out


_KEYS: "weakref.WeakKeyDictionary[Any, bytes]" = weakref.WeakKeyDictionary()


def server_key(engine) -> bytes:
    """The server's secret dither key: the meta table's :data:`KEY_NAME` row, made (32 random bytes)
    by the first process that needs it; every server and worker sharing the database reads the same."""
    if engine in _KEYS:
        return _KEYS[engine]
    from sqlalchemy import insert, select
    from sqlalchemy.exc import IntegrityError

    from tdof20.server.db import meta

    def read() -> str | None:
        with engine.begin() as c:
            return c.execute(select(meta.c.value).where(meta.c.key == KEY_NAME)).scalar()

    value = read()
    if value is None:
        try:
            with engine.begin() as c:
                c.execute(insert(meta).values(key=KEY_NAME, value=secrets.token_hex(32)))
        except IntegrityError:
            pass  # another process made it first
        value = read()
    _KEYS[engine] = bytes.fromhex(value)
    return _KEYS[engine]


__all__ = ["K", "KEY_NAME", "MIN_TARGETS", "RULE", "STEPS", "VAL_RULE", "disclose", "server_key", "step_for"]
