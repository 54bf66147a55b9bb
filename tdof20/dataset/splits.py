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

Validation (``part_of(..., with_val=True)`` returns 'val'; :func:`val_steps`, :func:`hard_val_scenes`):
carved out of each protocol's train part, for every choice (epochs kept, thresholds, depth mode,
voting), never the test part.

- **simple**: in every scene of the train part, each arm position's steps ``k`` with
  ``(k - a * steps / 4 - steps // 2) mod steps < n_test`` are validation: one contiguous arc per arm
  position, as long as the test arc and half a turn away from it (60 of 400 steps; 4,674 images of
  simple's 31,108, the same count as its test part) — simple tests on arcs of its scenes, so it
  validates on arcs of them too.
- **hard**: whole held-out training scenes, because hard tests on scenes it never trains on. Of each
  kind (single-object, multi-object) of the hard training scenes a dataset holds, the
  ``n // HARD_VAL_EVERY`` (one in 7) with the highest ids are held out whole: in the release
  single/whisky_cup_225 and single/whisky_cup_270 (ids 19, 20) and multi/18 and multi/19, so both
  kinds are represented. A kind with fewer than 7 training scenes cannot spare a whole scene (a
  small dataset, the smoke preset): its scenes keep simple's arcs as their validation part.
  Cost in training data: the release's hard train part (52,747 images) gives up those 4 scenes,
  about 6,190 images (11.7 %; the arcs it used before took 15 %, 7,912); at the cpu preset's 48
  images per scene, 192 of 1,632 (the arcs: 272). The held-out objects stay in training through
  the multi-object scenes that hold them (in the simulated scenes: whisky_cup_270 in multi 06, 07,
  12, 14; whisky_cup_225 in multi 00, 07), as the test scenes' objects do, and every object of
  multi/18 and multi/19 keeps its single-object scene.

The release has no validation files: readers compute the part from these rules
(:mod:`tdof20.dataset.validation`). hard's rule depends on how many training scenes of each kind
the dataset holds: :func:`part_of` and :func:`validation_images` take the dataset's scene ids
(``scenes``; None = the release's 40).
"""

from __future__ import annotations

from collections.abc import Iterable
from functools import lru_cache

from tdof20.errors import TdofError
from tdof20.dataset.naming import MULTI_ID_OFFSET, N_MULTI, scene_name, scene_number

PAPER_SIMPLE = (26434, 4674)
PAPER_HARD = (52747, 9139)
HARD_TEST_MULTI = (2, 8, 9, 10, 11, 15)  # multi/NN of the release's numbering (00..19)
SPLITS = ("simple", "hard")
PARTS = ("train", "test")
VAL_PART = "val"
#: hard validation holds out one whole training scene of each kind in this many (fewer: arcs)
HARD_VAL_EVERY = 7
#: every scene id of the release (single 1..20, multi 21..40)
RELEASE_SCENES = tuple(range(1, MULTI_ID_OFFSET + N_MULTI))
#: the protocols' rules in one line each, as dataset_info.json and tdof20_bop.json record them
SPLIT_RULES = {"simple": "single-object scenes, contiguous test arc per arm position; validation: an arc as long, "
                         "half a turn on (docs/dataset.md)",
               "hard": "train: single + multi 00,01,03-07,12-14,16-19; test: multi 02,08,09,10,11,15; validation: "
                       "whole held-out training scenes, one in 7 of each kind (arcs where a kind has fewer)"}
__all__ = ["HARD_TEST_MULTI", "PAPER_HARD", "PAPER_SIMPLE", "PARTS", "SPLITS", "SPLIT_PART_SCENES", "SPLIT_RULES",
           "HARD_VAL_EVERY", "RELEASE_SCENES", "hard_val_scenes", "min_simple_steps", "part_needs", "part_of",
           "VAL_PART", "val_steps", "validation_images", "scene_can_serve", "scene_name", "scene_number",
           "simple_test_steps"]


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


def hard_val_scenes(scenes: Iterable[int] | None = None) -> tuple[frozenset[int], frozenset[str]]:
    """hard's validation among the dataset's scenes ``scenes`` (scene ids; None = the release's 40):
    (the training scenes held out whole, the kinds — 'single', 'multi' — whose training scenes are
    too few to spare one and keep arcs instead). See the module docstring."""
    return _hard_val(frozenset(RELEASE_SCENES if scenes is None else (int(s) for s in scenes)))


@lru_cache(maxsize=64)
def _hard_val(scenes: frozenset[int]) -> tuple[frozenset[int], frozenset[str]]:
    train = [s for s in scenes if part_of("hard", s, 0, 1, 1) == "train"]
    held: set[int] = set()
    arcs: set[str] = set()
    for kind, single in (("single", True), ("multi", False)):
        mine = sorted((s for s in train if _is_single(s) == single), reverse=True)
        n = len(mine) // HARD_VAL_EVERY
        held |= set(mine[:n])
        if mine and not n:
            arcs.add(kind)
    return frozenset(held), frozenset(arcs)


def _kind(scene_id: int) -> str:
    return "single" if _is_single(scene_id) else "multi"


def part_of(split: str, scene_id: int, im_id: int, steps: int, n_arms: int, with_val: bool = False,
            scenes: Iterable[int] | None = None) -> str | None:
    """'train', 'test' or None (the image is not in this protocol); with ``with_val``, 'val' for the
    validation images of the train part (see the module docstring; ``scenes``: the dataset's scene
    ids, which hard's validation depends on; None = the release's 40)."""
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
        if split == "hard":
            held, arcs = hard_val_scenes(scenes)
            if scene_id in held:
                return VAL_PART
            if _kind(scene_id) not in arcs:
                return part
        arm, step = divmod(im_id, steps)
        if step in val_steps(arm, steps, n_arms):
            return VAL_PART
    return part


def validation_images(images: list[tuple[int, int]], split: str, steps: int, n_arms: int = 4,
                      fraction: float | None = None) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(train, validation) of a split's train part ``images`` ((scene_id, im_id), im_id = arm * steps
    + step, every scene with ``steps`` per arm position): simple's :func:`val_steps` arcs, or, with
    ``fraction``, arcs of that fraction of the steps from the same start (half a turn from the test
    arcs); hard's held-out scenes among the images' scenes (:func:`hard_val_scenes`), and those arcs
    in the scenes of a kind too few to spare one."""
    if split not in SPLITS:
        raise TdofError(f"unknown split '{split}' (valid: {', '.join(SPLITS)})")
    if steps < 1 or (fraction is not None and not 0.0 < fraction < 1.0):
        raise TdofError("validation needs steps >= 1 and a fraction in (0, 1)")
    n_val = None if fraction is None else max(1, round(steps * fraction))
    held, arcs = hard_val_scenes({s for s, _ in images}) if split == "hard" else (frozenset(), frozenset())
    train, val = [], []
    for s, im in images:
        arm, step = divmod(int(im), steps)
        if split == "hard" and (s in held or _kind(s) not in arcs):
            hold = s in held
        elif n_val is None:
            hold = step in val_steps(arm, steps, n_arms)
        else:
            hold = (step - (arm * steps) // max(n_arms, 4) - steps // 2) % steps < n_val
        (val if hold else train).append((s, im))
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
