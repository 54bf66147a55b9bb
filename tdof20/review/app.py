"""The review web app (FastAPI on uvicorn, Jinja2 pages with autoescaping, as the submission
server; three.js shipped in ``static/`` for the 3D view, nothing fetched from elsewhere).

Pages::

    /                       the scene: counts, failed objects, unresolved flags, the grid of arm
                            positions x steps (flagged frames marked, their reasons), the journal
    /frame/{arm}/{step}     the frame's colour image and its opaque twin, labelled masks and model
                            outlines over them; accept / reject the frame or its arm position
    /objects                per object: its fit figure (points and posed model), figures, evaluation
    /place                  the 3D view: reconstruction and placed models; nudge with keys, drag,
                            snap, assign a cluster, undo, relabel
    /qa/...                 the pipeline's QA report and pictures (``SCENE/qa/``)

API (JSON; a POST must say ``Content-Type: application/json``, which a page of another site
cannot send without the browser asking first, and this app never says yes)::

    GET  /api/state                          objects, frames, journal, counts, ``revision``
    GET  /api/revision                       {"revision", "scene_version", "busy"} (the pages poll it)
    GET  /api/scene3d                        reconstruction points (table frame), cluster per point
    GET  /api/model/{obj_id}                 a model's vertices and faces
    POST /api/objects/{index}/nudge          {"axis": "x|y|z|rx|ry|rz", "amount": mm or deg}
    POST /api/objects/{index}/pose           {"T_table_model": [16 numbers, row-major], "how": "drag|set"}
    POST /api/objects/{index}/snap           {"turn_deg": null | t}  the place stage's fit from its turns
    POST /api/objects/{index}/discard        {}  forget its draft
    POST /api/objects/{index}/assign         {"cluster": j}
    POST /api/frames                         {"arm": a, "steps": [k, ...] | null, "verdict": "accept|reject|clear",
                                              "object": index | null}
    POST /api/undo                           {}
    POST /api/relabel                        {}  place, label and QA again

Every POST may carry ``"base_revision"`` (the ``revision`` the page was showing): a correction made
from an older one is refused with 409 and ``{"detail", "stale": true, "revision"}`` (the page
reloads). A refusal is one line: ``{"detail": "..."}`` with status 400; 422 for a pose the gates
refused (with ``gates``, the figures, ``draft`` whether it was kept as the object's draft, and
``state``); 409 for a rerun the pipeline refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from pydantic import BaseModel

from tdof20.errors import TdofError
from tdof20.formats.io import safe_inside
from tdof20.review.scene import NUDGE_AXES, SNAP_REACH_MM, GateRefused, ReviewScene, Stale

__all__ = ["STATIC", "TEMPLATES", "make_app", "review_command"]

HERE = Path(__file__).parent
TEMPLATES = HERE / "templates"
STATIC = HERE / "static"
TRANSLATE_STEPS_MM = (0.5, 1.0, 2.0, 5.0, 10.0, 25.0)
ROTATE_STEPS_DEG = (0.5, 1.0, 5.0, 15.0)


class Correction(BaseModel):
    base_revision: int | None = None   # the journal revision the page showed (None: not checked)


class Nudge(Correction):
    axis: str
    amount: float


class Pose(Correction):
    T_table_model: list[float]
    how: str = "drag"                  # drag (the 3D view) | set (typed in the Place page's box)


class Snap(Correction):
    turn_deg: float | None = None      # None: every distinct turn


class Assign(Correction):
    cluster: int


class Frames(Correction):
    arm: int
    steps: list[int] | None = None
    verdict: str
    object: int | None = None


class Empty(Correction):
    pass


class Refused(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def _json_only(request: Request) -> None:
    """A POST's body must be declared JSON (see the module docstring: no cross-site form posts)."""
    if request.headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
        raise Refused(415, "send the request as JSON (Content-Type: application/json)")


