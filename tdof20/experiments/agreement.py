"""The agreement with the paper: its stated figures (sections 5.4-5.5) beside ours, and a computed
yes / no per claim (:data:`CLAIMS` says how each is judged; docs/reproduce.md).

A claim about a difference between rows (a ranking, simple above hard, a gain, the best number of
fused stages) is "yes" only when the difference exceeds the spread over seeds: the two rows'
half-ranges together (their ranges over the seeds do not overlap). A row trained with one seed has
no spread: such a claim is then "not measured". A row marked oracle (ground-truth masks) takes
part in no claim.

    claims = agreement(entries, profiles, fusion, seg_on, seg_off)   # [{"id", "paper", "ours", "agrees", ...}]
    print(agreement_markdown(claims))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from tdof20.experiments.entries import ORACLE, Entry, csv_text, pct, pm, signed

#: the paper's stated figures (sections 5.4-5.5); accuracies as fractions
PAPER = {
    "hff6dof_hard_add_s": 0.5050,          # "an average ADD of 50.5 %"; "the highest ADD of 50.50 %" (3 fused)
    "add_s_over_densefusion_hard": 0.0713,  # "7.13 % higher ADD accuracy on TDoF20-hard compared to DenseFusion"
    "proj2d_over_ffb6d_hard": 0.1191,      # "2D projection ... 11.91 % higher than that of FFB6DoF"
    "hff6dof_fps": 29.38,                  # on a GTX 1080Ti
    "hff6dof_parameters_M": 56.82,
    "macs_G": {"hff6dof": 85.12, "densefusion": 142.25, "ffb6d": 215.54},
    "seg_gain_add_s": 0.0852,
    "seg_gain_proj2d": 0.0263,
    "best_fuse_stages": 3,
    "gpu": "GTX 1080Ti",
}


#: how close a figure must be to the paper's to "agree"
TOLERANCE = {"accuracy_pp": 5.0,    # percentage points, for accuracies and margins
             "parameters_rel": 0.01,  # relative, parameters
             "macs_rel": 0.10,        # relative, multiply-adds
             "fps_rel": 0.10}         # ours at least (1 - this) x the paper's FPS


#: the claims :func:`agreement` judges, and how
CLAIMS = {
    "hff6dof_hard_add_s": "HFF6DoF's mean ADD(S) on TDoF20-hard is 50.50 %: yes when ours is within "
                          "±5 percentage points",
    "hff6dof_best_add_s_hard": "HFF6DoF has the best mean ADD(S) on TDoF20-hard, 7.13 % above DenseFusion, the best "
                               "of the others: yes when HFF6DoF is first and DenseFusion second",
    "hff6dof_best_proj2d_hard": "HFF6DoF has the best mean 2D projection on TDoF20-hard, 11.91 % above FFB6D, the "
                                "best of the others: yes when HFF6DoF is first and FFB6D second",
    "simple_above_hard": "every method scores a higher mean ADD(S) trained and tested on TDoF20-simple than on "
                         "TDoF20-hard: yes when it holds for every method with both",
    "hff6dof_fps": "HFF6DoF runs at 29.38 FPS (GTX 1080Ti): yes when ours, end to end on this device, is at least "
                   "90 % of it",
    "hff6dof_parameters": "HFF6DoF has 56.82 M parameters: yes within 1 %",
    "macs_hff6dof": "HFF6DoF: 85.12 G multiply-adds at 480x640: yes within 10 %",
    "macs_densefusion": "DenseFusion: 142.25 G multiply-adds at 480x640: yes within 10 %",
    "macs_ffb6d": "FFB6D: 215.54 G multiply-adds at 480x640: yes within 10 %",
    "macs_order": "HFF6DoF needs the fewest multiply-adds, then DenseFusion, then FFB6D: yes when our counts rank so",
    "seg_gain_add_s": "the segmentation module adds 8.52 % ADD(S) (hard): yes when ours is a gain beyond the "
                      "spread",
    "seg_gain_proj2d": "the segmentation module adds 2.63 % 2D projection (hard): yes when ours is a gain beyond "
                       "the spread",
    "best_fuse_stages": "3 fused stages give the best ADD(S) on TDoF20-hard: yes when 3 is our best of the "
                        "stages run, ahead of the next beyond the spread",
}

#: the claims judged on a difference between rows: "yes" only beyond the spread over seeds
DIFFERENCE_CLAIMS = ("hff6dof_best_add_s_hard", "hff6dof_best_proj2d_hard", "simple_above_hard", "seg_gain_add_s",
                     "seg_gain_proj2d", "best_fuse_stages")


def _spread(e: Entry, key: str) -> float | None:
    """A row's spread over seeds (half-range; None with one seed)."""
    return e.spread(key)


