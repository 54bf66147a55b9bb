"""The 40 TDoF20 scenes of the simulated rig, by name.

``single/NN`` holds object NN alone near the table centre; ``multi/NN`` holds 3-5 objects chosen
and placed deterministically from the scene number, standing on the turntable top without
touching each other. Each scene has one background sticker. Everything is a pure function of the
scene name, so every machine builds the same scene.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tdof20.errors import TdofError
from tdof20.geometry import make_T, rotation_matrix
from tdof20.objects import get_object, object_ids
from tdof20.sim.textures import STICKERS

SCENE_RE = re.compile(r"^(single|multi)/(\d{2})$")
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
        return int(self.scene_id.split("/")[1])


def scene_ids() -> list[str]:
    return [f"single/{i:02d}" for i in range(1, 21)] + [f"multi/{i:02d}" for i in range(1, 21)]


def parse_scene_id(scene_id: str) -> tuple[str, int]:
    m = SCENE_RE.match(str(scene_id))
    if not m or not 1 <= int(m.group(2)) <= 20:
        raise TdofError(f"unknown scene '{scene_id}' (valid: single/01..single/20, multi/01..multi/20)")
    return m.group(1), int(m.group(2))


def _place(obj_id: int, xy, yaw: float) -> Placement:
    obj = get_object(obj_id)
    R = rotation_matrix([0, 0, 1], yaw)
    return Placement(obj_id, make_T(R, [xy[0], xy[1], -obj.z_min]))


@lru_cache(maxsize=None)
def get_scene(scene_id: str, table_radius: float = 250.0) -> SceneSpec:
    """The scene called ``scene_id`` ('single/07', 'multi/08', ...). Unknown names -> TdofError."""
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
