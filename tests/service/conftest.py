"""Fixtures of the service tests: an app on a temporary data directory (no worker unless asked)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from fastapi.testclient import TestClient  # noqa: E402

from jobs.schema import DONE  # noqa: E402
from jobs.specs import parse_spec  # noqa: E402
from service.app import create_app  # noqa: E402
from tests.jobs.conftest import TINY, make_settings  # noqa: E402
from tests.jobs.fake_engine import write_result  # noqa: E402


@pytest.fixture
def settings(tmp_path):
    return make_settings(tmp_path)


@pytest.fixture
def client(settings):
    app = create_app(settings)
    with TestClient(app) as c:
        c.store = app.state.store
        yield c


def finish_with_fake_result(store, settings, job_id: str) -> None:
    """Play the worker for one job: claim it, write an engine-shaped HDF5 result, mark it done."""
    job = store.claim("test-worker", 30, job_id=job_id)
    settings.results_dir.mkdir(parents=True, exist_ok=True)
    path = write_result(settings.result_path(job_id), parse_spec(job.spec))
    store.finish(job_id, "test-worker", DONE, result_path=str(path), loop_s=0.5, job_wall_s=0.6, cundall=1e6,
                 error=None, progress=1.0)


__all__ = ["TINY", "finish_with_fake_result"]
