"""Kernel launches at the cost of the driver call, for the time loop's per-step and per-record kernels.

At N = 2M the per-step loop waits on the host: numba-cuda types every argument of every launch in Python
(the type dispatch ``_cuda_call``) and then flattens each array into its pointer, shape and strides. For the
loop's per-step kernels, with 20 to 28 arguments (one a tuple of arrays), that costs more host time per step than
the kernels take on an H100 (docs/performance.md, "GPU: the time loop").

:class:`LaunchCache` keeps, per kernel and set of argument arrays, the flattened argument list that numba-cuda's launch
builds, made once for the first launch with those arrays. A later launch with the same arrays (the same Python objects,
so the same device pointers) only replaces the scalar arguments (n, step, ...) and hands the list to cuda.core's
``launch``, as numba-cuda's own ``_Kernel.launch`` does. Same kernel, same argument values, same stream: the results are
bit-identical (tests/gpu/test_cuda_gpu.py runs both ways). Where it can (``DIRECT``), an entry also holds the argument
list as a parameter array of ctypes values and launches through the driver's ``cuLaunchKernel`` itself, refilling the
scalars in place: cuda.core's launch converts every argument again at every launch. The numba-cuda internals it needs
are engine/numba_support/numba_internals.py's (:func:`engine.numba_support.numba_internals.prepare_launch`).

Not used (every launch goes through numba-cuda) under the CUDA simulator, with ``ENABLED`` False (bench/e2e.py
``--off launch_cache``), for a kernel that is launch-config sensitive, compiled with debug, or has pre-launch
callbacks, or wherever preparing the cached list fails (numba-cuda internals other than those of numba-cuda 0.30:
the first such failure turns the cache off for the process and is recorded in :attr:`LaunchCache.off_reason`).
"""

from __future__ import annotations

import weakref
from collections import OrderedDict

import numpy as np

from engine.loops.cuda_cache import SIM

#: False: every launch goes through numba-cuda's dispatcher (bench/e2e.py --off launch_cache)
ENABLED = True
#: True: a cached launch calls the driver's cuLaunchKernel with a parameter array built once per entry
#: (engine.numba_support.numba_internals.direct_launch) instead of handing the argument list to cuda.core's launch,
#: which converts every one of the 200-odd flattened arguments at every launch (about 20 us of Python a launch; the
#: per-phase loop at 2^20 particles waited on it). False: cuda.core's launch (bench/e2e.py --off direct_launch).
DIRECT = True

_SCALAR = (bool, int, float, np.integer, np.floating, np.bool_)
#: the scalar types the loop passes, recognised by one set lookup (others by isinstance, :func:`_ident`)
_SCALAR_TYPES = frozenset((bool, int, float, np.int32, np.int64, np.float32, np.float64, np.bool_))


def _ident(a):
    """Cache-key part of one argument: the object for arrays (by identity), the type for scalars (whose value
    is filled in per launch), element identities for tuples. (Computed for every argument of every launch: a type
    lookup first, the isinstance checks only for what it does not know.)"""
    t = type(a)
    if t in _SCALAR_TYPES:
        return ("s", t)
    if t is tuple:
        return ("t",) + tuple(map(_ident, a))
    if isinstance(a, _SCALAR):
        return ("s", t)
    if isinstance(a, tuple):
        return ("t",) + tuple(map(_ident, a))
    return id(a)


#: the types of a launch's arguments -> (positions of its scalars, positions of its tuples): made once per combination
#: of types (a call site passes the same types at every launch), so that :func:`_args_key` calls Python per scalar and
#: per tuple only, not per argument
_LAYOUTS: dict = {}


def _args_key(args: tuple) -> tuple:
    """Cache-key part of a launch's arguments: their types, then each one's identity, a scalar's as 0 (its value is
    filled in per launch) and a tuple's element by element (:func:`_ident`). It tells apart what
    ``tuple(map(_ident, args))`` does (a scalar's type is among the types), with builtins mapped over the arguments
    instead of a Python call for each: about half the host time of a launch of the loop's kernels went to that."""
    types = tuple(map(type, args))
    layout = _LAYOUTS.get(types)
    if layout is None:
        kinds = [_ident(a) for a in args]
        layout = _LAYOUTS[types] = (tuple(p for p, k in enumerate(kinds) if type(k) is tuple and k[0] == "s"),
                                    tuple(p for p, k in enumerate(kinds) if type(k) is tuple and k[0] == "t"))
    scalars, tuples = layout
    ids = list(map(id, args))
    for p in scalars:
        ids[p] = 0
    for p in tuples:
        ids[p] = _ident(args[p])
    return types + tuple(ids)


def _weak_arrays(args) -> tuple:
    """Weak references to the non-scalar arguments (tuple elements included); TypeError for an object that
    takes none."""
    out = []
    for a in args:
        if isinstance(a, tuple):
            out.extend(_weak_arrays(a))
        elif not isinstance(a, _SCALAR):
            out.append(weakref.ref(a))
    return tuple(out)