def make_app(scene: str | Path) -> FastAPI:
    """The review app of the annotated scene folder ``scene`` (TdofError when it is not one)."""
    rs = ReviewScene(scene)
    templates = Jinja2Templates(directory=str(TEMPLATES))
    app = FastAPI(title=f"tdof20 review: {rs.info.scene_id}", version="1", docs_url=None, redoc_url=None)
    app.state.review = rs
    app.mount("/static", StaticFiles(directory=str(STATIC)), name="static")

    @app.exception_handler(Refused)
    async def _refused(request: Request, e: Refused):
        return JSONResponse({"detail": e.message}, status_code=e.status)

    @app.exception_handler(Stale)
    async def _stale(request: Request, e: Stale):
        return JSONResponse({"detail": str(e), "stale": True, "revision": e.revision}, status_code=409)

    @app.exception_handler(GateRefused)
    async def _gate(request: Request, e: GateRefused):
        return JSONResponse({"detail": str(e), "gates": e.figures, "draft": e.draft, "state": rs.state()},
                            status_code=422)

    @app.exception_handler(TdofError)
    async def _tdof(request: Request, e: TdofError):
        if request.url.path.startswith("/api/"):
            return JSONResponse({"detail": str(e)}, status_code=400)
        return page(request, "error.html", {"message": str(e)}, status=400)

    @app.middleware("http")
    async def _fresh(request: Request, call_next):
        # a tdof20 annotate run may have changed the scene since: read it again first (never waits)
        if not request.url.path.startswith("/static/"):
            rs.refresh()
        return await call_next(request)

    def page(request: Request, name: str, ctx: dict, status: int = 200) -> HTMLResponse:
        return templates.TemplateResponse(request, name, {"scene_id": rs.info.scene_id, "scene": str(rs.path),
                                                          "revision": rs.revision(), "scene_version": rs.scene_version,
                                                          **ctx}, status_code=status)

    # ------------------------------------------------------------------ pages
    @app.get("/", response_class=HTMLResponse)
    def index(request: Request):
        s = rs.state()
        grid = [[f for f in s["frames"] if f["arm"] == a] for a in range(s["n_arms"])]
        flagged = [f for f in s["frames"] if f["reasons"] or f["verdict"]]
        return page(request, "index.html", {"s": s, "grid": grid, "flagged": flagged,
                                            "failed": [o for o in s["objects"] if o["status"] == "failed"],
                                            "report": (rs.path / "qa" / "report.html").exists()})

    @app.get("/frame/{arm}/{step}", response_class=HTMLResponse)
    def frame(request: Request, arm: int, step: int):
        s = rs.state()
        f = next((x for x in s["frames"] if x["arm"] == arm and x["step"] == step), None)
        if f is None:
            raise TdofError(f"no frame arm {arm} step {step} (arms 0..{s['n_arms'] - 1}, steps 0..{s['steps'] - 1})")
        n = s["steps"]
        nav = {"prev": [arm, (step - 1) % n], "next": [arm, (step + 1) % n]}
        gt = [{"gt_id": g, "obj_id": e["obj_id"]} for g, e in enumerate(rs.gt.get(f["im_id"]) or [])]
        return page(request, "frame.html", {"s": s, "f": f, "nav": nav, "gt": gt})

    @app.get("/objects", response_class=HTMLResponse)
    def objects(request: Request):
        s = rs.state()
        ev = ((rs.evaluation or {}).get("objects") or {})
        return page(request, "objects.html", {"s": s, "ev": ev})

    @app.get("/place", response_class=HTMLResponse)
    def place(request: Request):
        return page(request, "place.html", {"s": rs.state(), "t_steps": TRANSLATE_STEPS_MM, "r_steps": ROTATE_STEPS_DEG,
                                            "reach": SNAP_REACH_MM})

    @app.get("/qa/{path:path}")
    def qa_file(path: str):
        root = rs.path / "qa"
        try:
            p = safe_inside(root, root / path)
        except TdofError:
            raise Refused(404, "not found") from None
        if not p.is_file():
            raise Refused(404, "not found")
        return FileResponse(p)

    @app.get("/favicon.ico")
    def favicon():
        return Response(status_code=204)

    # ------------------------------------------------------------------ pictures
    @app.get("/img/frame/{arm}/{step}/{kind}.png")
    def frame_png(arm: int, step: int, kind: str, object: int | None = None):
        return Response(rs.frame_image(arm, step, kind, selected=object), media_type="image/png",
                        headers={"Cache-Control": "no-store"})

    @app.get("/img/object/{index}.png")
    def object_png(index: int):
        return Response(rs.object_figure(index), media_type="image/png", headers={"Cache-Control": "no-store"})

    # ------------------------------------------------------------------ API
    @app.get("/api/state")
    def api_state() -> dict:
        return rs.state()

    @app.get("/api/revision")
    def api_revision() -> dict:
        """What the pages poll: the journal's revision and the scene's version (a relabel, a change
        on disk by a tdof20 annotate run), and whether a relabel is running."""
        return {"revision": rs.revision(), "scene_version": rs.scene_version, "busy": rs.relabeller.running,
                "changed_on_disk": rs.changed_on_disk}

    @app.get("/api/scene3d")
    def api_scene3d() -> dict:
        return rs.scene3d()

    @app.get("/api/model/{obj_id}")
    def api_model(obj_id: int) -> dict:
        return rs.model3d(obj_id)

    def correct(body: Correction, fn, *args) -> dict:
        """One correction, refused (409) when made from an older journal revision than the scene's;
        the check and the correction under the scene's lock, so no other correction comes between."""
        with rs.lock:
            rs.check_revision(body.base_revision)
            out = fn(*args)
        return {**out, "state": rs.state()}

    @app.post("/api/objects/{index}/nudge", dependencies=[Depends(_json_only)])
    def api_nudge(index: int, body: Nudge) -> dict:
        """Move (mm) or turn (deg) an object along / about a table-frame axis (through the gates)."""
        if body.axis not in NUDGE_AXES:
            raise TdofError(f"axis must be one of {', '.join(NUDGE_AXES)}, got '{body.axis}'")
        return correct(body, rs.nudge, index, body.axis, body.amount)

    @app.post("/api/objects/{index}/pose", dependencies=[Depends(_json_only)])
    def api_pose(index: int, body: Pose) -> dict:
        """An object's pose in the table frame: the 3D view's drag, or typed (through the gates)."""
        if body.how not in ("drag", "set"):
            raise TdofError(f"how must be drag or set, got '{body.how}'")
        return correct(body, rs.set_pose, index, body.T_table_model, body.how)

    @app.post("/api/objects/{index}/snap", dependencies=[Depends(_json_only)])
    def api_snap(index: int, body: Snap) -> dict:
        """The place stage's fit from the object's distinct turns; written when one is told apart."""
        return correct(body, rs.snap, index, body.turn_deg)

    @app.post("/api/objects/{index}/discard", dependencies=[Depends(_json_only)])
    def api_discard(index: int, body: Empty) -> dict:
        return correct(body, rs.discard, index)

    @app.post("/api/objects/{index}/assign", dependencies=[Depends(_json_only)])
    def api_assign(index: int, body: Assign) -> dict:
        return correct(body, rs.assign, index, body.cluster)

    @app.post("/api/frames", dependencies=[Depends(_json_only)])
    def api_frames(body: Frames) -> dict:
        if body.verdict not in ("accept", "reject", "clear"):
            raise TdofError(f"verdict must be accept, reject or clear, got '{body.verdict}'")
        return correct(body, rs.verdict, body.arm, body.steps, body.verdict, body.object)

    @app.post("/api/undo", dependencies=[Depends(_json_only)])
    def api_undo(body: Empty) -> dict:
        return correct(body, rs.undo)

    @app.post("/api/relabel", dependencies=[Depends(_json_only)])
    def api_relabel(body: Empty) -> Any:
        """Rerun place, label and QA from the corrections (seconds to minutes: the scene's size)."""
        try:
            with rs.lock:
                rs.check_revision(body.base_revision)
                summary = rs.relabel()
        except Stale:
            raise
        except TdofError as e:
            return JSONResponse({"detail": str(e), "state": rs.state()}, status_code=409)
        lab = summary.get("label") or {}
        return {"labelled": int(lab.get("labelled", 0)) + int(lab.get("already_done", 0)),
                "unresolved_flags": summary.get("unresolved_flags") or [], "partial": bool(summary.get("partial")),
                "evaluation": (summary.get("evaluation") or {}).get("all"), "state": rs.state()}

    return app


