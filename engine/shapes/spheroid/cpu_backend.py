"""CPU backend for ellipsoids (Rubio-Largo et al. 2015; frictionless, or rough with the tangential law
of docs/physics.md §2.5): the spheroid plug-in (engine/shapes/spheroid/kernels.py) in the shared CPU machinery
(engine/loops/cpu.py: CpuLoop, make_run_steps), with the same interface as CpuBackend.

This module holds only what is the ellipsoid's own on the host side: the state it keeps (angular momentum L
instead of the angular velocity, semi-axes, bounding radii, the state before the step for the screens), the
Perram-Wertheim tolerances, the observables (engine.shapes.spheroid.kernels.observe) and the conversions between L and
the angular velocity. Cells, the Verlet list of bounding spheres, its slot store, the time loop and its error handling
are the shared ones; the contact, force law and rotation step are the plug-in's (its docstring has the details:
broad phase, exact screens, lower id as "A", Fincham's leap-frog on L).
"""

from __future__ import annotations

import numba
import numpy as np

from engine.numba_support.jitcache import fast_loads  # before any cache=True kernel: keys the disk cache by source

from engine.loops.system import ContactParams, EllipsoidSystem
from engine.loops.cpu import CpuLoop
from engine.loops.cpu_shared import SLOT, collect_springs, restore_springs
from engine.setup.params import Q_SPHERE
from engine.physics.rotation import angular_momentum, quat_unit, space_omega
from engine.physics.sonine import DOF_ROTATION_SPHERE, DOF_ROTATION_SPHEROID, sonine_sums
from engine.setup.precision import check_shape, state_dtype
from engine.shapes.spheroid import kernels as spheroid

#: history words per list slot of a rough contact: spring (3), overlap, dashpot force, the contact's k_t
SLOT_ROUGH = SLOT + 1

def rotational_dof(rough: bool) -> int:
    """Rotational dof that exchange energy in collisions: 2 for frictionless spheroids (no torque about the
    symmetry axis), 3 for rough ones."""
    return DOF_ROTATION_SPHERE if rough else DOF_ROTATION_SPHEROID


def tangential_factor_of(k_t: float, k_n: float) -> float:
    """f = (arccos(-e_t)/pi)^2 of Hidalgo et al. (2013) Eq. 4
    from the sphere-convention k_t = k_n f q/(1 + q) (q = 2/5)."""
    return k_t * (1.0 + Q_SPHERE) / (Q_SPHERE * k_n)


#: Newton tolerance on the Perram-Wertheim lambda per precision (docs/performance.md).
PW_TOL = {"float64": 1e-15, "float32": 1e-7}
#: relative margin of the exact disjointness screens before/inside the Perram-Wertheim solve
#: (engine.physics.ellipsoid.ellipsoid_contact_screened; far above the rounding of F in each precision, so the
#: screens change no result: tests/engine/test_ellipsoid_screen.py); a negative value disables them
PW_SCREEN = {"float64": 1e-9, "float32": 1e-3}


# per particle and independent of the others: parallel loops (2M ellipsoids: the GPU ensemble's set-up and every
# snapshot's host copy take them too)
@numba.njit(cache=True, parallel=True)
def omega_from_angm(quat, angm, inv_i, half, out):
    for i in numba.prange(quat.shape[0]):
        w = space_omega(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], angm[i, 0], angm[i, 1], angm[i, 2],
                        inv_i[i, 0], inv_i[i, 1], inv_i[i, 2], half)
        out[i, 0] = w[0]
        out[i, 1] = w[1]
        out[i, 2] = w[2]


@numba.njit(cache=True, parallel=True)
def unit_quaternions(orient, out):
    """``out`` (in its own precision) = each row of the float64 ``orient`` over its norm (quat_unit: NumPy's
    ``orient / np.linalg.norm(orient, axis=1)[:, None]`` bit for bit, tests/engine/test_time_to_result.py)."""
    for i in numba.prange(orient.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = quat_unit(orient[i, 0], orient[i, 1], orient[i, 2], orient[i, 3])


@numba.njit(cache=True, parallel=True)
def angm_from_omega(quat, omega, inertia, half, out):
    for i in numba.prange(quat.shape[0]):
        L = angular_momentum(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], omega[i, 0], omega[i, 1],
                             omega[i, 2], inertia[i, 0], inertia[i, 1], inertia[i, 2], half)
        out[i, 0] = L[0]
        out[i, 1] = L[1]
        out[i, 2] = L[2]


