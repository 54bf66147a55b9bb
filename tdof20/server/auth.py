"""Accounts and ways in: API tokens (``tdof20_<id>_<secret>``; the secret stored as an argon2
hash, the id finds the row), page sessions (a random cookie, stored as its sha256, with a CSRF
token the forms carry) and the sign-in form's double-submit CSRF cookie."""

from __future__ import annotations

import hashlib
import re
import secrets
import time

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import Engine, delete, func, insert, select, update

from tdof20.errors import TdofError
from tdof20.server.db import sessions, users

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
TOKEN_RE = re.compile(r"tdof20_([0-9a-f]{16})_([A-Za-z0-9_-]{20,64})")
SESSION_S = 12 * 3600
_hasher = PasswordHasher()
VERIFIED_MAX = 4096  # (stored hash, sha256 of a secret) pairs argon2 has accepted, kept in memory
_verified: dict[tuple[str, str], bool] = {}
# A hash no secret matches, verified against when a token's id is unknown or revoked, so that every
# refusal costs argon2's time: an attacker cannot tell a real token id from a made-up one by timing.
_DUMMY_HASH = _hasher.hash(secrets.token_urlsafe(32))


def _verify(token_hash: str, secret: str) -> bool:
    """argon2's verdict on a secret against a stored hash. argon2 is slow on purpose (~0.1 s,
    against guessing) and an API client sends the same token with every request, so a pair once
    accepted is remembered by (hash, sha256 of the secret): the row is still read each time, so a
    revoked or replaced token fails at once (the row says revoked, or its hash changed). Refusals
    are not remembered: every wrong guess costs argon2's time."""
    key = (token_hash, hashlib.sha256(secret.encode()).hexdigest())
    if key in _verified:
        return True
    try:
        _hasher.verify(token_hash, secret)
    except (VerificationError, InvalidHashError):
        return False
    if len(_verified) >= VERIFIED_MAX:
        _verified.clear()
    _verified[key] = True
    return True


def _new_token() -> tuple[str, str, str]:
    """(token id, secret, the token a user holds)."""
    tid, secret = secrets.token_hex(8), secrets.token_urlsafe(32)
    return tid, secret, f"tdof20_{tid}_{secret}"


def add_user(engine: Engine, name: str) -> str:
    """Add user ``name``; returns its API token (shown once: only its hash is stored)."""
    if not NAME_RE.fullmatch(name):
        raise TdofError(f"user name {name[:70]!r}: use 1-64 letters, digits, '_', '.', '-' (a letter or digit first)")
    tid, secret, token = _new_token()
    with engine.begin() as c:
        same = c.execute(select(users.c.name).where(func.lower(users.c.name) == name.lower())).first()
        if same is not None:  # 'alice' and 'Alice' are one person to a reader of the leaderboard
            hint = "" if same.name == name else f" as {same.name!r} (names are compared ignoring case)"
            raise TdofError(f"user {name!r} exists{hint} (serve user token {same.name} gives it a new token)")
        c.execute(insert(users).values(name=name, token_id=tid, token_hash=_hasher.hash(secret), revoked=False,
                                       created=time.time()))
    return token


def new_token(engine: Engine, name: str) -> str:
    """A new token for ``name`` (the old one stops working; a revoked user is let in again)."""
    tid, secret, token = _new_token()
    with engine.begin() as c:
        r = c.execute(update(users).where(users.c.name == name).values(token_id=tid, token_hash=_hasher.hash(secret),
                                                                       revoked=False))
        if r.rowcount != 1:
            raise TdofError(f"no user {name!r}")
        c.execute(delete(sessions).where(sessions.c.user_id.in_(select(users.c.id).where(users.c.name == name))))
    return token


def revoke_user(engine: Engine, name: str) -> None:
    """Revoke ``name``'s token and end its sessions."""
    with engine.begin() as c:
        r = c.execute(update(users).where(users.c.name == name).values(revoked=True))
        if r.rowcount != 1:
            raise TdofError(f"no user {name!r}")
        c.execute(delete(sessions).where(sessions.c.user_id.in_(select(users.c.id).where(users.c.name == name))))


