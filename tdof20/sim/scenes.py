"""The 40 TDoF20 scenes of the simulated rig, by name.

``single/<class>`` (e.g. ``single/cube_136``) holds that object alone near the table centre;
``single/NN`` with NN = 01..20, the object id, is an alias of it, normalised to the name by
:func:`normalize_scene_id`. ``multi/00`` .. ``multi/19`` (the release's numbering) each hold 3-5
objects chosen and placed deterministically from the scene number, standing on the turntable top
without touching each other. Each scene has one background sticker. Everything is a pure function
of the scene name, so every machine builds the same scene.

Numeric (BOP) scene ids: ``single/<class>`` -> its object id (1..20), ``multi/NN`` -> 21 + NN
(21..40); the names and numbers are the dataset's (:mod:`tdof20.dataset.naming`, re-exported here).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tdof20.errors import TdofError
from tdof20.geometry import make_T, rotation_matrix
from tdof20.dataset.naming import (MULTI_ID_OFFSET, N_MULTI, VALID_FORMS, normalize_scene_id,  # noqa: F401
                                   parse_scene_id, scene_ids, scene_name, scene_number)
from tdof20.objects import get_object, object_ids
from tdof20.sim.textures import STICKERS

CLEARANCE_MM = 8.0  # free gap between object footprints


@dataclass(frozen=True)
class Placement:
    """One object on the turntable: pose of the model in the table frame (angle 0)."""

    obj_id: int
    T_table_obj: np.ndarray  # (4,4), mm


@dataclass(frozen=True)
class SceneSpec:
    scene_id: str
    placements: tuple[Placement, ...]
    sticker: str
    sticker_seed: int

    @property
    def obj_ids(self) -> list[int]:
        return [p.obj_id for p in self.placements]

    @property
    def kind(self) -> str:
        return self.scene_id.split("/")[0]

    @property
    def number(self) -> int:
        """The object id of a single-object scene, NN of multi/NN."""
        return parse_scene_id(self.scene_id)[1]

    @property
    def numeric_id(self) -> int:
        """The scene's numeric (BOP) id: 1..20 for single/<class>, 21 + NN for multi/NN."""
        return scene_number(self.scene_id)


def _place(obj_id: int, xy, yaw: float) -> Placement:
    obj = get_object(obj_id)
    R = rotation_matrix([0, 0, 1], yaw)
    return Placement(obj_id, make_T(R, [xy[0], xy[1], -obj.z_min]))


def get_scene(scene_id: str, table_radius: float = 250.0) -> SceneSpec:
    """The scene called ``scene_id`` ('single/goblet_180', its alias 'single/06', 'multi/08', ...);
    its ``scene_id`` is the canonical name. Unknown names -> TdofError."""
    return _get_scene(normalize_scene_id(scene_id), float(table_radius))


@lru_cache(maxsize=None)
def _get_scene(scene_id: str, table_radius: float) -> SceneSpec:
    kind, n = parse_scene_id(scene_id)
    rng = np.random.default_rng(1000 * (kind == "multi") + n)
    sticker = STICKERS[int(rng.integers(len(STICKERS)))]
    sticker_seed = int(rng.integers(1 << 30))
    if kind == "single":
        r = rng.uniform(0, 30)
        a = rng.uniform(0, 2 * np.pi)
        placements = (_place(n, (r * np.cos(a), r * np.sin(a)), rng.uniform(0, 2 * np.pi)),)
        return SceneSpec(scene_id, placements, sticker, sticker_seed)

    n_objects = int(rng.integers(3, 6))
    order = [int(i) for i in rng.permutation(object_ids())]
    chosen: list[tuple[int, np.ndarray, float]] = []  # (obj_id, xy, footprint radius)
    for obj_id in order:
        if len(chosen) == n_objects:
            break
        rad = get_object(obj_id).footprint_radius
        for _ in range(200):  # rejection sampling of a free spot on the table top
            r = np.sqrt(rng.uniform(0, 1)) * (table_radius - rad - CLEARANCE_MM)
            if r < 0:
                break
            a = rng.uniform(0, 2 * np.pi)
            xy = np.array([r * np.cos(a), r * np.sin(a)])
            if all(np.linalg.norm(xy - p) > rad + pr + CLEARANCE_MM for _, p, pr in chosen):
                chosen.append((obj_id, xy, rad))
                break
    if len(chosen) < 3:  # pragma: no cover - the fixed catalog always fits three
        raise RuntimeError(f"could not place three objects in {scene_id}")
    placements = tuple(_place(i, xy, rng.uniform(0, 2 * np.pi)) for i, xy, _ in chosen)
    return SceneSpec(scene_id, placements, sticker, sticker_seed)