class CpuEllipsoidBackend(CpuLoop):
    """The CPU time loop for ellipsoids (engine/shapes/spheroid/kernels.py); interface of
    :class:`engine.shapes.sphere.cpu_backend.CpuBackend`."""

    shape = spheroid

    def __init__(self, system: EllipsoidSystem, contact: ContactParams):
        self.rough = contact.rough
        self.slot_words = SLOT_ROUGH if self.rough else SLOT
        check_shape(contact.precision, spheroid.NAME)
        self.dtype = state_dtype(contact.precision)
        dt_ = self.dtype
        n = system.n
        self.n = n
        self.box = float(system.box_length)

        def arr(x):
            return np.array(x, dtype=dt_, order="C", copy=True)

        self.pos = arr(system.position)
        self.vel = arr(system.velocity)
        self.quat = np.empty((n, 4), dt_)
        unit_quaternions(np.ascontiguousarray(system.orientation, np.float64), self.quat)
        self.axes = arr(system.semi_axes)
        self.bound = arr(np.max(system.semi_axes, axis=1))
        self.mass = arr(system.mass)
        self.inertia = arr(system.inertia)
        self.inv_m = (1.0 / self.mass).astype(dt_)
        self.inv_i = (1.0 / self.inertia).astype(dt_)
        self.unit = np.ones(n, dt_)
        self.half = dt_(0.5)
        self.angm = np.zeros((n, 3), dt_)
        angm_from_omega(self.quat, arr(system.angular_velocity), self.inertia, self.half, self.angm)
        self.force = np.zeros((n, 3), dt_)
        self.torque = np.zeros((n, 3), dt_)
        self.x_ref = self.pos.copy()
        self.pos_prev = self.pos.copy()
        self.quat_prev = self.quat.copy()
        self.vel_p = self.vel.copy()
        self.omega_p = np.zeros((n, 3), dt_)
        omega_from_angm(self.quat, self.angm, self.inv_i, self.half, self.omega_p)
        self._rad_list = self.bound
        self._spin, self._spin_inv = self.angm, self.unit
        self._quat_arg, self._torque_arg = self.quat, self.torque
        self._ext = (self.inv_i, self.axes, self.omega_p, self.pos_prev, self.quat_prev)
        rmax = float(np.max(self.bound))
        self._init_loop(n, rmax, rmax, contact.skin)
        self.set_contact(contact)
        self._prime(system)

    def set_contact(self, contact: ContactParams) -> None:
        """Switch contact constants (thermalisation -> cooling); keeps lists and contact history.

        Rough contacts (k_t given): the spheroid's own k_t of each contact follows from the factor
        f = (arccos(-e_t)/pi)^2 of Hidalgo et al. (2013) Eq. 4, recovered from the sphere-convention k_t
        of ContactParams (k_t = k_n f q/(1 + q), engine.setup.params.k_t_paper), and the pair's tangential mass at the
        contact point (engine/physics/rough_spheroid.py)."""
        if contact.rough != self.rough:
            raise ValueError("an ellipsoid backend keeps its contact model: rough (k_t given) or smooth throughout")
        self._set_common(contact)
        c = self.dtype
        self.tol = c(PW_TOL[contact.precision])
        self.margin = c(PW_SCREEN[contact.precision])
        self.screened_gap = c(-np.inf)
        self.f_t = None if not self.rough else c(tangential_factor_of(contact.k_t, contact.k_n))
        self.mu = None if contact.friction is None or not self.rough else c(contact.friction)
        self._law = (self.tol, self.margin, self.screened_gap, self.f_t, self.mu)

    def _prime(self, system: EllipsoidSystem) -> None:
        self._build()
        # a fresh list holds bounding-sphere overlaps in slot 3; no contact history at t = 0
        self.hist[:, :, 3] = np.minimum(self.hist[:, :, 3], 0)
        if system.contact_pairs is not None and len(system.contact_pairs):
            restore_springs(self.nbr, self.nn, self.hist, np.asarray(system.contact_pairs, np.int64),
                            np.asarray(system.contact_springs, self.dtype))
        self._forces()

    # ---- host copies (output steps only) -----------------------------------------------------------

    def observe(self) -> dict:
        e_tr, e_rot, e_perp, contacts, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x = spheroid.observe(
            self.vel, self.angm, self.quat, self.mass, self.inv_i, self.nn, self.hist, self.half,
            float(self.k_n))
        bmin = float(np.min(self.axes))
        dof = rotational_dof(self.rough)
        return {"kinetic_energy_translational": float(e_tr), "kinetic_energy_rotational": float(e_rot),
                "kinetic_energy_rotational_active": float(e_perp), "rotational_dof": dof,
                "contacts": int(contacts), "elastic_energy": float(e_spring),
                "max_overlap": float(worst) / bmin, "momentum": (float(px), float(py), float(pz)),
                **sonine_sums(s_tr2, s_rot2, s_x, dof)}

    def omega(self) -> np.ndarray:
        out = np.zeros((self.n, 3), self.dtype)
        omega_from_angm(self.quat, self.angm, self.inv_i, self.half, out)
        return out

    def state(self, reuse=False) -> dict:
        """Copies of the state arrays in id order (angular velocity in the space frame; ``reuse`` is ignored)."""
        return {"position": self.pos.copy(), "velocity": self.vel.copy(),
                "angular_velocity": self.omega(), "orientation": self.quat.copy()}

    def contacts(self):
        """(pairs (M,2), slots (M,5)) of the list slots in contact (overlap, dashpot force in 3, 4)."""
        return collect_springs(self.pos, self.bound, self.nbr, self.nn, self.hist, self.box_c,
                               self.inv_box, self.half)


fast_loads(globals())  # their disk-cache loads skip numba's target refresh (engine/numba_support/jitcache.py)
