"""The jobs every reproduce preset makes, and that they are fair.

tests/reproduce_plans.json holds each preset's planned trainings, result rows, jobs in order with
their choices and what each needs first, counts, labels and config digests. It was rewritten on
purpose for issue 23 (a fair benchmark): budgets as images seen instead of epochs per method,
every row once per seed (run names ``<row>_s<seed>``), the same number of candidate sets for
every compared row, no choice between HFF6DoF's two separately trained pose recoveries (two rows),
the segmentation network's training in the segmentation ablation, and the jobs' "needs" (for the
Ray executor). Any other change to a preset's plan fails here: rewrite the file only on purpose
(the generator is in this file's ``regenerate``).

The fairness itself is asserted from the plans, not from the file: every compared row of every
preset sees the same images at the same size, gets the same number of candidate sets, and is
trained with the preset's seeds (>= 2 in cpu, >= 3 in gpu and full)."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from tdof20.experiments import reproduce as R
from tdof20.experiments import reproduce_config as C
from tdof20.errors import TdofError

GOLDEN_PATH = Path(__file__).parent / "reproduce_plans.json"
GOLDEN = json.loads(GOLDEN_PATH.read_text())
MIN_SEEDS = {"smoke": 1, "cpu": 2, "gpu": 3, "full": 3}


def plain(x):
    return json.loads(json.dumps(x))


def preset_plans(preset: str) -> dict:
    cfg = R.make_config(preset)
    return {"digest": R.config_digest(cfg), "config": plain(R.config_data(cfg)), "runs": plain(R.planned_runs(cfg)),
            "predictions": plain(R.planned_predictions(cfg)), "jobs": plain(R.job_plan(cfg)),
            "plan": plain(R.plan(cfg)), "methods": list(R.METHODS), "labels": R.LABELS,
            "choice_options": {k: list(v) for k, v in R.CHOICE_OPTIONS.items()}}


def regenerate() -> None:  # pragma: no cover - run by hand when a plan changes on purpose
    GOLDEN_PATH.write_text(json.dumps({p: preset_plans(p) for p in sorted(R.PRESETS)}, indent=1, sort_keys=True)
                           + "\n")


@pytest.mark.parametrize("preset", sorted(GOLDEN))
def test_each_preset_plans_the_jobs_recorded(preset):
    g, now = GOLDEN[preset], preset_plans(preset)
    for key in ("config", "runs", "predictions", "jobs", "plan", "methods", "labels", "choice_options", "digest"):
        assert now[key] == g[key], key


EXAMPLE = Path(__file__).parents[1] / "examples" / "comparison_cpu.toml"


@pytest.mark.parametrize("preset", sorted(R.PRESETS))
def test_every_compared_row_gets_the_same_budget_candidates_and_seeds(preset):
    assert_fair(R.make_config(preset), preset)


def test_the_example_comparison_is_fair_and_trains_every_row():
    """examples/comparison_cpu.toml, the first trained comparison's config (docs/results.md): a TOML
    over the cpu preset, as fair as the presets, every method on both protocols with both
    ablations and two seeds, and no privileged input in its method options."""
    cfg = R.make_config(config=str(EXAMPLE))
    C.check_fair(cfg, str(EXAMPLE))
    assert_fair(cfg, cfg.preset)
    assert set(cfg.methods) == set(C.METHODS) and set(cfg.protocols) == {"simple", "hard"}
    assert cfg.ablations.segmentation and cfg.ablations.fuse_stages and cfg.ablations.segmentation_masks == "segnet"
    rows = {r["row"] for r in R.plan(cfg)["runs"]}
    assert {f"{m}_{p}" for m in ("hff6dof", "pvnet", "densefusion", "ffb6d")
            for p in ("simple", "hard")} | {"hff6dof_noseg_hard", "segnet_hard", "hff6dof_fuse1_hard"} <= rows
    # HFF6DoF's one row is the paper's pose recovery, and says so; no prediction is an oracle
    labels = {p["label"] for p in R.planned_predictions(cfg) if p["role"] == "main"}
    assert labels == {"PVNet", "DenseFusion", "FFB6D", "HFF6DoF (3D voting + LSQ)"}
    assert not any(p["oracle"] for p in R.planned_predictions(cfg))


def test_a_row_label_follows_the_options_and_two_equal_rows_are_refused(tmp_path):
    """HFF6DoF's row is labelled by the pose recovery it predicts with, from the config's method
    options as from the row's own; asking for its 3D-voting row twice is refused in one line."""
    cfg = R.make_config("cpu")
    assert C.row_label(cfg, "hff6dof") == "HFF6DoF (bearing + PnP)"
    assert C.row_label(cfg, "hff6dof", {"voting": "3d"}) == "HFF6DoF (3D voting + LSQ)"
    assert C.row_label(cfg, "pvnet") == "PVNet"
    bad = tmp_path / "twice.toml"
    bad.write_text('preset = "cpu"\n[method_options.hff6dof]\nvoting = "3d"\n')
    with pytest.raises(TdofError, match=r"twice.toml.*two compared rows would be the same 'HFF6DoF \(3D voting"):
        R.make_config(config=str(bad))
    cfg = R.make_config(config={"preset": "cpu", "ablations": {"voting_3d": False},
                                "method_options": {"hff6dof": {"voting": "3d"}}})
    assert C.row_label(cfg, "hff6dof") == "HFF6DoF (3D voting + LSQ)"