def beyond_spread(a: Entry, b: Entry, key: str) -> bool | None:
    """Whether a's mean exceeds b's by more than their spreads together (their ranges over the
    seeds do not overlap); None when either row has one seed (no spread to judge by)."""
    sa, sb = _spread(a, key), _spread(b, key)
    if sa is None or sb is None:
        return None
    return a.value(key) - b.value(key) > sa + sb


def _spread_text(*es: Entry, key: str) -> str:
    sp = [_spread(e, key) for e in es]
    if any(v is None for v in sp):
        return "one seed: no spread to judge the difference by"
    return "spreads (half-ranges over seeds) " + " and ".join(f"±{100 * v:.2f}" for v in sp)


def _claim(cid: str, paper: str, ours: str, agrees: bool | None, detail: str = "") -> dict:
    return {"id": cid, "claim": CLAIMS[cid], "paper": paper, "ours": ours, "agrees": agrees, "detail": detail}


def _primary(entries: Sequence[Entry], method: str, split: str) -> Entry | None:
    """The row standing for ``method`` on ``split``: the one marked primary (fixed beforehand:
    HFF6DoF's default pose recovery), else the first; never a row with oracle masks."""
    clean = [e for e in entries if e.method == method and e.split == split and not e.oracle_masks]
    chosen = [e for e in clean if e.extra.get("primary")]
    return (chosen or clean or [None])[0]


def _ranking(entries: Sequence[Entry], key: str, first: str, second: str, margin: float, cid: str) -> dict:
    per = {}
    for e in sorted(entries, key=lambda e: not e.extra.get("primary")):  # a row chosen on validation first
        if e.split == "hard" and not e.oracle_masks and e.method not in per and e.value(key) is not None:
            per[e.method] = e
    mine = per.get(first)
    others = {m: e for m, e in per.items() if m != first}
    paper = f"{first} first, {second} second, +{100 * margin:.2f} %"
    if mine is None or not others:
        return _claim(cid, paper, "not measured (needs " + first + " and another method on hard)", None)
    best_m, best_e = max(others.items(), key=lambda kv: kv[1].value(key))
    diff = mine.value(key) - best_e.value(key)
    order = sorted(per, key=lambda m: -per[m].value(key))
    ranking = order[0]
    for a, b in zip(order, order[1:]):
        ranking += (" = " if per[a].value(key) == per[b].value(key) else " > ") + b
    ours = f"{ranking}; {first} {pm(mine.value(key), mine.spread(key))} % vs {best_m} " \
           f"{pm(best_e.value(key), best_e.spread(key))} % ({signed(diff)} %)"
    # first ahead of every other beyond the spread, and the paper's second ahead of the rest beyond it
    ahead = [beyond_spread(mine, e, key) for e in others.values()]
    runner = [beyond_spread(others[second], e, key) for m, e in others.items() if m != second] \
        if second in others else [False]
    verdicts = ahead + runner
    ok = None if any(v is None for v in verdicts) else (best_m == second and all(verdicts))
    return _claim(cid, paper, ours, ok, f"margin differs from the paper's by {100 * (diff - margin):+.2f} points; "
                  + _spread_text(mine, best_e, key=key))


