"""A reviewer's corrections of an annotated scene: the append-only journal ``SCENE/work/corrections.jsonl``.

``tdof20 annotate review`` (:mod:`tdof20.review`) writes it; the place and label stages read it,
so a rerun of ``tdof20 annotate`` (resume) and the review's "relabel" label from the corrected
placements and frame verdicts. It lives here, in the annotate layer, because the stages read it.

One JSON object per line, each with ``id`` (1, 2, ...: its place in the journal), ``t`` (UTC, ISO
8601) and ``op``:

==========  =====================================================================================
op          fields
==========  =====================================================================================
place       ``object`` (the object's index in session.json's objects = fits.json's ``index``),
            ``obj_id``, ``T_ref_model`` (16 numbers, row-major: the new pose in the reference
            frame), ``how`` ("nudge", "drag", "snap", "set"), ``detail`` (the nudge's axis and
            amount; the snap's fitness and mean distance; the gates' figures), optionally
            ``cluster`` (the cluster it now stands in, when the reviewer chose it)
assign      ``object``, ``obj_id``, ``cluster`` (the reconstruction's cluster that is this object),
            ``T_ref_model`` (its upright fit in that cluster, the model stage's quick fit)
frames      ``arm``, ``steps`` (a list; ``null`` = the whole arm position), ``verdict``:
            "accept" (label it although it was flagged), "reject" (never label it), "clear";
            with ``object`` (an index, as ``place``) and ``obj_id``: that one object only —
            "reject" (the frames are labelled without it: no gt entry, no masks; it still hides
            what it stands in front of) or "clear"
undo        ``undoes`` (the id of the entry it takes back; the last one not yet taken back)
relabel     a note that label and QA were rerun from the corrections so far (no effect on replay)
==========  =====================================================================================

Every line is written whole: one ``write`` of the encoded line with ``O_APPEND`` under an
``flock``, then ``fsync``, so a crash leaves at most a torn last line, which :func:`read_journal`
leaves out and the next append cuts off (a bad line before the last is an error naming the file
and the line). No entry is ever rewritten: undo is an entry too, and :func:`replay` folds the
entries in order.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdof20.errors import TdofError

__all__ = ["JOURNAL", "OPS", "Corrections", "append_entry", "read_journal", "replay", "undo_target"]

JOURNAL = "corrections.jsonl"
OPS = ("place", "assign", "frames", "undo", "relabel")
REJECTED = "rejected by the reviewer"   # the skip reason of a rejected frame (work/corrections.jsonl)
_HOW = ("nudge", "drag", "snap", "set")
_VERDICTS = ("accept", "reject", "clear")


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _pose(x: Any, where: str) -> list[float]:
    a = np.asarray(x, float) if isinstance(x, (list, tuple, np.ndarray)) else np.zeros(0)
    if a.size != 16 or not np.all(np.isfinite(a)):
        raise TdofError(f"{where}: T_ref_model must be 16 finite numbers (a 4x4 pose, row-major)")
    T = a.reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(R) < 0:
        raise TdofError(f"{where}: T_ref_model is not a rigid pose (rotation and translation, last row 0 0 0 1)")
    return [float(v) for v in a]


def check_entry(e: Any, where: str) -> dict:
    """One journal entry checked (TdofError naming ``where`` otherwise); returns it."""
    if not isinstance(e, dict) or e.get("op") not in OPS:
        raise TdofError(f"{where}: not a correction (op must be one of {', '.join(OPS)})")
    op = e["op"]
    if op in ("place", "assign"):
        if not isinstance(e.get("object"), int) or e["object"] < 0 or not isinstance(e.get("obj_id"), int):
            raise TdofError(f"{where}: '{op}' needs 'object' (an index >= 0) and 'obj_id'")
        e["T_ref_model"] = _pose(e.get("T_ref_model"), where)
        if op == "place" and e.get("how") not in _HOW:
            raise TdofError(f"{where}: 'place' needs 'how' (one of {', '.join(_HOW)})")
        if op == "assign" and (not isinstance(e.get("cluster"), int) or e["cluster"] < 0):
            raise TdofError(f"{where}: 'assign' needs 'cluster' (an index >= 0)")
        if op == "place" and e.get("cluster") is not None and (not isinstance(e["cluster"], int) or e["cluster"] < 0):
            raise TdofError(f"{where}: a 'place' entry's 'cluster' must be an index >= 0")
    elif op == "frames":
        steps = e.get("steps")
        if not isinstance(e.get("arm"), int) or e["arm"] < 0 or e.get("verdict") not in _VERDICTS or not (
                steps is None or (isinstance(steps, list) and all(isinstance(k, int) and k >= 0 for k in steps))):
            raise TdofError(f"{where}: 'frames' needs 'arm', 'steps' (a list, or null for the whole arm) and "
                            f"'verdict' ({', '.join(_VERDICTS)})")
        if e.get("object") is not None and (not isinstance(e["object"], int) or e["object"] < 0
                                            or not isinstance(e.get("obj_id"), int)
                                            or e["verdict"] not in ("reject", "clear")):
            raise TdofError(f"{where}: 'frames' for one object needs 'object' (an index >= 0), 'obj_id' and "
                            f"'verdict' reject or clear")
    elif op == "undo" and not isinstance(e.get("undoes"), int):
        raise TdofError(f"{where}: 'undo' needs 'undoes' (an entry id)")
    return e


def read_journal(work: str | Path) -> list[dict]:
    """The entries of ``work/corrections.jsonl`` in order ([] when there is none). A last line
    without its newline (a write cut short) is left out; any other bad line is a TdofError
    naming the file and the line."""
    path = Path(work) / JOURNAL
    if not path.exists():
        return []
    data = path.read_bytes()
    lines = data.split(b"\n")
    if lines and lines[-1] != b"":     # torn last line: the write never finished
        lines = lines[:-1]
    out = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            e = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise TdofError(f"line {i} is not JSON ({err.msg if hasattr(err, 'msg') else err})", path) from None
        out.append(check_entry(e, f"{path}: line {i}"))
    return out


def append_entry(work: str | Path, entry: dict) -> dict:
    """Append one correction (checked; ``id`` and ``t`` added) to ``work/corrections.jsonl`` and
    return it as written. The file is locked while the next id is read and the line written, so
    two writers never share an id or interleave their lines."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    path = work / JOURNAL
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        entries = read_journal(work)
        data = path.read_bytes()
        if data and not data.endswith(b"\n"):
            # a torn last line (a write cut short, never an entry): cut it off so the new line is whole
            os.ftruncate(fd, data.rfind(b"\n") + 1)
        e = check_entry({"id": (entries[-1]["id"] + 1) if entries else 1, "t": _now(), **entry}, str(path))
        os.write(fd, (json.dumps(e, sort_keys=True) + "\n").encode())
        os.fsync(fd)
        return e
    finally:
        os.close(fd)   # releases the flock


