"""A submission's multipart form, parsed as it streams in (python-multipart's parser): the file
part goes straight into the store's tmp/ (:class:`tdof20.server.store.Upload`: size and line limits
checked as it comes, a full disk the one-line 507), the text fields are kept (each at most
:data:`FIELD_BYTES`). Nothing holds the file in memory: the server's memory per upload is O(1) in
its size. The route calls this only after it has reserved the submission's slot in the daily limit."""

from __future__ import annotations

from dataclasses import dataclass, field

from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

from tdof20.server.store import Refused, Store, Stored, Upload

FIELD_BYTES = 16 * 1024  # a text field (the longest, description, is 4,000 characters)
MAX_FIELDS = 32
FEED = 256 * 1024  # bytes given to the parser at once


@dataclass
class Form:
    fields: dict[str, str] = field(default_factory=dict)
    file: Stored | None = None
    filename: str = ""


def _disposition(headers: dict[bytes, bytes]) -> tuple[str, str | None]:
    _, params = parse_options_header(headers.get(b"content-disposition", b""))
    name = params.get(b"name", b"").decode("utf-8", "replace")
    filename = params.get(b"filename")
    return name, None if filename is None else filename.decode("utf-8", "replace")


async def read_form(request: Request, store: Store, max_bytes: int, max_line: int) -> Form:
    """The form of ``request``; Refused (one line) on a body that is not multipart, a field too
    long, a second file, the file's limits or a full disk; the temp file goes on any refusal."""
    ctype, params = parse_options_header(request.headers.get("content-type", ""))
    boundary = params.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise Refused(400, "the body must be multipart/form-data (a file and the form's fields)")
    form = Form()
    state: dict = {"headers": {}, "name": None, "buf": None, "upload": None, "hfield": b"", "hvalue": b""}
    errors: list[Refused] = []

    def on_part_begin():
        state.update(headers={}, name=None, buf=None, upload=None, hfield=b"", hvalue=b"")

    def on_header_field(data, start, end):
        state["hfield"] += data[start:end]

    def on_header_value(data, start, end):
        state["hvalue"] += data[start:end]

    def on_header_end():
        state["headers"][state["hfield"].lower()] = state["hvalue"]
        state["hfield"], state["hvalue"] = b"", b""

    def on_headers_finished():
        name, filename = _disposition(state["headers"])
        state["name"] = name
        if filename is not None and name == "file":
            if form.file is not None or state.get("had_file"):
                raise Refused(400, "file: send one results file")
            state["had_file"] = True
            form.filename = filename
            state["upload"] = store.writer(max_bytes, max_line)
        else:
            if len(form.fields) >= MAX_FIELDS:
                raise Refused(400, f"the form has more than {MAX_FIELDS} fields")
            state["buf"] = bytearray()

    def on_part_data(data, start, end):
        if state["upload"] is not None:
            state["upload"].write(data[start:end])
        elif state["buf"] is not None:
            state["buf"] += data[start:end]
            if len(state["buf"]) > FIELD_BYTES:
                raise Refused(400, f"{state['name'][:40]}: a form field of more than {FIELD_BYTES} bytes")

    def on_part_end():
        if state["upload"] is not None:  # synced off the event loop, after this write
            state["ended"], state["upload"] = state["upload"], None
        elif state["buf"] is not None:
            try:
                form.fields[state["name"]] = bytes(state["buf"]).decode("utf-8")
            except UnicodeDecodeError:
                raise Refused(400, f"{state['name'][:40]}: not UTF-8 text") from None

    parser = MultipartParser(boundary, {
        "on_part_begin": on_part_begin, "on_part_data": on_part_data, "on_part_end": on_part_end,
        "on_header_field": on_header_field, "on_header_value": on_header_value, "on_header_end": on_header_end,
        "on_headers_finished": on_headers_finished})
    try:
        async for data in request.stream():
            for i in range(0, len(data), FEED):  # (uvicorn may hand over megabytes at once)
                parser.write(data[i:i + FEED])
            if state.get("ended") is not None:
                up, state["ended"] = state["ended"], None
                state["upload"] = up  # (dropped with the form if syncing fails)
                form.file = await run_in_threadpool(up.finish)
                state["upload"] = None
        parser.finalize()
        if state.get("ended") is not None:
            state["upload"], state["ended"] = state["ended"], None
            form.file = await run_in_threadpool(state["upload"].finish)
            state["upload"] = None
    except Refused as e:
        errors.append(e)
    except ClientDisconnect:
        errors.append(Refused(400, "the upload was cut off before its end"))
    except Exception as e:  # the parser's own errors on a malformed body
        if type(e).__module__.startswith("python_multipart"):
            errors.append(Refused(400, "the body is not a well-formed multipart form"))
        else:
            _drop(state, form)
            raise
    if errors or state["upload"] is not None:
        _drop(state, form)
        raise errors[0] if errors else Refused(400, "the body is not a well-formed multipart form")
    return form


def _drop(state: dict, form: Form) -> None:
    for key in ("upload", "ended"):
        up: Upload | None = state.get(key)
        if up is not None:
            up.abort()
    if form.file is not None:
        form.file.path.unlink(missing_ok=True)
        form.file = None


__all__ = ["FIELD_BYTES", "Form", "read_form"]
