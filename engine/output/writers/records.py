"""The records writer: the observables of a record step into the result file, and the energy-rise check of a
dissipative run (engine/output/writers/__init__.py)."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from engine.errors import InstabilityError
from engine.output.writers.triggers import Periodic
from engine.physics.sonine import sonine_observables

#: In a dissipative run the total mechanical energy may not rise between records by more than this
#: fraction (integration error is O(dt^2) ~ 1e-4 at dt = t_c/50; a real rise means instability).
ENERGY_RISE_TOLERANCE = 1e-2


def record(obs: dict, n: int) -> dict:
    """Observables written every record (temperatures per degree of freedom, J).

    Ellipsoids: T_rot counts the two rotational degrees of freedom that exchange energy (about the
    axes perpendicular to the symmetry axis), T_rot = E_rot,perp / N (Rubio-Largo et al. 2015, Eq. 25b as corrected in
    docs/physics.md §2.7); kinetic_energy_rotational stays the total.

    Velocity-distribution shape (docs/physics.md §6.5), dimensionless, where the backend reports the energy moments:
    ``sonine_a2_translational`` (a2 of the translational energies, d = 3), ``sonine_a2_rotational`` (of the
    rotational energies: spheres d = 3, spheroids the 2 active dof) and ``sonine_a11`` (the cross cumulant
    <e_tr e_rot>/(<e_tr><e_rot>) - 1), all from engine/physics/sonine.py (energy form, lab frame = centre-of-mass
    frame; 0 where the energy of those dof is zero). O(1) host work per record: the moments are per-scene sums
    of the observe kernel.
    """
    if "kinetic_energy_rotational_active" in obs:
        t_rot = 2.0 * obs["kinetic_energy_rotational_active"] / (obs.get("rotational_dof", 2) * n)
    else:
        t_rot = 2.0 * obs["kinetic_energy_rotational"] / (3.0 * n)
    return {
        "kinetic_energy_translational": obs["kinetic_energy_translational"],
        "kinetic_energy_rotational": obs["kinetic_energy_rotational"],
        "temperature_translational": 2.0 * obs["kinetic_energy_translational"] / (3.0 * n),
        "temperature_rotational": t_rot,
        "contacts": np.int64(obs["contacts"]),
        "elastic_energy": obs["elastic_energy"],
        "max_overlap": obs["max_overlap"],
        **sonine_observables(obs, n),
        # contacts begun since the scene started, thermalisation included (spheres; the collisions observable)
        **({"collisions": np.int64(obs["collisions"])} if "collisions" in obs else {}),
    }


class RecordWriter:
    """Writes the record of every record step (trigger: every ``output_every`` steps of the cooling run and its
    last step) and checks that a dissipative run's total energy (kinetic + elastic, J) did not rise since the
    lowest earlier record by more than ENERGY_RISE_TOLERANCE (InstabilityError naming the step otherwise)."""

    def __init__(self, p, n: int, dissipative: bool, prev_energy: Optional[float] = None):
        self.p, self.n, self.dissipative = p, n, dissipative
        self.trigger = Periodic(max(1, p.output_every), p.n_steps)
        #: the lowest total energy recorded so far (J; inf before the first record); checkpoints keep it
        self.prev_energy = math.inf if prev_energy is None else prev_energy

    def write(self, writer, step_done: int, t_sim: float, obs: dict) -> None:
        """The record of ``step_done`` (when the trigger fires there) into ``writer``, then the energy check."""
        if not self.trigger(step_done):
            return
        p = self.p
        writer.observables(step_done, t_sim, record(obs, self.n))
        energy = obs["kinetic_energy_translational"] + obs["kinetic_energy_rotational"] + obs["elastic_energy"]
        if self.dissipative and energy > self.prev_energy * (1.0 + ENERGY_RISE_TOLERANCE):
            raise InstabilityError(
                f"total energy rose by {100 * (energy / self.prev_energy - 1):.3g} % by step {step_done} "
                f"(t = {t_sim:.4g} s) in a dissipative run: likely cause: a time step too large "
                f"(dt = {p.dt:.3g} s, contact time {p.contact_time:.3g} s) or overlaps too deep",
                step=step_done)
        self.prev_energy = min(self.prev_energy, energy)
