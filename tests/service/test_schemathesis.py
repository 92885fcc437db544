"""Property-based fuzzing of every operation in the OpenAPI schema (schemathesis): never a 5xx.

Bounded for CI: at most 30 examples per operation, no worker, no engine. Set
DEMQ_SCHEMATHESIS_REPORT=path.json to write the statuses seen per operation (for the issue note).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings as hsettings

from service.app import create_app
from tests.jobs.conftest import make_settings


_DATA = tempfile.TemporaryDirectory(prefix="demq-fuzz-")
schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(make_settings(Path(_DATA.name))))
SEEN: dict[str, Counter] = defaultdict(Counter)


@pytest.fixture(scope="module", autouse=True)
def _report():
    yield
    path = os.environ.get("DEMQ_SCHEMATHESIS_REPORT")
    if path:
        with open(path, "w") as fh:
            json.dump({op: dict(c) for op, c in SEEN.items()}, fh, indent=1, sort_keys=True)


@schema.parametrize()
@hsettings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case):
    response = case.call()
    SEEN[f"{case.method} {case.path}"][response.status_code] += 1
    assert response.status_code < 500, (case.method, case.path, case.body, response.text[:500])
