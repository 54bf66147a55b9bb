"""The paper's tables from score dicts (tdof20.experiments.tables): layout, bold, oracle marks,
missing cells, agreement, CSV / JSON / plots.

Score dicts come from the real scorer on a tiny BOP dataset written here (catalog models, a
single-object scene of handle_cup_280 and a multi-object scene), or are synthetic with the
scorer's exact keys (scoring.KEYS) where a test needs chosen numbers."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tdof20.scoring import scoring
from tdof20.experiments import tables as T
from tdof20.scoring.scoring import evaluate
from tdof20.errors import TdofError
from tdof20.formats import BopSceneWriter, write_json
from tdof20.objects import export_models, get_object

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
OBJS = (1, 7, 17)  # cube_136 (symmetric), handle_cup_280 (asymmetric), water_cup_270 (symmetric)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """scene 7 (single/handle_cup_280): 4 images of object 7; scene 29 (multi/08): 4 images of 1, 7, 17."""
    root = tmp_path_factory.mktemp("ds")
    export_models(root / "models", OBJS)
    rng = np.random.default_rng(3)
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:5] = True
    gt, targets = [], []
    for sid, objs in ((7, [7]), (29, [1, 7, 17])):
        with BopSceneWriter(root / "scenes" / f"{sid:06d}") as w:
            for im in range(4):
                poses = [(o, Rotation.random(random_state=int(rng.integers(2**31))).as_matrix(),
                          np.array([rng.uniform(-50, 50), rng.uniform(-30, 30), rng.uniform(600, 800)]))
                         for o in objs]
                w.add_frame(im, K, 1.0, poses, [mask] * len(poses), [mask] * len(poses))
                targets += [{"scene_id": sid, "im_id": im, "obj_id": o, "inst_count": 1} for o in objs]
                gt += [(sid, im, o, R, t) for o, R, t in poses]
    write_json(root / "dataset_info.json", {"name": "tdof20", "scenes": {"7": "single/handle_cup_280",
                                                                        "29": "multi/08"}})
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_json(root / "test_targets_hard.json", [t for t in targets if t["scene_id"] == 29])
    write_json(root / "test_targets_simple.json", [t for t in targets if t["scene_id"] == 7])
    return root, gt


def rows(gt, shift_every: int = 0, shift_mm: float = 40.0):
    """Result rows: the ground truth, every ``shift_every``-th one moved by ``shift_mm`` along x."""
    out = []
    for k, (s, im, o, R, t) in enumerate(gt):
        t = t + (np.array([shift_mm, 0, 0]) if shift_every and k % shift_every == 0 else 0)
        out.append((s, im, o, 1.0, R, t, 0.1))
    return out


def scored(root, gt, split, shift_every=0):
    sc = {"simple": 7, "hard": 29}[split]
    ev = evaluate(rows([g for g in gt if g[0] == sc], shift_every), root, split=split)
    return {**ev.summary(), "curves": T.curves_from_evaluation(ev)}


def synthetic(values: dict[int, tuple[float, float]]) -> dict:
    """A score dict with the scorer's keys: obj_id -> (add_s, proj2d); the other metrics alike."""
    objs = {}
    for o, (a, p) in values.items():
        objs[str(o)] = {"n": 10, "add": a, "adds": a, "add_s": a, "proj2d": p, "auc_adds": a, "auc_add_s": a}
        assert set(objs[str(o)]) == set(scoring.KEYS)
    mean = {k: float(np.mean([v[k] for v in objs.values()])) for k in scoring.KEYS[1:]}
    return {"objects": objs, "mean": {"n": len(objs), **mean}, "all": {"n": 10 * len(objs), **mean}, "scenes": {}}


def seeds2(values: dict[int, tuple[float, float]], spread: float = 0.01) -> dict:
    """One row trained with two seeds: each value ``spread`` below, then above the given mean."""
    lo = synthetic({o: (a - spread, p - spread) for o, (a, p) in values.items()})
    hi = synthetic({o: (a + spread, p + spread) for o, (a, p) in values.items()})
    return T.over_seeds([lo, hi], [0, 1])


