"""The paper's two protocols as fixed, documented rules.

Scene ids (the release's names): ``single/<class>`` -> the object id (1..20; ``single/NN`` is an
alias), ``multi/NN`` (00..19) -> 21 + NN (21..40).

- **TDoF20-simple**: the 20 single-object scenes. Within each scene, each arm position's
  turntable steps are split into one contiguous test arc and the rest: at arm position ``a`` the
  steps ``k`` with ``(k - a * steps / 4) mod steps < n_test`` are test, where
  ``n_test = round(steps * 4674 / 31108)`` (60 of 400: the paper's 26,434 : 4,674). Contiguous
  arcs, rotated by a quarter turn from one arm position to the next, keep near-duplicate
  neighbouring frames (0.9 degrees apart) out of the other part, except at the two ends of each arc.
- **TDoF20-hard**: train = all 20 single-object scenes and multi-object scenes 00, 01, 03-07,
  12-14, 16-19; test = multi-object scenes 02, 08, 09, 10, 11, 15, every frame (as released).

Validation (``part_of(..., with_val=True)`` returns 'val'; :func:`val_steps`): carved out of each
protocol's train part, for every choice (epochs kept, thresholds, depth mode, voting), never the test
part. In every scene of the train part, each arm position's steps ``k`` with
``(k - a * steps / 4 - steps // 2) mod steps < n_test`` are validation: one contiguous arc per arm
position, as long as the test arc and half a turn away from it (60 of 400 steps; 4,674 images of
simple's 31,108, the same count as its test part). For simple those are images of the test arcs'
scenes; for hard the same arcs of every training scene (single- and multi-object) — held-out arcs,
not held-out scenes: the 14 training multi-object scenes each hold their own arrangement of objects,
so holding scenes out would take some objects' multi-object views out of training altogether (and a
small dataset has but one or two), while held-out arcs keep every scene and object in both parts
(near-duplicate neighbours only at the arcs' two ends). The release has no validation files: readers
compute the part from these rules (:mod:`tdof20.dataset.validation`).
"""

from __future__ import annotations

from tdof20.errors import TdofError
from tdof20.dataset.naming import MULTI_ID_OFFSET, N_MULTI, scene_name, scene_number

PAPER_SIMPLE = (26434, 4674)
PAPER_HARD = (52747, 9139)
HARD_TEST_MULTI = (2, 8, 9, 10, 11, 15)  # multi/NN of the release's numbering (00..19)
SPLITS = ("simple", "hard")
PARTS = ("train", "test")
VAL_PART = "val"
#: the protocols' rules in one line each, as dataset_info.json and tdof20_bop.json record them
SPLIT_RULES = {"simple": "single-object scenes, contiguous test arc per arm position (docs/dataset.md)",
               "hard": "train: single + multi 00,01,03-07,12-14,16-19; test: multi 02,08,09,10,11,15"}
__all__ = ["HARD_TEST_MULTI", "PAPER_HARD", "PAPER_SIMPLE", "PARTS", "SPLITS", "SPLIT_PART_SCENES", "SPLIT_RULES",
           "min_simple_steps", "part_needs", "part_of", "VAL_PART", "val_steps", "validation_images", "scene_can_serve", "scene_name",
           "scene_number", "simple_test_steps"]


def _is_single(scene_id: int) -> bool:
    return scene_id < MULTI_ID_OFFSET


def _hard_train_multi() -> str:
    """'00, 01, 03-07, 12-14, 16-19': the multi-object scenes hard trains on, as ranges."""
    rest = [m for m in range(N_MULTI) if m not in HARD_TEST_MULTI]
    runs: list[list[int]] = []
    for m in rest:
        if runs and m == runs[-1][-1] + 1:
            runs[-1].append(m)
        else:
            runs.append([m])
    return ", ".join(", ".join(f"{m:02d}" for m in r) if len(r) < 3 else f"{r[0]:02d}-{r[-1]:02d}" for r in runs)


