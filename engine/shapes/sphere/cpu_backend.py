"""The sphere's CPU host class: :class:`CpuBackend`, the sphere plug-in (engine/shapes/sphere/kernels.py) in the
shared CPU machinery (engine/loops/cpu.py: CpuLoop, make_run_steps).

Owns only what is the sphere's own on the host: its state arrays in the working precision (positions in the
position precision, engine/setup/precision.py; space-frame angular
velocity, radius, scalar inertia), the smooth/rough/Coulomb/orientation specialisation of the pair law
(``_law``, ``_torque_arg``, ``_quat_arg``: None switches a part off at compile time), the start-overlap error
and the observables (engine.shapes.sphere.kernels.observe). Cells, lists, slot store, time loop and error
handling are CpuLoop's.
"""

from __future__ import annotations

import math

import numpy as np

import engine.numba_support.jitcache  # noqa: F401  (before any cache=True kernel: keys the disk cache by source)

from engine.loops.system import ContactParams, SphereSystem
from engine.loops.cpu import CpuLoop
from engine.loops.cpu_shared import collect_springs, restore_springs, worst_overlap
from engine.errors import InstabilityError
from engine.physics.sonine import DOF_ROTATION_SPHERE, sonine_sums
from engine.setup.precision import position_dtype, state_dtype
from engine.shapes.sphere import kernels as sphere