def test_tables_from_the_real_scorer(dataset, tmp_path):
    root, gt = dataset
    entries = [T.Entry("PVNet", "pvnet", "simple", scored(root, gt, "simple", 2)),
               T.Entry("PVNet", "pvnet", "hard", scored(root, gt, "hard", 2)),
               T.Entry("HFF6DoF", "hff6dof", "simple", scored(root, gt, "simple")),
               T.Entry("HFF6DoF", "hff6dof", "hard", scored(root, gt, "hard", 3))]
    t1 = T.protocol_table(entries, "add_s")
    names = [r["name"] for r in t1["rows"]]
    assert names == ["cube_136", "handle_cup_280", "water_cup_270", "mean (3 objects)"]
    assert [r["asymmetric"] for r in t1["rows"]] == [False, True, False, False]
    assert [(c["label"], c["split"]) for c in t1["columns"]] == [
        ("PVNet", "simple"), ("PVNet", "hard"), ("HFF6DoF", "simple"), ("HFF6DoF", "hard")]
    cube, cup = t1["rows"][0], t1["rows"][1]
    # cube_136 is not in the simple test part: missing; HFF6DoF simple is the ground truth: 100 %
    assert cube["values"][0] is None and cube["values"][2] is None
    assert cup["values"][2] == pytest.approx(1.0) and cup["values"][0] == pytest.approx(0.5)
    assert cup["bold"] == [False, cup["values"][1] > cup["values"][3], True, cup["values"][3] > cup["values"][1]]
    mean = t1["rows"][-1]
    assert mean["values"] == [pytest.approx(e.scores["mean"]["add_s"]) for e in entries]

    paths = T.write_tables(tmp_path / "out", entries)
    md = (tmp_path / "out" / "tables.md").read_text()
    assert "**handle_cup_280** \\*" in md and "| cube_136 | — |" in md
    assert "| handle_cup_280" not in md  # the asymmetric name is always bold
    body = list(csv.reader(io.StringIO(paths["table1_add_s.csv"].read_text())))
    assert body[0] == ["obj_id", "object", "asymmetric", "PVNet/simple", "PVNet/hard", "HFF6DoF/simple",
                       "HFF6DoF/hard"]
    assert body[2][:3] == ["7", "handle_cup_280", "1"] and float(body[2][3]) == pytest.approx(50.0)
    assert body[1][3] == "" and body[-1][1] == "mean (3 objects)"
    js = json.loads(paths["tables.json"].read_text())
    assert js["table2"]["key"] == "proj2d" and len(js["table1"]["rows"]) == 4
    # plots: curves from the evaluations
    png = paths["plots/accuracy_HFF6DoF.png"].read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert entries[2].scores["curves"]["add_s"]["y"][-1] == pytest.approx(1.0)


def test_bold_oracle_marks_and_missing_cells(tmp_path):
    a = T.Entry("DenseFusion", "densefusion", "hard", synthetic({1: (0.30, 0.20), 7: (0.10, 0.50)}))
    b = T.Entry("FFB6D", "ffb6d", "hard", synthetic({1: (0.40, 0.20), 7: (0.05, 0.10)}))
    o = T.Entry("HFF6DoF no seg", "hff6dof", "hard", synthetic({1: (0.90, 0.90), 7: (0.90, 0.90)}),
                oracle_masks=True)
    s = T.Entry("FFB6D", "ffb6d", "simple", synthetic({1: (0.70, 0.60)}))
    t = T.protocol_table([a, b, o, s], "add_s")
    cols = [(c["label"], c["split"], c["oracle_masks"], c["present"]) for c in t["columns"]]
    assert cols[0] == ("DenseFusion", "simple", False, False) and cols[5] == ("HFF6DoF no seg", "hard", True, True)
    cube, cup, mean = t["rows"]
    # the oracle result is highest but never bold; a protocol with one result has no bold
    assert cube["bold"] == [False, False, False, True, False, False]
    assert cup["bold"] == [False, True, False, False, False, False]
    assert cup["values"][2] is None and cube["values"][2] == pytest.approx(0.70)
    assert mean["bold"][3] and not mean["bold"][5]
    md = T.protocol_markdown(t)
    assert "HFF6DoF no seg · hard (oracle masks)" in md and "**40.00**" in md and "**90.00**" not in md
    assert "| cube_136 | — | **30.00**" not in md and "| cube_136 | — | 30.00 | 70.00 | **40.00** | — | 90.00 |" in md
    head = T.protocol_csv(t).splitlines()[0]
    assert "HFF6DoF no seg/hard (oracle masks)" in head
    # ablations: the oracle mark reaches them too
    st = T.segmentation_table(T.Entry("on", "hff6dof", "hard", synthetic({1: (0.5, 0.4)})), o)
    assert st["rows"][1]["setting"] == "without segmentation head (oracle masks)"
    assert st["gain"]["add_s"] == pytest.approx(-0.4)
    assert "oracle masks" in T.ablation_markdown(st) and "-40.00" in T.ablation_markdown(st)
    with pytest.raises(TdofError, match="two results"):
        T.protocol_table([a, a])
    with pytest.raises(TdofError, match="not a score dict"):
        T.Entry("x", "x", "hard", {"mean": {}})


