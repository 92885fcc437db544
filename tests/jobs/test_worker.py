"""The worker with the fake engine in a real spawned simulation process (SQLite store)."""

from __future__ import annotations

import threading
from pathlib import Path

import h5py
import pytest

from jobs.runner import TEST_CRASH_ENV
from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING
from jobs.specs import parse_spec
from jobs.store import NewJob
from jobs.stores import open_store
from jobs.worker import Worker, describe_exit
from tests.jobs.conftest import TINY
from tests.jobs.fake_engine import FAIL_SEED
from tests.waiting import wait_for


def _enqueue(store, **keys):
    (job,) = store.submit([NewJob(parse_spec({**TINY, **keys}).to_json())])
    return job


@pytest.fixture
def local(settings):
    store = open_store(settings.database_url)
    yield store, Worker(store, settings)
    store.close()


def _wait(cond):
    wait_for(cond, "condition")


def test_job_runs_to_done_with_result_and_timings(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=0.5)
    seen = []
    worker.on_progress = lambda j, p: seen.append(p["fraction"])
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == DONE
    got = store.get(job.id)
    assert got.state == DONE and got.progress == 1.0 and got.error is None
    assert got.job_wall_s >= got.loop_s > 0.4 and got.cundall > 0 and got.backend == "fake"
    assert Path(got.result_path) == settings.result_path(job.id)
    with h5py.File(got.result_path) as f:
        assert f["observables/kinetic_energy_translational/value"].shape[0] > 1
    assert seen and seen == sorted(seen) and seen[-1] == 1.0
    assert not settings.checkpoint_dir(job.id).exists()


def test_engine_error_fails_the_job_and_the_next_runs(local, settings):
    store, worker = local
    bad, good = _enqueue(store, seed=FAIL_SEED), _enqueue(store)
    worker.execute(store.claim(worker.owner, settings.lease_s))
    worker.execute(store.claim(worker.owner, settings.lease_s))
    assert store.get(bad.id).state == FAILED
    assert store.get(bad.id).error.startswith("InstabilityError: overlap of particle 7")
    assert store.get(good.id).state == DONE


def test_crashing_simulation_fails_readably_and_the_next_runs(local, settings, monkeypatch):
    store, worker = local
    monkeypatch.setenv(TEST_CRASH_ENV, "99")
    crash, good = _enqueue(store, seed=99), _enqueue(store)
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == FAILED
    assert worker.execute(store.claim(worker.owner, settings.lease_s)) == DONE
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    assert store.get(good.id).state == DONE


def test_describe_exit():
    assert describe_exit(-9).startswith("simulation process killed by signal SIGKILL (out of memory?")
    assert describe_exit(3) == "simulation process exited with code 3 without reporting a result"


def test_cancel_of_running_job(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=30.0)  # the fake engine sleeps 30 s unless stopped
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(job.id).progress > 0)
        assert store.request_cancel(job.id).cancel_requested
        _wait(lambda: store.get(job.id).state == CANCELLED)
    finally:
        worker.stop()
        thread.join(30)
    assert store.get(job.id).finished_at is not None
    assert not settings.checkpoint_dir(job.id).exists()


def test_stop_releases_running_job_without_counting_the_attempt(local, settings):
    store, worker = local
    job = _enqueue(store, t_end=30.0)
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    _wait(lambda: store.get(job.id).progress > 0)
    worker.stop()
    thread.join(15)
    assert not thread.is_alive()
    got = store.get(job.id)
    assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)
    assert (settings.checkpoint_dir(job.id) / "fake.ckpt").exists()  # kept for the next attempt


def test_unresponsive_simulation_is_killed_after_grace(tmp_path, monkeypatch):
    """A simulation that ignores the cancel check is killed after the grace period; job cancelled."""
    from tests.jobs.conftest import make_settings

    settings = make_settings(tmp_path, cancel_grace_s=0.5, engine_run="tests.jobs.fake_engine:run_deaf")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    job = _enqueue(store, t_end=100.0)  # 20 steps of 5 s: ends by itself only after 100 s
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(job.id).state == RUNNING and store.get(job.id).progress > 0)
        store.request_cancel(job.id)
        _wait(lambda: store.get(job.id).state == CANCELLED)
        assert store.get(job.id).progress < 1.0  # killed: the deaf run did not reach its end
    finally:
        worker.stop()
        thread.join(30)


