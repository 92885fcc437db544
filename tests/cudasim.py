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
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_ANCHOR = "livethreads = set([t for t in livethreads if t.is_alive()])"
_SLEEP = "if livethreads and livethreads != blockedthreads: __demq_sleep(1e-5)"


def child_env() -> dict:
    """Environment of a simulator child: the simulator on, this checkout first on the path."""
    return {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}


def fast_block_polling() -> bool:
    """Let the simulator's block manager sleep 10 us per polling round while a thread runs; True if patched."""
    import inspect
    import textwrap
    import time

    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1", "only for the CUDA simulator"
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