def _profiles(hff=(56.82, 80.0, 35.0), df=140.0, ffb=210.0):
    return [{"method": "hff6dof", "parameters_M": hff[0], "macs_480x640_G": hff[1], "end_to_end_fps": hff[2],
             "network_fps": 50.0, "network_ms": 20.0, "pose_ms": 8.6, "end_to_end_ms": 28.6, "device": "test",
             "input": [1, 480, 640], "paper": {"parameters_M": 56.82, "macs_G": 85.12, "fps": 29.38}},
            {"method": "densefusion", "parameters_M": 41.7, "macs_480x640_G": df, "end_to_end_fps": 10.0,
             "device": "test"},
            {"method": "ffb6d", "parameters_M": 33.8, "macs_480x640_G": ffb, "end_to_end_fps": 5.0, "device": "test"},
            {"method": "pvnet", "error": "no"}]


def test_agreement_is_computed():
    def hard(m, a, p):
        return T.Entry(m, m, "hard", seeds2({1: (a, p), 7: (a, p)}))

    entries = [hard("pvnet", 0.20, 0.30), hard("densefusion", 0.44, 0.35), hard("ffb6d", 0.40, 0.40),
               hard("hff6dof", 0.51, 0.52), T.Entry("hff6dof", "hff6dof", "simple", seeds2({1: (0.8, 0.8)}))]
    fusion = {k: hard("hff6dof", v, 0.5) for k, v in {1: 0.3, 2: 0.4, 3: 0.5, 5: 0.45}.items()}
    seg_on, seg_off = hard("hff6dof", 0.51, 0.52), T.Entry("off", "hff6dof", "hard", seeds2({1: (0.45, 0.45)}))
    c = {x["id"]: x for x in T.agreement(entries, _profiles(), fusion, seg_on, seg_off)}
    assert set(c) == set(T.CLAIMS)
    assert c["hff6dof_hard_add_s"]["agrees"] is True and "51.00" in c["hff6dof_hard_add_s"]["ours"]
    assert c["hff6dof_best_add_s_hard"]["agrees"] is True and "+7.00" in c["hff6dof_best_add_s_hard"]["ours"]
    assert "51.00 ± 1.00" in c["hff6dof_best_add_s_hard"]["ours"]
    assert c["hff6dof_best_proj2d_hard"]["agrees"] is True
    assert c["simple_above_hard"]["agrees"] is True
    assert c["hff6dof_fps"]["agrees"] is True and c["hff6dof_parameters"]["agrees"] is True
    assert c["macs_hff6dof"]["agrees"] is True and c["macs_order"]["agrees"] is True
    assert c["seg_gain_add_s"]["agrees"] is True and "separately trained segmentation network" in \
        c["seg_gain_add_s"]["ours"]
    assert c["seg_gain_proj2d"]["agrees"] is True and c["best_fuse_stages"]["agrees"] is True

    # an oracle row takes part in no claim: the segmentation gain over ground-truth masks is not measured
    oracle = T.Entry("off", "hff6dof", "hard", seeds2({1: (0.45, 0.5)}), oracle_masks=True)
    c = {x["id"]: x for x in T.agreement(entries, (), fusion, seg_on, oracle)}
    assert c["seg_gain_add_s"]["agrees"] is None and "oracle masks" in c["seg_gain_add_s"]["ours"]

    # the other way: FFB6D beats HFF6DoF in ADD(S), 2 fused stages best, slow, MACs out of order
    entries[2] = hard("ffb6d", 0.60, 0.10)
    fusion[2] = hard("hff6dof", 0.55, 0.5)
    c = {x["id"]: x for x in T.agreement(entries, _profiles((60.0, 300.0, 2.0)), fusion, seg_on,
                                         T.Entry("off", "hff6dof", "hard", seeds2({1: (0.7, 0.6)})))}
    assert c["hff6dof_best_add_s_hard"]["agrees"] is False and "ffb6d > hff6dof" in c["hff6dof_best_add_s_hard"]["ours"]
    assert c["hff6dof_best_proj2d_hard"]["agrees"] is False  # DenseFusion, not FFB6D, is second now
    assert c["hff6dof_hard_add_s"]["agrees"] is True
    assert c["best_fuse_stages"]["agrees"] is False and c["best_fuse_stages"]["ours"].startswith("2 ")
    assert c["hff6dof_fps"]["agrees"] is False and c["hff6dof_parameters"]["agrees"] is False
    assert c["macs_order"]["agrees"] is False and c["macs_hff6dof"]["agrees"] is False
    assert c["seg_gain_add_s"]["agrees"] is False and c["seg_gain_proj2d"]["agrees"] is False
    # ties: nobody is first, no bold, 3 fused stages tied with 1 is no agreement
    tied = [hard("densefusion", 0.0, 0.0), hard("ffb6d", 0.0, 0.0), hard("hff6dof", 0.0, 0.0)]
    c = {x["id"]: x for x in T.agreement(tied, (), {1: tied[2], 3: tied[2]})}
    assert c["hff6dof_best_add_s_hard"]["agrees"] is False and "densefusion = ffb6d = hff6dof" in \
        c["hff6dof_best_add_s_hard"]["ours"]
    assert c["best_fuse_stages"]["agrees"] is False and c["best_fuse_stages"]["ours"].startswith("1 = 3 (tie)")
    assert not any(b for r in T.protocol_table(tied)["rows"] for b in r["bold"])
    # nothing measured: None, shown "not measured"
    c = T.agreement([])
    assert all(x["agrees"] is None for x in c)
    assert "not measured" in T.agreement_markdown(c)