# ---- the standby simulation process ------------------------------------------------------------------------

def _standby_worker(tmp_path, **kw):
    from tests.jobs.conftest import make_settings

    settings = make_settings(tmp_path, standby="on", **kw)
    store = open_store(settings.database_url)
    return settings, store, Worker(store, settings)


def _handed(caplog) -> list[tuple[str, str, str]]:
    """(job id, pid, claim number in that process) of each "handed to the standby" line of the worker's log."""
    import re

    pattern = r"job (\w+): handed to the standby simulation process \(pid (\d+), its claim (\d+)\)"
    return [re.match(pattern, r.getMessage()).groups() for r in caplog.records
            if "handed to the standby" in r.getMessage()]


def test_claims_run_in_standby_processes_and_none_is_left_behind(tmp_path, caplog):
    """A running worker hands its first claim to the process it started ahead (at its own start), and each later
    CPU claim to the same process, which stays for them (one start-up for all); when the worker stops, that process
    goes too."""
    import logging
    import multiprocessing

    settings, store, worker = _standby_worker(tmp_path, ensemble_max_jobs=1)
    jobs = [_enqueue(store, seed=s) for s in (1, 2, 3)]
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        worker.run_forever(exit_when_idle=True)
    assert [store.get(j.id).state for j in jobs] == [DONE] * 3
    handed = _handed(caplog)
    assert [job_id for job_id, _, _ in handed] == [j.id for j in jobs]
    assert len({pid for _, pid, _ in handed}) == 1 and [n for _, _, n in handed] == ["1", "2", "3"]
    assert "did not come back" not in caplog.text
    assert multiprocessing.active_children() == []
    store.close()


def test_a_lanes_process_clears_the_last_claims_cancel_and_a_crashed_one_is_replaced(tmp_path, caplog, monkeypatch):
    """The process that ran a claim in which a job was cancelled runs the next claim's job to its end (its cancel
    flags are cleared in between); a process that crashed is not reused: the next claim gets a fresh one, and the
    crash fails only its own job."""
    import logging

    monkeypatch.setenv(TEST_CRASH_ENV, "99")
    settings, store, worker = _standby_worker(tmp_path, ensemble_max_jobs=1, cancel_kill_s=30.0)
    thread = threading.Thread(target=worker.run_forever)
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        thread.start()
        try:
            cancelled = _enqueue(store, t_end=2.0, seed=5)
            _wait(lambda: store.get(cancelled.id).progress > 0)
            store.request_cancel(cancelled.id)
            _wait(lambda: store.get(cancelled.id).state == CANCELLED)
            after_cancel = _enqueue(store, seed=6)
            _wait(lambda: store.get(after_cancel.id).state in (DONE, FAILED))
            crash = _enqueue(store, seed=99)
            _wait(lambda: store.get(crash.id).state in (DONE, FAILED))
            after_crash = _enqueue(store, seed=7)
            _wait(lambda: store.get(after_crash.id).state in (DONE, FAILED))
        finally:
            worker.stop()
            thread.join(30)
    assert not thread.is_alive()
    assert store.get(after_cancel.id).state == DONE, store.get(after_cancel.id).error
    assert store.get(crash.id).error == "simulation process killed by signal SIGSEGV"
    assert store.get(after_crash.id).state == DONE
    pid = {job_id: pid for job_id, pid, _ in _handed(caplog)}
    assert pid[cancelled.id] == pid[after_cancel.id] == pid[crash.id] != pid[after_crash.id]
    store.close()