class CpuBackend(CpuLoop):
    """The CPU time loop for spheres (engine/shapes/sphere/kernels.py); see engine/loops/cpu.py for layout and
    specialisation."""

    shape = sphere

    def __init__(self, system: SphereSystem, contact: ContactParams):
        self.dtype = dt_ = state_dtype(contact.precision)
        self.pos_dtype = position_dtype(contact.precision)
        n = system.n
        self.n = n
        self.box = float(system.box_length)
        self.pos = np.array(system.position, dtype=self.pos_dtype, order="C", copy=True)
        self.vel = np.array(system.velocity, dtype=dt_, order="C", copy=True)
        self.omega = np.array(system.angular_velocity, dtype=dt_, order="C", copy=True)
        self._quat = np.array(system.orientation, dtype=dt_, order="C", copy=True)
        self.radius = np.array(system.radius, dtype=dt_, order="C", copy=True)
        self.mass = np.array(system.mass, dtype=dt_, order="C", copy=True)
        self.inertia = np.array(system.inertia, dtype=dt_, order="C", copy=True)
        self.inv_m = (1.0 / self.mass).astype(dt_)
        self.inv_i = (1.0 / self.inertia).astype(dt_)
        self.force = np.zeros((n, 3), dt_)
        self.torque = np.zeros((n, 3), dt_)
        self.x_ref = self.pos.copy()
        self.vel_p = self.vel.copy()      # predicted end-of-step velocities (see shapes/sphere.kick_drift)
        self._rad_list = self.radius
        # ext: the step (counted from the last full settle, engine/loops/cpu.py make_run_steps) from which each
        # sphere's orientation turns are pending (shapes/sphere/kernels.py rotate/settle)
        self._lag = np.zeros(n, np.int64)
        # ... and the contacts each sphere has begun (the collisions observable)
        self.begun = np.zeros(n, np.int64)
        self._spin, self._spin_inv, self._ext = self.omega, self.inv_i, (self._lag, self.begun)
        self._init_loop(n, float(np.max(system.radius)) if n else 0.0,
                        float(np.min(system.radius)) if n else 0.0, contact.skin)
        self.set_contact(contact)
        self._prime(system)

    @property
    def quat(self) -> np.ndarray:
        """The orientations (N, 4) brought up to date, as a new array (the time loop leaves free spheres' turns
        pending). The loop's own turns stay pending: a read — a snapshot, or a checkpoint taken on the wall clock —
        never changes the bits of the trajectory that follows."""
        if self.pending_turns[0] <= 0 or self._quat_arg is None:
            return self._quat.copy()
        kept = self._quat.copy(), self._lag.copy(), self.pending_turns.copy()
        self.settle_orientations()
        settled = self._quat.copy()
        self._quat[:], self._lag[:], self.pending_turns[:] = kept
        return settled

    def set_contact(self, contact: ContactParams) -> None:
        """Switch contact constants (e.g. thermalisation -> cooling); keeps lists and springs."""
        if hasattr(self, "contact"):
            self.settle_orientations()    # under the old switches: nothing left pending
        self._set_common(contact)
        c = self.dtype
        self.k_t = None if contact.k_t is None else c(contact.k_t)
        self.mu = None if contact.friction is None else c(contact.friction)
        self._law = (self.k_t, self.mu)
        self._torque_arg = self.torque if contact.rough else None
        self._quat_arg = self._quat if contact.orientation else None

    def _prime(self, system: SphereSystem) -> None:
        """First list build (restoring checkpointed springs) and forces at t = 0."""
        self._build()
        if system.contact_pairs is not None and len(system.contact_pairs):
            restore_springs(self.nbr, self.nn, self.hist, np.asarray(system.contact_pairs, np.int64),
                            np.asarray(system.contact_springs, self.dtype))
        self._forces()
        worst, who = worst_overlap(self.chunk_a, self.chunk_b)
        if worst > self.overlap_limit:
            raise _start_overlap(self, int(who), float(worst))


    # ---- host copies (output steps only) -----------------------------------------------------------

    def observe(self) -> dict:
        k_t = 0.0 if self.k_t is None else float(self.k_t)
        e_tr, e_rot, contacts, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x = sphere.observe(
            self.pos, self.vel, self.omega, self.radius, self.mass, self.inertia, self.nbr, self.nn,
            self.hist, self.box_c, self.inv_box, self.half, float(self.k_n), k_t)
        return {"kinetic_energy_translational": float(e_tr), "kinetic_energy_rotational": float(e_rot),
                "contacts": int(contacts), "elastic_energy": float(e_spring), "max_overlap": float(worst),
                "momentum": (float(px), float(py), float(pz)), "collisions": int(self.begun.sum()) // 2,
                **sonine_sums(s_tr2, s_rot2, s_x, DOF_ROTATION_SPHERE)}

    def state(self, reuse=False) -> dict:
        """Copies of the state arrays in id order (``reuse`` is ignored: every call returns new arrays)."""
        return {"position": self.pos.copy(), "velocity": self.vel.copy(),
                "angular_velocity": self.omega.copy(), "orientation": self.quat}

    def contacts(self):
        """(pairs (M,2) int64 ids, slots (M,5)) of the list slots in contact, for checkpoints.

        A slot holds the tangential spring (3), the overlap and the dashpot force of the last step.
        """
        return collect_springs(self.pos, self.radius, self.nbr, self.nn, self.hist, self.box_c,
                               self.inv_box, self.half)


def _start_overlap(backend, who: int, worst: float) -> InstabilityError:
    """The initial positions already overlap beyond the limit: name the deepest pair."""
    pos, rad = backend.pos.astype(np.float64), backend.radius.astype(np.float64)
    partner, depth = -1, -math.inf
    for j in backend.nbr[who, :backend.nn[who]]:
        r = pos[who] - pos[j]
        r -= backend.box * np.round(r / backend.box)
        ov = (rad[who] + rad[j] - math.sqrt(float(r @ r))) / min(rad[who], rad[j])
        if ov > depth:
            partner, depth = int(j), ov
    coincident = " (coincident centres)" if depth >= 2.0 - 1e-12 else ""
    return InstabilityError(
        f"particles {who} and {partner} overlap by {worst:.3g} radii{coincident} at the start (step 0), "
        f"above overlap_limit {backend.overlap_limit:g}: the initial positions overlap; place the particles "
        f"apart", step=0, particle=who)