def agreement(entries: Sequence[Entry], profiles: Sequence[Mapping] = (),
              fusion: Mapping[int, Entry] | None = None, seg_on: Entry | None = None,
              seg_off: Entry | None = None) -> list[dict]:
    """The paper's stated figures beside ours: one dict per claim of :data:`CLAIMS` — {"id",
    "claim", "paper", "ours", "agrees" (True / False / None = not measured), "detail"}."""
    tol = TOLERANCE
    out = []
    hff = _primary(entries, "hff6dof", "hard")
    if hff is None or hff.value("add_s") is None:
        out.append(_claim("hff6dof_hard_add_s", "50.50 %", "not measured", None))
    else:
        v = hff.value("add_s")
        out.append(_claim("hff6dof_hard_add_s", "50.50 %", f"{pm(v, hff.spread('add_s'))} % ({hff.title})",
                          abs(100 * (v - PAPER["hff6dof_hard_add_s"])) <= tol["accuracy_pp"],
                          f"{100 * (v - PAPER['hff6dof_hard_add_s']):+.2f} points"))
    out.append(_ranking(entries, "add_s", "hff6dof", "densefusion", PAPER["add_s_over_densefusion_hard"],
                        "hff6dof_best_add_s_hard"))
    out.append(_ranking(entries, "proj2d", "hff6dof", "ffb6d", PAPER["proj2d_over_ffb6d_hard"],
                        "hff6dof_best_proj2d_hard"))
    pairs = []
    for m in dict.fromkeys(e.method for e in entries):
        s, h = _primary(entries, m, "simple"), _primary(entries, m, "hard")
        if s is not None and h is not None and s.value("add_s") is not None and h.value("add_s") is not None:
            pairs.append((m, s, h))
    verdicts = [beyond_spread(s, h, "add_s") for _, s, h in pairs]
    out.append(_claim("simple_above_hard", "higher on simple for every method",
                      "; ".join(f"{m} {pm(s.value('add_s'), s.spread('add_s'))} vs "
                                f"{pm(h.value('add_s'), h.spread('add_s'))}" for m, s, h in pairs) or "not measured",
                      None if not pairs or any(v is None for v in verdicts) else all(verdicts),
                      "" if not pairs else _spread_text(*(e for _, s, h in pairs for e in (s, h)), key="add_s")))

    prof = {p.get("method"): p for p in profiles if not p.get("error")}
    hp = prof.get("hff6dof")
    if hp is None or hp.get("end_to_end_fps") is None:
        out += [_claim("hff6dof_fps", "29.38 FPS (GTX 1080Ti)", "not measured", None),
                _claim("hff6dof_parameters", "56.82 M", "not measured", None)]
    else:
        fps = float(hp["end_to_end_fps"])
        out.append(_claim("hff6dof_fps", "29.38 FPS (GTX 1080Ti)",
                          f"{fps:.2f} FPS end to end ({hp.get('network_fps')} network only) on {hp.get('device')}",
                          fps >= (1 - tol["fps_rel"]) * PAPER["hff6dof_fps"]))
        params = float(hp["parameters_M"])
        out.append(_claim("hff6dof_parameters", "56.82 M", f"{params:.2f} M",
                          abs(params - PAPER["hff6dof_parameters_M"]) <= tol["parameters_rel"] * PAPER["hff6dof_parameters_M"]))
    macs = {}
    for m, paper_g in PAPER["macs_G"].items():
        p = prof.get(m)
        g = None if p is None else p.get("macs_480x640_G")
        if g is None:
            out.append(_claim(f"macs_{m}", f"{paper_g} G", "not measured", None))
            continue
        macs[m] = float(g)
        out.append(_claim(f"macs_{m}", f"{paper_g} G", f"{float(g):.2f} G",
                          abs(float(g) - paper_g) <= tol["macs_rel"] * paper_g, f"{100 * (float(g) / paper_g - 1):+.1f} %"))
    order = ("hff6dof", "densefusion", "ffb6d")
    if all(m in macs for m in order):
        ours = " < ".join(sorted(order, key=lambda m: macs[m]))
        out.append(_claim("macs_order", "hff6dof < densefusion < ffb6d", ours,
                          macs["hff6dof"] < macs["densefusion"] < macs["ffb6d"]))
    else:
        out.append(_claim("macs_order", "hff6dof < densefusion < ffb6d", "not measured", None))

    for key, cid in (("add_s", "seg_gain_add_s"), ("proj2d", "seg_gain_proj2d")):
        paper = f"+{100 * PAPER[cid]:.2f} %"
        a = None if seg_on is None else seg_on.value(key)
        b = None if seg_off is None else seg_off.value(key)
        if a is None or b is None:
            out.append(_claim(cid, paper, "not measured", None))
        elif seg_off.oracle_masks:  # an oracle row takes part in no claim
            out.append(_claim(cid, paper, f"not measured: without the head the masks were ground truth ({ORACLE}, "
                                          f"an oracle row outside every claim): {signed(a - b)} % ({pct(a)} with, "
                                          f"{pct(b)} without)", None))
        else:
            out.append(_claim(cid, paper, f"{signed(a - b)} % ({pm(a, seg_on.spread(key))} with, "
                                          f"{pm(b, seg_off.spread(key))} without, masks of a separately trained "
                                          "segmentation network)", beyond_spread(seg_on, seg_off, key),
                              _spread_text(seg_on, seg_off, key=key)))
    fz = {int(k): e for k, e in (fusion or {}).items() if e.value("add_s") is not None and not e.oracle_masks}
    vals = {k: e.value("add_s") for k, e in fz.items()}
    if len(vals) < 2 or 3 not in vals:
        out.append(_claim("best_fuse_stages", "3", "not measured (needs 3 and another number of fused stages)", None))
    else:
        top = max(vals.values())
        best = [k for k in sorted(vals) if vals[k] == top]
        shown = " = ".join(str(k) for k in best) + (" (tie)" if len(best) > 1 else "")
        verdicts = [beyond_spread(fz[3], e, "add_s") for k, e in fz.items() if k != 3]
        ok = None if any(v is None for v in verdicts) else (best == [3] and all(verdicts))
        out.append(_claim("best_fuse_stages", "3", f"{shown} (" + ", ".join(
            f"{k}: {pm(v, fz[k].spread('add_s'))}" for k, v in sorted(vals.items())) + ")", ok,
            _spread_text(*fz.values(), key="add_s")))
    return out


