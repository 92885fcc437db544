"""Writing many small result files at once, in helper processes (docs/design.md §5).

h5py serialises every call of a process behind one lock, so the result files of a packed GPU ensemble,
which all finish in the same round, are written one after another: about 10 ms each (creating the
observable datasets and the metadata flush of the close), 2.4 s of a 13 s batch of 256 scenes. A scene of
such an ensemble keeps its whole file in memory (``H5MDWriter(deferred=True)``) and at its end hands it to
one of a few writer processes, which write it from scratch with the same writer code, close it and rename
it into place; the files of one round are written in parallel.

The writer processes are plain subprocesses (``python -c "...serve()"``) that read pickled requests on
stdin and answer on stdout; one parent thread per process waits for its answers. Not multiprocessing:
a spawned child re-imports the user's ``__main__`` (and so runs a script without an
``if __name__ == "__main__":`` guard a second time), and fork is unsafe after CUDA and threads started.
A process exits when its stdin closes, i.e. with its parent, however that ends.
"""

from __future__ import annotations

import atexit
import os
import pickle
import struct
import subprocess
import sys
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Optional

#: writer processes at most: one per core up to 16 (the bare files of a 256-scene round took 0.17 s with 8
#: processes and 0.11 s with 16 on the H200 host's 16 cores, 1.0 s in one process)
MAX_PROCESSES = max(1, min(16, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else
                               os.cpu_count() or 1))

_HEADER = struct.Struct("<Q")
_lock = threading.Lock()
_pool: Optional[ThreadPoolExecutor] = None
_procs: list = []
_local = threading.local()


class WriterProcessError(RuntimeError):
    """A writer process ended before it answered (killed, out of memory)."""


class _Proc:
    """One writer subprocess and its pipes (used by one parent thread only)."""

    def __init__(self):
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        self.p = subprocess.Popen([sys.executable, "-c", "from engine.output.h5md_pool import serve; serve()"],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, close_fds=True)
        with _lock:
            _procs.append(self)

    def call(self, fn, args):
        data = pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL)
        try:
            self.p.stdin.write(_HEADER.pack(len(data)))
            self.p.stdin.write(data)
            self.p.stdin.flush()
            head = self.p.stdout.read(_HEADER.size)
            if len(head) < _HEADER.size:
                raise EOFError
            ok, value = pickle.loads(self.p.stdout.read(_HEADER.unpack(head)[0]))
        except (OSError, EOFError, pickle.UnpicklingError) as exc:
            raise WriterProcessError(f"HDF5 writer process {self.p.pid} ended without an answer "
                                     f"(exit code {self.p.poll()})") from exc
        if not ok:
            raise value
        return value

    def close(self) -> None:
        try:
            self.p.stdin.close()
            self.p.wait(timeout=5)
        except Exception:  # noqa: BLE001  (at exit: a stuck child is killed)
            self.p.kill()


def _call(fn, args):
    """Run fn(*args) in this pool thread's writer process (started on first use, restarted if it died)."""
    proc = getattr(_local, "proc", None)
    if proc is None or proc.p.poll() is not None:
        proc = _local.proc = _Proc()
    return proc.call(fn, args)


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=MAX_PROCESSES, thread_name_prefix="demq-h5proc")
        return _pool


def prewarm(n: int = MAX_PROCESSES, ready=None) -> None:
    """Start up to ``n`` writer processes now, without waiting; each runs ``ready()`` (a module-level function
    of the module the later requests need: unpickling it imports that module), so the imports overlap the run."""
    ex = _executor()
    for _ in range(min(n, MAX_PROCESSES)):
        ex.submit(_call, ready or _ping, ())


def submit(fn, *args) -> Future:
    """fn(*args) in a writer process; fn and args must pickle (module-level functions, arrays, dicts)."""
    return _executor().submit(_call, fn, args)


def _ping() -> int:
    return os.getpid()


@atexit.register
def _shutdown() -> None:
    with _lock:
        procs = list(_procs)
        _procs.clear()
    for proc in procs:
        proc.close()


def serve() -> None:
    """The writer process: answer (fn, args) requests until stdin closes (unpickling fn imports its module)."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # anything printed must not corrupt the answers
    while True:
        head = inp.read(_HEADER.size)
        if len(head) < _HEADER.size:
            return
        fn, args = pickle.loads(inp.read(_HEADER.unpack(head)[0]))
        try:
            reply = (True, fn(*args))
        except BaseException as exc:  # noqa: BLE001  (sent back to the caller, raised there)
            reply = (False, exc)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001  (an exception that does not pickle: send its text)
            data = pickle.dumps((False, RuntimeError(repr(reply[1]))), protocol=pickle.HIGHEST_PROTOCOL)
        out.write(_HEADER.pack(len(data)))
        out.write(data)
        out.flush()