def test_a_difference_claim_needs_more_than_the_spread_and_two_seeds():
    """HFF6DoF 3 points above DenseFusion: yes with spreads of 1 point each, no with spreads of 2
    (the seeds' ranges overlap), not measured with one seed (no spread)."""
    def row(m, a, spread):
        return T.Entry(m, m, "hard", seeds2({1: (a, a)}, spread))

    for spread, verdict in ((0.01, True), (0.02, False)):
        rows = [row("pvnet", 0.10, spread), row("densefusion", 0.40, spread), row("ffb6d", 0.30, spread),
                row("hff6dof", 0.43, spread)]
        c = {x["id"]: x for x in T.agreement(rows)}
        assert c["hff6dof_best_add_s_hard"]["agrees"] is verdict, spread
        assert f"±{100 * spread:.2f}" in c["hff6dof_best_add_s_hard"]["detail"]
        assert c["hff6dof_best_proj2d_hard"]["agrees"] is False  # DenseFusion, not FFB6D, second
    one = [T.Entry(m, m, "hard", synthetic({1: (a, a)})) for m, a in (("densefusion", 0.1), ("hff6dof", 0.5))]
    c = {x["id"]: x for x in T.agreement(one)}
    assert c["hff6dof_best_add_s_hard"]["agrees"] is None
    assert "one seed" in c["hff6dof_best_add_s_hard"]["detail"]
    assert c["hff6dof_hard_add_s"]["agrees"] is True  # a closeness claim, not a difference: judged