def test_an_image_size_a_method_cannot_take_is_refused_before_any_job(tmp_path):
    """FFB6D's stride-8 encoder needs both sides divisible by 8: 60x80 is refused at once, with the
    file and a size that works, not hours into a run when FFB6D's turn comes."""
    bad = tmp_path / "size.toml"
    bad.write_text('preset = "cpu"\n[train]\nimage_size = [60, 80]\n')
    with pytest.raises(TdofError, match=r"size.toml.*train.image_size 60x80: FFB6D needs both sides divisible by 8 "
                                        r"\(e.g. 56x80\)"):
        R.make_config(config=str(bad))
    out = tmp_path / "out"
    with pytest.raises(TdofError, match="divisible by 8"):
        R.reproduce(out, config=str(bad), progress=False)
    assert not out.exists()
    assert R.make_config(config={"preset": "cpu", "methods": ["hff6dof", "pvnet"],
                                 "train": {"image_size": [60, 80]}}).train.image_size == (60, 80)
    assert C.segnet_available() is True


def assert_fair(cfg, preset: str) -> None:
    runs = R.plan(cfg)["runs"]
    size = tuple(cfg.train.image_size)
    # the same images seen, at the same size (one train.image_size for all), by every row and seed;
    # the segmentation ablation's row counts its segmentation network's training in its own budget
    budgets = R.budgets(cfg)
    assert set(budgets.values()) == {cfg.train.images}, budgets
    assert all(r["images_seen"] == r["steps"] * r["batch"] for r in runs)
    if cfg.ablations.segmentation:
        for seed in cfg.train.seeds:
            seg = next(r for r in runs if r["name"] == f"segnet_hard_s{seed}")
            noseg = next(r for r in runs if r["name"] == f"hff6dof_noseg_hard_s{seed}")
            assert 0 < seg["images_seen"] < cfg.train.images
            assert seg["images_seen"] + noseg["images_seen"] == cfg.train.images
    # the same number of candidate sets chosen on validation for every compared row (2, or 1 = none)
    mains = [r for r in runs if r["candidates"]]
    assert {r["candidates"] for r in mains} == ({2} if preset in C.CHOOSING_PRESETS else {1})
    assert len(mains) == len(cfg.train.seeds) * (len(cfg.methods) + cfg.ablations.voting_3d) * len(cfg.protocols)
    # every row once per seed, >= 2 seeds in cpu, >= 3 in gpu and full
    assert len(cfg.train.seeds) >= MIN_SEEDS[preset]
    per_row = Counter(r["row"] for r in runs)
    assert set(per_row.values()) == {len(cfg.train.seeds)}
    # no compared row predicts with a privileged input
    for p in R.planned_predictions(cfg):
        assert p["oracle"] or not C.privileged_inputs(
            {**cfg.method_options.get(p["method"], {}), **p["options"]}), p


def test_a_smaller_batch_sees_the_same_images_in_more_steps():
    cfg = R.make_config("cpu", {"batch": {"pvnet": 2, "ffb6d": 8}})
    runs = {r["name"]: r for r in R.plan(cfg)["runs"]}
    assert runs["pvnet_simple_s0"]["steps"] == 1600 and runs["ffb6d_simple_s0"]["steps"] == 400
    assert runs["hff6dof_simple_s0"]["steps"] == 800
    assert {r["images_seen"] for n, r in runs.items() if not n.startswith(("segnet", "hff6dof_noseg"))} == {3200}


def test_the_tables_derive_from_the_registry():
    """METHODS, LABELS, CHOICE_OPTIONS and the presets' method parts come from the records; the
    presets' candidates are the records' cut to the same number of sets per method."""
    from tdof20.methods.registry import get_method

    for name in R.METHODS:
        rs = get_method(name).reproduce
        assert R.LABELS[name] == rs.label and R.CHOICE_OPTIONS[name] == rs.choice_options
        assert R.BatchConfig().__getattribute__(name) == 0
        for preset, data in R.PRESETS.items():
            assert "epochs" not in data
            assert data.get("method_options", {}).get(name) == rs.preset_options.get(preset)
        cands = R.CANDIDATES.get(name, {})
        assert list(cands) == list(rs.candidates)[:len(cands)]
        assert all(cands[k] == list(rs.candidates[k]) for k in cands)
    assert "segnet" not in R.METHODS
    with pytest.raises(Exception, match="batch.pvnet must be >= 0"):
        R.BatchConfig(pvnet=-1)
