"""The HTTP server (FastAPI on uvicorn; Jinja2 pages with autoescaping; no JavaScript).

API (JSON; ``Authorization: Bearer TOKEN``; schema at /openapi.json)::

    POST /api/submissions                 multipart: file, method, split, [description, authors,
                                          hardware, time_per_image, training_data, public]
    GET  /api/submissions                 the caller's submissions
    GET  /api/submissions/{uid}           one (its owner's, or a public one)
    POST /api/submissions/{uid}/withdraw  the owner withdraws it
    GET  /api/leaderboard?split=&metric=  public scored submissions, best first

Pages: ``/`` leaderboard, ``/signin`` (name + token), ``/submit`` (upload form), ``/mine``,
``/s/{uid}`` (status, refreshing while queued; results: per-object table, per scene, figures
drawn when first asked for, :mod:`~tdof20.server.figures`), ``/s/{uid}/plots/{name}`` (a figure),
``/s/{uid}/withdraw`` (pages are left out of the OpenAPI schema, which is the API's). Every
form carries a CSRF token (the session's; the sign-in form's is a
double-submit cookie). Every refusal is one line: JSON ``{"detail": "..."}`` from the API.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import Depends, FastAPI, File, Form, Request, UploadFile
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from tdof20.server import auth, submissions as subs
from tdof20.server.config import ServerConfig
from tdof20.server.db import init_db, make_engine
from tdof20.server.facts import DatasetFacts
from tdof20.server.figures import figures
from tdof20.server.store import FULL, FULL_ERRNOS, Refused, Store

TEMPLATES = Path(__file__).with_name("templates")
SESSION_COOKIE = "tdof20_session"
SIGNIN_COOKIE = "tdof20_signin_csrf"
BODY_SLACK = 64 * 1024  # form fields and multipart framing beside the file


class BodyLimit:
    """Refuse a request body over ``max_bytes`` (413, one line) by its Content-Length, or while it
    streams in when it has none, without reading the rest."""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_bytes):
            await _too_large(self.max_bytes, send)
            return
        seen = 0
        started = refused = False

        async def limited() -> Message:
            nonlocal seen, started, refused
            if refused:
                return {"type": "http.disconnect"}
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.max_bytes:  # answer now; the app sees the client gone and stops reading
                    refused = True
                    if not started:
                        started = True
                        await _too_large(self.max_bytes, send)
                    return {"type": "http.disconnect"}
            return msg

        async def watch(msg: Message) -> None:
            nonlocal started
            if refused:
                return  # the 413 is the answer
            started = started or msg["type"] == "http.response.start"
            await send(msg)

        try:
            await self.app(scope, limited, watch)
        except Exception:
            if not refused:
                raise


async def _too_large(limit: int, send: Send) -> None:
    body = f'{{"detail":"the request is larger than the limit of {limit} bytes"}}'.encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def _out_of_room(e: BaseException) -> bool:
    """Whether ``e`` was caused, at any depth, by a write that found no room."""
    seen = 0
    while e is not None and seen < 20:  # bounded: a cause chain
        if isinstance(e, OSError) and e.errno in FULL_ERRNOS:
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


def create_app(cfg: ServerConfig) -> ASGIApp:
    """The server's ASGI application for ``cfg`` (the database is created where missing)."""
    store = Store(cfg.data)  # (the folder first: the SQLite file lies in it)
    store.remove_stale_uploads()
    engine = make_engine(cfg.db_url)
    init_db(engine)
    facts = DatasetFacts(cfg.dataset)
    templates = Jinja2Templates(directory=str(TEMPLATES))
    app = FastAPI(title="tdof20 benchmark server", version="1", docs_url=None, redoc_url=None)
    app.state.engine = engine

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, e: StarletteHTTPException):
        """FastAPI's own refusals, one line; a form that could not be parsed because the disk under
        the multipart parser's temp files is full is the full disk's 507, not a 400."""
        if _out_of_room(e):
            return await _refused(request, Refused(507, FULL))
        if request.url.path.startswith("/api/") or request.url.path.startswith("/openapi"):
            return JSONResponse({"detail": e.detail}, status_code=e.status_code, headers=e.headers)
        return page(request, "error.html", {"message": e.detail}, status=e.status_code)

    @app.exception_handler(Refused)
    async def _refused(request: Request, e: Refused):
        if request.url.path.startswith("/api/"):
            headers = {"WWW-Authenticate": "Bearer"} if e.status == 401 else None
            return JSONResponse({"detail": e.message}, status_code=e.status, headers=headers)
        return page(request, "error.html", {"message": e.message}, status=e.status)

    def api_user(request: Request) -> dict:
        header = request.headers.get("authorization", "")
        if not header:
            raise Refused(401, "missing token: send 'Authorization: Bearer TOKEN'")
        scheme, _, token = header.partition(" ")
        user = auth.authenticate(engine, token.strip()) if scheme.lower() == "bearer" else None
        if user is None:
            raise Refused(401, "invalid or revoked token")
        return user

    def page_user(request: Request) -> dict | None:
        return auth.session_user(engine, request.cookies.get(SESSION_COOKIE))

    def need_page_user(request: Request) -> dict:
        user = page_user(request)
        if user is None:
            raise Refused(401, "sign in first")
        return user

    def check_csrf(user: dict, token: str) -> None:
        if not auth.same_token(user["csrf"], token):
            raise Refused(403, "the form's CSRF token is missing or wrong: reload the page")

    def page(request: Request, name: str, ctx: dict, status: int = 200) -> HTMLResponse:
        user = page_user(request)
        return templates.TemplateResponse(request, name, {"user": user, "splits": facts.splits, **ctx},
                                          status_code=status)

    def fields(method, split, part, description, authors, hardware, time_per_image, training_data,
               public) -> subs.Fields:
        return subs.Fields(method=method, split=split, part=part, description=description, authors=authors,
                           hardware=hardware, time_per_image=time_per_image, training_data=training_data,
                           public=bool(public))

    def take(user: dict, file: UploadFile, f: subs.Fields) -> dict:
        return subs.accept(engine, store, facts, user, file.file, file.filename or "", f, cfg.max_upload_bytes,
                           cfg.max_line_bytes, cfg.daily_limit)

    # ------------------------------------------------------------------ API
    @app.post("/api/submissions", status_code=201)
    def api_submit(user: dict = Depends(api_user), file: UploadFile = File(...), method: str = Form(...),
                   split: str = Form(...), part: str = Form("test"), description: str = Form(""),
                   authors: str = Form(""),
                   hardware: str = Form(""), time_per_image: str = Form(""), training_data: str = Form(""),
                   public: bool = Form(False)) -> dict:
        """Submit a BOP results CSV: checked at once (a 400 names the line of the first error),
        stored, queued; returns its status (``uid``, ``status``: queued). ``part``: test (the
        default: ranked, aggregates only) or val (the protocol's validation part: per-image errors)."""
        return take(user, file, fields(method, split, part, description, authors, hardware, time_per_image,
                                       training_data, public))

    @app.get("/api/submissions")
    def api_mine(user: dict = Depends(api_user)) -> list[dict]:
        return subs.mine(engine, user)

    @app.get("/api/submissions/{uid}")
    def api_get(uid: str, user: dict = Depends(api_user)) -> dict:
        return subs.get(engine, uid, user)

    @app.post("/api/submissions/{uid}/withdraw")
    def api_withdraw(uid: str, user: dict = Depends(api_user)) -> dict:
        return subs.withdraw(engine, uid, user)

    @app.get("/api/leaderboard")
    def api_leaderboard(split: str, metric: str = "add_s") -> list[dict]:
        return subs.leaderboard(engine, split, metric)

    # ------------------------------------------------------------------ pages
    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def home(request: Request, split: str | None = None, metric: str = "add_s"):
        split = split if split in facts.splits else facts.splits[0]
        rows = subs.leaderboard(engine, split, metric)
        return page(request, "leaderboard.html", {"rows": rows, "split": split, "metric": metric,
                                                  "metrics": subs.LEADERBOARD_METRICS})

    @app.get("/signin", response_class=HTMLResponse, include_in_schema=False)
    def signin_form(request: Request):
        token = auth.secrets.token_urlsafe(24)
        resp = page(request, "signin.html", {"csrf": token})
        resp.set_cookie(SIGNIN_COOKIE, token, httponly=True, samesite="strict", secure=cfg.secure_cookies)
        return resp

    @app.post("/signin", include_in_schema=False)
    def signin(request: Request, name: str = Form(...), token: str = Form(...), csrf: str = Form("")):
        if not auth.same_token(request.cookies.get(SIGNIN_COOKIE), csrf):
            raise Refused(403, "the form's CSRF token is missing or wrong: reload the page")
        user = auth.authenticate(engine, token.strip())
        if user is None or user["name"] != name:
            raise Refused(401, "wrong name or token")
        resp = RedirectResponse("/mine", status_code=303)
        resp.set_cookie(SESSION_COOKIE, auth.create_session(engine, user["id"]), httponly=True, samesite="lax",
                        secure=cfg.secure_cookies, max_age=auth.SESSION_S)
        resp.delete_cookie(SIGNIN_COOKIE)
        return resp

    @app.post("/signout", include_in_schema=False)
    def signout(request: Request, csrf: str = Form("")):
        user = need_page_user(request)
        check_csrf(user, csrf)
        auth.end_session(engine, request.cookies.get(SESSION_COOKIE))
        resp = RedirectResponse("/", status_code=303)
        resp.delete_cookie(SESSION_COOKIE)
        return resp

    @app.get("/submit", response_class=HTMLResponse, include_in_schema=False)
    def submit_form(request: Request):
        need_page_user(request)
        return page(request, "submit.html", {"limits": cfg, "val_splits": [s for s in facts.splits
                                                                           if "val" in facts.parts(s)]})

    @app.post("/submit", include_in_schema=False)
    def submit_page(request: Request, file: UploadFile = File(...), method: str = Form(...), split: str = Form(...),
                    part: str = Form("test"), description: str = Form(""), authors: str = Form(""),
                    hardware: str = Form(""),
                    time_per_image: str = Form(""), training_data: str = Form(""), public: bool = Form(False),
                    csrf: str = Form("")):
        user = need_page_user(request)
        check_csrf(user, csrf)
        out = take(user, file, fields(method, split, part, description, authors, hardware, time_per_image,
                                      training_data,
                                      public))
        return RedirectResponse(f"/s/{out['uid']}", status_code=303)

    @app.get("/mine", response_class=HTMLResponse, include_in_schema=False)
    def mine_page(request: Request):
        return page(request, "mine.html", {"rows": subs.mine(engine, need_page_user(request))})

    @app.get("/s/{uid}", response_class=HTMLResponse, include_in_schema=False)
    def submission_page(request: Request, uid: str):
        s = subs.get(engine, uid, page_user(request))
        return page(request, "submission.html", {"s": s, "plots": plots_of(s)})

    @app.post("/s/{uid}/withdraw", include_in_schema=False)
    def withdraw_page(request: Request, uid: str, csrf: str = Form("")):
        user = need_page_user(request)
        check_csrf(user, csrf)
        subs.withdraw(engine, uid, user)
        return RedirectResponse(f"/s/{uid}", status_code=303)

    def plots_of(s: dict) -> list[str]:
        """A scored submission's figures (drawn and cached at the first request); [] before."""
        return figures(store.results_dir(s["uid"]), s["method"], s["result"]) if s["result"] else []

    @app.get("/s/{uid}/plots/{name}", include_in_schema=False)
    def plot(request: Request, uid: str, name: str) -> Response:
        s = subs.get(engine, uid, page_user(request))
        if name not in plots_of(s):  # (a name from the list: never a path the request made)
            raise Refused(404, "no such plot")
        return FileResponse(store.results_dir(s["uid"]) / name, media_type="image/png")

    return BodyLimit(app, cfg.max_upload_bytes + BODY_SLACK)


__all__ = ["BodyLimit", "create_app"]
