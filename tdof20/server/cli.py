"""The server's commands, for the main ``tdof20`` app to mount: the ``serve`` group (run the
server; ``worker``; ``requeue``; ``hold-back``, ``reveal`` and ``rescore``; ``user
add|token|revoke|list``), ``submit`` and ``publish`` (``tdof20 dataset publish``). ``app`` holds
all three for a quick mount and for tests."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tdof20.errors import TdofError
from tdof20.server.client import queue_line, submit
from tdof20.server.config import DAILY_LIMIT, LEASE_S, MAX_UPLOAD_BYTES, MAX_UPLOADS, ServerConfig
from tdof20.server.publish import publish

# the database, accounts and worker (sqlalchemy, argon2, the scorer: ~1 s of imports) are imported
# inside the commands that use them, so that every other ``tdof20`` command starts without them

DATA_HELP = "the server's folder: file store (and server.db when --db is not given)"
DB_HELP = "database URL: sqlite:///PATH (default DATA/server.db) or postgresql://USER@HOST/DB"

serve_app = typer.Typer(help="The benchmark server: run it, its workers, its users.", invoke_without_command=True)
user_app = typer.Typer(no_args_is_help=True, help="Manage the server's users and their API tokens.")
serve_app.add_typer(user_app, name="user")
app = typer.Typer(no_args_is_help=True, help="The benchmark server's commands.")
app.add_typer(serve_app, name="serve")


@serve_app.callback()
def serve(ctx: typer.Context,
          dataset: Optional[Path] = typer.Option(None, help="the full dataset (with test labels) to score against"),
          data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
          db: Optional[str] = typer.Option(None, help=DB_HELP),
          host: str = typer.Option("127.0.0.1", help="address to listen on"),
          port: int = typer.Option(8020, help="port"),
          max_upload: int = typer.Option(MAX_UPLOAD_BYTES, help="largest results file, bytes"),
          daily_limit: int = typer.Option(DAILY_LIMIT, help="submissions per user per 24 hours (failed or "
                                                            "withdrawn-before-scoring ones not counted)"),
          max_uploads: int = typer.Option(MAX_UPLOADS, help="uploads of one user in progress at once"),
          secure_cookies: bool = typer.Option(False, help="mark cookies Secure (behind HTTPS)")) -> None:
    """``tdof20 serve --dataset ROOT [--db URL] [--host H --port P]``: run the HTTP server (scoring
    happens in ``tdof20 serve worker`` processes)."""
    if ctx.invoked_subcommand is not None:
        return
    if dataset is None:
        raise TdofError("give --dataset ROOT (the full dataset the server scores against)")
    import uvicorn

    from tdof20.server.app import create_app

    if daily_limit < 1 or max_uploads < 1:
        raise TdofError("--daily-limit and --max-uploads must be at least 1")
    cfg = ServerConfig(dataset=dataset, data=data, db=db, max_upload_bytes=max_upload, daily_limit=daily_limit,
                       max_uploads=max_uploads, secure_cookies=secure_cookies)
    uvicorn.run(create_app(cfg), host=host, port=port, log_level="info")


@serve_app.command("worker")
def worker(dataset: Path = typer.Option(..., help="the full dataset (with test labels)"),
           data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
           db: Optional[str] = typer.Option(None, help=DB_HELP),
           lease: float = typer.Option(LEASE_S, help="seconds a claim lasts unless renewed"),
           once: bool = typer.Option(False, help="stop when the queue is empty"),
           poll: float = typer.Option(1.0, help="seconds between looks at an empty queue"),
           pause: float = typer.Option(0.0, help="seconds to wait after claiming a job (for drills)"),
           max_wait: float = typer.Option(30.0, help="longest wait, seconds, after a full disk or a database "
                                                     "error (the job goes back to the queue)")) -> None:
    """Score queued submissions (any number of workers, sharing the database and DATA). A full disk
    or a database error gives the job back (not counted as a try) and the worker waits and goes on."""
    from tdof20.server.worker import run_worker  # the database and the scorer

    n = run_worker(ServerConfig(dataset=dataset, data=data, db=db, lease_s=lease), once=once, poll_s=poll,
                   pause_s=pause, max_wait_s=max_wait)
    typer.echo(f"scored {n} submission(s)")


@serve_app.command("requeue")
def requeue_command(uid: Optional[str] = typer.Argument(None, help="the failed submission to score again"),
                    failed: bool = typer.Option(False, "--failed", help="every failed submission"),
                    data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
                    db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Queue failed submissions again, their tries reset (``requeue UID`` or ``requeue --failed``):
    after the operator fixed what made them fail (a full disk, a database down)."""
    from tdof20.server.db import requeue  # sqlalchemy

    if (uid is None) == (not failed):
        raise TdofError("give one submission's UID or --failed (every failed submission), not both")
    uids = requeue(_engine(data, db), uid, failed)
    typer.echo(f"queued again {len(uids)} submission(s){': ' + ', '.join(uids[:20]) if uids else ''}"
               f"{' ...' if len(uids) > 20 else ''}")


