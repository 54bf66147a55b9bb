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

import math
import sys
from pathlib import Path

from fastapi import Depends, FastAPI, Form, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from tdof20.server import auth, submissions as subs
from tdof20.server.config import ServerConfig
from tdof20.server.cells import dataset_version, scorer_version
from tdof20.server.db import init_db, make_engine, versions_behind
from tdof20.server.facts import FLOOR_MIN_LABELS, DatasetFacts
from tdof20.server.figures import figures
from tdof20.server.publish import DERIVABLE, derivable, hidden_frames
from tdof20.server.store import FULL, FULL_ERRNOS, Refused, Store
from tdof20.server.upload import read_form

TEMPLATES = Path(__file__).with_name("templates")
SESSION_COOKIE = "tdof20_session"
SIGNIN_COOKIE = "tdof20_signin_csrf"
BODY_SLACK = 64 * 1024  # form fields and multipart framing beside the file
BOOLEANS = {"true": True, "1": True, "on": True, "yes": True, "false": False, "0": False, "off": False, "no": False,
            "": False}
_TEXT = {"type": "string"}
SUBMIT_SCHEMA = {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["file", "method", "split"],
    "properties": {"file": {"type": "string", "format": "binary"}, "method": _TEXT, "split": _TEXT,
                   "part": {"type": "string", "enum": ["test", "val"], "default": "test"}, "description": _TEXT,
                   "authors": _TEXT, "hardware": _TEXT, "time_per_image": _TEXT, "training_data": _TEXT,
                   "paper": {"type": "string", "description": "a link (http/https)"},
                   "code": {"type": "string", "description": "a link (http/https)"},
                   "public": {"type": "boolean", "default": False}}}}}}}


class BodyLimit:
    """Refuse a request body over ``max_bytes`` (413, one line) by its Content-Length, or while it
    streams in when it has none, without reading the rest."""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    def __getattr__(self, name: str):  # (the application's ``state`` and the like, through the wrapper)
        return getattr(self.app, name)

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


CSP = ("default-src 'none'; style-src 'unsafe-inline'; img-src 'self'; form-action 'self'; frame-ancestors 'none'; "
       "base-uri 'none'")
SECURITY_HEADERS = [(b"x-frame-options", b"DENY"), (b"content-security-policy", CSP.encode()),
                    (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"same-origin")]


class SecurityHeaders:
    """Every response (pages, API, refusals, the body limit's 413) says: never in a frame
    (X-Frame-Options DENY; CSP frame-ancestors 'none'), no script, no plugin, forms to this server
    only (Content-Security-Policy: the pages carry no JavaScript and an inline style sheet), no
    content-type sniffing."""

    def __init__(self, app: ASGIApp):
        self.app = app

    def __getattr__(self, name: str):  # (the application's ``state`` and the like, through the wrapper)
        return getattr(self.app, name)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(msg: Message) -> None:
            if msg["type"] == "http.response.start":
                names = {k.lower() for k, _ in msg.get("headers", [])}
                msg["headers"] = list(msg.get("headers", [])) + [h for h in SECURITY_HEADERS if h[0] not in names]
            await send(msg)

        await self.app(scope, receive, with_headers)


class Limited(Refused):
    """A client over its failure limit: 429, one line, and ``Retry-After`` (seconds)."""

    def __init__(self, message: str, retry_after: float):
        super().__init__(429, message)
        self.retry_after = max(1, math.ceil(retry_after))


def client_key(request: Request) -> str:
    """The address a failure is counted against (the peer: a proxy in front passes its own)."""
    return request.client.host if request.client is not None else "?"


def derivable_notes(root: Path) -> dict[str, str]:
    """Per protocol whose test labels are derivable from public images (publish.json's rule:
    :func:`tdof20.server.publish.derivable`), the reason to print on its leaderboard; computed
    once at server start. A dataset whose layout publish does not know gives none."""
    try:
        facts = derivable(root, hidden_frames(root))
    except Exception as e:  # noqa: BLE001 (a layout publish cannot read: no note, said on stderr)
        print(f"server: whether test labels are derivable from public images: {type(e).__name__}: {e}",
              file=sys.stderr)
        return {}
    return {s: str(f.get("why", "")) for s, f in facts.items() if f.get(DERIVABLE)}


