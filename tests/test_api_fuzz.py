"""The API against its own OpenAPI, fuzzed by schemathesis (issue 15): for every operation, bounded
examples generated from the schema, sent to a real `compasscal serve` on SQLite and on PostgreSQL
with an admin key. No answer may be a server error, and every answer must match the schema it
declares (status code, content type, body). The event streams are left out: they stream until a run
ends."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterator

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, response_schema_conformance,
                                               status_code_conformance)

from conftest import free_port, fresh_database, wait_healthy

ROOT = Path(__file__).resolve().parent.parent
#: Examples per operation and database (the whole module takes about a minute).
EXAMPLES = 12


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def served(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """A real service on a fresh database: its base URL and an admin key."""
    tmp = tmp_path_factory.mktemp(f"fuzz-{request.param}")
    url = fresh_database(request.param, tmp)
    from service.auth import create_key
    from service.db import make_engine, sessions, upgrade

    engine = make_engine(url)
    upgrade(engine)
    with sessions(engine)() as s:
        key = create_key(s, "fuzzer", "admin")
    engine.dispose()
    port = free_port()
    env = {**os.environ, "COMPASSCAL_DATABASE_URL": url, "COMPASSCAL_PROMPT_TIMEOUT_S": "2"}
    log = (tmp / "serve.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)], cwd=ROOT, env=env,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_healthy(port, proc, tmp / "serve.log")
        yield f"http://127.0.0.1:{port}", key
    finally:
        os.killpg(proc.pid, 9)
        proc.wait(10)
        log.close()


@schemathesis.check
def no_server_error_but_a_declared_503(ctx: Any, response: Any, case: schemathesis.Case) -> None:
    """Every 5xx is a server error, except a 503 the operation declares: a station reset or a prompt
    answer whose table or worker does not answer (the fuzzer makes stations with made-up addresses)
    is that documented answer, not a bug; whether it comes up depends on timing."""
    if response.status_code == 503 and "503" in case.operation.definition.raw.get("responses", {}):
        return None
    return not_a_server_error(ctx, response, case)


def test_no_server_error_and_every_answer_as_declared(served: tuple[str, str]) -> None:
    """Each operation in turn (bounded examples each); every failure is listed with its operation."""
    base, key = served
    schema = schemathesis.openapi.from_url(f"{base}/openapi.json").exclude(path_regex=r".*/events$")
    failures: list[str] = []
    operations = 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        def check(case: schemathesis.Case) -> None:
            case.call_and_validate(base_url=base, headers={"X-API-Key": key}, timeout=30,
                                   checks=[no_server_error_but_a_declared_503, status_code_conformance, content_type_conformance,
                                           response_schema_conformance])
        try:
            check()
        except BaseException as e:  # noqa: BLE001 - (a failure group) collected: every operation that failed
            if isinstance(e, KeyboardInterrupt):
                raise
            failures.append(f"{operation.label}: {str(e)[:1500]}")
    assert operations >= 29  # every operation but the two event streams
    assert not failures, "\n\n".join(failures)
