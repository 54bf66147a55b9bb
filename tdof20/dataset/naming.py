"""TDoF20's scene names and numeric (BOP) scene ids, as released.

``single/<class>`` (e.g. ``single/cube_136``; alias ``single/NN`` with NN = 01..20, the object id)
and ``multi/00`` .. ``multi/19``. Numeric ids: ``single/<class>`` -> its object id (1..20),
``multi/NN`` -> 21 + NN (21..40). The simulated rig builds its scenes from these names
(:mod:`tdof20.sim.scenes`); splits, the importer and reproduce name scenes with them.
"""

from __future__ import annotations

import re

import numpy as np

from tdof20.errors import TdofError
from tdof20.objects import object_names

N_MULTI = 20  # multi/00 .. multi/19
MULTI_ID_OFFSET = 21  # multi/NN has the numeric scene id 21 + NN
VALID_FORMS = "single/<class name> (e.g. single/cube_136), single/01..single/20 (object id) or multi/00..multi/19"


def scene_ids() -> list[str]:
    """The 40 scene names: single/<class> in object id order, then multi/00 .. multi/19."""
    return [f"single/{name}" for name in object_names().values()] + [f"multi/{i:02d}" for i in range(N_MULTI)]


def parse_scene_id(scene_id: str) -> tuple[str, int]:
    """('single', object id) or ('multi', NN) of a scene name or alias; unknown -> one-line TdofError."""
    s = str(scene_id)
    kind, _, rest = s.partition("/")
    names = object_names()
    if kind == "single":
        if re.fullmatch(r"\d{2}", rest) and int(rest) in names:
            return "single", int(rest)
        for obj_id, name in names.items():
            if rest == name:
                return "single", obj_id
    elif kind == "multi" and re.fullmatch(r"\d{2}", rest) and int(rest) < N_MULTI:
        return "multi", int(rest)
    raise TdofError(f"unknown scene {s!r} (valid: {VALID_FORMS})")


def normalize_scene_id(scene_id: str) -> str:
    """The scene's canonical name: 'single/07' -> 'single/handle_cup_280'; names pass unchanged."""
    kind, n = parse_scene_id(scene_id)
    return f"single/{object_names()[n]}" if kind == "single" else f"multi/{n:02d}"


def scene_number(scene_id: str) -> int:
    """Numeric (BOP) scene id: 'single/cube_136' (or 'single/01') -> 1, 'multi/00' -> 21, 'multi/19' -> 40."""
    kind, n = parse_scene_id(scene_id)
    return n if kind == "single" else MULTI_ID_OFFSET + n


def scene_name(number: int) -> str:
    """The scene name of a numeric scene id: 1 -> 'single/cube_136', 21 -> 'multi/00'."""
    names = object_names()
    if isinstance(number, (int, np.integer)) and not isinstance(number, bool):
        k = int(number)
        if k in names:
            return f"single/{names[k]}"
        if 0 <= k - MULTI_ID_OFFSET < N_MULTI:
            return f"multi/{k - MULTI_ID_OFFSET:02d}"
    raise TdofError(f"unknown scene id {number!r} (valid: 1-{len(names)} for single/<class>, "
                    f"{MULTI_ID_OFFSET}-{MULTI_ID_OFFSET + N_MULTI - 1} for multi/00..multi/{N_MULTI - 1:02d})")