def test_every_lane_starts_its_process_with_the_worker(tmp_path):
    """With lanes, each lane starts its simulation process with the worker, before any claim (the first lane's
    warms the default spec; the others import the engine only)."""
    from tests.jobs.conftest import make_settings

    settings = make_settings(tmp_path, standby="on", lanes="3")
    store = open_store(settings.database_url)
    worker = Worker(store, settings)

    def started():
        lanes = [worker] + [lane for lane, _ in worker._lanes]
        return len(lanes) == 3 and all(w._standby is not None and w._standby.proc.is_alive() for w in lanes)

    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(started)
    finally:
        worker.stop()
        thread.join(30)
    assert not thread.is_alive()
    assert store.counts() == {}          # no job: the lanes' processes started without a claim
    store.close()


def test_the_next_claim_does_not_wait_for_a_finished_process_to_exit(tmp_path):
    """Once every job of a claim has ended done, the worker claims the next one without waiting for the old
    process's exit (a GPU process's context teardown takes seconds; here a thread holds the exit 3 s), and the
    process is still joined: none is left when the worker stops."""
    import multiprocessing

    settings, store, worker = _standby_worker(tmp_path, ensemble_max_jobs=1,
                                              engine_run="tests.jobs.fake_engine:run_slow_exit")
    first, second = (_enqueue(store, seed=s) for s in (1, 2))
    worker.run_forever(exit_when_idle=True)
    first, second = store.get(first.id), store.get(second.id)
    assert (first.state, second.state) == (DONE, DONE)
    assert second.started_at - first.finished_at < 1.5, (first.finished_at, second.started_at)
    assert multiprocessing.active_children() == []
    store.close()


def test_the_first_standby_starts_up_while_the_warm_up_runs(tmp_path):
    """A fresh worker's first claim must not wait for its simulation process after the warm-up: the standby is
    started before the warm-up begins."""
    settings, store, worker = _standby_worker(tmp_path)
    seen = []
    worker._warm = lambda backends: seen.append(worker._standby is not None and worker._standby.proc.is_alive())
    worker.run_forever(exit_when_idle=True)
    assert seen == [True]
    store.close()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc (Linux)")
def test_a_worker_claims_at_once_and_its_warm_up_waits_while_the_claim_runs(tmp_path, monkeypatch):
    """The first job does not wait for the warm-up of every kernel specialisation: the worker claims while the
    warm-up (the real one, jobs/warm.py, compiling into numba's cache at nice 19) still runs, stops it for the
    claim, lets it go on after, and ends it when the worker stops."""
    import time

    from jobs.settings import Settings
    from tests.jobs.conftest import make_settings
    from tests.jobs.test_warm import _state

    monkeypatch.setattr(Settings, "warm_enabled", property(lambda self: True))   # with the fake engine's jobs
    settings = make_settings(tmp_path, standby="off", ensemble_max_jobs=1)
    store = open_store(settings.database_url)
    worker = Worker(store, settings)
    job = _enqueue(store)
    during, execute_pack = [], worker.execute_pack

    def observed(jobs):
        warm_up = worker._warm_up
        assert warm_up is not None and warm_up.running, "the warm-up had ended before the first claim"
        deadline = time.monotonic() + 10
        while _state(warm_up._proc.pid) != "T" and time.monotonic() < deadline:
            time.sleep(0.02)
        during.append((warm_up.paused, _state(warm_up._proc.pid)))
        outcome = execute_pack(jobs)
        during.append(warm_up)
        return outcome

    worker.execute_pack = observed
    worker.run_forever(exit_when_idle=True)
    assert store.get(job.id).state == DONE
    (paused, state), warm_up = during
    assert (paused, state) == (True, "T")
    assert not warm_up.paused and worker._warm_up is None and not warm_up._proc.is_alive()
    store.close()


def test_cancel_and_stop_reach_a_job_in_a_standby_process(tmp_path):
    settings, store, worker = _standby_worker(tmp_path)
    cancel, stop = _enqueue(store, t_end=30.0, seed=5), None
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: store.get(cancel.id).progress > 0)
        store.request_cancel(cancel.id)
        _wait(lambda: store.get(cancel.id).state == CANCELLED)
        stop = _enqueue(store, t_end=30.0, seed=6)
        _wait(lambda: store.get(stop.id).progress > 0)
    finally:
        worker.stop()
        thread.join(30)
    assert not thread.is_alive()
    got = store.get(stop.id)
    assert (got.state, got.attempts, got.lease_owner) == (QUEUED, 0, None)
    store.close()


