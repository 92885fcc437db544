"""The simulation process: one per job, started by the worker with the ``spawn`` context.

It validates the spec, calls the engine with a progress callback and a cancel check, and reports
to the worker over a pipe, one message each::

    ("progress", {phase, fraction, step, time, eta_s, cundall, wall_s})
    ("done", {backend, device, wall_s, cundall, steps, resumed_from_step})
    ("cancelled", reason)
    ("error", readable message)

If the process dies instead (signal, out of memory), the worker reads its exit code. The process
ignores SIGINT/SIGTERM (the worker decides when it stops: cancel event, then SIGKILL after a grace
period) and dies with the worker: PR_SET_PDEATHSIG on Linux, and the cancel check also stops the run
when the worker is gone.
"""

from __future__ import annotations

import ctypes
import importlib
import os
import signal
import sys
import traceback
from dataclasses import asdict
from typing import Callable

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


def child_main(engine_run: str, spec_json: str, output: str, checkpoint_dir: str,
               checkpoint_interval: float, conn, cancel_event, parent_pid: int) -> None:
    """Entry point of the simulation process (a top-level function, so ``spawn`` can import it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _die_with_parent()
    try:
        conn.send(_run(engine_run, spec_json, output, checkpoint_dir, checkpoint_interval, conn,
                       cancel_event, parent_pid))
    except BrokenPipeError:
        pass  # the worker is gone; nothing to report to
    finally:
        conn.close()


def _run(engine_run, spec_json, output, checkpoint_dir, checkpoint_interval, conn, cancel_event,
         parent_pid) -> tuple:
    from pydantic import ValidationError

    from engine.errors import Cancelled, EngineError
    from engine.spec import SimulationSpec

    try:
        spec = SimulationSpec.model_validate_json(spec_json)
    except ValidationError as exc:
        return ("error", f"invalid spec: {exc}")
    crash_seed = os.environ.get(TEST_CRASH_ENV)

    def progress(p) -> None:
        if crash_seed is not None and crash_seed == str(spec.seed):  # TEST HOOK, see TEST_CRASH_ENV
            os.kill(os.getpid(), signal.SIGSEGV)
        conn.send(("progress", asdict(p)))

    def should_cancel() -> bool:
        return cancel_event.is_set() or os.getppid() != parent_pid

    try:
        run = load_callable(engine_run)
        s = run(spec, output, progress=progress, should_cancel=should_cancel, checkpoint_dir=checkpoint_dir,
                checkpoint_interval=checkpoint_interval)
    except Cancelled as exc:
        return ("cancelled", str(exc))
    except EngineError as exc:
        return ("error", f"{type(exc).__name__}: {exc}")
    except MemoryError:
        return ("error", "the simulation ran out of memory (MemoryError); use fewer particles")
    except Exception as exc:  # an engine bug: report it with its location, the worker goes on
        where = traceback.extract_tb(exc.__traceback__)[-1]
        return ("error", f"unexpected {type(exc).__name__} in the simulation: {exc} "
                         f"({os.path.basename(where.filename)}:{where.lineno})")
    return ("done", {"backend": s.backend, "device": s.device, "wall_s": s.wall_s, "cundall": s.cundall,
                     "steps": s.steps, "resumed_from_step": s.resumed_from_step})
