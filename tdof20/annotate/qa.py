"""Quality checks a person looks at: overlays, registration plots and one HTML report per scene.

:func:`write_qa` writes into ``SCENE_DIR/qa/`` (or ``out_dir``)::

    overlays/{im_id:06d}.png   colour image with, per object, the visible mask filled lightly and
                               outlined, the full silhouette's contour dashed, and the model's
                               Monte-Carlo points projected by the label pose; a caption (image
                               id, arm/step, object ids) and, for a flagged frame, the reason
    contact_sheet.png          the overlays in one grid
    registration.png           (with a registration result) residual_deg, residual_mm, fitness and
                               rmse against the step, one column per arm position; flagged frames
                               in red, the thresholds of the result's config dashed
    qa.json                    what the report shows, for scripts
    report.html                scene id, counts, flagged frames and reasons, per-object table
                               (scene_gt_info), registration plot, evaluation (when given), overlays

Overlays are drawn for ``sample`` labelled frames spread evenly over the image ids (so over the
arm positions and their steps) and for every flagged frame that has a colour image — the scene's
``rgb/``, else the source session's transparent frame (``scene_info.json`` ``source_session``);
a flagged frame without labels gets the plain colour image with its reason written on it.
Small images are enlarged (integer factor, nearest) to at least 320 px wide so the captions fit.
"""

from __future__ import annotations

import html
import io
import math
import textwrap
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from tdof20.annotate.registration_result import RegistrationResult, depth_scale_text
from tdof20.errors import TdofError
from tdof20.formats import (SCENE_CAMERA, BopScene, RawSession, atomic_write_bytes, read_json, read_png, read_scene,
                            write_json, write_png)
from tdof20.formats.bop_models import model_path, read_model_mesh
from tdof20.geometry.sampling import sample_mesh_surface
from tdof20.progress import progress as _progress
from tdof20.viz import contact_sheet, object_colour, put_label

__all__ = ["write_qa", "draw_overlay", "plot_registration", "normalise_flagged", "spread_sample"]

_MIN_WIDTH = 320
_PLOTS = (("residual_deg", "residual (deg)", "max_residual_deg"),
          ("residual_mm", "residual (mm)", "max_residual_mm"),
          ("fitness", "fitness", "min_fitness"),
          ("rmse", "inlier RMSE (mm)", "max_rmse_mm"))


# ---------------------------------------------------------------------------------------------
# drawing
# ---------------------------------------------------------------------------------------------
def _colour(obj_id: int) -> np.ndarray:
    """A bright colour (3,) uint8 fixed per object id (:func:`tdof20.viz.object_colour`)."""
    return object_colour(obj_id)


def _contour_pixels(mask: np.ndarray) -> np.ndarray:
    """(N,2) x,y of the outer contours' pixels of a mask, in order along each contour."""
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return np.concatenate([c.reshape(-1, 2) for c in cs]) if cs else np.zeros((0, 2), int)


