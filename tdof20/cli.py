"""The ``tdof20`` command line: thin — it parses options and calls a stage's public function."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from tdof20.errors import TdofError
from tdof20.progress import console

app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  help="Build and benchmark 6DoF pose datasets of transparent objects (TDoF20).")
objects_app = typer.Typer(no_args_is_help=True, help="The 20-object catalog: list, export, picture.")
sim_app = typer.Typer(no_args_is_help=True, help="The simulated rig: scenes, sessions, frames, contact sheets.")
app.add_typer(objects_app, name="objects")
app.add_typer(sim_app, name="sim")

out_console = console.__class__()  # stdout, for tables


def _ids(text: Optional[str]) -> Optional[list[int]]:
    if text is None:
        return None
    try:
        return [int(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        raise TdofError(f"--ids must be comma-separated integers, got '{text}'") from None


# ----------------------------------------------------------------------------------- objects
@objects_app.command("list")
def objects_list() -> None:
    """Print the catalog: id, name, kind, size, diameter, symmetry."""
    from tdof20.objects import all_objects

    t = Table(title="tdof20 object catalog (mm)")
    for c in ("id", "name", "kind", "size x*y*z", "diameter", "symmetry", "faces"):
        t.add_column(c, justify="right" if c in ("id", "diameter", "faces") else "left")
    for o in all_objects():
        info = o.models_info()
        sym = ("continuous z" if o.symmetries_continuous else
               f"discrete {len(o.symmetries_discrete) + 1}-fold" if o.symmetries_discrete else "[bold]none[/bold]")
        t.add_row(str(o.obj_id), o.name, o.kind,
                  f"{info['size_x']:.0f}*{info['size_y']:.0f}*{info['size_z']:.0f}", f"{o.diameter:.1f}", sym,
                  str(len(o.faces)))
    out_console.print(t)


@objects_app.command("export")
def objects_export(out: Path = typer.Argument(..., help="folder for the BOP models (created)"),
                   ids: Optional[str] = typer.Option(None, help="comma-separated object ids (default: all)")) -> None:
    """Write a BOP models folder: obj_000001.ply ... (mm) and models_info.json."""
    from tdof20.objects import export_models

    path = export_models(out, _ids(ids))
    console.print(f"wrote BOP models to {path}")


@objects_app.command("picture")
def objects_picture(out: Path = typer.Argument(..., help="PNG file to write"),
                    tile: int = typer.Option(200, help="tile width in pixels")) -> None:
    """Render all 20 objects, glass and opaque twin, into one picture."""
    from tdof20.formats import write_png
    from tdof20.sim.gallery import catalog_picture

    write_png(out, catalog_picture(tile))
    console.print(f"wrote {out}")


# ----------------------------------------------------------------------------------- sim
@sim_app.command("scenes")
def sim_scenes() -> None:
    """List the 40 TDoF20 scenes of the simulator with their objects and stickers."""
    from tdof20.objects import get_object
    from tdof20.sim.scenes import get_scene, scene_ids

    t = Table(title="simulated TDoF20 scenes")
    for c in ("scene", "objects", "sticker"):
        t.add_column(c)
    for sid in scene_ids():
        s = get_scene(sid)
        t.add_row(sid, ", ".join(f"{i} {get_object(i).name}" for i in s.obj_ids), s.sticker)
    out_console.print(t)


def _sim_config(scene: str, steps: int, step_deg: float, arm_positions: int, width: int, height: int,
                seed: int):
    from tdof20.sim.session import SimSessionConfig

    return SimSessionConfig(scene_id=scene, steps=steps, step_deg=step_deg, n_arms=arm_positions,
                            width=width, height=height, seed=seed).validate()


SCENE = typer.Option("multi/08", help="scene name: single/01..20 or multi/01..20")
WIDTH = typer.Option(640, help="image width in pixels")
HEIGHT = typer.Option(480, help="image height in pixels")
SEED = typer.Option(0, help="noise seed (frames are deterministic for a seed)")


@sim_app.command("session")
def sim_session(out: Path = typer.Option(..., "--out", help="session folder (created; resumed if partial)"),
                scene: str = SCENE,
                steps: int = typer.Option(400, help="turntable steps per arm position"),
                step_deg: float = typer.Option(0.9, help="turntable step in degrees"),
                arm_positions: int = typer.Option(4, help="number of arm positions (elevations)"),
                width: int = WIDTH, height: int = HEIGHT, seed: int = SEED,
                truth: bool = typer.Option(True, help="write truth/ (exact ground truth as a BOP scene)"),
                sheet: bool = typer.Option(True, help="write contact_sheet.png into the session")) -> None:
    """Render a whole simulated capture session in the raw session format (with truth/)."""
    from tdof20.formats import write_png
    from tdof20.sim.session import simulate_session
    from tdof20.viz import session_contact_sheet

    cfg = _sim_config(scene, steps, step_deg, arm_positions, width, height, seed)
    t0 = time.perf_counter()
    simulate_session(cfg, out, truth=truth)
    dt = time.perf_counter() - t0
    if sheet:
        write_png(out / "contact_sheet.png", session_contact_sheet(out))
    console.print(f"session {scene} in {out} ({dt:.1f} s)" + (f"; contact sheet {out / 'contact_sheet.png'}" if sheet else ""))


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
        raise TdofError(f"--angles must be comma-separated numbers, got '{angles}'") from None
    cfg = _sim_config(scene, 400, 0.9, 4, width, height, seed)
    sheet = render_frames(cfg, out, arm, angle_list)
    console.print(f"wrote frames and {sheet}")


@sim_app.command("sheet")
def sim_sheet(session: Path = typer.Argument(..., help="raw session folder"),
              out: Optional[Path] = typer.Option(None, help="PNG to write (default: SESSION/contact_sheet.png)"),
              frames: int = typer.Option(4, help="number of frames (rows)")) -> None:
    """Contact sheet of a raw session: colour and depth of both phases, truth masks if present."""
    from tdof20.formats import write_png
    from tdof20.viz import session_contact_sheet

    out = out or session / "contact_sheet.png"
    write_png(out, session_contact_sheet(session, frames))
    console.print(f"wrote {out}")


# ----------------------------------------------------------------------------------- demo
@app.command("demo")
def demo(out: Path = typer.Option(Path("demo_out"), help="folder for everything the demo writes"),
         scene: str = SCENE,
         steps: int = typer.Option(8, help="turntable steps per arm position"),
         step_deg: float = typer.Option(45.0, help="turntable step in degrees"),
         arm_positions: int = typer.Option(4, help="number of arm positions"),
         width: int = WIDTH, height: int = HEIGHT, seed: int = SEED) -> None:
    """Run the main job end to end on the simulator: a short simulated session and its contact sheet."""
    from tdof20.demo import run_demo

    run_demo(out, scene=scene, steps=steps, step_deg=step_deg, n_arms=arm_positions, width=width,
             height=height, seed=seed)


def main() -> None:
    try:
        app()
    except TdofError as e:
        console.print(f"[bold red]error:[/bold red] {e}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        console.print("[bold red]interrupted[/bold red]")
        sys.exit(130)


if __name__ == "__main__":
    main()
