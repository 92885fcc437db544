"""Fixtures of the deployment tests: real processes started from the command lines in deploy/,
the local PostgreSQL (DEMQ_TEST_POSTGRES_URL; required when CI is set, see tests/jobs/conftest.py),
and a Numba cache warmed once so the simulation processes load compiled kernels from disk."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import uuid
from pathlib import Path

import pytest

from tests import waiting
from tests.deploy.deployfiles import ROOT, clean_env, shim_bin
from tests.jobs.conftest import postgres_url

#: A real-engine job of about a second of CPU once compiled (checked valid by the tests).
#: t_end: long enough (about a second of one core) that a worker can be caught mid-job; records cost almost
#: next to nothing (O(1) host work each), so a job's wall time is its time loop
SPEC = {"n_particles": 64, "volume_fraction": 0.05, "box_length": 0.5, "t_end": 0.6,
        "thermalization": 0, "snapshots": 1, "backend": "cpu"}
#: Queue settings for the process tests: short leases so a SIGKILLed worker's job is reaped in
#: seconds, frequent checkpoints, one Numba thread per simulation (3 workers on 2 cores), and no warm-up of every
#: kernel specialisation at a worker's start (warm_jit loads the one these tests' jobs use).
FAST_ENV = {"DEMQ_LEASE_SECONDS": "5", "DEMQ_HEARTBEAT_SECONDS": "0.5", "DEMQ_POLL_SECONDS": "0.1",
            "DEMQ_PROGRESS_SECONDS": "0.2", "DEMQ_CHECKPOINT_INTERVAL": "0.3",
            "DEMQ_CANCEL_GRACE_SECONDS": "20", "NUMBA_NUM_THREADS": "1", "DEMQ_WORKER_WARM": "off"}


def wait_for(cond, what: str, procs=None):
    """Poll ``cond`` until it returns something truthy (returned); fail as soon as one of ``procs``
    (name -> Popen) has exited, or on a hang (tests/waiting.py: the limits never catch mere slowness)."""
    return waiting.wait_for(cond, what, procs=procs)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Processes:
    """Processes started by a test, each in its own session with its output in logs/<name>.log;
    whatever is still running at teardown is killed (by process group id)."""

    def __init__(self, directory: Path):
        self.dir = directory
        self.dir.mkdir(parents=True, exist_ok=True)
        self.started: dict[str, subprocess.Popen] = {}

    def start(self, name: str, argv, env: dict) -> subprocess.Popen:
        log = open(self.dir / f"{name}.log", "w")
        p = subprocess.Popen(list(argv), cwd=self.dir, env=env, stdout=log, stderr=subprocess.STDOUT,
                             start_new_session=True)
        log.close()
        self.started[name] = p
        return p

    def log(self, name: str) -> str:
        return (self.dir / f"{name}.log").read_text()

    def stop(self, name: str, timeout: float) -> int:
        """SIGTERM; the exit status, or fail if it has not exited within ``timeout`` seconds."""
        p = self.started[name]
        p.send_signal(signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name} did not exit within {timeout} s of SIGTERM:\n{self.log(name)[-3000:]}")

    def kill_all(self) -> None:
        for p in self.started.values():
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(10)


@pytest.fixture
def procs(tmp_path, request):
    ps = Processes(tmp_path / "logs")
    yield ps
    ps.kill_all()
    if request.node.rep_call.failed if hasattr(request.node, "rep_call") else False:
        for name in ps.started:
            print(f"---- {name}.log (tail) ----\n{ps.log(name)[-4000:]}")


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    rep = yield
    if rep.when == "call":
        item.rep_call = rep
    return rep


@pytest.fixture(scope="session")
def bin_dir(tmp_path_factory) -> Path:
    """``demq`` and ``python`` shims of this checkout, to put first on PATH."""
    return shim_bin(tmp_path_factory.mktemp("bin"))


@pytest.fixture
def pg():
    """(URL, table prefix, store) on the real PostgreSQL; the table is dropped afterwards."""
    from jobs.stores import open_store

    url, prefix = postgres_url(), f"d{uuid.uuid4().hex[:10]}_"
    store = open_store(url, prefix)
    yield url, prefix, store
    store.drop_tables()
    store.close()


@pytest.fixture(scope="session")
def warm_jit(tmp_path_factory) -> None:
    """Run one tiny real-engine job in this process (one Numba thread), so the kernels are compiled
    and cached on disk before the workers' simulation processes need them."""
    import numba

    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec.model_validate({**SPEC, "t_end": 0.002})
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        run(spec, tmp_path_factory.mktemp("warm") / "warm.h5")
    finally:
        numba.set_num_threads(previous)


def process_env(bin_dir: Path, **env: str) -> dict:
    return clean_env(bin_dir, **{**FAST_ENV, **env})


__all__ = ["ROOT", "SPEC", "FAST_ENV", "wait_for", "free_port", "process_env"]
