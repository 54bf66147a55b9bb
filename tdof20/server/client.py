"""``tdof20 submit R.csv --server URL --token T --method NAME --split S``: one multipart POST to
the server's API (the Python standard library; bounded timeout); prints the server's one-line refusal."""

from __future__ import annotations

import json
import secrets
import urllib.error
import urllib.request
from pathlib import Path

from tdof20.errors import TdofError
from tdof20.formats.io import read_text

TIMEOUT_S = 120.0


def _multipart(fields: dict[str, str], filename: str, data: bytes) -> tuple[bytes, str]:
    boundary = "tdof20-" + secrets.token_hex(12)
    parts = []
    for k, v in fields.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode())
    safe = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{safe}"\r\n'
                 f"Content-Type: text/csv\r\n\r\n".encode() + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def _detail_line(detail) -> str:
    """A refusal's ``detail`` as one line: a string as it is; a list of FastAPI's validation errors
    (an older server's 422) as ``loc: msg; ...``; anything else as compact JSON."""
    if isinstance(detail, str):
        text = detail
    elif isinstance(detail, list) and all(isinstance(d, dict) for d in detail):
        text = "; ".join(f"{'.'.join(str(x) for x in d.get('loc', ()) if x != 'body') or 'request'}: "
                         f"{d.get('msg', 'invalid')}" for d in detail)
    else:
        text = json.dumps(detail, separators=(",", ":"), default=str)
    return " ".join(text.split())[:500]


def refusal_line(e: urllib.error.HTTPError) -> str:
    """The one line of an HTTP refusal: its JSON ``detail``, else the first line of its text, else
    the status's reason (never a Python repr)."""
    try:
        body = e.read(64 * 1024)
    except OSError:
        body = b""
    try:
        data = json.loads(body)
        if isinstance(data, dict) and "detail" in data:
            return _detail_line(data["detail"]) or str(e.reason)
    except ValueError:
        pass
    first = next((ln.strip() for ln in body.decode("utf-8", "replace").splitlines() if ln.strip()), "")
    return (" ".join(first.split())[:200] if first and not first.startswith("<") else "") or str(e.reason)


def queue_line(q: dict | None) -> str:
    """A submission's place in the queue as one line ('' when it is not queued)."""
    if not q:
        return ""
    eta = q.get("eta_s")
    when = "no estimate yet" if eta is None else f"expected in about {_dur(eta)}"
    where = f"position {q['position']} in the queue" if q.get("position") else "being scored"
    return f"{where} ({q.get('ahead', 0)} ahead, {q.get('workers', 1)} worker(s)); {when}"


def _dur(x: float) -> str:
    return f"{round(x)} s" if x < 90 else f"{round(x / 60)} min" if x < 5400 else f"{x / 3600:.1f} h"


def submit(results: str | Path, server: str, token: str, method: str, split: str, description: str = "",
           authors: str = "", hardware: str = "", time_per_image: str = "", training_data: str = "",
           public: bool = False, part: str = "test", paper: str = "", code: str = "") -> dict:
    """Submit a results file; returns the server's status of it ({"uid", "status", ...})."""
    path = Path(results)
    data = read_text(path, "results file").encode()
    fields = {"method": method, "split": split, "part": part, "description": description, "authors": authors,
              "hardware": hardware, "time_per_image": time_per_image, "training_data": training_data,
              "paper": paper, "code": code, "public": "true" if public else "false"}
    body, ctype = _multipart(fields, path.name, data)
    url = server.rstrip("/") + "/api/submissions"
    if not url.startswith(("http://", "https://")):
        raise TdofError(f"--server must be an http:// or https:// URL, got {server[:60]!r}")
    req = urllib.request.Request(url, data=body, method="POST",
                                 headers={"Content-Type": ctype, "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=TIMEOUT_S) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as e:
        raise TdofError(f"the server refused the submission ({e.code}): {refusal_line(e)}", path) from None
    except (urllib.error.URLError, OSError) as e:
        raise TdofError(f"cannot reach the server {server}: {getattr(e, 'reason', e)}") from None


__all__ = ["queue_line", "refusal_line", "submit"]