def _alive(entry) -> bool:
    for ref in entry[-1]:
        if ref() is None:
            return False
    return True


class LaunchCache:
    """Cached flattened arguments per (kernel name, dispatcher, launch configuration, argument arrays); at most ``size``
    entries per kernel (the loop alternates between two force buffers). An entry holds weak references to its
    arrays: it keeps no device memory alive (a list reallocated on growth is freed as soon as the backend lets
    it go), and an entry whose array is gone is never used again, even when a new array gets the old one's
    identity; it is dropped at the next miss."""

    def __init__(self, size: int = 4, enabled: bool | None = None):
        self.size = size
        self.enabled = (ENABLED and not SIM) if enabled is None else enabled
        self.off_reason = None if self.enabled else (
            "simulator" if SIM else "engine.loops.cuda_launch.ENABLED is False" if not ENABLED
            else "turned off by the caller")
        self.entries: dict = {}
        self.name_misses: dict = {}
        self.given_up: set = set()
        self.hits = 0
        self.misses = 0
        self.direct = 0         # launches through the entry's direct driver call (DIRECT)
        self.direct_off_reason = None   # why the last entry prepared without one has none

    def launch(self, name: str, dispatcher, config: tuple, args: tuple) -> None:
        """Launch ``dispatcher[config](*args)``, through the cache when possible. config: (grid, block, stream)."""
        if not self.enabled:
            dispatcher[config](*args)
            return
        if name in self.given_up:
            dispatcher[config](*args)
            return
        # the dispatcher is part of the key: a scene that changes its specialisation (a contact law switched on
        # after the thermalisation) launches the new kernel under the same name with the same arrays
        key = (id(dispatcher), config[0], config[1], id(config[2])) + _args_key(args)
        per = self.entries.setdefault(name, OrderedDict())
        entry = per.get(key)
        if entry is not None and not _alive(entry):
            entry = None        # an array of the entry is gone: the identities may now be another array's
        if entry is None:
            entry = self._miss(name, per, key, dispatcher, config, args)
            if entry is None:
                return
        else:
            per.move_to_end(key)
            self.hits += 1
        go = entry[6]
        if callable(go):
            go(args)
            self.direct += 1
            return
        core_launch, stream, launch_config, kernel, kargs, slots = entry[:6]
        for pos, slot, ctype in slots:
            kargs[slot] = ctype(args[pos]) if ctype is not None else args[pos]
        core_launch(stream, launch_config, kernel, *kargs)

    def _miss(self, name: str, per: OrderedDict, key: tuple, dispatcher, config: tuple, args: tuple):
        """A launch with arrays the cache has no entry for. A kernel this process has not launched yet goes through
        numba-cuda (which compiles or loads it and learns its launch-configuration sensitivity) and its entry is
        kept; a kernel already launched is launched through its new entry, which the caller gets (numba-cuda's
        own launch would flatten the same arguments once more: half a millisecond for the loop's kernels). None:
        the launch has happened."""
        self.misses += 1
        self.name_misses[name] = self.name_misses.get(name, 0) + 1
        if self.name_misses[name] > 8 * self.size:   # new arrays at every launch: caching only costs
            self.given_up.add(name)
            per.clear()
            dispatcher[config](*args)
            return None
        first = not dispatcher.overloads      # numba-cuda's compiled kernels of this dispatcher, by signature
        if first:
            dispatcher[config](*args)
        try:
            entry = self._prepare(dispatcher, config, args)
        except Exception as exc:  # numba-cuda internals not as expected: numba-cuda launches from now on
            self.enabled, self.off_reason = False, f"{type(exc).__name__}: {exc}"
            self.entries.clear()
            entry = None
        for old in [k for k, e in per.items() if not _alive(e)]:
            del per[old]
        try:
            if entry is not None:
                if not callable(entry[6]):
                    self.direct_off_reason = entry[6]
                entry = entry[:7] + (dispatcher, _weak_arrays(args))  # (holds the dispatcher's id)
        except TypeError:   # an argument that takes no weak reference: not cached
            entry = None
        if entry is not None:
            per[key] = entry
            if len(per) > self.size:
                per.popitem(last=False)
        if first:               # launched above
            return None
        if entry is None:       # not cacheable: numba-cuda launches it
            dispatcher[config](*args)
        return entry

    @staticmethod
    def _prepare(dispatcher, config: tuple, args: tuple):
        """The cache entry of one launch (engine.numba_support.numba_internals.prepare_launch), or None where the cache
        must not be used for this kernel."""
        from engine.numba_support.numba_internals import prepare_launch

        return prepare_launch(dispatcher, config, args, _SCALAR, direct=DIRECT)