def _yes(v: bool | None) -> str:
    return "not measured" if v is None else ("yes" if v else "no")


def agreement_markdown(claims: Sequence[Mapping], hff_row: str | None = None) -> str:
    """The claims as markdown; ``hff_row`` names the row that stands for HFF6DoF in them (the one
    its method options select, fixed before any result)."""
    row = f"the row its method options select, {hff_row}" if hff_row else "its default row (bearing + PnP)"
    out = ["**Agreement with the paper's stated figures**", "", "| claim | paper | ours | agrees |",
           "| --- | --- | --- | :---: |"]
    for c in claims:
        out.append(f"| {c['claim']} | {c['paper']} | {c['ours']} | {_yes(c['agrees'])} |")
    n = [c["agrees"] for c in claims]
    out += ["", f"{sum(1 for v in n if v is True)} of {sum(1 for v in n if v is not None)} claims measured agree "
                f"({sum(1 for v in n if v is None)} not measured). Judged from what the data gives; nothing was "
                "tuned on a test part. A claim about a difference between rows is yes only when the difference "
                "exceeds the rows' spreads over seeds together (not measured with one seed); HFF6DoF is "
                f"{row}, fixed beforehand; rows with oracle masks take part in no claim."]
    return "\n".join(out)


def agreement_csv(claims: Sequence[Mapping]) -> str:
    keys = ["id", "claim", "paper", "ours", "agrees", "detail"]
    return csv_text([keys] + [[c[k] if k != "agrees" else _yes(c[k]) for k in keys] for c in claims])
