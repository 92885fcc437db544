"""The simulation process: it runs a claim — one job, a sequence of CPU jobs run one after another, or a pack of jobs
run as one ensemble (jobs/packing.py) — started by the worker with the ``spawn`` context, either with its claim
(:func:`child_main`: that claim only) or ahead of it as a standby (:func:`standby_main`: started up while the worker
waits or runs the previous claim, then handed its claims over a pipe, one at a time: a CPU lane's process runs claim
after claim, its imports and loaded code serving them all; the worker ends it with ``None`` instead of a claim).

It validates the specs, calls the engine with a progress callback and a cancel check per job (one job, and each
job of a sequence in turn, in this one warm process: ``DEMQ_ENGINE_RUN``, engine.driver.simulate.run; a pack:
``DEMQ_ENGINE_RUN_ENSEMBLE``, engine.driver.ensemble.run_ensemble), and reports to the worker over a pipe; every
message names the job by its index k in the claim::

    ("started", k, None)                  a sequence's job k starts (the jobs before it have ended)
    ("progress", k, {phase, fraction, step, time, eta_s, cundall, loop_s, resumed_from_step})
    ("progress_many", None, {k: {...}})   a pack's progress: the latest of each job that reported since the
                                          last such message, at most every PROGRESS_SEND_S (one message for
                                          the whole pack, not one per job: 256 jobs at each of 200 records had
                                          filled the pipe faster than the worker read it, and the pack waited)
    ("done", k, {backend, device, loop_s, job_wall_s, cundall, steps, resumed_from_step, ensemble_size})
    ("cancelled", k, reason)
    ("error", k, readable message)
    ("error", None, readable message)     the pack as a whole failed (no job is singled out)

A standby process says first, before its claim: ("warming", None, None) when it begins to warm up its spec's kernels
(no claim came or was promised during its imports), ("compiling", None, None) once if that warm-up compiles kernels
(an empty or partial kernel cache), then ("ready", None, None) when its start-up is done; and ("ready", None, None)
again after each claim, once everything of that claim has been said and it reads the next one.

A sequence's or a pack's jobs report done / cancelled / error one by one, as their runs end. Each job has its own
cancel flag (a shared byte array), so one job stops without disturbing the others; a sequence's job whose flag is
set before its turn is skipped (reported cancelled without starting).

If the process dies instead (signal, out of memory, or the worker killing it after a cancel), the worker reads
its exit code. The process ignores SIGINT/SIGTERM (the worker decides when it stops: cancel flag, then SIGKILL
after DEMQ_CANCEL_KILL_SECONDS or DEMQ_CANCEL_GRACE_SECONDS) and dies with the worker: PR_SET_PDEATHSIG on Linux,
and the cancel check also stops the run when the worker is gone.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import asdict
from typing import Callable, Optional

from jobs.packing import ENSEMBLE, ONE, SEQUENCE

#: Least wall seconds between two progress messages of one job (its first and last messages and a phase change go
#: at once). Each message is a pipe write here and a wake-up of the worker's thread, which shares its interpreter
#: with the HTTP service: at every record, a small job spent about a quarter of its time on them.
PROGRESS_SEND_S = 0.05

#: TEST HOOK: a job whose spec seed equals this variable's value kills its simulation process with
#: SIGSEGV at the first progress report (the crash-isolation tests use it). Unset in production.
TEST_CRASH_ENV = "DEMQ_TEST_CRASH"


def load_callable(target: str) -> Callable:
    """Import ``module:function``."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def _die_with_parent() -> None:
    if sys.platform.startswith("linux"):
        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _use_threads(threads: Optional[int]) -> None:
    """Run the engine's CPU loops on ``threads`` Numba threads (a worker's lane: its share of the cores); None: all.
    Set before the engine (and so numba) is imported in this process."""
    if threads is not None:
        os.environ["NUMBA_NUM_THREADS"] = str(threads)


