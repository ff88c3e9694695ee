"""Schema-driven fuzzing of the HTTP API (wm.serve, wm.ingest) with Schemathesis: requests made
from the OpenAPI schema (valid ones, and invalid ones: wrong types, out-of-range values,
missing parameters) against real uvicorn servers on localhost, one over a short simulated log
being replayed and one ingesting. No request may get a server error (5xx), and every answer
must conform to the schema (its documented status codes' bodies).

``make test`` runs a bounded pass (about 100 requests in all, well under a minute); the
``eval`` mark runs a larger one."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from serving import served

pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")
schemathesis = pytest.importorskip("schemathesis")

from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis.errors import Unsatisfiable  # noqa: E402

#: requests made in the bounded pass (split over the operations and both generation modes)
BOUNDED_REQUESTS = 100
LARGE_REQUESTS = 2000


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("fuzz") / "default.mcap"
    return simulate_to_log("default", path, seconds=3.0, seed=7, progress=False)


@pytest.fixture(scope="module")
def servers(log: Path, tmp_path_factory) -> Iterator[list[str]]:
    """Base URLs of a node replaying the log (twice real time) and of an ingesting node."""
    from wm.ingest import IngestNode
    from wm.serve import LiveNode, create_app

    kd = tmp_path_factory.mktemp("fuzz-kd")
    replay = LiveNode(log, kd / "replay.duckdb", rate=2.0).start()
    ingest = IngestNode(kd / "ingest.duckdb", queue_size=8).start()
    try:
        with served(create_app(replay)) as a, served(create_app(ingest)) as b:
            yield [a, b]
    finally:
        replay.stop()
        ingest.stop()


def fuzz(base: str, budget: int) -> int:
    """Fuzz every operation of the schema ``base`` serves with about ``budget`` requests in
    all (half valid, half invalid); fails on a 5xx or an answer off the schema. Returns the
    requests made."""
    import requests
    from schemathesis import GenerationMode
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import response_schema_conformance

    schema = schemathesis.openapi.from_url(f"{base}/openapi.json")
    ops = [r.ok() for r in schema.get_all_operations()]
    per_op = max(1, budget // (2 * len(ops)))
    session, made = requests.Session(), [0]
    for op in ops:
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):

            @settings(
                max_examples=per_op, deadline=None, database=None, derandomize=True,
                phases=[Phase.explicit, Phase.generate],  # no shrinking: bounded time
                suppress_health_check=list(HealthCheck),
            )  # fmt: skip
            @given(case=op.as_strategy(generation_mode=mode))
            def one(case) -> None:
                response = case.call(base_url=base, session=session, timeout=30)
                made[0] += 1
                case.validate_response(
                    response, checks=[not_a_server_error, response_schema_conformance]
                )

            try:
                one()
            except Unsatisfiable:  # nothing to make invalid (an operation without parameters)
                assert mode is GenerationMode.NEGATIVE, op.label
    return made[0]


def test_bounded_fuzz_finds_no_server_error(servers) -> None:
    """About 100 requests over both servers' schemas: no 5xx, every answer on the schema."""
    t0 = time.perf_counter()
    replay, ingest = servers
    made = fuzz(replay, int(0.8 * BOUNDED_REQUESTS)) + fuzz(ingest, int(0.2 * BOUNDED_REQUESTS))
    assert 0 < made <= BOUNDED_REQUESTS
    assert time.perf_counter() - t0 < 60


@pytest.mark.eval
def test_large_fuzz_finds_no_server_error(servers) -> None:
    """Some thousands of requests: no 5xx, every answer on the schema."""
    replay, ingest = servers
    assert fuzz(replay, LARGE_REQUESTS) + fuzz(ingest, LARGE_REQUESTS // 4) > 0