@serve_app.command("hold-back")
def hold_back_command(split: str = typer.Option(..., help="the protocol whose test images are split"),
                      dataset: Path = typer.Option(..., help="the full dataset (its test lists)"),
                      fraction: float = typer.Option(0.5, help="share of the test images held back"),
                      by: str = typer.Option("image", help="image (within every scene) or scene"),
                      data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
                      db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Hold back part of a protocol's test images for the final private leaderboard (chosen once,
    from a secret seed, recorded in the database): the test phase then shows the other part only;
    ``rescore`` scores earlier results again on the two parts."""
    from tdof20.dataset.layouts import open_dataset
    from tdof20.formats.io import read_json
    from tdof20.server.db import hold_back, scored_before

    ds = open_dataset(dataset)
    targets = read_json(ds.scoring_targets_path(split)) if ds.scoring_targets_path(split).is_file() else []
    frames = sorted({(int(t["scene_id"]), int(t["im_id"])) for t in targets})
    if not frames:
        raise TdofError(f"{split} has no test targets in {dataset}")
    engine = _engine(data, db)
    part = hold_back(engine, split, frames, fraction, by)
    earlier = scored_before(engine, split)
    typer.echo(f"held back {part['n_images']} of {len(frames)} {split} test images (by {part['by']})"
               + (f"; run tdof20 serve rescore --dataset {dataset} for the {earlier} result(s) scored before"
                  if earlier else ""))
    if earlier:
        typer.echo(f"warning: {earlier} {split} test result(s) were shown on the whole test set before this part "
                   "was chosen: with their public part's scores they give their held-back part's to about a step "
                   "(hold back before the first test submission)")


@serve_app.command("reveal")
def reveal_command(split: str = typer.Option(..., help="the protocol whose final leaderboard is shown"),
                   data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
                   db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Reveal a protocol's final leaderboard: the held-back part's scores, on every page and in the API."""
    from tdof20.server.db import reveal

    part = reveal(_engine(data, db), split)
    typer.echo(f"revealed the final leaderboard of {split} ({part['n_images']} held-back test images)")


@serve_app.command("rescore")
def rescore_command(dataset: Path = typer.Option(..., help="the full dataset the workers score against"),
                    data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
                    db: Optional[str] = typer.Option(None, help=DB_HELP),
                    everything: bool = typer.Option(False, "--all", help="every scored submission, whatever "
                                                                           "its versions")) -> None:
    """Queue again every scored submission whose result is on an older scorer or dataset version
    (it keeps its shown score until the new one is recorded); the workers score them."""
    from tdof20.server.db import rescore
    from tdof20.server.facts import DatasetFacts
    from tdof20.server.worker import current_versions

    engine = _engine(data, db)
    current = {s: current_versions(engine, dataset, s) for s in DatasetFacts(dataset).splits}
    scorer = next(iter(current.values()))["scorer"]
    uids = rescore(engine, current, everything)
    typer.echo(f"queued again {len(uids)} submission(s) to score on scorer {scorer}"
               f"{': ' + ', '.join(uids[:20]) if uids else ''}{' ...' if len(uids) > 20 else ''}")


