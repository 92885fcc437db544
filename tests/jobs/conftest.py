"""Fixtures of the queue tests: settings on a temporary data directory, stores on SQLite and PostgreSQL.

PostgreSQL: the URL comes from DEMQ_TEST_POSTGRES_URL. Without it the PostgreSQL cases are skipped
locally, but FAIL when CI is set (CI must run them). Every store gets a fresh table prefix, dropped
afterwards, so concurrent runs do not collide.
"""

from __future__ import annotations

import os
import sys
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # the simulation processes import tests.jobs.fake_engine from here
    sys.path.insert(0, str(ROOT))

from jobs.settings import Settings  # noqa: E402
from jobs.stores import open_store  # noqa: E402
from tests.jobs.fake_engine import TARGET  # noqa: E402

#: A scene the real engine runs in about a second once compiled (checked valid by test_specs).
TINY = {"n_particles": 64, "volume_fraction": 0.05, "box_length": 0.5, "t_end": 0.002,
        "thermalization": 0, "snapshots": 1}


def postgres_url() -> str:
    url = os.environ.get("DEMQ_TEST_POSTGRES_URL")
    if not url:
        if os.environ.get("CI"):
            pytest.fail("CI is set but DEMQ_TEST_POSTGRES_URL is not: the PostgreSQL tests must run in CI")
        pytest.skip("DEMQ_TEST_POSTGRES_URL not set (PostgreSQL tests run in CI)")
    return url


def make_settings(tmp_path: Path, **overrides) -> Settings:
    """Fast settings for tests: fake engine, short heartbeats and leases, no warm-up of every kernel
    specialisation before the first claim (a test with the real engine compiles only what its jobs need)."""
    values = dict(data_dir=tmp_path / "data", engine_run=TARGET, heartbeat_s=0.3, lease_s=3.0, poll_s=0.05,
                  progress_s=0.1, cancel_grace_s=5.0, checkpoint_interval=0.2, max_attempts=3, warm="off")
    values.update(overrides)
    return Settings.from_env(environ={}, **values)


@pytest.fixture
def settings(tmp_path) -> Settings:
    return make_settings(tmp_path)


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request, tmp_path):
    """(database URL, table prefix) for each backend."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'queue.sqlite3'}", ""
    return postgres_url(), f"t{uuid.uuid4().hex[:10]}_"


@pytest.fixture
def store(store_url):
    url, prefix = store_url
    s = open_store(url, prefix)
    yield s
    s.drop_tables()
    s.close()