def test_a_standby_that_died_is_replaced_by_a_fresh_process(tmp_path):
    settings, store, worker = _standby_worker(tmp_path)
    thread = threading.Thread(target=worker.run_forever)
    thread.start()
    try:
        _wait(lambda: worker._standby is not None)
        dead = worker._standby.proc
        dead.kill()
        dead.join()
        job = _enqueue(store)
        worker.wake()
        _wait(lambda: store.get(job.id).state == DONE)
    finally:
        worker.stop()
        thread.join(30)
    assert not thread.is_alive()
    store.close()


def test_a_standby_process_writes_the_same_file_as_engine_run(tmp_path):
    """The real engine through a started-up standby process (warmed for the default spec: imports, numba's CPU
    target, a parallel start) against engine.run in this process: the same result, bit for bit (CPU)."""
    from engine.driver.simulate import run
    from jobs.settings import DEFAULT_ENGINE_RUN

    settings, store, worker = _standby_worker(tmp_path, engine_run=DEFAULT_ENGINE_RUN, ensemble_max_jobs=1)
    spec = {**TINY, "t_end": 0.05, "seed": 11, "backend": "cpu"}
    job = _enqueue(store, **spec)
    worker.run_forever(exit_when_idle=True)
    got = store.get(job.id)
    assert got.state == DONE, got.error
    direct = run(parse_spec({**TINY, **spec}), tmp_path / "direct.h5")
    with h5py.File(got.result_path) as a, h5py.File(direct.output) as b:
        names = []
        a.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        assert names and "observables/kinetic_energy_translational/value" in names
        for n in names:
            assert (a[n][()] == b[n][()]).all(), n
    store.close()


def test_a_last_message_sent_just_before_the_process_exits_is_read(local, settings):
    """The supervisor's poll can time out just before the simulation sends its result and exits; the exit must
    not hide the message still in the pipe (it did: 'exited with code 0 without reporting a result' under load)."""
    from jobs.worker import _Slot

    store, worker = local
    _enqueue(store)
    job = store.claim(worker.owner, settings.lease_s)
    done = {"backend": "fake", "device": "cpu", "loop_s": 0.1, "job_wall_s": 0.2, "cundall": 1.0, "steps": 1,
            "resumed_from_step": None, "ensemble_size": 1}

    class Receiver:                 # nothing at the first poll; the message is there once the process is gone
        def __init__(self):
            self.polls, self.messages = 0, [("done", 0, done)]

        def poll(self, timeout=0.0):
            self.polls += 1
            return self.polls > 1

        def recv(self):
            if self.messages:
                return self.messages.pop(0)
            raise EOFError

    class DeadProcess:
        def is_alive(self):
            return False

    slot = _Slot(job, settings.result_path(job.id), settings.checkpoint_dir(job.id))
    assert worker._supervise([slot], DeadProcess(), Receiver(), [0]) is None
    assert slot.final == ("done", done) and store.get(job.id).state == DONE


def test_the_size_classes_of_a_standbys_specialisation_are_the_engines():
    from engine.loops.cpu import SERIAL_LOOP_BELOW
    from jobs.worker import SMALL_SCENE_BELOW, _specialisation

    assert SMALL_SCENE_BELOW == SERIAL_LOOP_BELOW
    default = _specialisation("{}")
    assert default == _specialisation('{"seed": 3, "e_n": 0.5}')          # run-time values: the same code
    assert default != _specialisation('{"n_particles": 2097152}')         # a large start
    assert default != _specialisation('{"n_particles": 512}')             # the CPU loop without regions
    assert default != _specialisation('{"e_t": -1}') != _specialisation('{"precision": "float32"}')
    assert _specialisation('{"n_particles": "many"}') is None


