"""The API fuzzed from its own OpenAPI schema (schemathesis; hypothesis draws valid and invalid
requests for every operation): no request, signed in or not, gets a 500 or raises in the app.
A small example budget per operation keeps this well under 40 s."""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode

from tests.test_server_support import Server, dataset, results_csv  # noqa: F401

EXAMPLES = 12  # per operation and generation mode


@pytest.fixture(scope="module")
def fuzzed(dataset, tmp_path_factory):  # noqa: F811
    root, gt = dataset
    s = Server(root, tmp_path_factory.mktemp("fuzz") / "data", daily_limit=10_000)
    # a scored submission so that the uid and withdraw routes have something real to find
    assert s.submit("alice", results_csv(gt, "hard"), public=True).status_code == 201
    return s


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_no_request_gets_a_500(fuzzed, mode):
    # (schemathesis.pytest.from_fixture needs pytest internals that pytest 9 renamed: the
    # operations' strategies are driven with hypothesis directly)
    schema = schemathesis.openapi.from_asgi("/openapi.json", fuzzed.client.app)
    operations = [r.ok() for r in schema.get_all_operations()]
    assert {op.path for op in operations} >= {"/api/submissions", "/api/submissions/{uid}", "/api/leaderboard"}
    ran = []
    for op in operations:
        if mode is GenerationMode.NEGATIVE and not op.get_request_payload_content_types() \
                and not any(p.location.value == "query" for p in op.iter_parameters()):
            continue  # nothing to make invalid but a path's free-text uid (any text is a valid one)

        @given(case=op.as_strategy(generation_mode=mode))
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        def fuzz(case):
            for headers in (fuzzed.headers("alice"), None):  # signed in, and not
                response = case.call(headers=headers)
                assert response.status_code < 500, (case.method, case.path, response.status_code,
                                                     response.text[:300])

        fuzz()
        ran.append(op.label)
    assert {"POST /api/submissions", "GET /api/leaderboard"} <= set(ran), ran