def undo_target(entries: list[dict]) -> dict | None:
    """The entry an undo now takes back: the last correction not yet taken back (None: nothing)."""
    undone = _undone(entries)
    for e in reversed(entries):
        if e["op"] in ("place", "assign", "frames") and e["id"] not in undone:
            return e
    return None


def _undone(entries: list[dict]) -> set[int]:
    return {int(e["undoes"]) for e in entries if e["op"] == "undo"}


@dataclass
class Corrections:
    """The journal folded: what the stages apply."""

    entries: list[dict] = field(default_factory=list)
    placed: dict[int, dict] = field(default_factory=dict)        # object index -> {obj_id, T_ref_model, cluster, how, id}
    arm_verdicts: dict[int, str] = field(default_factory=dict)   # arm -> accept | reject
    frame_verdicts: dict[tuple[int, int], str] = field(default_factory=dict)
    # one object rejected in frames: {object index: obj_id} per arm (every step) and per frame
    arm_objects: dict[int, dict[int, int]] = field(default_factory=dict)
    frame_objects: dict[tuple[int, int], dict[int, int]] = field(default_factory=dict)

    def verdict(self, arm: int, step: int) -> str | None:
        return self.frame_verdicts.get((arm, step), self.arm_verdicts.get(arm))

    def rejected_objects(self, arm: int, step: int) -> dict[int, int]:
        """{object index: obj_id} of the objects rejected in frame (arm, step)."""
        return {**self.arm_objects.get(arm, {}), **self.frame_objects.get((arm, step), {})}

    def placement_key(self) -> dict:
        """What the place stage's result depends on (its fingerprint): the corrected poses."""
        return {str(i): {k: p[k] for k in ("obj_id", "T_ref_model", "cluster")} for i, p in sorted(self.placed.items())}

    def verdict_key(self) -> dict:
        """What the label stage's result depends on: the frame verdicts."""
        key = {"arms": {str(a): v for a, v in sorted(self.arm_verdicts.items())},
               "frames": [[a, k, v] for (a, k), v in sorted(self.frame_verdicts.items())]}
        if self.arm_objects or self.frame_objects:   # (absent when none: older fingerprints stay valid)
            key["objects"] = {"arms": {str(a): sorted(o) for a, o in sorted(self.arm_objects.items()) if o},
                              "frames": [[a, k, sorted(o)] for (a, k), o in sorted(self.frame_objects.items()) if o]}
        return key

    def skip(self, flagged: list, n_arms: int, steps: int) -> list[tuple[int, int, str]]:
        """The frames the label stage skips: registration's ``flagged`` [(arm, step, reason)] less
        those the reviewer accepted, plus those rejected; and, for a frame labelled with objects
        the reviewer rejected in it, ``(arm, step, reason, obj_ids)``: label it without those
        objects (:func:`~tdof20.annotate.label.label_scene`'s ``skip``)."""
        out = [(a, k, r) for a, k, r in flagged if self.verdict(a, k) != "accept"]
        have = {(a, k) for a, k, _ in out}
        for a in range(n_arms):
            for k in range(steps):
                if self.verdict(a, k) == "reject" and (a, k) not in have:
                    out.append((a, k, f"{REJECTED} ({JOURNAL})"))
                    have.add((a, k))
        for a in range(n_arms):
            for k in range(steps):
                objs = self.rejected_objects(a, k)
                if objs and (a, k) not in have:
                    out.append((a, k, f"{REJECTED} ({JOURNAL}): objects {sorted(set(objs.values()))}",
                                tuple(sorted(set(objs.values())))))
        return sorted(out)

    def apply(self, placements: list[dict], failed: list[dict], fits_objects: list[dict],
              score: Any) -> tuple[list[dict], list[dict]]:
        """``placements`` and ``failed`` of the place stage with the reviewer's poses put in: a
        corrected object takes its corrected pose (and cluster), leaves ``failed``, and the gt ids
        follow the objects' order in fits.json. ``score(obj_id, cluster, T)`` gives the figures
        (fitness, rmse_mm, score_mm) of a pose against its cluster, for the summary."""
        if not self.placed:
            return placements, failed
        by_index = {int(p.get("index", i)): p for i, p in enumerate(placements)}
        keep_failed = []
        for f in failed:
            if int(f.get("index", -1)) not in self.placed:
                keep_failed.append(f)
        out = []
        for e in sorted(fits_objects, key=lambda x: int(x["index"])):
            i = int(e["index"])
            if i in self.placed:
                c = self.placed[i]
                cluster = int(c["cluster"]) if c.get("cluster") is not None else int(e["cluster"])
                fitness, rmse, sc = score(int(c["obj_id"]), cluster, np.asarray(c["T_ref_model"], float).reshape(4, 4))
                out.append({"index": i, "obj_id": int(c["obj_id"]), "cluster": cluster,
                            "T_ref_model": list(c["T_ref_model"]), "fitness": fitness, "rmse_mm": rmse,
                            "score_mm": sc, "upright_correction_deg": None,
                            "source": by_index[i].get("source", "models") if i in by_index else "models",
                            "note": f"corrected by the reviewer ({c['how']}, {JOURNAL} entry {c['id']})",
                            "corrected": c["how"]})
            elif i in by_index:
                out.append(dict(by_index[i]))
        for g, p in enumerate(out):
            p["gt_id"] = g
        return out, keep_failed