def test_a_claim_of_another_specialisation_does_not_wait_for_a_compiling_standby(tmp_path, caplog):
    """A standby that said it is compiling (an empty kernel cache) the default spec's kernels is ended when a claim
    of another specialisation comes, and the claim gets a process of its own; a claim of its own specialisation is
    handed to it (it compiles what that claim needs anyway)."""
    import logging

    from jobs.worker import _specialisation

    settings, store, worker = _standby_worker(tmp_path, ensemble_max_jobs=1)
    worker._keep_standby = True
    standby = worker._spawn_standby(None)   # the fake engine's: it warms nothing
    # as if it started up for 4096 spheres and had said it compiles (the real compile is the engine's: tests/gpu)
    standby.warm_key, standby.compiling = _specialisation('{"n_particles": 4096}'), True
    standby.read_start_up = lambda: None     # and had not said "ready" yet
    worker._standby = standby
    other = _enqueue(store, n_particles=512, seed=1)
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        assert worker.execute_pack(worker._next(None)) == {other.id: DONE}
    assert "still compiling another specialisation's kernels" in caplog.text
    assert not standby.proc.is_alive()
    mine = worker._spawn_standby(None)
    mine.warm_key, mine.compiling = _specialisation('{"n_particles": 4096}'), True
    mine.read_start_up = lambda: None
    worker._standby = mine
    same = _enqueue(store, n_particles=4096, box_length=2.0, seed=2)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        assert worker.execute_pack(worker._next(None)) == {same.id: DONE}
    assert "handed to the standby" in caplog.text
    worker._keep_standby = False
    worker._standby.close()
    worker._reap(wait=True)
    store.close()


def test_a_gpu_pack_does_not_wait_for_a_standby_warming_one_job_of_its_spec(tmp_path, caplog, monkeypatch):
    """A GPU pack runs the packed kernels, which a standby warming one job of the same spec does not compile: a
    standby that said it began its warm-up is ended and the pack gets a process of its own (a pack of 256 jobs of
    the default size had waited 23 s for such a standby's compile)."""
    import logging

    from jobs.worker import _specialisation
    from tests.jobs.fake_engine import ENSEMBLE_TARGET

    settings, store, worker = _standby_worker(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, cpu_packs="ensemble")
    worker._keep_standby = True
    monkeypatch.setattr(worker._packer, "backend", lambda job: "cuda")    # a GPU host's packs (the fake engine runs)
    standby = worker._spawn_standby(None)
    standby.warm_key, standby.warming = _specialisation('{"n_particles": 4096}'), True
    standby.read_start_up = lambda: None     # it had not said "compiling" or "ready" yet
    worker._standby = standby
    jobs = [_enqueue(store, n_particles=4096, box_length=2.0, seed=s) for s in (1, 2)]
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        assert worker.execute_pack(worker._next(None)) == {j.id: DONE for j in jobs}
    assert "warming up one job's kernels, not a GPU pack's" in caplog.text
    assert "handed to the standby" not in caplog.text and not standby.proc.is_alive()
    worker._keep_standby = False
    worker._standby.close()
    worker._reap(wait=True)
    store.close()


