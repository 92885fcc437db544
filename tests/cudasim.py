"""Child processes that run the CUDA kernels under the Numba CUDA simulator (CI has no GPU).

The simulator must be switched on before numba.cuda is first imported, and other tests in the same pytest
process may import it first, so each simulator check runs in a child process started with ``child_env()``;
the child calls ``fast_block_polling()`` before it launches a kernel.

Why ``fast_block_polling``: the simulator runs every CUDA thread of a block as a Python thread and its
BlockManager.run polls them (``is_alive`` on each, in a loop that never blocks) until they are all done. That
loop competes for the GIL with the very threads it waits for, so about half the time of a kernel launch went
to polling (measured: 40 spheres x 30 steps took 9.6-13 s, 3.9-4.2 s with the sleep). The patch adds one
short sleep per polling round while some thread is still running, nothing else: the threads, the
syncthreads barriers, the order of the checks and the exception handling are the simulator's own code
(the patched function is compiled from the installed simulator's source with the one line inserted). If the
installed simulator's loop does not have the expected line, nothing is patched (stock speed, same results).

``fast_block_polling`` first calls ``atomic_shared_arrays``: the simulator gives a ``cuda.shared.array`` line one
array per launch, made by the first thread that reaches it: it looks the line up, and when it is not there makes an
``np.empty`` array and stores it, and that look-up and store are two steps. A thread that takes the GIL between
them (the interpreter switches threads every 5 ms, more often on a busy machine) makes and keeps an array of its
own, which the other threads never write: in block 0 of ``tile_scan`` it read another thread's count from its own
uninitialised array and stored a heap address as an int32 row offset ("OverflowError: tid=[7,0,0] ctaid=[0,0,0]:
Python integer 140434626053834 out of bounds for int32", once in five CI runs of the children of
tests/engine/test_lent_scratch_simulator.py side by side); a float64 block maximum can be wrong without an error.
The patch makes the look-up and store one ``dict.setdefault`` (atomic under the GIL), nothing else; if the
installed simulator does not have the expected line, nothing is patched.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_ANCHOR = "livethreads = set([t for t in livethreads if t.is_alive()])"
_SLEEP = "if livethreads and livethreads != blockedthreads: __demq_sleep(1e-5)"
_SHARED_ANCHOR = "res = self._allocations.get(caller)"
_SHARED_ONCE = "res = self._allocations.setdefault(caller, np.empty(shape, dtype))"


def child_env() -> dict:
    """Environment of a simulator child: the simulator on, this checkout first on the path."""
    return {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}


def atomic_shared_arrays() -> bool:
    """Let every thread of a launch get the same array at a ``cuda.shared.array`` line: the simulator's look-up and
    store of the line's array made one ``dict.setdefault`` (module docstring); True if patched."""
    import inspect
    import textwrap

    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1", "only for the CUDA simulator"
    from numba.cuda.simulator import kernelapi as K

    array = K.FakeCUDAShared.array
    if getattr(array, "__demq_atomic__", False):
        return True
    lines = textwrap.dedent(inspect.getsource(array)).splitlines()
    hits = [i for i, line in enumerate(lines) if line.strip() == _SHARED_ANCHOR]
    if len(hits) != 1:
        return False
    line = lines[hits[0]]
    lines[hits[0]] = line[: len(line) - len(line.lstrip())] + _SHARED_ONCE   # (the `if res is None` below: dead)
    ns = dict(vars(K))
    exec(compile("\n".join(lines) + "\n", K.__file__, "exec"), ns)
    patched = ns["array"]
    patched.__demq_atomic__ = True
    K.FakeCUDAShared.array = patched
    return True


def fast_block_polling() -> bool:
    """Let the simulator's block manager sleep 10 us per polling round while a thread runs; True if patched. Makes
    the simulator's shared arrays one per launch first (:func:`atomic_shared_arrays`)."""
    import inspect
    import textwrap
    import time

    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1", "only for the CUDA simulator"
    atomic_shared_arrays()
    from numba.cuda.simulator import kernel as K

    run = K.BlockManager.run
    if getattr(run, "__demq_fast_polling__", False):
        return True
    src = textwrap.dedent(inspect.getsource(run))
    lines = src.splitlines()
    hits = [i for i, line in enumerate(lines) if line.strip() == _ANCHOR]
    if len(hits) != 1:
        return False
    indent = lines[hits[0]][: len(lines[hits[0]]) - len(lines[hits[0]].lstrip())]
    lines.insert(hits[0] + 1, indent + _SLEEP)
    ns = dict(vars(K))
    ns["__demq_sleep"] = time.sleep
    exec(compile("\n".join(lines) + "\n", K.__file__, "exec"), ns)
    patched = ns["run"]
    patched.__demq_fast_polling__ = True
    K.BlockManager.run = patched
    return True


def run_children(commands: dict, timeout: float) -> dict:
    """Run ``python *args`` for every {part: args} of ``commands`` in simulator children, all at the same time,
    and wait for all of them; returns {part: (exit status, stdout, stderr)}. A simulator child is one
    single-threaded Python process while the pytest process only waits for it, so the independent parts of
    one check use both cores of the CI machine.
    """
    import subprocess
    import sys
    import tempfile
    import time

    procs = {}
    try:
        for part, args in commands.items():
            out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
            p = subprocess.Popen([sys.executable, *map(str, args)], env=child_env(), cwd=ROOT, stdout=out,
                                 stderr=err, text=True)
            procs[part] = (p, out, err)
        end = time.monotonic() + timeout
        res = {}
        for part, (p, out, err) in procs.items():
            rc = p.wait(timeout=max(1.0, end - time.monotonic()))
            out.seek(0)
            err.seek(0)
            res[part] = (rc, out.read(), err.read())
        return res
    finally:
        for p, out, err in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
            out.close()
            err.close()


def kept_ensembles() -> list:
    """The CUDA ensembles made in this process from now on, in the list returned (engine.loops.cuda_ensemble
    ``CudaEnsembleBase.__init__`` patched to append each), for a test that reads an ensemble's counters or arrays
    after ``engine.run`` made and dropped it."""
    from engine.loops import cuda_ensemble

    kept = []
    init = cuda_ensemble.CudaEnsembleBase.__init__

    def keep(self, *a, **k):
        kept.append(self)
        init(self, *a, **k)

    cuda_ensemble.CudaEnsembleBase.__init__ = keep
    return kept