def replay(entries: list[dict]) -> Corrections:
    """Fold the journal's entries in order (undone ones left out) into :class:`Corrections`."""
    undone = _undone(entries)
    c = Corrections(entries=list(entries))
    for e in entries:
        if e["id"] in undone:
            continue
        op = e["op"]
        if op == "assign":
            c.placed[e["object"]] = {"obj_id": e["obj_id"], "T_ref_model": e["T_ref_model"], "cluster": e["cluster"],
                                     "how": "assign", "id": e["id"]}
        elif op == "place":
            prev = c.placed.get(e["object"], {})
            c.placed[e["object"]] = {"obj_id": e["obj_id"], "T_ref_model": e["T_ref_model"],
                                     "cluster": e["cluster"] if e.get("cluster") is not None else prev.get("cluster"),
                                     "how": e["how"], "id": e["id"]}
        elif op == "frames" and e.get("object") is not None:
            a, i, reject = e["arm"], e["object"], e["verdict"] == "reject"
            if e["steps"] is None:
                for key in [k for k in c.frame_objects if k[0] == a]:
                    c.frame_objects[key].pop(i, None)
                if reject:
                    c.arm_objects.setdefault(a, {})[i] = e["obj_id"]
                else:
                    c.arm_objects.get(a, {}).pop(i, None)
            else:
                for k in e["steps"]:
                    if reject:
                        c.frame_objects.setdefault((a, k), {})[i] = e["obj_id"]
                    else:
                        c.frame_objects.get((a, k), {}).pop(i, None)   # (an arm-wide reject is cleared arm-wide)
        elif op == "frames":
            a, v = e["arm"], e["verdict"]
            if e["steps"] is None:
                for key in [k for k in c.frame_verdicts if k[0] == a]:
                    del c.frame_verdicts[key]
                if v == "clear":
                    c.arm_verdicts.pop(a, None)
                else:
                    c.arm_verdicts[a] = v
            else:
                for k in e["steps"]:
                    if v == "clear":
                        c.frame_verdicts.pop((a, k), None)
                    else:
                        c.frame_verdicts[(a, k)] = v
    return c
