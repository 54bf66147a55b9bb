"""The jobs every reproduce preset makes are those of the code before the methods' reproduce settings
moved into their registry records (issue 21): tests/reproduce_plans.json was written from that code
(its planned trainings, result rows, jobs in order with their choices, counts, labels and config
digests); the presets derived from the registry give the same, and so does a preset's TOML."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tdof20.experiments import reproduce as R

GOLDEN = json.loads((Path(__file__).parent / "reproduce_plans.json").read_text())


def plain(x):
    return json.loads(json.dumps(x))


@pytest.mark.parametrize("preset", sorted(GOLDEN))
def test_each_preset_plans_the_same_jobs_as_before(preset):
    g = GOLDEN[preset]
    cfg = R.make_config(preset)
    assert R.config_digest(cfg) == g["digest"]
    assert plain(R.config_data(cfg)) == g["config"]
    assert plain(R.planned_runs(cfg)) == g["runs"]
    assert plain(R.planned_predictions(cfg)) == g["predictions"]
    assert plain(R.job_plan(cfg)) == g["jobs"]
    assert plain(R.plan(cfg)) == g["plan"]
    assert list(R.METHODS) == g["methods"]
    assert R.LABELS == g["labels"]
    assert {k: list(v) for k, v in R.CHOICE_OPTIONS.items()} == g["choice_options"]


def test_the_tables_derive_from_the_registry():
    """METHODS, LABELS, CHOICE_OPTIONS, [epochs] and the presets' method parts come from the records."""
    from tdof20.methods.registry import get_method

    for name in R.METHODS:
        rs = get_method(name).reproduce
        assert R.LABELS[name] == rs.label and R.CHOICE_OPTIONS[name] == rs.choice_options
        assert getattr(R.EpochsConfig(), name) == 1
        for preset, data in R.PRESETS.items():
            assert data["epochs"][name] == rs.epochs.get(preset, 1)
            assert data.get("method_options", {}).get(name) == rs.preset_options.get(preset)
    with pytest.raises(Exception, match="epochs.pvnet must be > 0"):
        R.EpochsConfig(pvnet=0)
