"""Accounts against an attacker: names that differ only in case, token refusals that take the same
time whether the token id exists or not, and a limit on failed sign-ins (issue 32, part 6)."""

from __future__ import annotations

import statistics
import time

import pytest

from tdof20.errors import TdofError
from tdof20.server import auth
from tdof20.server.db import init_db, make_engine


@pytest.fixture()
def engine(tmp_path):
    eng = make_engine(f"sqlite:///{tmp_path / 'server.db'}")
    init_db(eng)
    return eng


def test_names_are_unique_ignoring_case(engine):
    auth.add_user(engine, "alice")
    for other in ("Alice", "ALICE", "alice"):
        with pytest.raises(TdofError, match="exists"):
            auth.add_user(engine, other)
    assert [u["name"] for u in auth.list_users(engine)] == ["alice"]
    auth.add_user(engine, "alice2")  # a different name is still allowed
    assert len(auth.list_users(engine)) == 2


def _refusal_s(engine, token: str, n: int = 5) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        assert auth.authenticate(engine, token) is None
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def test_a_real_token_id_is_refused_as_slowly_as_an_unknown_one(engine):
    token = auth.add_user(engine, "alice")
    real_id = token.split("_")[1]
    wrong_secret = f"tdof20_{real_id}_{'x' * 43}"
    unknown_id = f"tdof20_{'0' * 16}_{'x' * 43}"
    assert auth.authenticate(engine, token)["name"] == "alice"
    real, unknown = _refusal_s(engine, wrong_secret), _refusal_s(engine, unknown_id)
    # both pay argon2's verification (tens of ms); before, the unknown id was refused ~100x sooner
    assert unknown > 0.3 * real and real > 0.3 * unknown, (real, unknown)
    auth.revoke_user(engine, "alice")
    revoked = _refusal_s(engine, token)
    assert revoked > 0.3 * real, (revoked, real)


def test_failure_limit_refuses_a_guessing_client_until_its_window_passes():
    now = [1000.0]
    limit = auth.FailureLimit(max_failures=3, window_s=60.0, clock=lambda: now[0])
    for _ in range(3):
        assert limit.retry_after("10.0.0.1") == 0.0
        limit.failed("10.0.0.1")
        now[0] += 1.0
    assert limit.retry_after("10.0.0.1") == pytest.approx(57.0)  # the first failure is 3 s old
    assert limit.retry_after("10.0.0.2") == 0.0  # another client is not held up
    now[0] += 57.0
    assert limit.retry_after("10.0.0.1") == 0.0  # the oldest failure left the window
    limit.failed("10.0.0.1")
    assert limit.retry_after("10.0.0.1") == pytest.approx(1.0)  # three in the last minute again
