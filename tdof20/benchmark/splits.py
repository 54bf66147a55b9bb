"""The paper's two protocols as fixed, documented rules.

Scene ids: ``single/NN`` -> NN, ``multi/NN`` -> 20 + NN.

- **TDoF20-simple**: the 20 single-object scenes. Within each scene, each arm position's
  turntable steps are split into one contiguous test arc and the rest: at arm position ``a`` the
  steps ``k`` with ``(k - a * steps / 4) mod steps < n_test`` are test, where
  ``n_test = round(steps * 4674 / 31108)`` (60 of 400: the paper's 26,434 : 4,674). Contiguous
  arcs, rotated by a quarter turn from one arm position to the next, keep near-duplicate
  neighbouring frames (0.9 degrees apart) out of the other part, except at the two ends of each arc.
- **TDoF20-hard**: train = all 20 single-object scenes and multi-object scenes 01, 03-07, 12-14,
  16-20; test = multi-object scenes 02, 08, 09, 10, 11, 15, every frame.
"""

from __future__ import annotations

import re

from tdof20.errors import TdofError

PAPER_SIMPLE = (26434, 4674)
PAPER_HARD = (52747, 9139)
HARD_TEST_MULTI = (2, 8, 9, 10, 11, 15)
SPLITS = ("simple", "hard")
PARTS = ("train", "test")


def scene_number(name: str) -> int:
    """'single/07' -> 7, 'multi/08' -> 28."""
    m = re.match(r"^(single|multi)/(\d{2})$", str(name))
    if not m or not 1 <= int(m.group(2)) <= 20:
        raise TdofError(f"unknown scene '{name}' (valid: single/01..20, multi/01..20)")
    return int(m.group(2)) + (20 if m.group(1) == "multi" else 0)


def scene_name(scene_id: int) -> str:
    if not 1 <= scene_id <= 40:
        raise TdofError(f"unknown scene id {scene_id} (valid: 1-40)")
    return f"single/{scene_id:02d}" if scene_id <= 20 else f"multi/{scene_id - 20:02d}"


def simple_test_steps(arm: int, steps: int, n_arms: int = 4) -> set[int]:
    n_test = round(steps * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE))
    start = (arm * steps) // max(n_arms, 4)
    return {(start + i) % steps for i in range(n_test)}


def part_of(split: str, scene_id: int, im_id: int, steps: int, n_arms: int) -> str | None:
    """'train', 'test' or None (the image is not in this protocol)."""
    if split == "simple":
        if scene_id > 20:
            return None
        arm, step = divmod(im_id, steps)
        return "test" if step in simple_test_steps(arm, steps, n_arms) else "train"
    if split == "hard":
        return "test" if scene_id - 20 in HARD_TEST_MULTI else "train"
    raise TdofError(f"unknown split '{split}' (valid: {', '.join(SPLITS)})")


def min_simple_steps() -> int:
    """The fewest turntable steps per arm position whose TDoF20-simple test arc is not empty."""
    return next(s for s in range(1, 100) if round(s * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE)) >= 1)


def scene_can_serve(split: str, part: str, scene_id: int) -> bool:
    """Whether images of scene ``scene_id`` can fall in the ``part`` of ``split`` at all."""
    if split == "simple":
        return scene_id <= 20
    return part_of(split, scene_id, 0, 1, 1) == part


def part_needs(split: str, part: str) -> str:
    """What a dataset must hold for a split part to have images (for messages)."""
    if split == "simple":
        return "simple needs single-object scenes (single/NN)"
    if part == "test":
        return "hard tests on multi-object scenes " + ", ".join(f"multi/{m:02d}" for m in HARD_TEST_MULTI)
    return ("hard trains on single-object scenes (single/NN) and the multi-object scenes not in its test set "
            "(multi/01, 03-07, 12-14, 16-20)")
