"""Fixtures of the queue tests: settings on a temporary data directory, stores on SQLite and PostgreSQL.

PostgreSQL: the URL comes from DEMQ_TEST_POSTGRES_URL, the driver from the ``postgres`` extra (psycopg). Without
the URL the PostgreSQL cases are skipped, but FAIL when CI is set and the driver is installed (CI must run them:
.ci/run's first stage, the README's light install, has no driver and no URL; its second stage installs the extra,
sets the URL and runs the tests marked postgres). With the URL set they run, driver or not. Every test that uses
PostgreSQL must be marked ``postgres`` (the store fixtures' PostgreSQL case is): :func:`postgres_url` fails a
test that is not, so none is left out of that second stage. Every store gets a fresh table prefix, dropped
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
from tests.conftest import current_test  # noqa: E402
from tests.extras import HAVE_POSTGRES_DRIVER  # noqa: E402
from tests.jobs.fake_engine import TARGET  # noqa: E402

#: A scene the real engine runs in about a second once compiled (checked valid by test_specs).
TINY = {"n_particles": 64, "volume_fraction": 0.05, "box_length": 0.5, "t_end": 0.002,
        "thermalization": 0, "snapshots": 1}


def _marked_postgres() -> None:
    test = current_test()
    if test is not None and test.get_closest_marker("postgres") is None:
        pytest.fail(f"{test.nodeid} uses PostgreSQL but is not marked postgres (.ci/run selects the PostgreSQL "
                    f"tests by that mark)")


def postgres_url() -> str:
    """DEMQ_TEST_POSTGRES_URL, or the test skipped without it (failed when CI is set and the driver installed)."""
    _marked_postgres()
    url = os.environ.get("DEMQ_TEST_POSTGRES_URL")
    if not url:
        if os.environ.get("CI") and HAVE_POSTGRES_DRIVER:
            pytest.fail("CI is set but DEMQ_TEST_POSTGRES_URL is not: the PostgreSQL tests must run in CI")
        pytest.skip("DEMQ_TEST_POSTGRES_URL not set (PostgreSQL tests run in CI)")
    return url


def postgres_driver() -> None:
    """For a test that needs the psycopg driver but no server: skipped without the driver unless
    DEMQ_TEST_POSTGRES_URL is set (then it runs, and fails without the driver)."""
    _marked_postgres()
    if not HAVE_POSTGRES_DRIVER and not os.environ.get("DEMQ_TEST_POSTGRES_URL"):
        pytest.skip("psycopg not installed (pip install '.[postgres]'; the PostgreSQL tests run in CI)")


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


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
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
