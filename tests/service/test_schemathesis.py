"""Property-based fuzzing of every operation in the OpenAPI schema (schemathesis), with all its checks.

Every built-in check runs (server errors, status codes, content types, response schemas, schema-violating
requests accepted, missing or ignored auth, ...) on schema-valid and schema-violating requests, except that
"schema-violating request accepted" skips a case whose violations never reach the server
(:func:`negative_data_rejection_as_sent`: an added query parameter whose value is None is not sent; on the
token server this test sets the Authorization header itself), and that the built-in "schema-valid request
rejected" is replaced by :func:`schema_predicts_every_422`: a
spec may be refused for a rule across its fields that no JSON schema can state (the box must hold the
neighbour cutoff, dt must resolve a contact, every species must get a particle, the run's cost must be within
the server's limits, a 'cuda' spec needs a live worker that runs CUDA: none runs here), so a 422 on a
schema-valid request is allowed only with errors of those kinds, never with an error of one field or of the
entries of one list (a species list has none: engine.setup.spec.normal_species), which the schema should have
predicted.

Bounded for CI: a few examples per operation and mode, no worker, no engine. Set
DEMQ_SCHEMATHESIS_REPORT=path.json to write the statuses seen per operation.

Needs the ``fuzz`` extra (schemathesis, which brings some 40 MB of packages of its own into the environment), so
it is marked heavy: the README's light run leaves it out, .ci/run's second stage installs the extra and runs it.
Checks of the OpenAPI document itself, which need no schemathesis, are in test_openapi.py.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis", reason="the fuzz extra (pip install '.[fuzz]')")

from hypothesis import HealthCheck, settings as hsettings  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402
from schemathesis.core.parameters import ParameterLocation  # noqa: E402
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance  # noqa: E402

from service.app import create_app  # noqa: E402
from tests.jobs.conftest import make_settings  # noqa: E402

pytestmark = pytest.mark.heavy   # the fuzz extra (schemathesis), not in the light install

TOKEN = "fuzz-token"
_DATA = tempfile.TemporaryDirectory(prefix="demq-fuzz-")
open_schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(make_settings(Path(_DATA.name) / "open")))
open_schema.config.generation.update(modes=[GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
token_app = create_app(make_settings(Path(_DATA.name) / "token", token=TOKEN))
token_schema = schemathesis.openapi.from_asgi("/openapi.json", token_app)
token_schema.config.generation.update(modes=[GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
token_schema.config.phases.update(phases=["examples", "fuzzing"])  # the open run covers the boundary values
SEEN: dict[str, Counter] = defaultdict(Counter)


@pytest.fixture(scope="module", autouse=True)
def _report():
    yield
    path = os.environ.get("DEMQ_SCHEMATHESIS_REPORT")
    if path:
        with open(path, "w") as fh:
            json.dump({op: dict(c) for op, c in SEEN.items()}, fh, indent=1, sort_keys=True)


def _beyond_the_schema(path: str, error: dict) -> bool:
    """Whether a 422 error is of a kind no JSON schema states: a cost limit, no live worker for the spec's
    backend (a state of the server, not of the request), or a spec's cross-field rule (reported at the spec's
    root: the body of POST /jobs, one spec or sweep combination of a batch)."""
    loc, kind = error["loc"], error["type"]
    if kind.startswith("limit_") or kind == "backend_unavailable":
        return True
    if path == "/jobs":
        return loc == ["body"]
    if path == "/batches":
        return (len(loc) == 3 and loc[:2] == ["body", "specs"]) or (
            len(loc) == 4 and loc[:3] == ["body", "sweep", "combination"])
    return False


def schema_predicts_every_422(ctx, response, case) -> None:
    """A schema-valid request may be refused (422) only for rules beyond the schema (see module doc)."""
    if case.meta is None or not case.meta.generation.mode.is_positive or response.status_code != 422:
        return None
    errors = response.json()["detail"]
    unpredicted = [e for e in errors if not _beyond_the_schema(case.path, e)]
    assert not unpredicted, (f"schema-valid {case.method} {case.path} refused with errors the schema should "
                             f"state: {unpredicted}; body {case.body!r}")
    return None


def _query_violation_unsent(case) -> bool:
    """Whether the case's query violation never reaches the server: every parameter it adds that the operation
    does not declare has the value None, for which the HTTP client sends no parameter at all."""
    declared = {p.name for p in case.operation.query}
    extra = {k: v for k, v in (case.query or {}).items() if k not in declared}
    return bool(extra) and all(v is None for v in extra.values())


def negative_data_rejection_as_sent(ctx, response, case, sent_headers: bool = False):
    """schemathesis's "schema-violating request accepted", except for a case whose violations all stay behind in
    the client: a query of :func:`_query_violation_unsent`, and with ``sent_headers`` (the token server: this test
    sets the Authorization header itself) the headers."""
    if case.meta is not None and not case.meta.generation.mode.is_positive:
        negative = {loc for loc, info in (case.meta.components or {}).items() if not info.mode.is_positive}
        unsent = {ParameterLocation.QUERY} if _query_violation_unsent(case) else set()
        if sent_headers:
            unsent.add(ParameterLocation.HEADER)
        if negative and negative <= unsent:
            return None
    return negative_data_rejection(ctx, response, case)


def _with_sent_headers(ctx, response, case):
    return negative_data_rejection_as_sent(ctx, response, case, sent_headers=True)


def _run(case, **kwargs) -> None:
    token = "headers" in kwargs
    response = case.call_and_validate(excluded_checks=[positive_data_acceptance, negative_data_rejection],
                                      additional_checks=[schema_predicts_every_422, _with_sent_headers if token
                                                         else negative_data_rejection_as_sent], **kwargs)
    SEEN[f"{case.method} {case.path}"][response.status_code] += 1


@open_schema.parametrize()
@hsettings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
def test_open_server_all_checks(case):
    """No token configured: no operation declares auth, and every check passes."""
    _run(case)


@token_schema.parametrize()
@hsettings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck))
def test_token_server_all_checks(case):
    """A token configured: the auth checks (missing or wrong credentials refused with 401) and the rest."""
    _run(case, headers={"Authorization": f"Bearer {TOKEN}"})
