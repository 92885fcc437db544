"""Cost limits of a run: the particle-steps and memory a spec may need before it is refused up front.

One place for the defaults and the check, shared by the queue (DEMQ_MAX_PARTICLE_STEPS and
DEMQ_MAX_MEMORY_BYTES, jobs/settings.py; a job over them gets 422 before it is queued) and
``demq run`` (refused the same way unless ``--allow-large``).
"""

from __future__ import annotations

from dataclasses import dataclass

#: Default largest N x steps (cooling plus thermalisation) of one job: about a day of a large GPU run.
DEFAULT_MAX_PARTICLE_STEPS = 1.0e12
#: Default largest estimated memory of one job, bytes.
DEFAULT_MAX_MEMORY_BYTES = 64 * 2**30


@dataclass(frozen=True)
class Excess:
    """One limit a spec exceeds: ``kind`` 'particle_steps' or 'memory_bytes', and a message naming the
    estimate and the limit."""

    kind: str
    message: str


def sci(n: float) -> str:
    """Three significant digits, also for integers too large for a float."""
    try:
        return f"{float(n):.3g}"
    except OverflowError:
        return f"~1e{len(str(int(n))) - 1}"


def cost_excesses(spec, max_particle_steps: float, max_memory_bytes: float,
                  names: tuple[str, str] = ("DEMQ_MAX_PARTICLE_STEPS", "DEMQ_MAX_MEMORY_BYTES")) -> list[Excess]:
    """The limits a (valid) spec exceeds, by :func:`engine.setup.params.estimate_cost`; ``names`` are how the two
    limits are called in the messages. A spec whose step count t_end/dt cannot be computed (it overflows)
    needs unboundedly many particle-steps."""
    from engine.setup.params import estimate_cost      # here: jobs/settings.py reads the defaults without numpy

    try:
        cost = estimate_cost(spec)
    except ArithmeticError:       # t_end / dt overflows, or dt underflows to 0 (a huge stiffness)
        return [Excess("particle_steps", (
            f"the run's number of steps t_end / dt (t_end = {spec.t_end:g} s) is too large to count, "
            f"above the limit {names[0]} = {max_particle_steps:.3g} particle-steps"))]
    out = []
    if cost["particle_steps"] > max_particle_steps:
        out.append(Excess("particle_steps", (
            f"the run needs {sci(cost['particle_steps'])} particle-steps ({spec.n_particles} particles x "
            f"{sci(cost['steps'])} steps), above the limit {names[0]} = {max_particle_steps:.3g}")))
    if cost["memory_bytes"] > max_memory_bytes:
        out.append(Excess("memory_bytes", (
            f"the run needs about {sci(cost['memory_bytes'])} bytes of memory, above the limit "
            f"{names[1]} = {max_memory_bytes:.3g}")))
    return out
