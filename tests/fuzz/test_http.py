"""HTTP fuzz: schemathesis generates requests from our OpenAPI description (positive and
negative: values outside the schema too) against the real ApiServer on 127.0.0.1, in front
of a live scan loop. Never a 5xx, never a traceback in a body, every error in the JSON shape.
Examples per operation scale with SOFTPLC_FUZZ_SCALE; derandomized (reproducible in CI)."""

from __future__ import annotations

import contextlib
import importlib
import pkgutil
import random
from collections.abc import Iterator
from pathlib import Path

import hypothesis.internal
import hypothesis.strategies
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error

from softplc.api.openapi import openapi_document
from softplc.api.server import ApiServer
from softplc.security import auth
from tests.api.conftest import ServerThread
from tests.fuzz import budget
from tests.fuzz.live import LivePlc
from tests.fuzz.mutate import mutant


def _import_lazy_modules() -> None:
    """schemathesis and hypothesis import modules lazily, inside hypothesis' draw, and pytest
    parses (rewrites) them there, while the PLC's scan thread in this process may be compiling
    a download: CPython 3.11's AST bookkeeping is per interpreter, not per thread (gh-106905),
    and the two parses at once raised "SystemError: AST constructor recursion depth mismatch"
    (two full runs). The status document no longer parses on the scan thread
    (core/whyguard.py); imported here, before any PLC runs, these modules are
    parsed before any draw too (~1.5 s)."""
    for package in (schemathesis, hypothesis.strategies, hypothesis.internal):
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}.",
                                          onerror=lambda name: None):
            if info.name.startswith(("schemathesis.cli", "schemathesis.reporting")):
                continue
            with contextlib.suppress(Exception):  # an optional extra's missing dependency
                importlib.import_module(info.name)


_import_lazy_modules()

ROOT = Path(__file__).resolve().parents[2]
# Server-sent event streams never end: tests/api, tests/web, tests/security/test_audit_stream.py
ENDLESS = {"events", "live", "auditEvents"}
SCHEMA = schemathesis.openapi.from_dict(openapi_document())
OPERATIONS = [op for op in (r.ok() for r in SCHEMA.get_all_operations())
              if op.definition.raw.get("operationId") not in ENDLESS]


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str]]]:
    """A token-guarded service (as off loopback), with the token for the requests."""
    state = tmp_path_factory.mktemp("state")
    with LivePlc(ROOT, ROOT / "programs" / "transport.yaml") as plc:
        server = ApiServer(plc.channel, plc.reader, plc.board, port=0, state_dir=state,
                           token_required=True, command_timeout_s=5.0)
        with ServerThread(server) as handle:
            token = (state / auth.TOKEN_FILE).read_text().strip()
            yield handle.url, {"Authorization": f"Bearer {token}"}


# The schema cannot know the loaded program: a third of the cases name a real symbol, and
# a third of the downloads are a mutated real program instead of random text.
SYMBOLS = ["m1", "m2", "s1_i", "hold", "parts_delivered", "drill_time_ms"]
TRANSPORT = (ROOT / "programs" / "transport.yaml").read_text()


def _informed(case: schemathesis.Case, pick: int, seed: int) -> schemathesis.Case:
    if pick % 3 == 0 and case.path_parameters and "name" in case.path_parameters:
        case.path_parameters["name"] = SYMBOLS[seed % len(SYMBOLS)]
    if pick % 3 == 0 and case.operation.definition.raw.get("operationId") == "download":
        # Bytes, as a client sends them: a mutant may hold a lone surrogate, which goes out
        # as invalid UTF-8 (make fuzz found that schemathesis cannot encode it as text).
        case.body = mutant(random.Random(seed), TRANSPORT).encode("utf-8", "surrogatepass")
        case.media_type = "application/yaml"
    return case


def cases(operation: schemathesis.APIOperation) -> st.SearchStrategy[schemathesis.Case]:
    """Schema-valid and schema-violating cases (negative mode: wrong types, out-of-range
    values, missing required parts), some of them informed by the loaded program."""
    generated = [operation.as_strategy(GenerationMode.POSITIVE)]
    try:
        negative = operation.as_strategy(GenerationMode.NEGATIVE)
        negative.validate()
        generated.append(negative)
    except Unsatisfiable:
        pass  # nothing in this operation can be made invalid (no parameters, no body)
    return st.builds(_informed, st.one_of(generated), st.integers(0, 2), st.integers(0, 1 << 30))


@pytest.mark.parametrize("operation", OPERATIONS, ids=lambda op: op.label)
def test_generated_requests_never_get_a_5xx_or_a_traceback(
        service: tuple[str, dict[str, str]], operation: schemathesis.APIOperation) -> None:
    url, headers = service
    statuses: dict[int, int] = {}

    @settings(max_examples=budget.scaled(25), derandomize=True, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(case=cases(operation))
    def check(case: schemathesis.Case) -> None:
        response = case.call(base_url=url, headers=headers, timeout=10)
        statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
        case.validate_response(response, checks=[not_a_server_error])
        text = response.text
        assert "Traceback" not in text and 'File "' not in text, text[:300]
        if response.status_code >= 400:
            body = response.json()
            assert isinstance(body["error"], str) and isinstance(body["problems"], list)

    check()
    budget.record("http.schemathesis", operation=operation.label,
                  requests=sum(statuses.values()),
                  statuses={str(k): v for k, v in sorted(statuses.items())}, server_errors=0)
