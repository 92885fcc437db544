"""Admission by backend: a spec that asks for ``backend: "cuda"`` is accepted only while a worker that can
run CUDA is registered and alive (the worker table, jobs/store.py ``live_workers``); otherwise it would
wait in the queue and then fail with BackendUnavailable. ``auto`` and ``cpu`` run on any worker. A CUDA sphere
spec whose predicted device memory (engine/loops/cuda_memory.py) exceeds the largest live GPU worker's is refused
the same way, naming the estimate and the largest n_particles that fits.

A worker counts as alive when it was seen within one lease (DEMQ_LEASE_SECONDS): the same time after
which the reaper gives a lost worker's jobs back to the queue.
"""

from __future__ import annotations

from typing import Iterable, Optional, Sequence

from engine.setup.spec import SimulationSpec
from jobs.settings import Settings
from jobs.specs import SpecRejected
from jobs.store import JobStore

#: Backends a spec may name that only some workers can run.
WORKER_BACKENDS = ("cuda",)


def check_backends(store: JobStore, settings: Settings, specs: Sequence[SimulationSpec],
                   locs: Iterable[list]) -> None:
    """Refuse specs whose backend no live worker runs: :class:`SpecRejected` (422) with one error per spec
    at ``loc + ['backend']``."""
    wanted = [(spec, loc) for spec, loc in zip(specs, locs) if spec.backend in WORKER_BACKENDS]
    if not wanted:
        return
    live = store.live_workers(max_age_s=settings.lease_s)
    available = {b for w in live for b in w.backends}
    errors = [{"loc": [*loc, "backend"], "type": "backend_unavailable", "msg": (
        f"backend = {spec.backend!r} cannot run: no live worker can run {spec.backend.upper()} "
        f"({len(live)} worker(s) seen in the last {settings.lease_s:g} s, none with {spec.backend}); use "
        f"'auto' or 'cpu', or start a worker on a host with a GPU")}
        for spec, loc in wanted if spec.backend not in available]
    if errors:
        raise SpecRejected(errors)
    errors = [{"loc": [*loc, "n_particles"], "type": "device_memory", "msg": why}
              for spec, loc in wanted if (why := _device_memory_refusal(spec, live)) is not None]
    if errors:
        raise SpecRejected(errors)


def _device_memory_refusal(spec: SimulationSpec, live) -> Optional[str]:
    """Why a CUDA sphere spec fits no live GPU worker's device (engine/loops/cuda_memory.py, the prediction a
    worker's run checks again against its free memory), or None: it fits the largest, or some CUDA worker's memory
    is not known."""
    sizes = [w.device_memory for w in live if spec.backend in w.backends]
    if spec.shape != "sphere" or not sizes or any(b is None for b in sizes):
        return None
    from engine.loops.cuda_memory import memory_refusal
    from engine.setup.params import derive      # a null verlet_skin is CUDA's default: spec.backend is 'cuda'

    why = memory_refusal(spec, derive(spec), max(sizes), "the largest GPU of the live workers", derive,
                         reads_state=True)
    return None if why is None else f"{why} (its total memory)"
