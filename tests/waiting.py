"""Waiting for events in tests, independent of the machine's speed.

A wait polls a condition until it holds. Its limits only catch hangs, never slowness: it fails when what it
watches (``activity``: job progress, states, files) has not changed for ``stall_s`` seconds, or, for a wait
with nothing to watch, after a ceiling far above any healthy run on a loaded 2-core machine. A slow or busy
machine makes a wait longer, not a failure.
"""

from __future__ import annotations

import time
from typing import Any, Callable

#: Seconds without any change in the watched activity that count as a hang (a cold Numba compile on a loaded
#: 2-core machine shows no progress for a few minutes).
STALL_S = 600.0
#: Seconds after which a wait with nothing to watch counts as a hang.
CEILING_S = 900.0
#: Seconds after which a wait whose activity keeps changing counts as a hang (a livelock).
CEILING_WATCHED_S = 3600.0


def wait_for(cond: Callable[[], Any], what: str, *, activity: Callable[[], Any] | None = None,
             procs: dict | None = None, stall_s: float = STALL_S, ceiling_s: float | None = None,
             poll_s: float = 0.05) -> Any:
    """Poll ``cond`` until it returns something truthy, and return that.

    Fails (AssertionError naming ``what``) as soon as one of ``procs`` (name -> Popen) has exited, when
    ``activity()`` has returned the same value for ``stall_s`` seconds, or after ``ceiling_s`` seconds (default
    CEILING_S, or CEILING_WATCHED_S with an ``activity``)."""
    if ceiling_s is None:
        ceiling_s = CEILING_S if activity is None else CEILING_WATCHED_S
    start = last_change = time.monotonic()
    seen = activity() if activity is not None else None
    while True:
        value = cond()
        if value:
            return value
        for name, p in (procs or {}).items():
            if p.poll() is not None:
                raise AssertionError(f"{name} exited with {p.returncode} while waiting for {what}")
        now = time.monotonic()
        if activity is not None:
            current = activity()
            if current != seen:
                seen, last_change = current, now
            elif now - last_change > stall_s:
                raise AssertionError(f"hung: nothing changed for {stall_s:.0f} s while waiting for {what}")
        if now - start > ceiling_s:
            raise AssertionError(f"hung: {what} not reached after {ceiling_s:.0f} s")
        time.sleep(poll_s)
