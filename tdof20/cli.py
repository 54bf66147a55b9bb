"""The ``tdof20`` command line: thin — it parses options and calls a stage's public function.

The stages whose modules import torch or open3d (training, prediction, profiling, the annotation
pipeline, the simulator's renderer and oracle labels) are imported inside their commands, so that
``tdof20 --help`` imports neither; every other module is imported here.
"""

from __future__ import annotations

import os

# torch's OpenMP (libgomp) spin-waits at each barrier unless told otherwise, read once when torch
# loads: on shared cores a training step took 6-10x the CPU and wall time
# (benchmarks/train_throughput.py --wait-policy)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json
import re
import shlex
import sys
import time
from pathlib import Path
from typing import Optional

import click
import typer
from rich.markup import escape
from rich.table import Table

from tdof20.annotate.evaluate import evaluate_command
from tdof20.capture import check_workspace, describe, load_config, run_capture, sim_config, verify_session
from tdof20.capture.rig import build_rig
from tdof20.dataset.build import pack, stats
from tdof20.dataset.importer import import_tdof20
from tdof20.dataset.splits import HARD_TEST_MULTI, PAPER_HARD, PAPER_SIMPLE
from tdof20.dataset.validation import write_val_targets
from tdof20.errors import TdofError
from tdof20.experiments.demo import parse_methods, run_demo
from tdof20.experiments.reproduce import reproduce
from tdof20.formats import write_png
from tdof20.formats.io import check_output_file
from tdof20.methods.registry import get_method, method_names, parse_set_options
from tdof20.objects import all_objects, export_models, object_names
from tdof20.progress import console, out_console
from tdof20.scoring.scoring import score_command
from tdof20.server import cli as server_cli
from tdof20.sim.lab import DIRECTIONS, clutter_names
from tdof20.sim.scenes import get_scene, scene_ids
from tdof20.viz import session_contact_sheet

app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  help="Build and benchmark 6DoF pose datasets of transparent objects (TDoF20).")
objects_app = typer.Typer(no_args_is_help=True, help="The 20-object catalog: list, export, picture.")
sim_app = typer.Typer(no_args_is_help=True, help="The simulated rig: scenes, frames, contact sheets.")
capture_app = typer.Typer(no_args_is_help=True, help="Capture sessions on the rig or the simulator: plan, run, verify.")
dataset_app = typer.Typer(no_args_is_help=True, help="Assemble annotated scenes into the TDoF20 dataset and its splits.")


class _AnnotateGroup(typer.core.TyperGroup):
    """``tdof20 annotate RAW --out SCENE`` runs the pipeline (the hidden subcommand ``run``);
    ``tdof20 annotate evaluate ...`` is a subcommand."""

    def parse_args(self, ctx, args):
        # a raw session folder named like a subcommand (./review, evaluate) with the pipeline's --out
        # is a session: no subcommand takes --out
        session_named_like = bool(args) and args[0] in self.commands and "--out" in args \
            and (Path(args[0]) / "session.json").is_file()
        if args and (args[0] not in self.commands or session_named_like) and not args[0].startswith("-"):
            args = ["run", *args]
        return super().parse_args(ctx, args)

    def format_help(self, ctx, formatter):
        """The group's help, then the pipeline's own usage and options (its command is hidden)."""
        super().format_help(ctx, formatter)
        run = self.commands["run"]
        with click.Context(run, info_name=ctx.info_name, parent=ctx.parent) as sub:
            run.format_help(sub, formatter)


annotate_app = typer.Typer(cls=_AnnotateGroup, no_args_is_help=True,
                           help="Annotate a raw session: RAW_DIR --out SCENE_DIR (register, reconstruct, model, "
                                "place, label, qa), or several: RAW_DIR... --out DIR (DIR/multi/08 ...); evaluate "
                                "labels against the simulator's truth; review: correct a scene in a web app.")
benchmark_app = typer.Typer(no_args_is_help=True, help="Score results (ADD, ADD-S, 2D projection) and profile methods.")
app.add_typer(annotate_app, name="annotate")
app.add_typer(benchmark_app, name="benchmark")
app.add_typer(capture_app, name="capture")
app.add_typer(dataset_app, name="dataset")
app.add_typer(objects_app, name="objects")
app.add_typer(sim_app, name="sim")
app.add_typer(server_cli.serve_app, name="serve")
app.command("submit")(server_cli.submit_command)
dataset_app.command("publish")(server_cli.publish_command)

#: the exit code of an annotation that labelled some objects and flagged others (docs/annotate.md)
PARTIAL_EXIT = 3

SCENE = typer.Option("multi/08", help="scene name: single/<class> (e.g. single/cube_136; single/01..20 = object "
                                     "id is an alias) or multi/00..19")
WIDTH = typer.Option(640, help="image width in pixels")
HEIGHT = typer.Option(480, help="image height in pixels")
SEED = typer.Option(0, help="noise seed (frames are deterministic for a seed)")




def _scene(name: str) -> str:
    """``--scene`` checked before any work: an unknown name is one line naming the option."""
    try:
        get_scene(name)
    except TdofError as e:
        raise TdofError(f"--scene: {e}") from None
    return name