def one_line(errors) -> str:
    """FastAPI's list of validation errors as one line: ``method: field required; split: ...``."""
    out = []
    for e in errors:
        loc = [str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path", "header", "cookie")]
        msg = str(e.get("msg", "invalid")).replace("Field required", "field required")
        out.append(f"{'.'.join(loc) or 'request'}: {msg}")
    return "; ".join(out)[:500] or "the request is not valid"


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
    subs.sweep_reservations(engine)
    facts = DatasetFacts(cfg.dataset)
    templates = Jinja2Templates(directory=str(TEMPLATES))
    templates.env.filters["utc"] = subs.utc
    notes = derivable_notes(Path(cfg.dataset))
    scorer = scorer_version()

    def current() -> dict[str, dict]:
        """The versions a result computed now would be on, per protocol (the page says whether a
        score is on them; ``tdof20 serve rescore`` scores the others again)."""
        held = subs.held_parts(engine)
        return {s: {"scorer": scorer, "dataset": dataset_version(cfg.dataset, s, (held.get(s) or {}).get("digest"))}
                for s in facts.splits}

    behind = versions_behind(engine, current())
    if behind:  # (the operator changed the dataset or upgraded the scorer: say so once, at start)
        print(f"server: {behind} scored submission(s) are on an older scorer or dataset version than this "
              f"server's (scorer {scorer}): run tdof20 serve rescore --dataset {cfg.dataset} to score them again",
              file=sys.stderr)
    signin_failures = auth.FailureLimit(cfg.max_failures, cfg.failure_window_s)
    token_failures = auth.FailureLimit(cfg.max_failures, cfg.failure_window_s)
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

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, e: RequestValidationError):
        """A missing or malformed field: one line (``{"detail": "method: field required"}``), 422."""
        return await _refused(request, Refused(422, one_line(e.errors())))

    @app.exception_handler(Refused)
    async def _refused(request: Request, e: Refused):
        headers = {"Connection": "close"} if getattr(request.state, "unread", False) else {}
        if isinstance(e, Limited):
            headers["Retry-After"] = str(e.retry_after)
        if request.url.path.startswith("/api/"):
            if e.status == 401:
                headers["WWW-Authenticate"] = "Bearer"
            return JSONResponse({"detail": e.message}, status_code=e.status, headers=headers)
        resp = page(request, "error.html", {"message": e.message}, status=e.status)
        resp.headers.update(headers)
        return resp

    def api_user(request: Request) -> dict:
        header = request.headers.get("authorization", "")
        if not header:
            raise Refused(401, "missing token: send 'Authorization: Bearer TOKEN'")
        client = client_key(request)
        wait = token_failures.retry_after(client)
        if wait > 0:  # before the token is checked: guessing costs the guesser, not argon2's time
            raise Limited(f"too many refused tokens from your address: try again in {math.ceil(wait)} s", wait)
        scheme, _, token = header.partition(" ")
        user = auth.authenticate(engine, token.strip()) if scheme.lower() == "bearer" else None
        if user is None:
            token_failures.failed(client)
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

    def fields(form: dict[str, str]) -> subs.Fields:
        """The form's fields (a missing one named in one line, 422, as FastAPI would)."""
        for name in ("method", "split"):
            if name not in form:
                raise Refused(422, f"{name}: field required")
        public = form.get("public", "false").strip().lower()
        if public not in BOOLEANS:
            raise Refused(422, "public: must be true or false")
        return subs.Fields(method=form["method"], split=form["split"], part=form.get("part", "test"),
                           description=form.get("description", ""), authors=form.get("authors", ""),
                           hardware=form.get("hardware", ""), time_per_image=form.get("time_per_image", ""),
                           training_data=form.get("training_data", ""), paper=form.get("paper", ""),
                           code=form.get("code", ""), public=BOOLEANS[public])

    async def take(request: Request, user: dict, csrf: bool = False) -> dict:
        """Reserve the slot (daily limit, uploads at once) before reading a byte of the body, then
        stream the form into the store, check and queue; the slot goes back on any refusal."""
        request.state.unread = True  # a refusal before the body's end closes the connection after it
        slot = await run_in_threadpool(subs.reserve, engine, user, cfg.daily_limit, cfg.max_uploads)
        form = None
        try:
            form = await read_form(request, store, cfg.max_upload_bytes, cfg.max_line_bytes)
            request.state.unread = False
            if csrf:
                check_csrf(user, form.fields.get("csrf", ""))
            f = fields(form.fields)
            if form.file is None:
                raise Refused(422, "file: field required")
            return await run_in_threadpool(subs.accept, engine, store, facts, user, form.file, form.filename, f,
                                           cfg.max_upload_bytes, cfg.max_line_bytes, cfg.daily_limit, slot,
                                           cfg.max_uploads)
        finally:
            if form is not None and form.file is not None:
                form.file.path.unlink(missing_ok=True)
            if not slot.taken:
                await run_in_threadpool(_release, slot)

    def _release(slot) -> None:
        try:
            subs.release(engine, slot)
        except Exception:  # (a database without room: the slot lapses after RESERVE_S)
            pass

    # ------------------------------------------------------------------ API
    @app.post("/api/submissions", status_code=201, openapi_extra=SUBMIT_SCHEMA)
    async def api_submit(request: Request, user: dict = Depends(api_user)) -> dict:
        """Submit a BOP results CSV (multipart: ``file``, ``method``, ``split``, optional ``part``,
        ``description``, ``authors``, ``hardware``, ``time_per_image``, ``training_data``,
        ``public``): the daily limit is checked and a slot reserved before the file is read; the
        file is streamed to disk, checked (a 400 names the line of the first error), stored, queued;
        returns its status (``uid``, ``status``: queued, ``quota``). ``part``: test (the default:
        ranked, aggregates only) or val (the protocol's validation part: per-image errors)."""
        return await take(request, user)

    @app.get("/api/quota")
    def api_quota(user: dict = Depends(api_user)) -> dict:
        """The caller's daily limit: ``limit``, ``used``, ``left``, ``resets_at`` (UTC: when the
        oldest counted submission leaves the 24-hour window), ``uploading``."""
        return subs.quota(engine, user, cfg.daily_limit)

    @app.get("/api/submissions")
    def api_mine(user: dict = Depends(api_user)) -> list[dict]:
        """The caller's submissions, newest first (a queued one with ``queue``: position and ETA)."""
        return subs.mine(engine, user, current())

    @app.get("/api/submissions/{uid}")
    def api_get(uid: str, user: dict = Depends(api_user)) -> dict:
        """One submission: ``status``; while queued or scored, ``queue`` (``position``, ``ahead``,
        ``workers``, ``typical_s``, ``eta_s``); once scored, ``result`` as the disclosure rule shows
        it and ``version`` (the scorer and dataset versions, ``current``: whether they are this server's)."""
        return subs.get(engine, uid, user, current())

    @app.post("/api/submissions/{uid}/withdraw")
    def api_withdraw(uid: str, user: dict = Depends(api_user)) -> dict:
        return subs.withdraw(engine, uid, user)

    @app.get("/api/leaderboard")
    def api_leaderboard(split: str, metric: str = "add_s", phase: str = "test") -> list[dict]:
        """Public scored submissions of a phase, best first (``phase``: val, test or final; ``rank``,
        ``score`` as shown, ``score_step``, ``score_withheld``, the method's description and links)."""
        return subs.leaderboard(engine, split, metric, phase, current())

    @app.get("/api/leaderboard.csv", response_class=Response)
    def api_leaderboard_csv(split: str, metric: str = "add_s", phase: str = "test") -> Response:
        """The same leaderboard as CSV (scores in %, as shown)."""
        if split not in facts.splits:
            raise Refused(400, f"split must be one of {', '.join(facts.splits)}")
        text = subs.leaderboard_csv(subs.leaderboard(engine, split, metric, phase, current()), metric, phase)
        return Response(text, media_type="text/csv; charset=utf-8", headers={
            "Content-Disposition": f'attachment; filename="tdof20_{split}_{phase}_{metric}.csv"'})

    # ------------------------------------------------------------------ pages
    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def home(request: Request, split: str | None = None, metric: str = "add_s", phase: str = "test"):
        split = split if split in facts.splits else facts.splits[0]
        phase = phase if phase in subs.PHASES else "test"
        held = subs.held_parts(engine).get(split)
        if phase == "final" and not (held or {}).get("revealed"):
            rows = []
        else:
            rows = subs.leaderboard(engine, split, metric, phase, current())
        return page(request, "leaderboard.html", {"rows": rows, "split": split, "metric": metric, "phase": phase,
                                                  "metrics": subs.LEADERBOARD_METRICS, "held": held,
                                                  "has_val": "val" in facts.parts(split),
                                                  "derivable": notes.get(split)})

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
        client = client_key(request)
        wait = signin_failures.retry_after(client)
        if wait > 0:
            raise Limited(f"too many failed sign-ins from your address: try again in {math.ceil(wait)} s", wait)
        user = auth.authenticate(engine, token.strip())
        if user is None or user["name"] != name:
            signin_failures.failed(client)
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
        user = need_page_user(request)
        return page(request, "submit.html", {"limits": cfg, "quota": subs.quota(engine, user, cfg.daily_limit),
                                             "val_splits": [s for s in facts.splits if "val" in facts.parts(s)]})

    @app.post("/submit", include_in_schema=False)
    async def submit_page(request: Request):
        user = await run_in_threadpool(need_page_user, request)
        out = await take(request, user, csrf=True)
        return RedirectResponse(f"/s/{out['uid']}", status_code=303)

    @app.get("/mine", response_class=HTMLResponse, include_in_schema=False)
    def mine_page(request: Request):
        user = need_page_user(request)
        return page(request, "mine.html", {"rows": subs.mine(engine, user, current()),
                                           "quota": subs.quota(engine, user, cfg.daily_limit)})

    @app.get("/s/{uid}", response_class=HTMLResponse, include_in_schema=False)
    def submission_page(request: Request, uid: str):
        s = subs.get(engine, uid, page_user(request), current())
        return page(request, "submission.html", {"s": s, "plots": plots_of(s),
                                                 "held": subs.held_parts(engine).get(s["split"]),
                                                 "objects": facts.object_facts(s["split"], s.get("part") or "test"),
                                                 "floor_min": FLOOR_MIN_LABELS})

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

    return SecurityHeaders(BodyLimit(app, cfg.max_upload_bytes + BODY_SLACK))


__all__ = ["BodyLimit", "SecurityHeaders", "create_app", "one_line"]