def test_a_gpu_pack_is_promised_to_a_standby_under_its_hand_over_lock(tmp_path, caplog, monkeypatch):
    """The worker reads what a standby has said, and promises it the claim, under the lock under which the standby
    decides whether to warm up (jobs/runner.py standby_main): a standby that says "warming" while the worker is about
    to hand over a GPU pack does not get it (the pack had been sent, and waited for the warm-up, when "warming" came
    between the worker's read and its send); a standby that has said nothing is promised the pack, then sent it."""
    import logging
    import threading
    import time

    from tests.jobs.fake_engine import ENSEMBLE_TARGET

    settings, store, worker = _standby_worker(tmp_path, engine_run_ensemble=ENSEMBLE_TARGET, cpu_packs="ensemble")
    worker._keep_standby = True
    monkeypatch.setattr(worker._packer, "backend", lambda job: "cuda")    # a GPU host's packs (the fake engine runs)
    standby = worker._spawn_standby(None)
    said, promised_when_deciding = [], []
    standby.read_start_up = lambda: setattr(standby, "warming", "warming" in said)
    deciding = threading.Event()

    def standby_decides():   # as standby_main: under the lock it finds no claim promised, so it says "warming"
        with standby.claim_promised.get_lock():
            deciding.set()
            time.sleep(0.3)
            promised_when_deciding.append(standby.claim_promised.value)
            said.append("warming")

    decider = threading.Thread(target=standby_decides)
    decider.start()
    assert deciding.wait(timeout=10)
    worker._standby = standby
    jobs = [_enqueue(store, n_particles=4096, box_length=2.0, seed=s) for s in (1, 2)]
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        assert worker.execute_pack(worker._next(None)) == {j.id: DONE for j in jobs}
    decider.join()
    assert promised_when_deciding == [0]
    assert "warming up one job's kernels, not a GPU pack's" in caplog.text
    assert "handed to the standby" not in caplog.text and not standby.proc.is_alive()
    worker._standby.close()
    quiet = worker._spawn_standby(None)
    quiet.read_start_up = lambda: None       # it has said nothing yet
    worker._standby = quiet
    jobs = [_enqueue(store, n_particles=4096, box_length=2.0, seed=s) for s in (3, 4)]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="demq.worker"):
        assert worker.execute_pack(worker._next(None)) == {j.id: DONE for j in jobs}
    assert "handed to the standby" in caplog.text and quiet.claim_promised.value == 1
    worker._keep_standby = False
    worker._standby.close()
    worker._reap(wait=True)
    store.close()


@pytest.mark.parametrize("claim_waiting", [True, "promised", False])
def test_a_standby_that_finds_a_claim_after_its_imports_skips_the_warm_spec(monkeypatch, claim_waiting):
    """A claim handed to a standby while it still imported, or promised to it (the worker has decided to send it), is
    run at once: the standby does not first compile (or load) the warm spec's kernels, which with an empty cache would
    cost a first job of another specialisation a whole compile and a GPU pack a wait; without a waiting or promised
    claim it warms up as before and then runs the claim that comes."""
    import multiprocessing
    import threading

    import engine.driver.simulate
    from jobs import runner

    warmed, ran = [], []
    claims_in, claims_out = multiprocessing.Pipe(duplex=False)
    receiver, sender = multiprocessing.Pipe(duplex=False)
    claim = ("engine.driver.simulate:run", ['{"n_particles": 512}'], ["out.h5"], ["ck"], 60.0, "one")

    def warm_process(spec):
        warmed.append(spec.n_particles)
        claims_out.send(claim)           # the claim comes while the standby warms up
        claims_out.send(None)            # and no other: the process ends after it

    monkeypatch.setattr(engine.driver.simulate, "warm_process", warm_process)
    monkeypatch.setattr(runner, "run_claim", lambda *args: ran.append(args[:2]))
    monkeypatch.setattr(runner, "_die_with_parent", lambda: None)
    monkeypatch.setattr(runner.signal, "signal", lambda *a: None)
    claim_promised = multiprocessing.Value("b", 0)
    if claim_waiting is True:
        claims_out.send(claim)
        claims_out.send(None)
    elif claim_waiting:      # promised before the standby looks, sent a little later (after the worker's lock)
        claim_promised.value = 1

        def send_late():
            claims_out.send(claim)
            claims_out.send(None)

        threading.Timer(0.3, send_late).start()
    runner.standby_main(claims_in, sender, None, 0, '{"n_particles": 4096}', claim_promised=claim_promised)
    assert warmed == ([] if claim_waiting else [4096])
    assert ran == [("engine.driver.simulate:run", ['{"n_particles": 512}'])]
    # (warming;) started up; the claim over
    said = ["ready", "ready"] if claim_waiting else ["warming", "ready", "ready"]
    assert [receiver.recv()[0] for _ in range(len(said))] == said