def review_command(scene: str | Path, port: int = 8765, host: str = "127.0.0.1", open_browser: bool = False) -> None:
    """``tdof20 annotate review SCENE [--port N] [--host H] [--open]``: serve the review app of the
    annotated scene folder ``SCENE`` on http://HOST:PORT/ until interrupted. Only requests naming
    this host (or localhost) are answered, so a page of another site cannot reach it through a
    DNS name pointed at this machine. A scene that is not one, or a port in use, is one line.

    The port is bound here with SO_REUSEADDR (what uvicorn does too), so it can be used again at
    once after the app was killed (its last connections wait out TCP's TIME_WAIT); and Ctrl+C or
    SIGTERM first kills a running relabel with every process it started (uvicorn would otherwise
    wait for the relabel request to finish)."""
    import socket
    import threading
    import webbrowser

    import uvicorn
    from starlette.middleware.trustedhost import TrustedHostMiddleware

    if not 0 < int(port) < 65536:
        raise TdofError(f"--port must be in 1..65535, got {port}")
    app = make_app(scene)
    rs: ReviewScene = app.state.review
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, int(port)))
        sock.listen(128)
    except OSError as e:
        sock.close()
        raise TdofError(f"cannot listen on {host}:{port} ({e.strerror}): give another --port") from None
    sock.set_inheritable(False)
    hosts = sorted({host, "localhost", "127.0.0.1", "[::1]"})
    url = f"http://{'[' + host + ']' if ':' in host else host}:{port}/"

    class _Server(uvicorn.Server):
        def handle_exit(self, sig, frame):   # Ctrl+C, SIGTERM: the relabel and its workers go first
            rs.relabeller.stop()
            super().handle_exit(sig, frame)

    server = _Server(uvicorn.Config(TrustedHostMiddleware(app, allowed_hosts=hosts), log_level="warning",
                                    timeout_graceful_shutdown=5))
    print(f"reviewing {rs.info.scene_id} ({Path(scene)}) at {url}  (Ctrl+C stops)", flush=True)
    if open_browser:
        threading.Timer(1.0, webbrowser.open, args=(url,)).start()
    try:
        server.run(sockets=[sock])
    finally:
        rs.relabeller.stop()
        sock.close()