def list_users(engine: Engine) -> list[dict]:
    with engine.begin() as c:
        return [dict(r._mapping) for r in c.execute(select(users.c.name, users.c.revoked, users.c.created)
                                                     .order_by(users.c.name))]


def authenticate(engine: Engine, token: str | None) -> dict | None:
    """The user row ({"id", "name"}) of a valid, unrevoked token, else None."""
    m = TOKEN_RE.fullmatch(token or "")
    if m is None:
        return None
    with engine.begin() as c:
        row = c.execute(select(users.c.id, users.c.name, users.c.token_hash, users.c.revoked)
                        .where(users.c.token_id == m.group(1))).first()
    if row is None or row.revoked:
        _verify(_DUMMY_HASH, m.group(2))  # the same time as a wrong secret for a real id
        return None
    if not _verify(row.token_hash, m.group(2)):
        return None
    return {"id": row.id, "name": row.name}


class FailureLimit:
    """Failed sign-ins per client (its address): after ``max_failures`` within ``window_s`` the
    client is refused until the oldest of them is ``window_s`` old, before any token is checked.
    Kept in this server process's memory (each process of a multi-process deployment counts its
    own); a success does not erase failures, so guessing cannot be interleaved with a valid token."""

    def __init__(self, max_failures: int = 10, window_s: float = 900.0, clock=time.monotonic):
        self.max_failures, self.window_s, self.clock = max_failures, window_s, clock
        self._failures: dict[str, list[float]] = {}

    def _recent(self, client: str) -> list[float]:
        now = self.clock()
        kept = [t for t in self._failures.get(client, []) if now - t < self.window_s]
        if kept:
            self._failures[client] = kept
        else:
            self._failures.pop(client, None)
        return kept

    def retry_after(self, client: str) -> float:
        """Seconds until ``client`` may try again (0: it may now)."""
        recent = self._recent(client)
        if len(recent) < self.max_failures:
            return 0.0
        return max(0.0, recent[-self.max_failures] + self.window_s - self.clock())

    def failed(self, client: str) -> None:
        if len(self._failures) > 100_000:  # a flood of addresses: forget the quiet ones first
            for k in [k for k in list(self._failures) if not self._recent(k)]:
                self._failures.pop(k, None)
        self._failures.setdefault(client, []).append(self.clock())


def _sid(cookie: str) -> str:
    return hashlib.sha256(cookie.encode()).hexdigest()


def create_session(engine: Engine, user_id: int) -> str:
    """A new page session; returns the cookie value."""
    cookie = secrets.token_urlsafe(32)
    now = time.time()
    with engine.begin() as c:
        c.execute(delete(sessions).where(sessions.c.expires < now))
        c.execute(insert(sessions).values(id=_sid(cookie), user_id=user_id, csrf=secrets.token_urlsafe(24),
                                          expires=now + SESSION_S))
    return cookie


def session_user(engine: Engine, cookie: str | None) -> dict | None:
    """{"id", "name", "csrf"} of a live session whose user is not revoked, else None."""
    if not cookie or len(cookie) > 100:
        return None
    with engine.begin() as c:
        row = c.execute(select(users.c.id, users.c.name, sessions.c.csrf)
                        .select_from(sessions.join(users, users.c.id == sessions.c.user_id))
                        .where(sessions.c.id == _sid(cookie), sessions.c.expires > time.time(),
                               users.c.revoked.is_(False))).first()
    return None if row is None else {"id": row.id, "name": row.name, "csrf": row.csrf}


def end_session(engine: Engine, cookie: str | None) -> None:
    if cookie:
        with engine.begin() as c:
            c.execute(delete(sessions).where(sessions.c.id == _sid(cookie)))


def same_token(a: str | None, b: str | None) -> bool:
    """Constant-time comparison of two CSRF tokens (both present)."""
    return bool(a) and bool(b) and secrets.compare_digest(str(a), str(b))


__all__ = ["FailureLimit", "add_user", "authenticate", "create_session", "end_session", "list_users", "new_token", "revoke_user",
           "same_token", "session_user"]