def _ids(text: Optional[str]) -> Optional[list[int]]:
    if text is None:
        return None
    try:
        ids = [int(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        raise TdofError(f"--ids must be comma-separated integers, got '{text}'") from None
    if not ids:
        raise TdofError(f"--ids names no object, got '{text}' (leave it out for all)")
    return ids


# ----------------------------------------------------------------------------------- capture
def _capture_config(config: Optional[Path], sim: bool, scene: str, steps: int, step_deg: float, arm_positions: int,
                    width: int, height: int, seed: int, clutter: str = "", direction: str = "ccw",
                    record_direction: bool = True, hand_eye_error: str = "", step_jitter: float = 0.0,
                    depth_bias: float = 1.0, twin_offset: str = ""):
    if config is not None and sim:
        raise TdofError("give either a CONFIG file or --sim, not both")
    if config is None and not sim:
        raise TdofError("give a CONFIG file (see examples/real_rig.toml), or --sim for the simulated rig")
    lab_given = [o for o, v in (("--clutter", clutter), ("--direction", direction != "ccw"),
                                ("--no-record-direction", not record_direction),
                                ("--hand-eye-error", hand_eye_error), ("--step-jitter", step_jitter),
                                ("--depth-bias", depth_bias != 1.0), ("--twin-offset", twin_offset)) if v]
    if config is not None:
        if lab_given:
            raise TdofError(f"{', '.join(lab_given)} go with --sim; in a CONFIG set them in its [sim] table "
                            f"(clutter, record_direction, hand_eye_error_mm/_deg, step_jitter_deg, depth_bias, "
                            f"twin_offset_mm/_deg) and "
                            f"[turntable] direction")
        return load_config(config)

    names = [c for c in clutter.replace(" ", "").split(",") if c]
    bad = [c for c in names if c not in clutter_names()]
    if bad:
        raise TdofError(f"--clutter: unknown preset {', '.join(repr(b) for b in bad)} (known: {', '.join(clutter_names())})")
    if direction not in DIRECTIONS:
        raise TdofError(f"--direction must be {' or '.join(DIRECTIONS)} (seen from above), got '{direction}'")
    he_mm, he_deg = _mm_deg(hand_eye_error, "--hand-eye-error", "2,0.5")
    tw_mm, tw_deg = _mm_deg(twin_offset, "--twin-offset", "2,1")
    return sim_config(_scene(scene), steps=steps, step_deg=step_deg, n_arms=arm_positions, width=width, height=height,
                      seed=seed, clutter=names, direction=direction, record_direction=record_direction,
                      hand_eye_error_mm=he_mm, hand_eye_error_deg=he_deg, step_jitter_deg=step_jitter,
                      depth_bias=depth_bias, twin_offset_mm=tw_mm, twin_offset_deg=tw_deg)


def _mm_deg(text: str, option: str, example: str) -> tuple[float, float]:
    """'MM' or 'MM,DEG' (an option's value) as two floats; '' is (0, 0)."""
    try:
        v = [float(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        v = None
    if v is None or len(v) > 2:
        raise TdofError(f"{option} must be MM or MM,DEG (e.g. {example}), got '{text}'")
    return tuple((v + [0.0, 0.0])[:2])


CONFIG_ARG = typer.Argument(None, help="capture config (TOML); leave out with --sim")
SIM = typer.Option(False, "--sim", help="use the simulated rig (no config needed)")
STEPS = typer.Option(400, help="--sim: turntable steps per arm position")
STEP_DEG = typer.Option(0.9, help="--sim: turntable step in degrees")
ARMS = typer.Option(4, help="--sim: number of arm positions")
CLUTTER = typer.Option("", help="--sim: static lab clutter beside the table, comma-separated presets "
                                "(cabinet, monitor, box, wall)")
DIRECTION = typer.Option("ccw", help="--sim: which way the table turns, seen from above: ccw or cw")
RECORD_DIRECTION = typer.Option(True, "--record-direction/--no-record-direction",
                                help="--sim: write turntable.direction to session.json")
HAND_EYE_ERROR = typer.Option("", help="--sim: hand-eye error MM[,DEG]: the camera really sits this far "
                                       "from the recorded mount (e.g. 2,0.5)")
STEP_JITTER = typer.Option(0.0, help="--sim: step-angle error bound in degrees (uniform, per frame)")
TWIN_OFFSET = typer.Option("", help="--sim: each opaque twin stands MM[,DEG] off its transparent object's slot "
                                    "(moved along the table, turned about the table axis; e.g. 2,1)")
DEPTH_BIAS = typer.Option(1.0, help="--sim: the camera's depth scale error, reported / true depth "
                                    "(1.02: depth reads 2 % long, as consumer stereo cameras often do)")


@capture_app.command("plan")
def capture_plan(config: Optional[Path] = CONFIG_ARG, sim: bool = SIM, scene: str = SCENE, steps: int = STEPS,
                 step_deg: float = STEP_DEG, arm_positions: int = ARMS, width: int = WIDTH, height: int = HEIGHT,
                 seed: int = SEED, clutter: str = CLUTTER, direction: str = DIRECTION,
                 record_direction: bool = RECORD_DIRECTION, hand_eye_error: str = HAND_EYE_ERROR,
                 step_jitter: float = STEP_JITTER, depth_bias: float = DEPTH_BIAS, twin_offset: str = TWIN_OFFSET,
                 json_out: bool = typer.Option(False, "--json", help="print JSON")) -> None:
    """Print the sequence a session will run and its estimated duration; checks every arm target
    against the workspace limits. Touches no hardware."""
    cfg = _capture_config(config, sim, scene, steps, step_deg, arm_positions, width, height, seed, clutter,
                          direction, record_direction, hand_eye_error, step_jitter, depth_bias, twin_offset)
    d = describe(cfg)
    if json_out:
        print(json.dumps(d, indent=2))
    else:
        est = d["estimate"]
        out_console.print(f"scene {d['scene_id']}, phases {' then '.join(d['phases'])}, backends "
                          + ", ".join(f"{k} {v}" for k, v in d["backends"].items()))
        t = Table(title="arm positions (moveJ targets)")
        for c in ("arm", "joints (deg)", "TCP xyz (mm)", "limits"):
            t.add_column(c)
        for a in d["arms"]:
            t.add_row(str(a["arm"]), " ".join(f"{v:.1f}" for v in a["q_deg"]), " ".join(f"{v:.0f}" for v in a["tcp_mm"]),
                      "[green]ok[/green]" if not a["problems"] else "[red]" + "; ".join(a["problems"]) + "[/red]")
        out_console.print(t)
        out_console.print(f"per phase and arm position: {d['steps']} steps of {d['step_deg']:g} deg "
                          f"({d['direction']}); {est['frames']} RGB-D pairs in all")
        if d["lab"]:
            out_console.print("simulated lab: " + "; ".join(f"{k} {v}" for k, v in d["lab"].items()))
        out_console.print(f"estimated duration on the hardware: {est['total_s'] / 60:.1f} min "
                          f"({est['per_frame_s']:.2f} s a frame, {est['arm_moves_s']:.0f} s of arm moves; "
                          f"the operator's swap between phases not counted)")
    if not d["ok"]:
        check_workspace(cfg)  # raises the one-line refusal


@capture_app.command("run")
def capture_run(config: Optional[Path] = CONFIG_ARG,
                out: Path = typer.Option(..., "--out", help="session folder (created; resumed if it holds this session)"),
                sim: bool = SIM, scene: str = SCENE, steps: int = STEPS, step_deg: float = STEP_DEG,
                arm_positions: int = ARMS, width: int = WIDTH, height: int = HEIGHT, seed: int = SEED,
                clutter: str = CLUTTER, direction: str = DIRECTION, record_direction: bool = RECORD_DIRECTION,
                hand_eye_error: str = HAND_EYE_ERROR, step_jitter: float = STEP_JITTER,
                depth_bias: float = DEPTH_BIAS, twin_offset: str = TWIN_OFFSET,
                yes: bool = typer.Option(False, "--yes", help="do not wait for the operator (scripted runs)")) -> None:
    """Run (or resume) a capture session and write the raw session format."""
    cfg = _capture_config(config, sim, scene, steps, step_deg, arm_positions, width, height, seed, clutter,
                          direction, record_direction, hand_eye_error, step_jitter, depth_bias, twin_offset)
    resume = "tdof20 " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    summary = run_capture(cfg, out, yes=yes, resume_command=resume)
    for line in summary.lines():
        console.print(line, markup=False)
    console.print(f"session in {out} (log: {out / 'capture.log'})", markup=False)


@capture_app.command("verify")
def capture_verify(session: Path = typer.Argument(..., help="raw session folder")) -> None:
    """Check a session: every planned frame present, files decodable, of session.json's camera size
    and matching their checksums, depths in millimetres (what annotate would refuse)."""
    problems = verify_session(session)
    if problems:
        for p in problems[:200]:
            out_console.print(p, highlight=False, soft_wrap=True, markup=False)
        if len(problems) > 200:
            out_console.print(f"... and {len(problems) - 200} more", markup=False)
        console.print(f"[bold red]{len(problems)} problem{'s' if len(problems) != 1 else ''}[/bold red] in {escape(str(session))}")
        raise typer.Exit(1)
    console.print(f"[green]ok[/green]: {escape(str(session))} is complete and every file matches its checksum")



# ----------------------------------------------------------------------------------- objects
def _object_entry(o) -> dict:
    """One catalog row for ``objects list --json``."""
    info = o.models_info()
    return {"id": o.obj_id, "name": o.name, "kind": o.kind,
            "size_mm": [round(info[k], 3) for k in ("size_x", "size_y", "size_z")],
            "capacity_ml": o.capacity_ml, "diameter_mm": round(o.diameter, 3),
            "symmetry": ("continuous z" if o.symmetries_continuous else
                         f"discrete {len(o.symmetries_discrete) + 1}-fold" if o.symmetries_discrete else "none"),
            "faces": len(o.faces)}


@objects_app.command("list")
def objects_list(json_out: bool = typer.Option(False, "--json", help="print JSON (one object per entry)")) -> None:
    """Print the catalog (TDoF20's 20 classes): id, name, kind, size, capacity, diameter, symmetry."""
    if json_out:
        print(json.dumps([_object_entry(o) for o in all_objects()], indent=2))
        return
    t = Table(title="tdof20 object catalog: TDoF20's classes (mm; the number in a name is its capacity in ml)")
    for c in ("id", "name", "kind", "size x*y*z", "capacity ml", "diameter", "symmetry", "faces"):
        t.add_column(c, justify="right" if c in ("id", "capacity ml", "diameter", "faces") else "left",
                     no_wrap=c == "name")
    for o in all_objects():
        info = o.models_info()
        sym = ("continuous z" if o.symmetries_continuous else
               f"discrete {len(o.symmetries_discrete) + 1}-fold" if o.symmetries_discrete else "[bold]none[/bold]")
        t.add_row(str(o.obj_id), o.name, o.kind,
                  f"{info['size_x']:.0f}*{info['size_y']:.0f}*{info['size_z']:.0f}", f"{o.capacity_ml:.0f}",
                  f"{o.diameter:.1f}", sym,
                  str(len(o.faces)))
    out_console.print(t)


@objects_app.command("export")
def objects_export(out: Path = typer.Argument(..., help="folder for the BOP models (created)"),
                   ids: Optional[str] = typer.Option(None, help="comma-separated object ids (default: all)")) -> None:
    """Write a BOP models folder: obj_000001.ply ... (mm) and models_info.json."""
    path = export_models(out, _ids(ids))
    console.print(f"wrote BOP models to {path}", markup=False)


@objects_app.command("picture")
def objects_picture(out: Path = typer.Argument(..., help="PNG file to write"),
                    tile: int = typer.Option(200, help="tile width in pixels")) -> None:
    """Render all 20 objects, glass and opaque twin, into one picture."""
    from tdof20.sim.gallery import catalog_picture

    if not 16 <= tile <= 1024:
        raise TdofError(f"--tile must be in 16..1024 pixels, got {tile}")
    check_output_file(out, "OUT", "PNG file")
    write_png(out, catalog_picture(tile))
    console.print(f"wrote {out}", markup=False)


# ----------------------------------------------------------------------------------- sim
@sim_app.command("scenes")
def sim_scenes() -> None:
    """List the 40 TDoF20 scenes of the simulator (single/<class>, multi/00..19) with their numeric (BOP)
    scene ids, objects and stickers; TDoF20-hard tests on multi/02, 08, 09, 10, 11, 15."""
    names = object_names()
    t = Table(title="simulated TDoF20 scenes")
    for c in ("scene", "id", "objects", "sticker", "hard"):
        t.add_column(c, justify="right" if c == "id" else "left")
    for sid in scene_ids():
        s = get_scene(sid)
        hard = "test" if s.kind == "multi" and s.number in HARD_TEST_MULTI else "train"
        t.add_row(sid, str(s.numeric_id), ", ".join(f"{i} {names[i]}" for i in s.obj_ids), s.sticker, hard)
    out_console.print(t)


@sim_app.command("frames")
def sim_frames(out: Path = typer.Option(..., "--out", help="folder for the PNGs (created)"),
               scene: str = SCENE,
               arm: int = typer.Option(0, help="arm position (0..3)"),
               angles: str = typer.Option("0,90,180,270", help="comma-separated table angles in degrees"),
               width: int = WIDTH, height: int = HEIGHT, seed: int = SEED) -> None:
    """Render a few frames of a scene (both phases) as PNGs and a contact sheet."""
    from tdof20.sim.gallery import render_frames

    try:
        angle_list = [float(a) for a in angles.split(",") if a.strip()]
    except ValueError:
        angle_list = []
    if not angle_list or not all(abs(a) <= 3600 for a in angle_list):  # nan and inf fail the bound too
        raise TdofError(f"--angles must be comma-separated numbers of degrees (|a| <= 3600), got '{angles}'")

    renderer = build_rig(sim_config(_scene(scene), width=width, height=height, seed=seed)).world.renderer
    sheet = render_frames(renderer, out, arm, angle_list)
    console.print(f"wrote frames and {sheet}", markup=False)


@sim_app.command("label")
def sim_label(session: Path = typer.Argument(..., help="simulated raw session (with truth/)"),
              out: Path = typer.Option(..., "--out", help="annotated scene folder to write")) -> None:
    """Labels from the simulator's exact truth (an oracle annotation): a BOP scene in the format
    the annotation pipeline writes, ready for `tdof20 dataset build`."""
    from tdof20.sim.truth import oracle_scene

    oracle_scene(session, out)
    console.print(f"oracle-labelled scene in {out}", markup=False)


@sim_app.command("sheet")
def sim_sheet(session: Path = typer.Argument(..., help="raw session folder"),
              out: Optional[Path] = typer.Option(None, help="PNG to write (default: SESSION/contact_sheet.png)"),
              frames: int = typer.Option(4, help="number of frames (rows)")) -> None:
    """Contact sheet of a raw session: colour and depth of both phases, truth masks if present."""
    if not 1 <= frames <= 100:
        raise TdofError(f"--frames must be in 1..100, got {frames}")

    out = check_output_file(out or session / "contact_sheet.png", "--out", "PNG file")
    write_png(out, session_contact_sheet(session, frames))
    console.print(f"wrote {out}", markup=False)


# ----------------------------------------------------------------------------------- dataset
@dataset_app.command("build")
def dataset_build(scenes: list[Path] = typer.Argument(..., help="annotated scene folders (BOP scene + scene_info.json + models/)"),
                  out: Path = typer.Option(..., "--out", help="dataset root (created; an existing one only with "
                                           "the same scenes, or with --add)"),
                  add: bool = typer.Option(False, "--add", help="add the scenes to the dataset in --out (models, "
                                           "splits and targets are updated)"),
                  layout: str = typer.Option("tdof20", "--layout", help="tdof20 (both protocols, splits/) or bop (the "
                                             "standard BOP layout: train/ and test/ of one protocol)"),
                  split: Optional[str] = typer.Option(None, "--split", help="with --layout bop: the protocol (simple "
                                                      "or hard) whose train and test parts become train/ and test/"),
                  allow_flagged: bool = typer.Option(False, "--allow-flagged", help="build even from scenes with "
                                                     "unresolved flags (frames not labelled, failed objects: tdof20 "
                                                     "annotate review)")) -> None:
    """Gather annotated scenes into one BOP dataset with the TDoF20-simple and -hard splits."""
    from tdof20.dataset.build import build_dataset_in_layout

    s = build_dataset_in_layout(layout, scenes, out, split=split, add=add, allow_flagged=allow_flagged)
    _print_stats(s)
    console.print(f"dataset in {out}", markup=False)


@dataset_app.command("stats")
def dataset_stats(root: Path = typer.Argument(..., help="dataset root"),
                  json_out: bool = typer.Option(False, "--json", help="print JSON")) -> None:
    """Counts per split, scene and object (the paper's figures beside the splits)."""
    s = stats(root)
    if json_out:
        print(json.dumps(s, indent=2))
    else:
        _print_stats(s)


@dataset_app.command("pack")
def dataset_pack(root: Path = typer.Argument(..., help="dataset root"),
                 split: str = typer.Option(..., help="simple or hard (a BOP dataset: a split folder, e.g. train_pbr)"),
                 part: str = typer.Option(..., help="train or test"),
                 out: Path = typer.Option(..., "--out", help="HDF5 file to write"),
                 cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="where restored depth the dataset "
                                                          "lacks is rendered to (default ROOT/.cache)")) -> None:
    """Write what training reads (colour, depths, masks, poses, camera) into one HDF5 file."""
    pack(root, split, part, out, cache_dir=cache_dir)
    console.print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB)", markup=False)


@dataset_app.command("import-tdof20")
def dataset_import_tdof20(src: Path = typer.Argument(..., help="the released TDoF20 folder (dataset_config/, models/, "
                                                     "single_data/, multi_data/, ...)"),
                          out: Optional[Path] = typer.Option(None, "--out", help="dataset root to write (created; a "
                                                             "rerun of the same import resumes it)"),
                          check: bool = typer.Option(False, "--check", help="read and check everything, print what "
                                                     "was found, write nothing"),
                          scenes: Optional[str] = typer.Option(None, "--scenes", help="only these scenes, comma-"
                                                               "separated: single/<class>, multi/NN")) -> None:
    """Import the released TDoF20 (its documented layout) as a tdof20 dataset: released splits, depth
    modes raw/stabilized/restored, masks, models in mm, the released keypoints (docs/tdof20_release.md)."""
    if out is None and not check:
        raise TdofError("give --out ROOT to import, or --check to only read and check the release")
    names = [x.strip() for x in scenes.split(",") if x.strip()] if scenes else None
    s = import_tdof20(src, out, check=check, scenes=names)
    t = Table(title=f"TDoF20 release {src}: {len(s['classes'])} classes, {len(s['scenes'])} scenes")
    for c in ("scene", "id", "frames", "mask IoU (first frame)"):
        t.add_column(c, justify="right")
    for name, n in s["scenes"].items():
        t.add_row(name, str(s["scene_ids"][name]), str(n), f"{s['mask_iou_first_frame'][name]:.2f}")
    out_console.print(t)
    t = Table(title="lists")
    for c in ("list", "file", "frames", "form"):
        t.add_column(c)
    for k, n in s["lists"].items():
        t.add_row(k, s["list_files"][k], str(n), "; ".join(s["list_forms"][k]))
    out_console.print(t)
    lines = [f"classes: {', '.join(s['classes'])}", f"intrinsics: {s['intrinsics']}",
             f"image size: {s['image_size'][0]}x{s['image_size'][1]}", f"poses: {s['units']['poses']}",
             f"depth: {s['units']['depth']}", *(f"model {k}: {v}" for k, v in s["units"]["models"].items()),
             *(f"im_id: {r}" for r in s["im_id_rule"]), *(f"symmetry: {x}" for x in s["symmetries"]),
             *(f"note: {x}" for x in s["notes"])]
    for ln in lines:
        out_console.print(ln, highlight=False, markup=False)
    if s["written"]:
        console.print(f"{'resumed and finished' if s.get('resumed') else 'imported'} into {s['out']}", markup=False)
    else:
        console.print("checked: nothing written")


def _print_stats(s: dict) -> None:
    t = Table(title=f"{s.get('layout', 'tdof20')} layout: {s['scenes']} scenes, {s['images']} images")
    sp = s["splits"]
    if "split_folders" in s:
        for c in ("split folder", "scenes", "images", "test images", "test targets"):
            t.add_column(c, justify="right")
        for name, f in s["split_folders"].items():
            t.add_row(name, str(f["scenes"]), str(f["images"]), str(f["test_images"]), str(f["targets"]))
    else:
        for c in ("split", "train", "test", "test targets", "paper train : test"):
            t.add_column(c, justify="right")
        papers = {"simple": PAPER_SIMPLE, "hard": PAPER_HARD}
        for name in dict.fromkeys(k.rsplit("_", 1)[0] for k in sp):
            paper = papers.get(name)
            t.add_row(name, str(sp.get(f"{name}_train", 0)), str(sp.get(f"{name}_test", 0)),
                      str(sp.get(f"{name}_targets", 0)), f"{paper[0]} : {paper[1]}" if paper else "")
    out_console.print(t)
    t = Table(title="images per scene")
    t.add_column("scene")
    t.add_column("images", justify="right")
    for name, n in sorted(s["per_scene"].items()):
        t.add_row(name, str(n))
    out_console.print(t)
    t = Table(title="images per object")
    for c in ("id", "name", "images"):
        t.add_column(c)
    names = s.get("objects", {})
    for oid, n in s["per_object"].items():
        t.add_row(str(oid), names.get(oid, names.get(str(oid), f"obj_{int(oid):06d}")), str(n))
    out_console.print(t)
    noise = s.get("label_noise") or {}
    if noise:
        t = Table(title="label-noise floor per object (95 % bounds of scene_gt_uncertainty.json: median / 95th pct)")
        for c in ("id", "name", "labels bounded", "translation (mm)", "rotation (deg)", "surface (mm)"):
            t.add_column(c, justify="left" if c == "name" else "right")
        for oid, f in noise.items():
            cells = [f"{f[k]['median']:.2f} / {f[k]['p95']:.2f}" if f.get(k) else "not recorded"
                     for k in ("trans_mm", "rot_deg", "surface_mm")]
            t.add_row(str(oid), names.get(oid, names.get(str(oid), f"obj_{int(oid):06d}")),
                      f"{f['bounded']} / {f['labels']}", *cells)
        out_console.print(t)


# ----------------------------------------------------------------------------------- annotate
@annotate_app.command("run", hidden=True)
def annotate_run(raw: list[Path] = typer.Argument(..., help="raw session folder(s) (tdof20 capture)"),
                 out: Path = typer.Option(..., "--out", help="the annotated scene folder (created; a rerun resumes); "
                                          "with several sessions the folder of their scenes, DIR/multi/08 ..."),
                 models: Optional[Path] = typer.Option(None, "--models", help="BOP models folder in mm (CAD models, or "
                                                       "the models the single-object scenes got)"),
                 stages: Optional[str] = typer.Option(None, "--stages", help="e.g. register..model or label,qa "
                                                      "(default: all: register, reconstruct, model, place, label, qa)"),
                 config: Optional[Path] = typer.Option(None, "--config", help="TOML options (docs/annotate.md)"),
                 executor: Optional[str] = typer.Option(None, "--executor", help="local (worker processes) or ray"),
                 ray_address: Optional[str] = typer.Option(None, "--ray-address", help="Ray cluster, e.g. 10.0.0.5:6379"),
                 workers: Optional[int] = typer.Option(None, "--workers", help="worker processes (or a local Ray "
                                                       "instance's CPUs) shared by the scenes, their registration (one "
                                                       "arm each) and labels (default: cores)"),
                 force: bool = typer.Option(False, "--force", help="rerun the chosen stages even when up to date")) -> None:
    """Annotate RAW into a labelled BOP scene in --out: poses, masks, restored depth, QA report.
    Several RAWs: one scene folder each, DIR/<scene id> (multi/08 -> DIR/multi/08), side by side."""
    from tdof20.annotate.pipeline import AnnotateConfig, annotate, load_annotate_config, summary_text

    cfg = load_annotate_config(config) if config is not None else AnnotateConfig()
    cfg = cfg.with_label_options(executor=executor, ray_address=ray_address, workers=workers)
    if len(raw) == 1:
        summary = annotate(raw[0], out, models_dir=models, stages=stages, cfg=cfg, force=force)
        out_console.print(summary_text(summary), highlight=False, markup=False)
        if summary.get("partial"):
            raise typer.Exit(PARTIAL_EXIT)
        return
    from tdof20.annotate.batch import SUMMARY, annotate_many, batch_text

    batch = annotate_many(raw, out, models_dir=models, stages=stages, cfg=cfg, force=force)
    out_console.print(batch_text(batch), highlight=False, soft_wrap=True, markup=False)
    if batch["failed"]:
        raise TdofError(f"{len(batch['failed'])} of {len(batch['scenes'])} scenes failed: {', '.join(batch['failed'])} "
                        f"({'the others finished; ' if len(batch['failed']) < len(batch['scenes']) else ''}"
                        f"errors above and in {out / SUMMARY}; a rerun resumes each scene)")
    if batch.get("partial"):
        raise typer.Exit(PARTIAL_EXIT)


@annotate_app.command("evaluate")
def annotate_evaluate(scene: Path = typer.Argument(..., help="annotated scene folder"),
                      truth: Path = typer.Option(..., "--truth", help="the simulated session's truth/ folder"),
                      max_frames: Optional[int] = typer.Option(None, "--max-frames", help="evaluate at most this many frames"),
                      points: int = typer.Option(2000, "--points", help="surface samples per model")) -> None:
    """Compare labels with the simulator's truth: motions, surface distance, mask IoU (JSON)."""
    print(evaluate_command(scene, truth, max_frames=max_frames, n_points=points))


@annotate_app.command("review")
def annotate_review(scene: Path = typer.Argument(..., help="annotated scene folder (tdof20 annotate's --out)"),
                    port: int = typer.Option(8765, "--port", help="port of the local web app"),
                    host: str = typer.Option("127.0.0.1", "--host", help="address to listen on (this machine by "
                                             "default)"),
                    open_browser: bool = typer.Option(False, "--open", help="open it in the web browser")) -> None:
    """Review and correct an annotated scene in a local web app (frames and flags, overlays, object fits,
    a 3D view to nudge, drag and snap); corrections go to SCENE/work/corrections.jsonl."""
    from tdof20.review import review_command

    review_command(scene, port=port, host=host, open_browser=open_browser)


# ----------------------------------------------------------------------------------- train / predict
def _image_size(text: Optional[str]) -> Optional[tuple[int, int]]:
    """'240x320' (height x width) or 'native' -> (240, 320) or None."""
    if text is None or text.strip().lower() in ("native", "full", "none"):
        return None
    try:
        h, w = (int(v) for v in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise TdofError(f"--image-size must look like 240x320 (height x width) or 'native', got '{text}'") from None
    return h, w


def _method_help(short: bool = False) -> str:
    """The registered methods (the registry imports no torch: --help stays fast)."""
    if short:
        return ", ".join(method_names(None))
    return "; ".join(f"{n}: {get_method(n).description}" for n in method_names(None))


@app.command("train", help="Train a method on the train part of a split (checkpoints, resume, loss curves); run "
                           "again on the same --out to resume or extend. METHOD is one of: " + _method_help(),
             short_help=f"Train a method ({_method_help(short=True)}) on a split: checkpoints, resume, loss curves.")
def train_cmd(method: str = typer.Argument(..., help="the method: " + _method_help(short=True)),
              dataset: Path = typer.Option(..., "--dataset", help="dataset root (tdof20 dataset build)"),
              split: str = typer.Option(..., "--split", help="simple or hard (a BOP dataset: a split folder, "
                                        "e.g. train_pbr)"),
              out: Path = typer.Option(..., "--out", help="run folder (created; an existing run resumes)"),
              config: Optional[Path] = typer.Option(None, "--config", help="TOML with \\[train] (the options below) "
                                                    "and \\[method] (the method's options) tables; options given "
                                                    "on the command line win"),
              image_size: Optional[str] = typer.Option(None, help="HxW the images are resized to, or 'native' "
                                                       "(default: the method's, 240x320)"),
              batch_size: Optional[int] = typer.Option(None, help="images per optimiser step (per process) [8]"),
              epochs: Optional[int] = typer.Option(None, help="passes over the training images, in all [20]"),
              lr: Optional[float] = typer.Option(None, help="peak learning rate (AdamW) [1e-3]"),
              lr_schedule: Optional[str] = typer.Option(None, help="cosine or step \\[cosine]"),
              depth_mode: Optional[str] = typer.Option(None, help="input depth of an RGB-D method: raw, filled or "
                                                       "restored (privileged) \\[filled]"),
              set_options: Optional[list[str]] = typer.Option(
                  None, "--set", metavar="KEY=VALUE", help="an option of the method's config (repeatable; the value "
                  "as in TOML, e.g. --set fuse_stages=2); over --config's \\[method]"),
              device: str = typer.Option("auto", help="auto, cpu, cuda, cuda:N or mps"),
              amp: Optional[bool] = typer.Option(None, "--amp/--no-amp", help="mixed precision (default: on CUDA)"),
              workers: Optional[int] = typer.Option(None, help="data-loading worker processes [2]"),
              max_steps: Optional[int] = typer.Option(None, help="stop after this many optimiser steps in all"),
              seed: Optional[int] = typer.Option(None, help="seed of the initial weights and the sampling [0]"),
              backbone_weights: Optional[Path] = typer.Option(None, help="torchvision ResNet state dict (.pth) for "
                                                              "the method's encoder(s)"),
              shard: Optional[Path] = typer.Option(None, help="train on this HDF5 shard (tdof20 dataset pack)"),
              save_every: Optional[float] = typer.Option(None, help="checkpoint at an epoch end when the last is "
                                                         "older (s) [600]"),
              cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="where restored depth the dataset "
                                                       "lacks is rendered to (default ROOT/.cache)"),
              part: str = typer.Option("train", "--part", help="train (the split's whole train part) or train-val "
                                       "(the train part minus its validation part, for choices made on --part val)")
              ) -> None:
    from tdof20.methods.devices import is_main_process
    from tdof20.methods.train import TrainOptions, load_train_config, train

    try:
        m = get_method(method)
        opts, mcfg = load_train_config(config, m) if config is not None else (TrainOptions(), None)
        if set_options:
            mcfg = m.with_options(mcfg or m.default_config(), parse_set_options(set_options), "--set")
        size = opts.image_size
        size = "method" if not size else (None if tuple(size) == (0, 0) else tuple(size))
        if image_size is not None:
            size = _image_size(image_size)

        def pick(given, default):
            return default if given is None else given

        train(dataset, split, out, method=m.name, method_config=mcfg, image_size=size,
              batch_size=pick(batch_size, opts.batch_size), epochs=pick(epochs, opts.epochs), lr=pick(lr, opts.lr),
              lr_schedule=pick(lr_schedule, opts.lr_schedule), weight_decay=opts.weight_decay,
              depth_mode=depth_mode, device=device, amp=amp,
              num_workers=pick(workers, opts.num_workers),
              max_steps=pick(max_steps, opts.max_steps if opts.max_steps > 0 else None),
              seed=pick(seed, opts.seed), backbone_weights=backbone_weights, shard=shard,
              save_every_s=pick(save_every, opts.save_every_s), cache_dir=cache_dir, part=part)
    except TdofError as e:
        if getattr(e, "same_in_every_process", False) and not is_main_process():
            # under torchrun: process 0 prints the line. Exiting at once raced it: torchrun stops every
            # process when one fails, and a busy process 0 was stopped before it printed. So wait for
            # torchrun to stop this one (process 0's failure), for at most a minute.
            time.sleep(60)
            sys.exit(2)
        raise


@app.command("predict")
def predict_cmd(run: Path = typer.Argument(..., help="run folder (tdof20 train METHOD --out); the run knows its method"),
                dataset: Path = typer.Option(..., "--dataset", help="dataset root"),
                split: str = typer.Option(..., "--split", help="simple or hard (a BOP dataset: a split folder, e.g. test)"),
                out: Path = typer.Option(..., "--out", help="results CSV to write (BOP format)"),
                device: str = typer.Option("auto", help="auto, cpu, cuda, cuda:N or mps"),
                batch_size: int = typer.Option(1, help="images per forward pass"),
                workers: int = typer.Option(2, help="data-loading worker processes"),
                set_options: Optional[list[str]] = typer.Option(
                    None, "--set", metavar="KEY=VALUE", help="a prediction option of the run's method config "
                    "(repeatable; the value as in TOML), e.g. hff6dof's --set masks=gt (oracle masks: not a valid "
                    "submission) or --set voting=3d \\[the run's]"),
                part: str = typer.Option("test", "--part", help="test, or val: the validation part of the split's "
                                         "train part (where choices are made)"),
                cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="where restored depth the dataset "
                                                         "lacks is rendered (default ROOT/.cache; for a read-only "
                                                         "dataset)"),
                seed: int = SEED) -> None:
    """Estimate the poses of a split's test images with a run of any method; writes the results CSV with
    per-image times and, beside it, <stem>_info.json (method, its config, depth mode, timings)."""
    from tdof20.methods.predict import predict

    predict(run, dataset, split, out, device=device, batch_size=batch_size, num_workers=workers, seed=seed,
            part=part, cache_dir=cache_dir, method_options=parse_set_options(set_options or ()))


# ----------------------------------------------------------------------------------- benchmark
@benchmark_app.command("score")
def benchmark_score(results: list[Path] = typer.Argument(..., help="results CSV files (scene_id,im_id,obj_id,score,R,t,time)"),
                    dataset: Path = typer.Option(..., "--dataset", help="dataset root"),
                    split: Optional[str] = typer.Option(None, "--split", help="simple or hard (its test targets; a BOP "
                                                        "dataset: test, for test_targets_bop19.json)"),
                    targets: Optional[Path] = typer.Option(None, "--targets", help="a targets JSON instead of --split"),
                    json_out: Optional[Path] = typer.Option(None, "--json", help="write the scores as JSON here"),
                    plots: Optional[Path] = typer.Option(None, "--plots", help="folder for the accuracy curves and report.md"),
                    metrics: Optional[str] = typer.Option(None, "--metrics", help="comma-separated: add,proj,vsd,mssd,mspd,ar "
                                                          "(default: add,proj,mssd,mspd, plus vsd,ar when the dataset has depth)"),
                    proj_px: Optional[float] = typer.Option(None, "--proj-px", help="2D projection threshold in "
                                                            "pixels (default: 5 px at 640 pixels wide, scaled with the "
                                                            "image width)"),
                    part: str = typer.Option("test", "--part", help="test, or val: the targets of the --split's "
                                             "validation part (written to ROOT/.cache/val_targets_<split>.json)")
                    ) -> None:
    """Score results: ADD(-S) at 10 % of the diameter, 2D projection at 5 px per 640 pixels of width, AUC, and BOP19's VSD, MSSD,
    MSPD and AR; per object, per scene and mean."""
    if part not in ("test", "val"):
        raise TdofError(f"--part must be test or val, got '{part}'")
    if part == "val":
        if split is None or targets is not None:
            raise TdofError("--part val scores against the validation targets of --split: give --split, not --targets")
        split, targets = None, write_val_targets(dataset, split)
    out_console.print(score_command(results, dataset, split, targets, json_out, plots, metrics, proj_px), highlight=False, markup=False)


@benchmark_app.command("profile")
def benchmark_profile(method: str = typer.Argument(..., help="a registered method (hff6dof, pvnet, densefusion, "
                                                   "ffb6d) or all"),
                      json_out: bool = typer.Option(False, "--json", help="print JSON"),
                      device: str = typer.Option("auto", help="auto, cpu, cuda, cuda:N or mps"),
                      height: int = typer.Option(480, help="input height"),
                      width: int = typer.Option(640, help="input width"),
                      repeats: int = typer.Option(5, "--repeats", "--runs", help="timed runs (median)"),
                      batch_size: int = typer.Option(1, help="images per forward pass")) -> None:
    """Table 3: parameters, multiply-adds at 480x640, latency and FPS (network and pose recovery apart) on
    this device, beside the paper's figures and the originals' parameter counts (untrained networks)."""
    from tdof20.methods.profile import format_profile, format_table, profile, select_device

    if method.strip().lower() != "all":
        get_method(method)  # an unknown method: one line listing the known ones, before any work
        p = profile(method, device=device, height=height, width=width, repeats=repeats, batch_size=batch_size)
    else:  # method by method, a progress line each (all of them take minutes on a CPU)
        names = method_names()
        select_device(device)  # a bad --device is one error, not one per method
        p = []
        for i, name in enumerate(names, 1):
            console.print(f"profiling {name} ({i}/{len(names)}) ...", markup=False, highlight=False)
            t0 = time.perf_counter()
            try:
                p.append(profile(name, device=device, height=height, width=width, repeats=repeats,
                                 batch_size=batch_size))
            except TdofError as e:  # as profile('all'): a failing method gets its error in the table
                p.append({"method": name, "error": str(e)})
            console.print(f"profiled {name} in {time.perf_counter() - t0:.1f} s", markup=False, highlight=False)
    if json_out:
        print(json.dumps(p, indent=2))
    else:
        print(format_table(p) if isinstance(p, list) else format_profile(p))


# ----------------------------------------------------------------------------------- demo
@app.command("demo")
def demo(out: Path = typer.Option(Path("demo_out"), help="folder for everything the demo writes (a rerun resumes)"),
         scenes: str = typer.Option("single/juice_cup_340,multi/08", help="comma-separated scene names; training and "
                                    "scoring use the single-object ones (TDoF20-simple)"),
         steps: int = typer.Option(16, help="turntable steps per arm position (annotate needs about 12 or more)"),
         step_deg: float = typer.Option(5.0, help="turntable step in degrees (at most 30 for the registration)"),
         arm_positions: int = typer.Option(4, help="number of arm positions"),
         width: int = typer.Option(320, help="capture width in pixels"),
         height: int = typer.Option(240, help="capture height in pixels"), seed: int = SEED,
         train: bool = typer.Option(True, "--train/--no-train", help="train, predict and score the methods"),
         methods: str = typer.Option("hff6dof,pvnet", help="comma-separated registered methods trained, "
                                     "predicted and scored side by side"),
         image_size: str = typer.Option("60x80", help="HxW of the short training"),
         epochs: Optional[int] = typer.Option(None, help="training epochs of every method, the same budget for "
                                              "all \\[default: 840 images seen = 15 epochs of the default data]"),
         batch_size: int = typer.Option(4, help="training batch size"),
         device: str = typer.Option("auto", help="auto, cpu, cuda, cuda:N or mps")) -> None:
    """Run the main job end to end on the simulator: capture, annotate, dataset, train, predict and
    score HFF6DoF and PVNet side by side, OUT/report.md (7 min 1 s measured on 2 idle CPU cores with
    the defaults, several times that on a busy machine; a rerun resumes)."""
    names = tuple(x.strip() for x in scenes.split(",") if x.strip())
    if not names:
        raise TdofError("--scenes needs at least one scene name")
    size = _image_size(image_size)
    if size is None:
        raise TdofError("--image-size must be HxW for the demo")
    if steps < 2 or not 0 < step_deg <= 30.0:
        raise TdofError(f"--steps must be >= 2 and --step-deg in (0, 30] (registration), got {steps} and {step_deg}")
    if batch_size < 1 or (epochs is not None and epochs < 1):
        raise TdofError("--batch-size and --epochs must be >= 1")
    method_names = parse_methods(methods) if train else ()
    run_demo(out, scenes=names, steps=steps, step_deg=step_deg, n_arms=arm_positions, width=width,
             height=height, seed=seed, train=train, image_size=size, epochs=epochs, batch_size=batch_size,
             device=device, methods=method_names)


# ----------------------------------------------------------------------------------- reproduce
@app.command("reproduce")
def reproduce_cmd(out: Path = typer.Option(..., "--out", help="folder for everything (a rerun resumes)"),
                  preset: Optional[str] = typer.Option(None, "--preset", help="smoke, cpu, gpu or full "
                                                       "\\[the TOML's, else smoke]"),
                  config: Optional[Path] = typer.Option(None, "--config", help="TOML over the preset (methods, "
                                                        "\\[data], \\[train], \\[batch], \\[ablations], \\[profile], "
                                                        "\\[select], \\[method_options.METHOD], \\[candidates.METHOD])"),
                  dataset: Optional[Path] = typer.Option(None, "--dataset", help="a dataset root to use instead of "
                                                         "simulating one (e.g. an imported TDoF20)"),
                  executor: str = typer.Option("local", "--executor", help="local, or ray: the independent jobs "
                                               "(trainings, predictions) as Ray tasks with their CPUs and GPUs"),
                  ray_address: Optional[str] = typer.Option(None, "--ray-address", help="HOST:PORT of a Ray "
                                                            "cluster \\[a new local instance]"),
                  gpus_per_job: Optional[float] = typer.Option(None, "--gpus-per-job", help="GPUs per Ray task "
                                                               "\\[1 where the cluster has GPUs]"),
                  validation_only: bool = typer.Option(False, "--validation-only", help="the dataset, trainings and "
                                                       "choices only: the tables give validation figures and no test "
                                                       "part is predicted (a scale or budget study); the same line "
                                                       "without it goes on to the test part")) -> None:
    """The paper's Tables 1-3 and both ablations with one command: dataset, train every method on
    both protocols with the same budget (images seen) and seeds, choose epochs and options on
    validation, predict and score the test part, profile, OUT/tables/tables.md (+ CSV, JSON,
    plots); resumable, locally or on a Ray cluster. See docs/reproduce.md."""
    reproduce(out, preset=preset, config=config, dataset=dataset, executor=executor, ray_address=ray_address,
              gpus_per_job=gpus_per_job, validation_only=validation_only)


#: a line break inside a paragraph (not a blank line), with the next line's indentation
_PARAGRAPH_LINES = re.compile(r"[ \t]*(?<!\n)\n(?!\s*\n)[ \t]*")


def _tidy_help(cmd: click.Command) -> click.Command:
    """No type shown for a flag in the help: typer 0.29 writes ``<bool>`` after ``--help`` and every
    ``--x/--no-x``, which take no value. And a docstring's line breaks are not sentence breaks: the
    help renders each paragraph as one line wrapped at the terminal's width (typer's rich help keeps
    a docstring's newlines, which broke descriptions mid-sentence at any width)."""
    for attr in ("help", "short_help"):
        text = getattr(cmd, attr, None)
        if text:
            setattr(cmd, attr, _PARAGRAPH_LINES.sub(" ", text.strip()))
    for p in cmd.params:
        if getattr(p, "is_flag", False) and p.metavar is None:
            p.metavar = ""
    get_help_option = cmd.get_help_option

    def help_option(ctx: click.Context):
        opt = get_help_option(ctx)
        if opt is not None and opt.metavar is None:
            opt.metavar = ""
        return opt

    cmd.get_help_option = help_option
    for sub in getattr(cmd, "commands", {}).values():
        _tidy_help(sub)
    return cmd


def cli() -> click.Command:
    """The click command of :data:`app` with its help tidied (:func:`_tidy_help`)."""
    return _tidy_help(typer.main.get_command(app))


def main() -> None:
    try:
        cli()(prog_name="tdof20")
    except TdofError as e:
        console.print(f"[bold red]error:[/bold red] {escape(str(e))}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        console.print("[bold red]interrupted[/bold red]")
        sys.exit(130)
    except OSError as e:
        # the last net: a file the stages did not check themselves (a full disk, a folder that
        # turned read-only mid-run) is still one line naming it, not a traceback
        where = f"{e.filename}: " if e.filename else ""
        console.print(f"[bold red]error:[/bold red] {escape(where + str(e.strerror or e))}", highlight=False,
                      soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