#: what each part of a split takes, for the message when it is empty
SPLIT_PART_SCENES = {
    ("simple", "train"): "the single-object scenes' frames outside the test arcs",
    ("simple", "test"): "one arc of turntable steps per arm position of the single-object scenes",
    ("hard", "train"): f"the single-object scenes and multi-object scenes {_hard_train_multi()}",
    ("hard", "test"): "multi-object scenes " + ", ".join(f"{m:02d}" for m in HARD_TEST_MULTI),
}


def simple_test_steps(arm: int, steps: int, n_arms: int = 4) -> set[int]:
    n_test = round(steps * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE))
    start = (arm * steps) // max(n_arms, 4)
    return {(start + i) % steps for i in range(n_test)}


def val_steps(arm: int, steps: int, n_arms: int = 4) -> set[int]:
    """The validation arc of arm position ``arm``: as many steps as the test arc, half a turn on."""
    n_val = round(steps * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE))
    start = (arm * steps) // max(n_arms, 4) + steps // 2
    return {(start + i) % steps for i in range(n_val)}


def part_of(split: str, scene_id: int, im_id: int, steps: int, n_arms: int, with_val: bool = False) -> str | None:
    """'train', 'test' or None (the image is not in this protocol); with ``with_val``, 'val' for the
    validation images of the train part (see the module docstring)."""
    if split == "simple":
        if not _is_single(scene_id):
            return None
        arm, step = divmod(im_id, steps)
        part = "test" if step in simple_test_steps(arm, steps, n_arms) else "train"
    elif split == "hard":
        part = "test" if scene_id - MULTI_ID_OFFSET in HARD_TEST_MULTI else "train"
    else:
        raise TdofError(f"unknown split '{split}' (valid: {', '.join(SPLITS)})")
    if with_val and part == "train":
        arm, step = divmod(im_id, steps)
        if step in val_steps(arm, steps, n_arms):
            return VAL_PART
    return part


def validation_images(images: list[tuple[int, int]], split: str, steps: int, n_arms: int = 4,
                      fraction: float | None = None) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(train, validation) of a split's train part ``images`` ((scene_id, im_id), im_id = arm * steps
    + step, every scene with ``steps`` per arm position): the :func:`val_steps` arcs, or, with
    ``fraction``, arcs of that fraction of the steps from the same start (half a turn from the test
    arcs). The same rule for 'simple' and 'hard' (held-out arcs of every training scene)."""
    if split not in SPLITS:
        raise TdofError(f"unknown split '{split}' (valid: {', '.join(SPLITS)})")
    if steps < 1 or (fraction is not None and not 0.0 < fraction < 1.0):
        raise TdofError("validation needs steps >= 1 and a fraction in (0, 1)")
    n_val = None if fraction is None else max(1, round(steps * fraction))
    train, val = [], []
    for s, im in images:
        arm, step = divmod(int(im), steps)
        if n_val is None:
            held = step in val_steps(arm, steps, n_arms)
        else:
            held = (step - (arm * steps) // max(n_arms, 4) - steps // 2) % steps < n_val
        (val if held else train).append((s, im))
    return train, val


def min_simple_steps() -> int:
    """The fewest turntable steps per arm position whose TDoF20-simple test arc is not empty."""
    return next(s for s in range(1, 100) if round(s * PAPER_SIMPLE[1] / sum(PAPER_SIMPLE)) >= 1)


def scene_can_serve(split: str, part: str, scene_id: int) -> bool:
    """Whether images of scene ``scene_id`` can fall in the ``part`` of ``split`` at all."""
    if split == "simple":
        return _is_single(scene_id)
    return part_of(split, scene_id, 0, 1, 1) == part


def part_needs(split: str, part: str) -> str:
    """What a dataset must hold for a split part to have images (for messages)."""
    if split == "simple":
        return "simple needs single-object scenes (single/<class>)"
    if part == "test":
        return "hard tests on multi-object scenes " + ", ".join(f"multi/{m:02d}" for m in HARD_TEST_MULTI)
    return ("hard trains on single-object scenes (single/<class>) and the multi-object scenes not in its test set "
            f"(multi/{_hard_train_multi()})")
