"""The simulated rig gets the lab: what a real lab adds to a clean turntable.

- **Clutter**: static things beside the turntable that do not turn with it (a cabinet, a
  monitor, a cardboard box, a back wall close by). They are opaque parts of the static world:
  seen in colour and in depth in both phases, hiding objects where the geometry says so, and
  never in ``truth/`` as objects. Presets are placed relative to the turntable's edge and axis
  (:data:`CLUTTER`), so they follow a changed :class:`~tdof20.sim.rig.RigLayout`.
- **Table motion** (:class:`TableMotion`): the turntable turning counter-clockwise or clockwise
  seen from above, and a step-angle error: the table stands at ``nominal + e`` with ``e``
  uniform in ``[-jitter, jitter]``, drawn per visit (phase, arm position, step).
- **Hand-eye error** (:func:`hand_eye_offset`): the camera really sits at
  ``T_tcp_cam @ offset``, a rigid offset of exactly ``error_mm`` and ``error_deg`` in a seeded
  random direction, while the session records the nominal calibration.

Everything is a pure function of its arguments (and the seed): resuming a capture gives the
same table angles and the same mount.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # imported where a mesh is built: importing the lab (as the CLI does) stays light
    import trimesh

from tdof20.formats.session import TURN_DIRECTIONS as DIRECTIONS
from tdof20.geometry import make_T, rotation_matrix

PHASES = ("transparent", "opaque")


# ------------------------------------------------------------------------------------ table
@dataclass(frozen=True)
class TableMotion:
    """How the simulated table really moves when told to go to a nominal angle (degrees)."""

    direction: str = "ccw"        # "ccw" | "cw", seen from above
    jitter_deg: float = 0.0       # step-angle error bound: e ~ U[-jitter, jitter] per visit
    seed: int = 0

    def __post_init__(self):
        if self.direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {self.direction!r}")
        if not self.jitter_deg >= 0:
            raise ValueError(f"jitter_deg must be >= 0, got {self.jitter_deg}")

    @property
    def is_nominal(self) -> bool:
        return self.direction == "ccw" and self.jitter_deg == 0

    def error(self, phase: str, arm: int, nominal_deg: float) -> float:
        """The step-angle error (deg) of one visit, deterministic for (seed, phase, arm, angle)."""
        if self.jitter_deg == 0:
            return 0.0
        key = int(round(float(nominal_deg) * 1000)) % 360000
        rng = np.random.default_rng([int(self.seed), 7301, PHASES.index(phase), int(arm), key])
        return float(rng.uniform(-self.jitter_deg, self.jitter_deg))

    def actual(self, phase: str, arm: int, nominal_deg: float) -> float:
        """The table's physical angle (deg, counter-clockwise from above, the renderer's sense)
        when it was told ``nominal_deg``: ``±(nominal + error)``, minus for a clockwise table."""
        if self.is_nominal:
            return nominal_deg
        a = float(nominal_deg) + self.error(phase, arm, nominal_deg)
        return -a if self.direction == "cw" else a


# ------------------------------------------------------------------------------------ hand-eye
def hand_eye_offset(error_mm: float, error_deg: float, seed: int = 0) -> np.ndarray:
    """(4,4) rigid offset in the camera frame: a rotation by exactly ``error_deg`` about a seeded
    random axis and a translation of exactly ``error_mm`` in a seeded random direction. The true
    mount is ``T_tcp_cam @ offset``; identity for zero errors."""
    if error_mm == 0 and error_deg == 0:
        return np.eye(4)
    rng = np.random.default_rng([int(seed), 4242])
    axis = rng.standard_normal(3)
    tdir = rng.standard_normal(3)
    R = rotation_matrix(axis, np.radians(error_deg)) if error_deg else np.eye(3)
    return make_T(R, float(error_mm) * tdir / np.linalg.norm(tdir))


def true_hand_eye(T_tcp_cam: np.ndarray, error_mm: float, error_deg: float, seed: int = 0) -> np.ndarray:
    """The camera mount the simulator renders with, given the recorded (nominal) one."""
    T = np.asarray(T_tcp_cam, float)
    if error_mm == 0 and error_deg == 0:
        return T.copy()
    return T @ hand_eye_offset(error_mm, error_deg, seed)


def twin_offsets(T_table_objs: list[np.ndarray], centres: list[np.ndarray], error_mm: float, error_deg: float,
                 seed: int = 0) -> list[np.ndarray] | None:
    """Where each opaque twin really stands: a table-frame offset D per object (T_table_twin =
    D @ T_table_obj), a move of ``error_mm`` along the table top in a seeded direction and a turn
    of ``error_deg`` (seeded sign) about the vertical axis through the object's centre (model
    frame ``centres``); None for twins exactly in their slots."""
    if error_mm == 0 and error_deg == 0:
        return None
    rng = np.random.default_rng([int(seed), 77])
    out = []
    for T, c in zip(T_table_objs, centres):
        phi = rng.uniform(0, 2 * np.pi)
        turn = np.radians(error_deg) * rng.choice([-1.0, 1.0])
        p = np.asarray(T, float)[:3, :3] @ np.asarray(c, float) + np.asarray(T, float)[:3, 3]
        ct, st = np.cos(turn), np.sin(turn)
        D = np.eye(4)
        D[:2, :2] = [[ct, -st], [st, ct]]
        D[:3, 3] = p - D[:3, :3] @ p + [error_mm * np.cos(phi), error_mm * np.sin(phi), 0.0]
        out.append(D)
    return out


# ------------------------------------------------------------------------------------ clutter
# A clutter part: a box in the preset's local frame, whose origin is the point on the bench top
# ``gap_mm`` beyond the disk's edge at ``azimuth_deg`` (about the table axis, counter-clockwise
# from above, 0 = away from the robot, 180 = the robot's side); local x points away from the
# axis (the near face is x = 0), y along the edge (counter-clockwise), z up.


@dataclass(frozen=True)
class ClutterPreset:
    name: str
    what: str
    azimuth_deg: float
    gap_mm: float
    boxes: tuple            # ((lo xyz, hi xyz, material), ...) in the local frame, mm
    material: Callable      # (material name, local points (N,3)) -> albedo (N,3)


def _in(p, y0, y1, z0, z1):
    return (p[:, 1] >= y0) & (p[:, 1] <= y1) & (p[:, 2] >= z0) & (p[:, 2] <= z1)


def _text_lines(p, y0, y1, z0, z1, pitch=9.0, ink=0.5):
    """Rows of 'text' (broken dark bars) inside a rectangle of a face: (N,) bool."""
    inside = _in(p, y0 + 4, y1 - 4, z0 + 4, z1 - 6)
    row = ((p[:, 2] - z0) % pitch) < pitch * ink
    words = (np.sin(p[:, 1] * 0.35 + np.floor((p[:, 2] - z0) / pitch) * 1.7) > -0.55)
    return inside & row & words


def _grain(p, scale=7.0):
    return 0.5 + 0.25 * np.sin(p[:, 0] / scale + 2.1 * np.sin(p[:, 2] / 23.0)) + 0.25 * np.sin(p[:, 1] / (1.7 * scale))


def _cabinet_albedo(mat: str, p: np.ndarray) -> np.ndarray:
    n = len(p)
    if mat == "handle":
        return np.full((n, 3), 0.12, np.float32)
    col = np.tile(np.array([0.70, 0.72, 0.69]), (n, 1)) * (0.96 + 0.04 * _grain(p, 31.0))[:, None]
    near = p[:, 0] < 0.5
    col[p[:, 2] < 16] = 0.22                                           # plinth
    col[near & (np.abs(p[:, 1]) < 1.5) & (p[:, 2] > 16)] = 0.25        # door seam
    col[near & (np.abs(p[:, 2] - 245) < 1.2)] = 0.3                    # drawer seam
    label = near & _in(p, -62, -10, 196, 232)
    col[label] = [0.95, 0.95, 0.92]
    col[near & _text_lines(p, -62, -10, 196, 232, pitch=7.0)] = 0.15
    col[near & _in(p, 10, 60, 60, 110)] = [0.85, 0.2, 0.15]            # a red warning sticker
    col[near & _in(p, 18, 52, 68, 102) & (np.abs(p[:, 1] - 35) + np.abs(p[:, 2] - 85) < 15)] = [0.95, 0.85, 0.2]
    return col.astype(np.float32)


def _monitor_albedo(mat: str, p: np.ndarray) -> np.ndarray:
    n = len(p)
    col = np.full((n, 3), 0.07, np.float32)
    if mat != "screen":
        return col
    scr = (p[:, 0] < 40.5) & _in(p, -198, 198, 134, 366)
    y, z = p[:, 1], p[:, 2]
    desk = np.stack([0.10 + 0.10 * (z - 134) / 232, 0.30 + 0.15 * (z - 134) / 232, 0.55 + 0.2 * (y + 198) / 396], 1)
    col[scr] = desk[scr]
    for (y0, y1, z0, z1, c) in ((-170, 20, 180, 340, (0.93, 0.93, 0.93)), (-20, 170, 150, 290, (0.2, 0.2, 0.22))):
        w = scr & _in(p, y0, y1, z0, z1)
        col[w] = c
        col[w & (z > z1 - 14)] = (0.3, 0.45, 0.75)                   # title bar
        txt = w & _text_lines(p, y0 + 4, y1, z0, z1 - 14, pitch=10.0)
        col[txt] = (0.2, 0.2, 0.2) if c[0] > 0.5 else (0.3, 0.9, 0.4)  # a document; a terminal
    col[scr & (z < 146)] = (0.75, 0.76, 0.8)                           # task bar
    return col.astype(np.float32)


def _box_albedo(mat: str, p: np.ndarray) -> np.ndarray:
    col = np.tile(np.array([0.60, 0.45, 0.28]), (len(p), 1)) * (0.92 + 0.1 * _grain(p, 3.0))[:, None]
    top = p[:, 2] > 199.5
    col[top & (np.abs(p[:, 1]) < 24)] = [0.78, 0.68, 0.48]             # packing tape
    near = p[:, 0] < 0.5
    col[near & (np.abs(p[:, 1]) < 24) & (p[:, 2] > 170)] = [0.78, 0.68, 0.48]
    lab = near & _in(p, -55, 15, 40, 110)
    col[lab] = [0.96, 0.96, 0.94]
    col[near & _text_lines(p, -55, 15, 40, 110, pitch=8.0)] = 0.1
    dy = np.abs(p[:, 1] - 40)
    arrow = (_in(p, 25, 55, 60, 100) & (dy < 3)) | (_in(p, 25, 55, 100, 118) & (dy < (118 - p[:, 2]) * 0.8))
    col[near & arrow] = 0.12                                           # "this side up"
    return col.astype(np.float32)


def _wall_albedo(mat: str, p: np.ndarray) -> np.ndarray:
    y, z = p[:, 1], p[:, 2]
    w = 0.84 + 0.03 * np.sin(y / 97.0) * np.cos(z / 61.0) + 0.02 * np.sin((y + z) / 13.0)
    col = np.stack([w, w * 0.98, w * 0.92], 1)
    near = p[:, 0] < 0.5
    board = near & _in(p, -620, 260, 40, 340)
    cork = np.array([0.66, 0.49, 0.31]) * (0.85 + 0.3 * (0.5 + 0.5 * np.sin(y * 1.3) * np.sin(z * 1.7)))[:, None]
    col[board] = cork[board]
    frame = board & ~_in(p, -612, 252, 48, 332)
    col[frame] = [0.45, 0.32, 0.2]
    papers = ((-590, -430, 70, 300, (0.96, 0.96, 0.94)), (-400, -230, 150, 320, (0.98, 0.92, 0.55)),
              (-200, -40, 60, 250, (0.96, 0.96, 0.94)), (-10, 230, 170, 320, (0.7, 0.85, 0.95)),
              (20, 150, 60, 150, (0.95, 0.6, 0.6)))
    for (y0, y1, z0, z1, c) in papers:
        sheet = board & _in(p, y0, y1, z0, z1)
        col[sheet] = c
        col[sheet & _text_lines(p, y0, y1, z0, z1 - 16, pitch=11.0)] = 0.2
        col[board & (np.hypot(y - (y0 + y1) / 2, z - (z1 - 8)) < 4)] = [0.85, 0.1, 0.1]  # pin
    strip = near & _in(p, 320, 700, 20, 60)                              # a socket strip
    col[strip] = 0.93
    col[strip & ((np.abs((y - 340) % 60 - 20) < 7) & (np.abs(z - 40) < 8))] = 0.35
    return col.astype(np.float32)


CLUTTER: dict[str, ClutterPreset] = {
    "cabinet": ClutterPreset(
        "cabinet", "a steel cabinet, 140 wide x 160 deep x 260 tall, near face 55 mm beyond the edge, behind left",
        azimuth_deg=40.0, gap_mm=55.0,
        boxes=(((0, -70, 0), (160, 70, 260), "body"),
               ((-10, -24, 150), (0, -16, 205), "handle"), ((-10, 16, 150), (0, 24, 205), "handle")),
        material=_cabinet_albedo),
    "monitor": ClutterPreset(
        "monitor", "a 19-inch monitor on its stand, facing the table, 150 mm beyond the edge, behind right",
        azimuth_deg=-30.0, gap_mm=150.0,
        boxes=(((20, -95, 0), (180, 95, 10), "stand"), ((85, -22, 10), (115, 22, 150), "stand"),
               ((40, -210, 120), (72, 210, 380), "screen")),
        material=_monitor_albedo),
    "box": ClutterPreset(
        "box", "a cardboard box, 130 x 130 x 200 tall, 25 mm beside the edge, right",
        azimuth_deg=-72.0, gap_mm=25.0,
        boxes=(((0, -65, 0), (130, 65, 200), "body"),),
        material=_box_albedo),
    "wall": ClutterPreset(
        "wall", "a wall with a pinboard 300 mm behind the table's edge, 2 m wide",
        azimuth_deg=0.0, gap_mm=300.0,
        boxes=(((0, -1000, -760), (25, 1000, 1200), "wall"),),
        material=_wall_albedo),
}


# "near" variants: the same parts with the near face over the table's rim (a cabinet ~300 mm from
# the axis, as in a crowded lab; the disk turns beneath its overhang): what the crop cannot cut off.
for _n in ("cabinet", "box"):
    _p = CLUTTER[_n]
    CLUTTER[f"{_n}_near"] = ClutterPreset(f"{_n}_near", _p.what.split(",")[0] + ", near face 30 mm inside the "
                                          "table's edge", _p.azimuth_deg, -30.0, _p.boxes, _p.material)


def clutter_names() -> list[str]:
    return list(CLUTTER)


def check_clutter(names) -> None:
    """ValueError naming the unknown presets and the known ones."""
    bad = [n for n in names if n not in CLUTTER]
    if bad:
        raise ValueError(f"unknown clutter {', '.join(repr(b) for b in bad)} (known: {', '.join(CLUTTER)})")


def T_base_local(preset: ClutterPreset, layout) -> np.ndarray:
    """Pose of a preset's local frame in the base frame for a rig layout."""
    cx, cy, cz = layout.table_centre
    a = np.radians(preset.azimuth_deg)
    r = layout.table_radius + preset.gap_mm
    R = rotation_matrix([0, 0, 1], a)
    return make_T(R, [cx + r * np.cos(a), cy + r * np.sin(a), cz - layout.table_thickness])


def clutter_parts(names, layout) -> list[tuple[trimesh.Trimesh, Callable[[np.ndarray], np.ndarray]]]:
    """[(mesh in the base frame, albedo of base-frame points (N,3) -> (N,3) float32)] of the
    named presets, in order."""
    import trimesh

    check_clutter(names)
    out = []
    for name in names:
        pre = CLUTTER[name]
        T = T_base_local(pre, layout)
        T_inv = np.linalg.inv(T)
        for lo, hi, mat in pre.boxes:
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            centre = make_T(np.eye(3), (lo + hi) / 2)
            mesh = trimesh.creation.box(extents=hi - lo, transform=T @ centre)

            def albedo(points, _f=pre.material, _m=mat, _T=T_inv):
                local = np.asarray(points, float) @ _T[:3, :3].T + _T[:3, 3]
                return _f(_m, local)

            out.append((mesh, albedo))
    return out
