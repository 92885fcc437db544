"""Which queued jobs a worker packs into one ensemble run (issue 8).

A pack is the job the worker claimed first plus queued jobs, in claim order (priority, then
submission), that are *compatible* with it — same ``shape``, same ``precision`` and the same engine
backend once 'auto' is resolved on this host (engine.backends.ensemble.resolve_backend) — while the pack
holds at most ``DEMQ_ENSEMBLE_MAX_JOBS`` jobs and ``DEMQ_ENSEMBLE_MAX_PARTICLES`` particles. Any mix of
N, φ, e_n, e_t, ξ, dt, t_end, seeds and Verlet skins packs together (a null ``verlet_skin`` is the default
of the pack's one resolved backend, engine.spec.default_verlet_skin, the same as the job run alone there).

A job whose queued row carries the :data:`SOLO` note runs alone: its previous pack's simulation process
died (signal, out of memory) or failed as a whole, so the worker could not tell which job caused it;
alone, the culprit fails by itself and the others complete.
"""

from __future__ import annotations

from typing import Callable, Iterable, Optional

from jobs.store import Job

#: Start of the ``error`` note of a job released from a pack that must run alone next time.
SOLO = "runs alone next: "


def is_solo(job: Job) -> bool:
    return (job.error or "").startswith(SOLO)


class Packer:
    """Pack selection for one worker; caches the backend resolution ('auto' -> 'cuda' or 'cpu')."""

    def __init__(self, max_jobs: int, max_particles: int, resolve: Optional[Callable[[str, str], str]] = None):
        self.max_jobs, self.max_particles = max_jobs, max_particles
        self._resolve = resolve
        self._cache: dict = {}

    def key(self, job: Job) -> Optional[tuple]:
        """(shape, precision, resolved backend) of a job; None if it cannot be packed."""
        spec = job.spec
        if spec.get("list_mode", "auto") in ("cpu-sequential", "cpu-pipelined"):
            return None  # a CPU-built Verlet list serves one scene (paper 004 §3): it runs alone
        try:
            shape, precision, backend = spec["shape"], spec["precision"], spec["backend"]
            resolved = self._cache.get((backend, shape))
            if resolved is None:
                resolved = self._cache[(backend, shape)] = self._resolver()(backend, shape)
        except Exception:  # a spec the engine refuses: it runs (and fails) alone
            return None
        return shape, precision, resolved

    def select(self, first: Job, candidates: Iterable[Job]) -> list[Job]:
        """Jobs of ``candidates`` to pack with ``first`` (which is already claimed), in order."""
        key = self.key(first)
        if key is None or is_solo(first) or self.max_jobs <= 1:
            return []
        particles = int(first.spec.get("n_particles", 0))
        chosen: list[Job] = []
        for job in candidates:
            if len(chosen) + 1 >= self.max_jobs:
                break
            if job.id == first.id or is_solo(job):
                continue
            n = int(job.spec.get("n_particles", 0))
            if particles + n > self.max_particles or self.key(job) != key:
                continue
            chosen.append(job)
            particles += n
        return chosen

    def _resolver(self) -> Callable[[str, str], str]:
        if self._resolve is None:
            from engine.backends.ensemble import resolve_backend
            self._resolve = resolve_backend
        return self._resolve