def test_seeds_combine_into_mean_and_spread(tmp_path):
    """over_seeds: the mean and half-range per object and overall, the seeds' curves averaged; the
    tables print "mean ± half-range" and a ± column per result in the CSV."""
    s0, s1 = synthetic({1: (0.2, 0.4), 7: (0.6, 0.8)}), synthetic({1: (0.4, 0.4), 7: (0.6, 0.2)})
    s0["curves"] = {"add_s": {"x": [0, 1], "y": [0.0, 0.5]}}
    s1["curves"] = {"add_s": {"x": [0, 1], "y": [0.0, 0.7]}}
    s0["proj_px"] = s1["proj_px"] = 1.25
    e = T.Entry("PVNet", "pvnet", "hard", T.over_seeds([s0, s1], [0, 1]))
    assert e.seeds == [0, 1] and e.value("add_s", 1) == pytest.approx(0.3) and e.spread("add_s", 1) == pytest.approx(0.1)
    assert e.value("proj2d", 7) == pytest.approx(0.5) and e.spread("proj2d", 7) == pytest.approx(0.3)
    assert e.value("add_s") == pytest.approx(0.45) and e.spread("add_s") == pytest.approx(0.05)
    assert e.scores["curves"]["add_s"]["y"] == pytest.approx([0.0, 0.6]) and e.scores["proj_px"] == 1.25
    single = T.Entry("PVNet", "pvnet", "hard", s0)
    assert single.spread("add_s") is None and single.seeds == [None]
    t = T.protocol_table([e], "proj2d")
    assert t["title"].endswith("< 1.25 px") and any("1.25 px" in n for n in t["notes"])
    md = T.protocol_markdown(t)
    assert "| **handle_cup_280** \\* | — | 50.00 ± 30.00 |" in md and "mean over the row's 2 seeds" in md
    body = list(csv.reader(io.StringIO(T.protocol_csv(t))))
    assert body[0][3:] == ["PVNet/simple", "PVNet/simple ±", "PVNet/hard", "PVNet/hard ±"]
    assert float(body[2][5]) == pytest.approx(50.0) and float(body[2][6]) == pytest.approx(30.0)
    plain = T.Entry("PVNet", "pvnet", "hard", synthetic({1: (0.1, 0.1)}))
    assert T.protocol_table([plain], "proj2d")["title"].endswith("< 5 px")


def test_table3_ablations_and_files(tmp_path):
    t3 = T.efficiency_table(_profiles())
    md = T.efficiency_markdown(t3)
    assert "| hff6dof | 56.82 (56.82) | 80.00 (85.12) |" in md and "35.00 (29.38)" in md
    assert "| densefusion | 41.70 | 140.00 (142.25) |" in md and "pvnet | error: no" in md
    fusion = {k: T.Entry(f"f{k}", "hff6dof", "hard", synthetic({1: (0.1 * k, 0.5)})) for k in (1, 3, 4)}
    ft = T.fusion_table(fusion)
    assert [r["fuse_stages"] for r in ft["rows"]] == [1, 2, 3, 4, 5]
    assert ft["rows"][1]["add_s"] is None and ft["rows"][3]["add_s_bold"] and not ft["rows"][2]["add_s_bold"]
    assert "skip" in " ".join(ft["notes"])
    with pytest.raises(TdofError, match="1..5"):
        T.fusion_table({6: fusion[1]})
    e = [T.Entry("PVNet", "pvnet", "hard", synthetic({7: (0.2, 0.3), 30: (0.4, 0.1)}))]
    paths = T.write_tables(tmp_path, e, _profiles(), fusion, None, None, header=["# test"])
    for name in ("tables.md", "tables.json", "table1_add_s.csv", "table2_proj2d.csv", "table3_efficiency.csv",
                 "ablation_fusion.csv", "agreement.csv", "plots/accuracy_PVNet.png"):
        assert paths[name].exists(), name
    assert "ablation_segmentation.csv" not in paths
    md = paths["tables.md"].read_text()
    assert md.startswith("# test") and "Segmentation ablation: not run." in md and "obj_000030" in md
    fz = list(csv.reader(io.StringIO(paths["ablation_fusion.csv"].read_text())))
    assert fz[1] == ["1 fused stage", "0", "1", "10.0", "50.0", "", ""] and fz[2][3] == ""
    ag = list(csv.reader(io.StringIO(paths["agreement.csv"].read_text())))
    assert ag[0] == ["id", "claim", "paper", "ours", "agrees", "detail"] and len(ag) == 1 + len(T.CLAIMS)
    # no curves in the score dict: bars per object
    assert paths["plots/accuracy_PVNet.png"].read_bytes()[:4] == b"\x89PNG"
    assert T.catalog_objects([7, 12])[7] == (get_object(7).name, True)


