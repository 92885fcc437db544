"""Settings of every test process, made before anything imports Numba.

Numba runs its parallel loops on one thread (NUMBA_NUM_THREADS=1 unless it is set before pytest starts), in this
process and in every process it starts (workers, simulation and simulator children inherit the environment). The
scenes of the tests are tiny, and the threads of a parallel loop meet at every step: beside another busy process
on 2 cores those meetings wait for the scheduler, and a run slows down by an order of magnitude or more (measured:
a packed pair of 64-sphere scenes ran 12 s on one thread, over 150 s on two, beside a busy loop). That more
threads change no result is checked where it is the point, in child processes given more threads
(tests/engine/test_threads.py, the parallel start in tests/engine/test_time_to_result.py).
"""

import os

import pytest

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

#: The test running in this process (set before its fixtures): tests.jobs.conftest.postgres_url checks its marks.
_CURRENT: dict = {}


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    _CURRENT["item"] = item


def current_test():
    """The pytest item now running in this process, or None outside a test."""
    return _CURRENT.get("item")
