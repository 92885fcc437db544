"""Which queued jobs a worker claims together, and how the claim runs (docs/design.md §7).

A claim is the job the worker claimed first plus queued jobs, in claim order (priority, then submission), that
can go with it, up to a size the worker gives (DEMQ_ENSEMBLE_MAX_JOBS, and its fair share of the queue:
jobs/worker.py). How a claim of several jobs runs depends on the backend its jobs resolve to on this host
(engine.backends.ensemble.resolve_backend):

- ``sequence`` (the CPU, DEMQ_CPU_PACKS=sequence, the default): the jobs run one after another in one warm
  simulation process, each through the engine alone, the cheapest first (estimated particle-steps N x steps,
  :func:`particle_steps`; a higher priority still goes first), so a job's latency is close to its own run time
  plus the runs of the cheaper jobs before it. Any CPU job goes with any other (shape, precision and memory do
  not matter: one scene is in memory at a time).
- ``ensemble`` (the GPU; the CPU with DEMQ_CPU_PACKS=ensemble): the jobs run as one ensemble
  (engine.driver.ensemble.run_ensemble), which needs the same ``shape``, ``precision`` and resolved backend, at most
  ``DEMQ_ENSEMBLE_MAX_PARTICLES`` particles together, and — so that a small job does not wait in a pack of large
  ones — an estimated cost within a factor DEMQ_ENSEMBLE_COST_RATIO (default :data:`COST_RATIO`) of the first
  job's. Any mix of N, φ, e_n, e_t, ξ,
  dt, t_end, seeds and Verlet skins packs together (a null ``verlet_skin`` is the default of the pack's one
  resolved backend, engine.setup.params.default_verlet_skin, the same as the job run alone there). A scene that ends
  leaves the pack at once; its job ends then.

A job whose queued row carries the :data:`SOLO` note runs alone: its previous pack's simulation process
died (signal, out of memory) or failed as a whole, so the worker could not tell which job caused it;
alone, the culprit fails by itself and the others complete.
"""

from __future__ import annotations

import math
from typing import Callable, Iterable, Optional

from jobs.store import Job

#: Start of the ``error`` note of a job released from a pack that must run alone next time.
SOLO = "runs alone next: "

#: How a claim of several jobs runs (see the module docstring); a claim of one job runs alone ("one").
SEQUENCE, ENSEMBLE, ONE = "sequence", "ensemble", "one"
CPU_PACK_MODES = (SEQUENCE, ENSEMBLE)

#: An ensemble pack holds jobs whose estimated particle-steps are within this factor of the first job's (a scene
#: of a quarter of the cost waits at most for about four times its own run; one of four times the cost runs
#: in a pack that is four times shorter than itself, with no job waiting on it for long).
COST_RATIO = 4.0


def is_solo(job: Job) -> bool:
    return (job.error or "").startswith(SOLO)


def particle_steps(job: Job) -> float:
    """Estimated particle-steps N x (thermalisation + cooling steps) of a job (engine.setup.params.estimate_cost): the
    measure of its run time at a given Cundall number. 0 for a spec the engine refuses (it fails at once)."""
    from engine.setup.params import estimate_cost
    from engine.setup.spec import SimulationSpec

    try:
        return float(estimate_cost(SimulationSpec.model_validate(job.spec))["particle_steps"])
    except Exception:  # noqa: BLE001  (an invalid spec: its job fails at its start, in no time)
        return 0.0


def sequence_order(jobs: list[Job]) -> list[Job]:
    """The order a ``sequence`` claim runs its jobs: higher priority first, then the cheapest, then claim order."""
    costs = {j.id: particle_steps(j) for j in jobs}
    return sorted(jobs, key=lambda j: (-j.priority, costs[j.id]))


class Packer:
    """Claim selection for one worker; caches the backend resolution ('auto' -> 'cuda' or 'cpu')."""

    def __init__(self, max_jobs: int, max_particles: int, resolve: Optional[Callable[[str, str], str]] = None,
                 cpu_mode: str = SEQUENCE, cost_ratio: float = COST_RATIO):
        if cpu_mode not in CPU_PACK_MODES:
            raise ValueError(f"cpu_mode = {cpu_mode!r} must be one of {', '.join(CPU_PACK_MODES)}")
        self.max_jobs, self.max_particles = max_jobs, max_particles
        self.cpu_mode, self.cost_ratio = cpu_mode, cost_ratio
        self._resolve = resolve
        self._cache: dict = {}

    def key(self, job: Job) -> Optional[tuple]:
        """(shape, precision, resolved backend) of a job; None if it cannot be packed."""
        spec = job.spec
        if spec.get("list_mode", "auto") in ("cpu-sequential", "cpu-pipelined"):
            return None  # a CPU-built Verlet list serves one scene (Skorych & Dosta 2022, §3): it runs alone
        try:
            shape, precision, backend = spec["shape"], spec["precision"], spec["backend"]
            resolved = self.resolve(backend, shape)
        except Exception:  # a spec the engine refuses: it runs (and fails) alone
            return None
        return shape, precision, resolved

    def backend(self, job: Job) -> Optional[str]:
        """The backend ('cpu' or 'cuda') a job resolves to here; None if it cannot be packed."""
        key = self.key(job)
        return None if key is None else key[2]

    def mode(self, jobs: list[Job]) -> str:
        """How a claim of these jobs runs: ``one``, ``sequence`` or ``ensemble`` (module docstring)."""
        if len(jobs) == 1:
            return ONE
        return SEQUENCE if self.backend(jobs[0]) == "cpu" and self.cpu_mode == SEQUENCE else ENSEMBLE

    def select(self, first: Job, candidates: Iterable[Job], max_jobs: Optional[int] = None) -> list[Job]:
        """Jobs of ``candidates`` to claim with ``first`` (which is already claimed), in order; the claim holds
        at most ``max_jobs`` jobs (and never more than the packer's ``max_jobs``)."""
        limit = self.max_jobs if max_jobs is None else min(self.max_jobs, max_jobs)
        key = self.key(first)
        if key is None or is_solo(first) or limit <= 1:
            return []
        sequence = key[2] == "cpu" and self.cpu_mode == SEQUENCE
        particles = int(first.spec.get("n_particles", 0))
        cost = particle_steps(first)
        low, high = cost / self.cost_ratio, cost * self.cost_ratio
        chosen: list[Job] = []
        for job in candidates:
            if len(chosen) + 1 >= limit:
                break
            if job.id == first.id or is_solo(job):
                continue
            if sequence:
                if self.backend(job) != "cpu":
                    continue
            else:
                n = int(job.spec.get("n_particles", 0))
                if particles + n > self.max_particles or self.key(job) != key:
                    continue
                if not low <= particle_steps(job) <= high:
                    continue
                particles += n
            chosen.append(job)
        return chosen

    def resolve(self, backend: str, shape: str) -> str:
        """'auto', 'cpu' or 'cuda' resolved on this host (cached)."""
        resolved = self._cache.get((backend, shape))
        if resolved is None:
            resolved = self._cache[(backend, shape)] = self._resolver()(backend, shape)
        return resolved

    def _resolver(self) -> Callable[[str, str], str]:
        if self._resolve is None:
            from engine.backends.ensemble import resolve_backend
            self._resolve = resolve_backend
        return self._resolve


def fair_share(queued: int, live_workers: int) -> int:
    """The most jobs one worker claims at once while ``live_workers`` workers (itself included) can run them:
    ceil(queued / live_workers), at least 1."""
    return max(1, math.ceil(queued / max(1, live_workers)))