def test_the_primary_row_stands_for_the_method_and_choices_render(tmp_path):
    """Of HFF6DoF's two rows, the one marked primary (reproduce marks the default pose recovery,
    fixed before any result) is the one the claims judge, whatever the order; the choices table
    lands in tables.md, tables.json and choices.csv."""
    bearing = T.Entry("HFF6DoF (bearing + PnP)", "hff6dof", "hard", seeds2({1: (0.30, 0.4)}))
    voting = T.Entry("HFF6DoF (3D voting + LSQ)", "hff6dof", "hard", seeds2({1: (0.52, 0.6)}),
                     extra={"primary": True})
    others = [T.Entry("DenseFusion", "densefusion", "hard", seeds2({1: (0.45, 0.5)}))]
    c = {x["id"]: x for x in T.agreement([bearing, voting, *others])}
    assert "3D voting + LSQ" in c["hff6dof_hard_add_s"]["ours"] and c["hff6dof_hard_add_s"]["agrees"] is True
    assert c["hff6dof_best_add_s_hard"]["agrees"] is True and "+7.00" in c["hff6dof_best_add_s_hard"]["ours"]
    c = {x["id"]: x for x in T.agreement([bearing, T.Entry(voting.label, "hff6dof", "hard", voting.scores), *others])}
    assert "bearing + PnP" in c["hff6dof_hard_add_s"]["ours"] and c["hff6dof_best_add_s_hard"]["agrees"] is False
    ch = [{"result": "pvnet_hard", "choice": "epoch", "chosen": "epoch 3 of 4 (step 30)",
           "validation": "epoch 2: 10.0 / 20.0 %; epoch 3: 12.0 / 20.0 %"}]
    paths = T.write_tables(tmp_path, [bearing, voting, *others], plots=False, choices=ch)
    md = paths["tables.md"].read_text()
    assert md.index("**Chosen on validation**") < md.index("**Table 1")
    assert "| pvnet_hard | epoch | epoch 3 of 4 (step 30) | epoch 2: 10.0 / 20.0 %; epoch 3: 12.0 / 20.0 % |" in md
    assert json.loads(paths["tables.json"].read_text())["choices"] == ch
    assert list(csv.reader(io.StringIO(paths["choices.csv"].read_text())))[1][0] == "pvnet_hard"
    assert "Nothing to choose" in T.choices_markdown([])
    assert "HFF6DoF is the row its method options select, HFF6DoF (3D voting + LSQ), fixed beforehand" in md


def test_the_main_hard_run_is_the_fusion_ablations_three_stage_row(tmp_path):
    """examples/comparison_cpu.toml's fuse_stages = [1, 5] trains no separate 3-stage run: the main
    hard run (3 fused stages) fills that row, so 'best fused stages' is measured (it read '—' and
    'not measured' in the first trained comparison)."""
    from pathlib import Path

    from tdof20.experiments.reproduce_config import make_config
    from tdof20.experiments.reproduce_plan import planned_predictions
    from tdof20.experiments.reproduce_report import table_entries

    cfg = make_config(config=Path(__file__).parents[1] / "examples" / "comparison_cpu.toml")
    assert cfg.ablations.fuse_stages == (1, 5)
    (tmp_path / "scores").mkdir()
    values = {"hff6dof_hard": 0.40, "hff6dof_fuse1_hard": 0.10, "hff6dof_fuse5_hard": 0.20}
    for p in planned_predictions(cfg):
        v = values.get(p["row"], 0.05)
        write_json(tmp_path / "scores" / f"{p['name']}.json", synthetic({17: (v + 0.01 * p["seed"], v)}))
    entries, fusion, seg_on, _ = table_entries(tmp_path, cfg, None)
    assert sorted(fusion) == [1, 3, 5] and fusion[3] is seg_on
    assert fusion[3].value("add_s") == pytest.approx(0.405)
    ft = T.fusion_table(fusion)
    assert [r["add_s"] is not None for r in ft["rows"]] == [True, False, True, False, True]
    c = {x["id"]: x for x in T.agreement(entries, [], fusion, seg_on, None)}
    assert c["best_fuse_stages"]["agrees"] is True


def test_one_object_is_counted_in_the_singular(dataset):
    """A split of one object: "mean (1 object)" in the tables and the score report, not "1 objects"."""
    from tdof20.scoring.report import report_markdown, report_text

    root, gt = dataset
    ev = evaluate(rows([g for g in gt if g[0] == 7]), root, split="simple")
    names = [r["name"] for r in T.protocol_table([T.Entry("PVNet", "pvnet", "simple", scored(root, gt, "simple"))],
                                                 "add_s")["rows"]]
    assert names == ["handle_cup_280", "mean (1 object)"]
    for text in (report_text([ev]), report_markdown([ev])):
        assert "mean (1 object)" in text and "all (4 targets)" in text, text
        assert "1 objects" not in text