def _auth():
    from tdof20.server import auth  # argon2, sqlalchemy

    return auth


def _engine(data: Path, db: Optional[str]):
    from tdof20.server.db import init_db, make_engine  # sqlalchemy

    engine = make_engine(ServerConfig(dataset=Path("."), data=data, db=db).db_url)
    Path(data).mkdir(parents=True, exist_ok=True)
    init_db(engine)
    return engine


@user_app.command("add")
def user_add(name: str, data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
             db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Add a user and print its API token (shown once; only its hash is stored)."""
    typer.echo(_auth().add_user(_engine(data, db), name))


@user_app.command("token")
def user_token(name: str, data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
               db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Give a user a new token (the old one stops working) and print it."""
    typer.echo(_auth().new_token(_engine(data, db), name))


@user_app.command("revoke")
def user_revoke(name: str, data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
                db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """Revoke a user's token and end its sessions."""
    _auth().revoke_user(_engine(data, db), name)
    typer.echo(f"revoked {name}")


@user_app.command("list")
def user_list(data: Path = typer.Option(Path("tdof20_server"), help=DATA_HELP),
              db: Optional[str] = typer.Option(None, help=DB_HELP)) -> None:
    """The users, and which are revoked."""
    for u in _auth().list_users(_engine(data, db)):
        typer.echo(f"{u['name']}{'  (revoked)' if u['revoked'] else ''}")


@app.command("submit")
def submit_command(results: Path = typer.Argument(..., help="a BOP results CSV"),
                   server: str = typer.Option(..., help="the server's URL, e.g. http://127.0.0.1:8020"),
                   token: str = typer.Option(..., envvar="TDOF20_TOKEN", help="your API token"),
                   method: str = typer.Option(..., help="the method's name"),
                   split: str = typer.Option(..., help="the protocol: simple or hard"),
                   part: str = typer.Option("test", help="test, or val: the protocol's validation part "
                                                         "(per-image errors shown, not ranked)"),
                   description: str = typer.Option("", help="the method in a few lines"),
                   authors: str = typer.Option("", help="authors"),
                   hardware: str = typer.Option("", help="the hardware the times were measured on"),
                   time_per_image: str = typer.Option("", help="e.g. '34 ms'"),
                   training_data: str = typer.Option("", help="what the method was trained on"),
                   paper: str = typer.Option("", help="a link to the paper (http/https)"),
                   code: str = typer.Option("", help="a link to the code (http/https)"),
                   public: bool = typer.Option(False, help="show it on the leaderboard once scored")) -> None:
    """Submit a results file to a benchmark server."""
    out = submit(results, server, token, method, split, description, authors, hardware, time_per_image,
                 training_data, public, part, paper, code)
    typer.echo(f"submitted {out['uid']}: {out['status']} ({server.rstrip('/')}/s/{out['uid']})")
    if out.get("queue"):
        typer.echo(queue_line(out["queue"]))
    for w in out.get("warnings", []):
        typer.echo(f"warning: {w}")


@app.command("publish")
def publish_command(root: Path = typer.Argument(..., help="the full dataset (tdof20's layout)"),
                    out: Path = typer.Option(..., help="the new folder of the public release"),
                    split: Optional[list[str]] = typer.Option(None, help="protocols whose test labels are hidden "
                                                                          "(default: all)")) -> None:
    """Write the public release: the dataset without its test images' labels."""
    info = publish(root, out, split)
    typer.echo(f"wrote {out}: {info['hidden_test_images']} test images without labels, "
               f"{info['label_files_dropped']} label files left out")


__all__ = ["app", "hold_back_command", "publish_command", "requeue_command", "rescore_command", "reveal_command",
           "serve", "serve_app", "submit_command", "user_app", "worker"]