def draw_overlay(rgb: np.ndarray, K: np.ndarray, instances: list[dict], alpha: float = 0.3,
                 scale: int = 1, dash: int = 3) -> np.ndarray:
    """Labels drawn on a colour image (H,W,3 uint8; returns (H*scale, W*scale, 3) uint8).

    ``instances``: [{"obj_id", "full" (H,W) bool, "visib" (H,W) bool, optional "R" (3,3), "t" (3,)
    mm and "points" (N,3) model samples}]: the visible mask filled with ``alpha`` of the object's
    colour and outlined (solid), the full mask's contour dashed (``dash`` pixels on, off), and the
    model points posed by (R, t) and projected with ``K`` (one pixel each, index assignment)."""
    s = max(1, int(scale))
    out = rgb if s == 1 else cv2.resize(rgb, None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
    out = np.ascontiguousarray(out, dtype=np.uint8).copy()
    H, W = out.shape[:2]
    up = (lambda m: m) if s == 1 else (lambda m: cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0)
    ups = [(up(np.asarray(i["full"], bool)), up(np.asarray(i["visib"], bool))) for i in instances]
    f = out.astype(np.float32)
    for inst, (_, vis) in zip(instances, ups):
        f[vis] = (1 - alpha) * f[vis] + alpha * _colour(inst["obj_id"])
    out = f.astype(np.uint8)
    for inst, (full, vis) in zip(instances, ups):
        col = _colour(inst["obj_id"])
        cs, _ = cv2.findContours(vis.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, cs, -1, tuple(int(c) for c in col), 1)
        xy = _contour_pixels(full)
        on = (np.arange(len(xy)) // dash) % 2 == 0
        out[xy[on, 1], xy[on, 0]] = col
        if inst.get("points") is not None and inst.get("R") is not None:
            X = np.asarray(inst["points"], float) @ np.asarray(inst["R"], float).T + np.asarray(inst["t"], float)
            X = X[X[:, 2] > 1.0]
            p = X @ np.asarray(K, float).T
            uv = np.rint(p[:, :2] / p[:, 2:3] * s + (s - 1) / 2).astype(np.int64)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            out[uv[ok, 1], uv[ok, 0]] = np.minimum(255, col.astype(int) + 60).astype(np.uint8)
    return out


def _put_bottom(img: np.ndarray, text: str, colour=(255, 90, 90), max_lines: int = 3) -> np.ndarray:
    """Write ``text`` (wrapped to the width) at the bottom on a dark band (returns a copy)."""
    out = np.ascontiguousarray(img.copy())
    scale = max(0.35, img.shape[1] / 900)
    (cw, th), base = cv2.getTextSize("M", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    per_line = max(8, int((img.shape[1] - 6) / max(cw * 0.75, 1)))
    lines = textwrap.wrap(" ".join(text.split()), per_line)[:max_lines] or [""]
    lh = th + base + 3
    y0 = img.shape[0] - lh * len(lines) - 3
    cv2.rectangle(out, (0, y0), (img.shape[1], img.shape[0]), (0, 0, 0), -1)
    for k, line in enumerate(lines):
        cv2.putText(out, line, (3, y0 + th + 2 + k * lh), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return out


# ---------------------------------------------------------------------------------------------
# registration plot
# ---------------------------------------------------------------------------------------------
def plot_registration(result, path: str | Path) -> Path:
    """Residuals of a RegistrationResult against the step, one column per arm position (PNG,
    written atomically): residual_deg, residual_mm, fitness, rmse; flagged frames (also every
    frame of a flagged arm) in red; the config's thresholds as dashed lines."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_arms = max(1, int(result.n_arms))
    flagged = {(a, k) for a, k, _ in result.flagged_frames()}
    fig = Figure(figsize=(3.4 * n_arms + 0.6, 8.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(_PLOTS), n_arms, squeeze=False, sharex="col")
    for a in range(n_arms):
        fr = sorted((f for f in result.frames if f.arm == a), key=lambda f: f.step)
        steps = np.array([f.step for f in fr], float)
        bad = np.array([(f.arm, f.step) in flagged for f in fr], bool)
        arm = next((x for x in result.arms if x.arm == a), None)
        for r, (key, label, thr_key) in enumerate(_PLOTS):
            ax = axes[r, a]
            y = np.array([getattr(f, key) for f in fr], float)
            if len(fr):
                ax.plot(steps, y, "-", color="0.6", lw=0.8)
                ax.plot(steps[~bad], y[~bad], ".", color="tab:blue", ms=3, label="ok")
                if bad.any():
                    ax.plot(steps[bad], y[bad], "x", color="red", ms=6, mew=1.5, label="flagged")
            thr = result.config.get(thr_key) if isinstance(result.config, dict) else None
            if isinstance(thr, (int, float)) and math.isfinite(thr):
                ax.axhline(float(thr), ls="--", color="red" if thr_key != "min_fitness" else "darkorange", lw=1,
                           label=f"{thr_key} {thr:g}")
            if a == 0:
                ax.set_ylabel(label)
            if r == 0:
                title = f"arm {a}"
                if arm is not None and arm.flagged:
                    title += " (arm flagged)"
                ax.set_title(title, color="red" if arm is not None and arm.flagged else "black", fontsize=10)
            if r == len(_PLOTS) - 1:
                ax.set_xlabel("turntable step")
            ax.grid(alpha=0.3)
            if a == n_arms - 1 and r == 0:
                ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"registration residuals — scene {result.scene_id}", fontsize=11)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    return path


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------
def normalise_flagged(flagged: Iterable[Any], steps: int | None) -> dict[int, list[str]]:
    """{im_id: [reasons]} from items (arm, step, reason), (im_id, reason), im_id, or dicts with
    "im_id" or "arm"/"step" and "reason". (arm, step) needs ``steps`` (im_id = arm * steps + step)."""
    out: dict[int, list[str]] = {}

    def add(im, reason):
        reasons = out.setdefault(int(im), [])
        if reason and reason not in reasons:
            reasons.append(str(reason))

    for item in flagged or ():
        if isinstance(item, dict):
            if "im_id" in item:
                add(item["im_id"], item.get("reason", "flagged"))
                continue
            item = (item.get("arm"), item.get("step"), item.get("reason", "flagged"))
        if isinstance(item, (int, np.integer)):
            add(item, "flagged")
        elif isinstance(item, (tuple, list)) and len(item) == 2:
            add(item[0], item[1] or "flagged")
        elif isinstance(item, (tuple, list)) and len(item) == 3:
            if not steps:
                raise TdofError("flagged frames given as (arm, step, reason) but the number of steps is "
                                "unknown (no scene_info.json and no registration result)")
            add(int(item[0]) * int(steps) + int(item[1]), item[2] or "flagged")
        else:
            raise TdofError(f"cannot read the flagged frame {item!r}: give (arm, step, reason), "
                            f"(im_id, reason) or an image id")
    for reasons in out.values():
        if not reasons:
            reasons.append("flagged")
    return out


def spread_sample(ids: list[int], k: int) -> list[int]:
    """``k`` of the sorted ``ids`` spread evenly (image ids run arm-major, so the pick covers
    every arm position and its steps in proportion)."""
    ids = sorted(ids)
    if k <= 0 or not ids:
        return []
    if len(ids) <= k:
        return ids
    return [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, k).round().astype(int))]


def _open_scene(scene_dir: str | Path) -> BopScene:
    p = Path(scene_dir)
    if not p.is_dir():
        raise TdofError("no such scene folder", p)
    if not (p / SCENE_CAMERA).exists():
        raise TdofError(f"not an annotated scene: no {SCENE_CAMERA}", p)
    return read_scene(p, require_gt=False)


def _load_registration(registration):
    if registration is None:
        return None
    if isinstance(registration, RegistrationResult):
        return registration
    return RegistrationResult.load(registration)


class _Points:
    """Monte-Carlo samples of the scene's models (loaded on first use; None when absent)."""

    def __init__(self, models_dir: Path, n: int):
        self.dir, self.n, self.cache, self.problems = models_dir, n, {}, []

    def __call__(self, obj_id: int) -> np.ndarray | None:
        if obj_id not in self.cache:
            path = model_path(self.dir, obj_id)
            pts = None
            try:
                pts = sample_mesh_surface(*read_model_mesh(path), self.n, seed=0)
            except TdofError as e:  # a missing or bad model only loses the points of the overlay
                self.problems.append(f"{e}: model points not drawn")
            self.cache[obj_id] = pts
        return self.cache[obj_id]


# ---------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------
def write_qa(scene_dir: str | Path, registration=None, flagged: Iterable[Any] = (), sample: int = 12,
             out_dir: str | Path | None = None, progress: bool = True, evaluation: dict | None = None,
             n_points: int = 600, session_dir: str | Path | None = None,
             failed_objects: Iterable[dict] = (), twins: Iterable[dict] = (),
             uncertainty: dict | None = None) -> Path:
    """Write the QA outputs of an annotated scene (see the module docstring); returns the path of
    ``report.html``. ``registration``: a RegistrationResult or the path of its JSON (its flagged
    frames join ``flagged``); ``flagged``: [(arm, step, reason) | (im_id, reason) | im_id];
    ``evaluation``: the dict of :func:`tdof20.annotate.evaluate.evaluate_scene`; ``session_dir``:
    where to find colour images of frames the scene lacks (default: scene_info's source_session);
    ``twins``: the place stage's twin check per object ({obj_id, action, note, offset_mm, ...});
    ``uncertainty``: the labels' 95 % error bounds per object (label.json's "uncertainty":
    :func:`tdof20.annotate.uncertainty.per_object`)."""
    scene = _open_scene(scene_dir)
    out = Path(out_dir) if out_dir is not None else scene.path / "qa"
    info = read_json(scene.path / "scene_info.json") if (scene.path / "scene_info.json").exists() else {}
    reg = _load_registration(registration)
    steps = info.get("steps") or (reg.steps if reg is not None else None)
    n_arms = info.get("n_arms") or (reg.n_arms if reg is not None else None)
    flags = normalise_flagged(list(reg.flagged_frames()) if reg is not None else [], steps)
    for im, reasons in normalise_flagged(flagged, steps).items():
        for r in reasons:
            if r not in flags.setdefault(im, []):
                flags[im].append(r)

    src = session_dir or info.get("source_session")
    opened: list = []   # the source session, opened when a frame first needs it (parsing its
                        # journal costs ~1 s for 3,200 frames; a labelled frame never does)

    def source_session():
        if not opened:
            session = None
            if src and Path(src).is_dir():
                try:
                    session = RawSession.open(src)
                except TdofError:
                    session = None
            opened.append(session)
        return opened[0]

    def arm_step(im: int):
        return divmod(int(im), int(steps)) if steps else (None, None)

    def colour_image(im: int) -> np.ndarray | None:
        p = scene.path / "rgb" / f"{im:06d}.png"
        if p.exists():
            return read_png(p, kind="rgb")
        a, k = arm_step(im)
        session = source_session() if a is not None else None
        if session is not None and session.has_frame("transparent", a, k):
            return session.load_rgb("transparent", a, k)
        return None

    labelled = sorted(i for i, lst in scene.gt.items() if lst)
    picks = sorted(set(spread_sample(labelled, sample)) | set(flags))
    points = _Points(scene.path / "models", n_points)
    problems: list[str] = []
    overlays: list[dict] = []
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    with _progress(progress and bool(picks), unit="img") as bar:
        task = bar.add_task("qa overlays", total=len(picks))
        for im in picks:
            bar.advance(task)
            rgb = colour_image(im)
            if rgb is None:
                if im in flags:
                    problems.append(f"image {im}: flagged, but no colour image to draw on")
                continue
            scale = max(1, math.ceil(_MIN_WIDTH / rgb.shape[1]))
            insts, reasons = [], list(flags.get(im, []))
            if scene.gt.get(im):
                try:
                    for g, e in enumerate(scene.gt[im]):
                        insts.append({"obj_id": e["obj_id"], "full": scene.mask(im, g), "visib": scene.mask(im, g, visib=True),
                                      "R": e["cam_R_m2c"], "t": e["cam_t_m2c"], "points": points(e["obj_id"])})
                except TdofError as err:
                    insts = []
                    reasons.append(f"labels not drawn: {err}")
                    problems.append(f"image {im}: {err}")
            K = scene.camera[im]["cam_K"] if im in scene.camera else np.eye(3)
            img = draw_overlay(rgb, K, insts, scale=scale)
            a, k = arm_step(im)
            cap = f"im {im}" + (f" arm {a} step {k}" if a is not None else "")
            cap += (" obj " + ",".join(str(i["obj_id"]) for i in insts)) if insts else " (no labels)"
            img = put_label(img, cap)
            if reasons:
                img = _put_bottom(img, "FLAGGED: " + "; ".join(reasons) if im in flags else "; ".join(reasons))
            name = f"overlays/{im:06d}.png"
            write_png(out / name, img)
            overlays.append({"im_id": im, "arm": a, "step": k, "file": name, "caption": cap,
                             "flagged": im in flags, "labelled": bool(insts)})
    problems += points.problems
    written = {Path(o["file"]).name for o in overlays}
    for f in (out / "overlays").glob("[0-9][0-9][0-9][0-9][0-9][0-9].png"):
        if f.name not in written:   # an overlay of an earlier run: the report no longer shows it
            f.unlink()

    sheet = None
    if overlays:
        tiles = [read_png(out / o["file"], kind="rgb") for o in overlays]
        sheet_img = contact_sheet(tiles, cols=4, tile_width=min(320, max(t.shape[1] for t in tiles)))
        write_png(out / "contact_sheet.png", sheet_img)
        sheet = "contact_sheet.png"
    reg_png = None
    if reg is not None:
        plot_registration(reg, out / "registration.png")
        reg_png = "registration.png"

    objects = _object_table(scene)
    summary = {
        "scene_id": info.get("scene_id", scene.path.name), "scene": str(scene.path),
        "labels": info.get("labels"), "n_arms": n_arms, "steps": steps,
        "n_planned": (n_arms * steps) if (n_arms and steps) else None,
        "n_images": len(scene.camera), "n_labelled": len(labelled),
        "flagged": [{"im_id": im, "arm": arm_step(im)[0], "step": arm_step(im)[1], "labelled": im in labelled,
                     "reason": "; ".join(r)} for im, r in sorted(flags.items())],
        "objects": objects, "overlays": overlays, "contact_sheet": sheet, "registration_plot": reg_png,
        "problems": problems,
        # objects the place stage's quality gate refused (a partial scene): {obj_id, cluster, reason}
        "failed_objects": [dict(f) for f in failed_objects],
        # the twin check: where each transparent object stands against its opaque twin
        "twins": [dict(t) for t in twins],
        # the labels' 95 % error bounds per object (scene_gt_uncertainty.json): the label-noise floor
        "label_bounds": {str(k): dict(v) for k, v in (uncertainty or {}).items()},
    }
    write_json(out / "qa.json", summary)
    report = out / "report.html"
    atomic_write_bytes(report, _html(summary, reg, evaluation).encode("utf-8"))
    return report


def _object_table(scene: BopScene) -> list[dict]:
    per: dict[int, list[dict]] = {}
    for im, lst in scene.gt.items():
        infos = scene.gt_info.get(im, [])
        for g, e in enumerate(lst):
            per.setdefault(int(e["obj_id"]), []).append(infos[g] if g < len(infos) else {})
    rows = []
    for o in sorted(per):
        es = per[o]

        def med(key, fn=np.median):
            v = [e[key] for e in es if key in e]
            return float(fn(v)) if v else None
        rows.append({"obj_id": o, "instances": len(es), "visib_fract_median": med("visib_fract"),
                     "visib_fract_min": med("visib_fract", np.min), "px_count_visib_median": med("px_count_visib"),
                     "px_count_all_median": med("px_count_all"),
                     "n_hidden": sum(1 for e in es if e.get("px_count_visib", 1) == 0)})
    return rows


# ---------------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------------
_CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.2em}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td.l,th.l{text-align:left}tr.bad td{background:#fde8e8}
.grid{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0;width:330px}figure img{width:100%}
figcaption{font-size:.8em}.flag{color:#c00;font-weight:bold}img.plot{max-width:100%}"""


def _e(x: Any) -> str:
    return html.escape("" if x is None else str(x), quote=True)


def _n(v: Any, d: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.{d}f}"
    return _e(v)


def _table(head: list[str], rows: list[list[str]], left: Iterable[int] = (), bad: Iterable[int] = ()) -> str:
    left, bad = set(left), set(bad)
    h = "".join(f'<th class="l">{_e(c)}</th>' if i in left else f"<th>{_e(c)}</th>" for i, c in enumerate(head))
    body = []
    for r, row in enumerate(rows):
        cells = "".join(f'<td class="l">{c}</td>' if i in left else f"<td>{c}</td>" for i, c in enumerate(row))
        body.append(f'<tr class="bad">{cells}</tr>' if r in bad else f"<tr>{cells}</tr>")
    return f"<table><tr>{h}</tr>{''.join(body)}</table>"


def _html(s: dict, reg, evaluation: dict | None) -> str:
    p: list[str] = []
    title = f"QA report — scene {s['scene_id']}"
    p.append(f"<!doctype html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{_CSS}</style></head><body>")
    p.append(f"<h1>{_e(title)}</h1><p>{_e(s['scene'])}" + (f" — labels: {_e(s['labels'])}" if s.get("labels") else "") + "</p>")
    p.append("<h2>Counts</h2>")
    p.append(_table(["", "frames"], [["planned (arms × steps)", _n(s["n_planned"])], ["images in the scene", _n(s["n_images"])],
                                     ["labelled", _n(s["n_labelled"])], ["flagged", _n(len(s["flagged"]))]], left=[0]))
    if s.get("failed_objects"):
        p.append("<h2>Objects not labelled (partial scene)</h2>")
        p.append(_table(["obj_id", "reason"], [[_n(f["obj_id"]), _e(f["reason"])] for f in s["failed_objects"]],
                        left=[1], bad=range(len(s["failed_objects"]))))
    if s.get("twins"):
        p.append("<h2>Twin placement</h2><p>where each transparent object stands against its opaque twin, "
                 "from the transparent phase's glass returns (docs/annotate.md)</p>")
        tw = s["twins"]
        p.append(_table(["obj_id", "action", "offset (mm)", "± 95 %", "turn (deg)", "± 95 %", "returns", "note"],
                        [[_n(t["obj_id"]), _e(t["action"]), _n(t.get("offset_mm")), _n(t.get("ci95_mm")),
                          _n(t.get("turn_deg")), _n(t.get("ci95_deg")), _n(t.get("points")), _e(t["note"])]
                         for t in tw], left=[1, 7], bad=[i for i, t in enumerate(tw) if t["action"] == "flagged"]))
    if s.get("label_bounds"):
        p.append("<h2>Label error bounds (95 %)</h2><p>how far each label may be from the truth, per label in "
                 "scene_gt_uncertainty.json (depth scale, twin placement, model fit, frame motion: "
                 "docs/annotate.md); median and 95th percentile over the object's labels</p>")
        lb = s["label_bounds"]
        p.append(_table(["obj_id", "labels", "translation (mm)", "p95", "rotation (deg)", "p95", "surface (mm)", "p95"],
                        [[_n(int(o)), _n(b["n"]), _n(b["trans_mm_median"]), _n(b["trans_mm_p95"]),
                          _n(b["rot_deg_median"]), _n(b["rot_deg_p95"]), _n(b["surface_mm_median"]),
                          _n(b["surface_mm_p95"])] for o, b in sorted(lb.items(), key=lambda kv: int(kv[0]))]))
    p.append("<h2>Flagged frames</h2>")
    if s["flagged"]:
        files = {o["im_id"]: o["file"] for o in s["overlays"]}
        rows = [[_n(f["im_id"]), _n(f["arm"]), _n(f["step"]), _n(f["labelled"]), _e(f["reason"]),
                 (f'<a href="{_e(files[f["im_id"]])}">overlay</a>' if f["im_id"] in files else "no image")]
                for f in s["flagged"]]
        p.append(_table(["im_id", "arm", "step", "labelled", "reason", ""], rows, left=[4]))
    else:
        p.append("<p>none</p>")
    if s["problems"]:
        p.append("<h2>Problems</h2><ul>" + "".join(f"<li>{_e(x)}</li>" for x in s["problems"]) + "</ul>")
    p.append("<h2>Objects</h2>")
    rows = [[_n(o["obj_id"]), _n(o["instances"]), _n(o["visib_fract_median"]), _n(o["visib_fract_min"]),
             _n(o["px_count_visib_median"], 0), _n(o["px_count_all_median"], 0), _n(o["n_hidden"])] for o in s["objects"]]
    p.append(_table(["obj_id", "instances", "visib_fract median", "visib_fract min", "px visible median",
                     "px all median", "fully hidden"], rows))
    if reg is not None:
        p.append("<h2>Registration</h2>")
        if s.get("registration_plot"):
            p.append(f'<img class="plot" src="{_e(s["registration_plot"])}" alt="registration residuals">')
        rows = [[_n(a.arm), _n(float(a.fitness)), _n(float(a.rmse)), _n(float(a.correction_deg)), _n(float(a.correction_mm)),
                 _n(bool(a.flagged)), _e(a.reason)] for a in reg.arms]
        p.append(_table(["arm", "fitness", "rmse (mm)", "correction (deg)", "correction (mm)", "flagged", "reason"], rows,
                        left=[6], bad=[i for i, a in enumerate(reg.arms) if a.flagged]))
        p.append(f"<p>Depth scale: {_e(depth_scale_text(reg.depth_scale))}</p>")
    if evaluation:
        p.append(_evaluation_html(evaluation))
    p.append("<h2>Overlays</h2><p>visible mask filled and outlined, full silhouette dashed, model points "
             "projected by the label pose.</p><div class='grid'>")
    for o in s["overlays"]:
        cls = " class='flag'" if o["flagged"] else ""
        p.append(f"<figure><a href='{_e(o['file'])}'><img src='{_e(o['file'])}' alt='{_e(o['caption'])}'></a>"
                 f"<figcaption{cls}>{_e(o['caption'])}{' — flagged' if o['flagged'] else ''}</figcaption></figure>")
    p.append("</div>")
    if s.get("contact_sheet"):
        p.append(f"<p><a href='{_e(s['contact_sheet'])}'>contact sheet of the overlays</a></p>")
    p.append("</body></html>\n")
    return "\n".join(p)


_EVAL_COLS = (("motion_rot_deg", "motion rot (deg)", "p95"), ("motion_trans_mm", "motion trans (mm)", "p95"),
              ("surface_mm", "surface (mm)", "p95"), ("iou_full", "IoU full", "p5"), ("iou_visib", "IoU visible", "p5"))


def _evaluation_html(ev: dict) -> str:
    p = ["<h2>Evaluation against the truth</h2>",
         f"<p>{_n(ev.get('n_evaluated_frames'))} frames evaluated of {_n(ev.get('n_truth_frames'))} in the truth "
         f"({_e(ev.get('truth'))}); {len(ev.get('missing_frames') or [])} truth frames missing from the labels.</p>"]
    head = ["object", "frames"] + [f"{lab} median / {q}" for _, lab, q in _EVAL_COLS]
    rows = []
    entries = list((ev.get("objects") or {}).items()) + ([("all", ev["all"])] if "all" in ev else [])
    for name, e in entries:
        row = [_e(name), _n(e.get("n_frames"))]
        for key, _, q in _EVAL_COLS:
            st = e.get(key) or {}
            row.append(f"{_n(st.get('median'))} / {_n(st.get(q))}")
        rows.append(row)
    p.append(_table(head, rows, left=[0]))
    targets = (ev.get("all") or {}).get("targets") or {}
    if targets:
        rows = [[_e(k), _n(t.get("median")), _e(t.get("target")), _n(t.get("ok"))] for k, t in targets.items()]
        p.append(_table(["measure", "median", "target", "met"], rows, left=[0],
                        bad=[i for i, t in enumerate(targets.values()) if t.get("ok") is False]))
    miss = ev.get("missing_frames") or []
    if miss:
        more = f" … ({len(miss)} in all)" if len(miss) > 100 else ""
        p.append(f"<p>missing frames: {_e(', '.join(map(str, miss[:100])))}{_e(more)}</p>")
    low = ev.get("low_visib_iou") or []
    if low:
        rows = [[_n(d.get("im_id")), _n(d.get("obj_id")), _n(d.get("iou_visib")), _n(d.get("iou_full"))] for d in low[:200]]
        thr = (ev.get("settings") or {}).get("iou_warn", 0.9)
        p.append(f"<h3>Visible IoU below {_e(thr)} ({len(low)})</h3>")
        p.append(_table(["im_id", "obj_id", "IoU visible", "IoU full"], rows))
    return "\n".join(p)