def child_main(engine_target: str, spec_jsons: list, outputs: list, checkpoint_dirs: list,
               checkpoint_interval: float, conn, cancel_flags, parent_pid: int, mode: str = ONE,
               threads: Optional[int] = None) -> None:
    """Entry point of the simulation process (a top-level function, so ``spawn`` can import it). ``mode``: ONE
    (``engine_target`` runs spec_jsons[0]), SEQUENCE (it runs each spec in turn, in the given order) or ENSEMBLE
    (``engine_target`` runs them all as one ensemble). ``threads``: Numba threads of its CPU loops (None: all)."""
    _use_threads(threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _die_with_parent()
    try:
        run_claim(engine_target, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
                  parent_pid, mode)
    except BrokenPipeError:
        pass  # the worker is gone; nothing to report to
    finally:
        conn.close()


def run_claim(engine_target: str, spec_jsons: list, outputs: list, checkpoint_dirs: list,
              checkpoint_interval: float, conn, cancel_flags, parent_pid: int, mode: str = ONE) -> None:
    """One claim in this process, reported on ``conn`` (see :func:`child_main` for the arguments)."""
    if mode == ENSEMBLE:
        _run_pack(engine_target, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
                  parent_pid)
    elif mode == SEQUENCE:
        _run_sequence(engine_target, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
                      parent_pid)
    else:
        conn.send(_run(engine_target, 0, spec_jsons[0], outputs[0], checkpoint_dirs[0], checkpoint_interval, conn,
                       cancel_flags, parent_pid))


def standby_main(claims, conn, cancel_flags, parent_pid: int, warm_spec_json: Optional[str] = None,
                 threads: Optional[int] = None, engine_targets: tuple = (), claim_promised=None) -> None:
    """Entry point of a standby simulation process: started by the worker before its claim, it pays the
    process's one-off start-up (the engine's imports, numba's targets, on a GPU the driver, the context and
    the kernels of ``warm_spec_json``'s specialisation: engine.driver.simulate.warm_process) while the worker waits
    for work or runs the previous claim, then runs the claims it receives on ``claims`` one after another, as
    :func:`child_main` would, saying ("ready", None, None) after each. ``None`` instead of a claim (or a closed
    pipe): exit. ``engine_targets``: the ``module:function`` entry points its claims call, imported first (a
    non-default engine's too). ``warm_spec_json`` None: nothing is warmed (a non-default engine). ``threads``: as for
    :func:`child_main`. ``claim_promised``: a shared byte with its lock (``multiprocessing.Value``), set by the worker
    when it has decided to send a claim (jobs/worker.py ``_hand_to_standby``): under that lock the standby either sees
    a claim sent or promised and skips the warm-up, or says "warming" before the worker reads what it said."""
    _use_threads(threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _die_with_parent()
    for target in engine_targets:
        try:
            load_callable(target)
        except Exception:  # noqa: BLE001  (a claim that calls it fails with the reason)
            pass
    if warm_spec_json is not None:
        try:
            import engine.driver.ensemble  # noqa: F401  (the pack entry point's imports)
            from engine.driver.simulate import warm_process
            from engine.setup.spec import SimulationSpec

            # a claim already waiting, or promised, gets its own kernels compiled (or loaded) by its run, not the
            # warm spec's first: with an empty kernel cache the default spec's would cost a first job of another
            # specialisation a whole compile, and a GPU pack waits for no warm-up
            with claim_promised.get_lock() if claim_promised is not None else contextlib.nullcontext():
                warm = not claims.poll(0) and not (claim_promised is not None and claim_promised.value)
                if warm:
                    conn.send(("warming", None, None))
            if warm:
                with _tell_when_compiling(conn):
                    warm_process(SimulationSpec.model_validate_json(warm_spec_json))
        except BrokenPipeError:
            pass
        except Exception:  # noqa: BLE001  (a start-up that fails here is paid again, and reported, by the job)
            pass
    try:
        while True:
            conn.send(("ready", None, None))
            claim = claims.recv()
            if claim is None:
                break
            engine_target, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, mode = claim
            run_claim(engine_target, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
                      parent_pid, mode)
    except (EOFError, OSError):   # the worker closed the claims pipe, or is gone (BrokenPipeError)
        pass
    finally:
        claims.close()
        conn.close()


def _tell_when_compiling(conn):
    """A context in which the first numba compilation sends ("compiling", None, None): a standby whose start-up
    compiles (the kernel cache lacked something) will not be ready soon, and the worker does not hold a claim of
    another specialisation for it (jobs/worker.py ``_hand_to_standby``)."""
    from jobs.warm import numba_compiles

    told = threading.Event()

    def tell() -> None:
        if not told.is_set():
            told.set()
            try:
                conn.send(("compiling", None, None))
            except OSError:
                pass

    return numba_compiles(tell)


def _crash_if_test_seed(crash_seed: Optional[str], spec) -> None:
    """TEST HOOK (:data:`TEST_CRASH_ENV`): SIGSEGV this process if ``spec``'s seed is the one named."""
    if crash_seed is not None and crash_seed == str(spec.seed):
        os.kill(os.getpid(), signal.SIGSEGV)


def _hooks(specs: dict, conn, cancel_flags, parent_pid: int):
    """Per-job progress callback and cancel check: progress(k, p), should_cancel(k).

    The engine reports progress at every record (200 times in a default job); a job's report goes to the worker
    when it is its first or its last (fraction 1), when its phase changed, or :data:`PROGRESS_SEND_S` after the
    last one sent (the worker writes the latest to the row at most every DEMQ_PROGRESS_SECONDS anyway)."""
    crash_seed = os.environ.get(TEST_CRASH_ENV)
    sent: dict = {}   # k -> (monotonic time, phase) of the job's last message

    def progress(k: int, p) -> None:
        _crash_if_test_seed(crash_seed, specs[k])
        now = time.monotonic()
        last = sent.get(k)
        if last is not None and last[1] == p.phase and now - last[0] < PROGRESS_SEND_S and p.fraction < 1.0:
            return
        sent[k] = (now, p.phase)
        conn.send(("progress", k, asdict(p)))

    def should_cancel(k: int) -> bool:
        return bool(cancel_flags[k]) or os.getppid() != parent_pid

    return progress, should_cancel


class _PackProgress:
    """A pack's progress reports, gathered: the latest report of each job, sent as one ``progress_many`` message at
    most every :data:`PROGRESS_SEND_S` (and before any job's final message, so a job's last progress precedes its
    end)."""

    def __init__(self, specs: dict, conn):
        self.conn = conn
        self.latest: dict = {}
        self.sent_at = 0.0
        self.crash_seed = os.environ.get(TEST_CRASH_ENV)
        self.specs = specs

    def report(self, k: int, p) -> None:
        _crash_if_test_seed(self.crash_seed, self.specs[k])
        self.latest[k] = p
        if time.monotonic() - self.sent_at >= PROGRESS_SEND_S:
            self.flush()

    def flush(self) -> None:
        if self.latest:
            self.conn.send(("progress_many", None, {k: asdict(p) for k, p in self.latest.items()}))
            self.latest = {}
        self.sent_at = time.monotonic()


def _final(k: Optional[int], outcome) -> tuple:
    """The message that ends job k: its RunSummary, or the exception that ended it."""
    from engine.errors import Cancelled, EngineError

    if isinstance(outcome, Cancelled):
        return ("cancelled", k, str(outcome))
    if isinstance(outcome, EngineError):
        return ("error", k, f"{type(outcome).__name__}: {outcome}")
    if isinstance(outcome, MemoryError):
        return ("error", k, "the simulation ran out of memory (MemoryError); use fewer particles")
    if isinstance(outcome, BaseException):  # an engine bug: report it with its location, the worker goes on
        tb = traceback.extract_tb(outcome.__traceback__)
        where = f" ({os.path.basename(tb[-1].filename)}:{tb[-1].lineno})" if tb else ""
        return ("error", k, f"unexpected {type(outcome).__name__} in the simulation: {outcome}{where}")
    s = outcome
    return ("done", k, {"backend": s.backend, "device": s.device, "loop_s": s.loop_s, "job_wall_s": s.job_wall_s,
                        "cundall": s.cundall,
                        "steps": s.steps, "resumed_from_step": s.resumed_from_step,
                        "ensemble_size": s.extra.get("ensemble_size", 1)})


def _parse(spec_json: str):
    from pydantic import ValidationError

    from engine.setup.spec import SimulationSpec

    try:
        return SimulationSpec.model_validate_json(spec_json)
    except ValidationError as exc:
        return ("error", f"invalid spec: {exc}")


def _run(engine_run, k, spec_json, output, checkpoint_dir, checkpoint_interval, conn, cancel_flags,
         parent_pid) -> tuple:
    """Job k of the claim through ``engine_run`` (engine.driver.simulate.run's signature); its final message."""
    spec = _parse(spec_json)
    if isinstance(spec, tuple):
        return (spec[0], k, spec[1])
    progress, should_cancel = _hooks({k: spec}, conn, cancel_flags, parent_pid)
    try:
        run = load_callable(engine_run)
        s = run(spec, output, progress=lambda p: progress(k, p), should_cancel=lambda: should_cancel(k),
                checkpoint_dir=checkpoint_dir, checkpoint_interval=checkpoint_interval)
    except Exception as exc:
        return _final(k, exc)
    return _final(k, s)


def _run_sequence(engine_run, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
                  parent_pid) -> None:
    """The jobs of a CPU claim one after another through ``engine_run``, in this one process (its imports and
    compiled code serve every job); each job's final message is sent as soon as its run ends. A job whose cancel
    flag is set before its turn is reported cancelled without starting."""
    for k, spec_json in enumerate(spec_jsons):
        if cancel_flags[k] or os.getppid() != parent_pid:
            conn.send(("cancelled", k, "stopped before its run started"))
            continue
        conn.send(("started", k, None))
        conn.send(_run(engine_run, k, spec_json, outputs[k], checkpoint_dirs[k], checkpoint_interval, conn,
                       cancel_flags, parent_pid))


def _run_pack(engine_run_ensemble, spec_jsons, outputs, checkpoint_dirs, checkpoint_interval, conn, cancel_flags,
              parent_pid) -> None:
    """A pack through ``engine_run_ensemble`` (engine.driver.ensemble.run_ensemble's signature); each job's final
    message is sent as soon as its scene ends."""
    specs, index = {}, []
    for k, text in enumerate(spec_jsons):
        spec = _parse(text)
        if isinstance(spec, tuple):
            conn.send((spec[0], k, spec[1]))  # this job fails alone
        else:
            specs[k] = spec
            index.append(k)
    if not index:
        return
    _, should_cancel = _hooks(specs, conn, cancel_flags, parent_pid)
    gathered = _PackProgress(specs, conn)
    sent: set = set()

    def on_result(i: int, outcome) -> None:
        sent.add(index[i])
        gathered.flush()
        conn.send(_final(index[i], outcome))

    try:
        run_ensemble = load_callable(engine_run_ensemble)
        run_ensemble([specs[k] for k in index], [outputs[k] for k in index],
                     progress=lambda i, p: gathered.report(index[i], p),
                     should_cancel=lambda i: should_cancel(index[i]),
                     checkpoint_dirs=[checkpoint_dirs[k] for k in index], checkpoint_interval=checkpoint_interval,
                     on_result=on_result)
    except BrokenPipeError:
        raise
    except Exception as exc:  # the pack as a whole failed: the worker decides what its jobs become
        gathered.flush()
        conn.send(("error", None, _final(None, exc)[2]))
        return
    missing = [k for k in index if k not in sent]
    if missing:
        conn.send(("error", None, f"the ensemble engine ended without a result for job(s) {missing}"))
