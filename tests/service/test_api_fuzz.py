"""Property-based fuzz of the OpenAPI schema (schemathesis): no request, valid or not, gets a 500.

The service runs for real (uvicorn in a thread, its own in-process simulated bench with the fast renderer), and the
fuzzer holds a token, so generated runs really start (and then get 409s) while everything else is exercised."""

from __future__ import annotations

import os
import socket
import threading
import time

import pytest

from service.auth import hash_token
from service.main import create_app
from service.settings import Settings
from tests.service.conftest import AUTH, SMALL, TOKEN

schemathesis = pytest.importorskip("schemathesis")
MAX_EXAMPLES = int(os.environ.get("I4CAL_FUZZ_EXAMPLES", "25"))


@schemathesis.serializer("application/zip", "application/gzip")
def _archive_bytes(ctx, value):
    """Archives are raw bytes: generated values (usually not archives at all) are sent as they are."""
    if isinstance(value, bytes):
        return value
    return str(value).encode("utf-8", "surrogatepass")


@pytest.fixture(scope="module")
def live_url(tmp_path_factory):
    import uvicorn

    data = tmp_path_factory.mktemp("fuzz")
    settings = Settings(
        data_dir=data,
        sim_bench=True,
        sim_fast_renderer=True,
        token_hashes=[hash_token(TOKEN)],
        plan_sizes=SMALL,
        max_upload_bytes=2_000_000,
        # the operator's cap on a design's cost (a design of 300 candidates computes for ~7 s): the fuzz is about the
        # routes' answers to any input, the designs' size is tests/service/test_plan_design.py's
        design_max_candidates=40,
        design_max_tradeoff_designs=2,
    )
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="error"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    for _ in range(500):
        if server.started:
            break
        time.sleep(0.02)
    assert server.started
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        th.join(30)


def test_openapi_fuzz_no_server_errors(live_url):
    from hypothesis import HealthCheck, given, settings
    from hypothesis.errors import Unsatisfiable

    schema = schemathesis.openapi.from_url(live_url + "/api/v1/openapi.json")
    failures: list[str] = []
    seen: dict[tuple[str, int], int] = {}
    ops = [r.ok() for r in schema.get_all_operations()]
    assert len(ops) >= 15

    modes = list(schemathesis.GenerationMode)
    for op, mode in [(op, mode) for mode in modes for op in ops]:
        # a valid plan design computes for 7-14 s of CPU: a few of them show it answers; its refusals (422, negative
        # mode) are fuzzed as fully as every other route's
        design = op.path.endswith("/plans/design") and mode == schemathesis.GenerationMode.POSITIVE
        n_examples = min(MAX_EXAMPLES, 5) if design else MAX_EXAMPLES

        @settings(max_examples=n_examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy(mode))
        def check(case):
            # a plan design computes for seconds (7-14 s CPU on this 2-core machine, more under load): its own
            # timeout; the others answer in milliseconds. A design in progress makes the next ones answer 429 at once.
            timeout = 180 if case.operation.path.endswith("/plans/design") else 15
            resp = case.call(base_url=live_url, headers=AUTH, timeout=timeout)
            key = (f"{case.method} {case.operation.path}", resp.status_code)
            seen[key] = seen.get(key, 0) + 1
            if resp.status_code >= 500:
                failures.append(
                    f"{resp.status_code} {case.method} {case.formatted_path} {resp.text[:300]}\n"
                    f"{case.as_curl_command()}"
                )

        try:
            check()
        except Unsatisfiable:  # nothing to negate (no parameters)
            assert mode == schemathesis.GenerationMode.NEGATIVE
    print(sorted(seen.items()))
    assert not failures, "\n".join(failures[:10])
    assert seen.get(("POST /api/v1/runs", 202)) and seen.get(("POST /api/v1/runs", 422))
