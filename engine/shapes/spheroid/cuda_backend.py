"""CUDA backend for ellipsoids (Rubio-Largo et al. 2015; frictionless or rough, docs/physics.md §2.5): the CPU ellipsoid
backend's step on the GPU.

:class:`CudaEllipsoidEnsemble` advances K independent ellipsoid scenes stored back to back on the device,
built exactly as the sphere's (both are subclasses of :class:`engine.loops.cuda_ensemble.CudaEnsembleBase`: per-scene
constant tables, scene index per particle, cell grids per scene, compact contact-history store, the
cooperative many-steps-per-launch loop for small scenes and the per-phase loop for large ones, a scene that
blows up stops alone) and runs the same kernels: the one CUDA time loop (:mod:`engine.loops.cuda_loop`)
specialised by the spheroid's device functions (engine/shapes/spheroid/device.py, which call the njit physics
of the CPU plug-in engine/shapes/spheroid/kernels.py: Perram-Wertheim contact, Fincham's leap-frog on the
body-frame angular velocity, Rubio-Largo et al. (2015) Eqs. 13-24). This module owns only the spheroid's host side: its
state and per-scene constants on the device, the arrays it hands to the kernels and its observables.
:class:`CudaEllipsoidBackend` is the one-scene case (K = 1) with the interface of
:class:`engine.shapes.spheroid.cpu_backend.CpuEllipsoidBackend`.

The step is the CPU backend's:
  1. kick + drift: v += F/m hk, L += tau hk, x += v dt (wrapped), q by Fincham with L(t) and L(t + dt/2);
     predicted end-of-step v and w = R I^-1 R^T (L + tau dt/2) stored for the dashpot;
  2. rebuild when some particle has moved more than L_v/2 since the last build (bounding spheres of
     radius a: the shared list kernels of engine/loops/cuda_kernels.py with radius = a);
  3. forces: for each list slot whose bounding spheres overlap (or that was in contact at the previous
     step) the Perram-Wertheim contact with the lower id as "A", summed in list order.
State on the device is the space-frame angular momentum L; ``state()`` returns the space-frame angular
velocity computed on the host with the CPU backend's own function (bit-identical to the CPU's state()).
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops import cuda_loop
from engine.loops.system import ContactParams, EllipsoidSystem
from engine.shapes.spheroid.cpu_backend import (PW_SCREEN, PW_TOL, SLOT_ROUGH, angm_from_omega, omega_from_angm,
                                                rotational_dof, tangential_factor_of, unit_quaternions)
from engine.loops.cuda_ensemble import CudaEnsembleBase, CudaSceneBackend
from engine.physics.sonine import sonine_sums
from engine.shapes import device as shape_device   # the device module of this class's shape (a subclass's own)
from engine.shapes.spheroid import device as CE

#: the spheroid columns of spd (engine/shapes/spheroid/device.py: offsets from the common K.ND)
E_A, E_B, E_C, E_II1, E_II2, E_II3, E_TOL, E_BMIN, E_SCR, E_FT = (K.ND + c for c in range(CE.NCOL))


class CudaEllipsoidEnsemble(CudaEnsembleBase):
    """K scenes of ellipsoids advanced together on the GPU (see the module docstring).

    All scenes share the precision; N, box, semi-axes, masses, contact constants, dt, skin are per scene.
    The ensemble protocol of engine/backends/ensemble.py: ``advance`` returns the scenes that blew up in
    the call, ``observe`` the keys of the CPU ellipsoid backend's observe per scene.
    """

    shape = "ellipsoid"
    _ND = K.ND + CE.NCOL
    #: the Verlet list is built on the GPU (no host-built list modes for ellipsoids)
    host_lists = False
    _view_names = ("radius1", "inv_m1")

    def __init__(self, systems: list, contacts: list, reads_state: bool = True):
        for k, s in enumerate(systems):
            if not isinstance(s, EllipsoidSystem):
                raise TypeError(f"scene {k}: CudaEllipsoidEnsemble needs EllipsoidSystem scenes, "
                                f"got {type(s).__name__}")
        # rough contacts keep the spring and the contact's k_t: 6 history words (engine/shapes/spheroid/device.py)
        self.hist_words = SLOT_ROUGH if any(c.rough for c in contacts) else K.HW
        super().__init__(systems, contacts, reads_state)

    # ---- set-up (hooks of CudaEnsembleBase) -------------------------------------------------------------

    def _upload_particles(self, systems) -> None:
        """State (L from the angular velocity, as the CPU backend does) and constants on the device."""
        dt_, n, s = self.dtype, self.n, self.stream
        half = dt_(0.5)
        cat = self._cat
        axes = cat([sy.semi_axes for sy in systems])
        mass = cat([sy.mass for sy in systems])[:, 0]
        inertia = cat([sy.inertia for sy in systems])
        orient = cat([sy.orientation for sy in systems])
        self.uniform = all(sy.n == 0 or (np.all(sy.semi_axes == sy.semi_axes[0]) and np.all(sy.mass == sy.mass[0])
                                         and np.all(sy.inertia == sy.inertia[0])) for sy in systems)
        self._rmax = [float(np.max(sy.semi_axes)) if sy.n else 0.0 for sy in systems]
        # host arrays in the working precision, exactly as CpuEllipsoidBackend builds them
        quat = np.empty((n, 4), dt_)
        unit_quaternions(np.ascontiguousarray(orient), quat)
        axes_c = axes.astype(dt_, copy=False)
        inertia_c = np.ascontiguousarray(inertia.astype(dt_, copy=False))
        inv_i = (1.0 / inertia_c).astype(dt_, copy=False)
        inv_m = (1.0 / mass.astype(dt_)).astype(dt_)
        angm = np.empty((n, 3), dt_)        # every row written by the loops below
        angm_from_omega(quat,
                        np.ascontiguousarray(cat([sy.angular_velocity for sy in systems]).astype(dt_, copy=False)),
                        inertia_c, half, angm)
        omega_p = np.empty((n, 3), dt_)
        omega_from_angm(quat, angm, inv_i, half, omega_p)
        self._inv_i_h = inv_i
        self._bmin = [float(np.min(axes_c[a:a + m])) if m else 1.0 for a, m in zip(self.starts, self.sizes)]
        self._scene0 = [(axes_c[a], mass[a], inertia_c[a]) if m else (np.ones(3, dt_), 1.0, np.ones(3, dt_))
                        for a, m in zip(self.starts, self.sizes)]
        up = self._up
        self.pos = up(cat([sy.position for sy in systems]), 3)
        self.vel = up(cat([sy.velocity for sy in systems]), 3)
        self.vel_p = self._copy(self.vel)
        self.angm = up(angm, 3)
        self.omega_p = up(omega_p, 3)
        self.quat = up(quat, 4)
        # state before the current step (a contact starting after a screened step needs that step's gap)
        self.pos_prev = self._copy(self.pos)
        self.quat_prev = self._copy(self.quat)
        self.force = self._zeros((3, n), dt_)
        self.torque = self._zeros((3, n), dt_)
        # one force buffer (the force phase reads vel_p/omega_p, not other particles' forces): the sphere
        # loop's double-buffer swaps exchange two references to it
        self.f_cur = self.f_nxt = self.force
        if self.uniform:
            self.radius = self.inv_m = self.mass = cuda.device_array((1, 1), dt_, stream=s)
            self.axes = self.inv_i = cuda.device_array((3, 1), dt_, stream=s)
            self._per_particle = ()
        else:
            self.radius = up(np.max(axes_c, axis=1), 1)
            self.axes = up(axes_c, 3)
            self.inv_m = up(inv_m, 1)
            self.inv_i = up(inv_i, 3)
            self.mass = up(mass, 1)
            self._per_particle = (self.radius, self.axes, self.inv_m, self.inv_i, self.mass)

    def _permuted_arrays(self) -> tuple:
        return self.pos, self.vel, self.angm, self.quat, self.vel_p, self.omega_p, self.pos_prev, self.quat_prev

    def _permuted_i64(self) -> tuple:
        return ()

    def state_arrays(self) -> dict:
        """The device state copied out by _scene_rows: the angular momentum L (:meth:`state` turns it into the
        space-frame angular velocity)."""
        return {"position": self.pos, "velocity": self.vel, "angm": self.angm, "orientation": self.quat}

    def _views(self) -> None:
        self.radius1, self.inv_m1 = self.radius[0], self.inv_m[0]

    def _scene_constants(self, s: int) -> None:
        """Scene s's particle constants in spd: bounding radius a, mass, semi-axes, principal 1/I, b_min."""
        c = self.dtype
        ax, m0, i0 = self._scene0[s]
        self.spd_h[s, K.D_R0] = np.max(ax)
        self.spd_h[s, K.D_M0] = c(m0)
        self.spd_h[s, K.D_IM0] = (1.0 / np.array([m0], c))[0]
        self.spd_h[s, [E_A, E_B, E_C]] = ax
        self.spd_h[s, [E_II1, E_II2, E_II3]] = (1.0 / np.asarray(i0, c)).astype(c)
        self.spd_h[s, E_BMIN] = min(ax[1], ax[2])

    def _set_scene_contact(self, s: int, contact: ContactParams) -> None:
        if contact.rough and self.hist_words < SLOT_ROUGH:
            raise ValueError("an ellipsoid ensemble built for frictionless scenes cannot switch a scene to rough "
                             "contacts (the list slots hold no spring)")
        super()._set_scene_contact(s, contact)
        c = self.dtype
        self.spd_h[s, E_TOL] = c(PW_TOL[contact.precision])
        self.spd_h[s, E_SCR] = c(PW_SCREEN[contact.precision])
        self.spd_h[s, E_FT] = c(tangential_factor_of(contact.k_t, contact.k_n)) if contact.rough else c(0.0)

    def _specialise(self) -> None:
        act = [c for c, a in zip(self.contact, self.active) if a] or self.contact
        rough = self.hist_words >= SLOT_ROUGH and any(c.rough for c in act)
        coulomb = rough and any(c.friction is not None for c in act)
        self.rough = rough          # the observe sums count the active rotational dof of the compiled law
        self.k = cuda_loop.kernels(self.shape, self.dtype, (rough, coulomb), self.uniform, self.tpb,
                                   shape_device(self.shape))
        self._coop_blocks = None

    def _prime(self, systems) -> None:
        """First list build, no contact history at t = 0 (checkpointed slots restored), forces at t = 0."""
        self._rebuild()
        self.k["clamp_history"][self._grid(self.n)](self.n, self.nn, self.hist)
        for s, sy in enumerate(systems):
            if sy.contact_pairs is not None and len(sy.contact_pairs):
                self._restore_springs(self.starts[s] + np.asarray(sy.contact_pairs, np.int64),
                                      np.asarray(sy.contact_springs, np.float64))
        self._forces(step=0)
        self._pending = self._collect(self._read_status_now())

    # ---- the time loop's arrays (engine/loops/cuda_loop.py) -------------------------------------

    def _step_arrays(self) -> tuple:
        """(spin, spin_inv, list radius, ext): the angular momentum L, the principal 1/I, the bounding radius a,
        and (axes, vel_p, omega_p, pos_prev, quat_prev) (engine/shapes/spheroid/device.py)."""
        return self.angm, self.inv_i, self.radius1, (self.axes, self.vel_p, self.omega_p, self.pos_prev,
                                                     self.quat_prev, self.inv_i)

    # ---- host copies (output steps only) -----------------------------------------------------------

    _NOBS = CE.NACC

    def _observe_args(self) -> tuple:
        """observe(pos, vel, spin, quat, rad, mass, inertia, ..., ext) with inertia = the principal 1/I."""
        return (self.pos, self.vel, self.angm, self.quat, self.radius1, self.mass, self.inv_i, self.nbr, self.nn,
                self.hist, self.spd, self.spf, self.spi, self._step_arrays()[3])

    def _observables(self, s: int, r: list) -> dict:
        """Scene s's keys of CpuEllipsoidBackend.observe from its observe sums r (engine/shapes/spheroid/device.py:
        observe_one)."""
        return {"kinetic_energy_translational": r[CE.A_TR], "kinetic_energy_rotational": r[CE.A_ROT],
                "kinetic_energy_rotational_active": r[CE.A_PERP],
                "rotational_dof": rotational_dof(self._scene_rough(s)),
                "contacts": int(round(r[CE.A_CON])) // 2, "elastic_energy": r[CE.A_EL],
                "max_overlap": r[CE.A_OVL] / self._bmin[s], "momentum": (r[CE.A_PX], r[CE.A_PY], r[CE.A_PZ]),
                **sonine_sums(r[CE.A_TR2], r[CE.A_ROT2], r[CE.A_X], rotational_dof(self._scene_rough(s)))}

    def contacts(self, k: int):
        """As CudaEnsembleBase.contacts, with the scene's own history words (a frictionless scene in a rough-compiled
        ensemble: the 5 of the CPU backend)."""
        pairs, slots = super().contacts(k)
        return pairs, (slots if self.contact[k].rough else slots[:, :K.HW].copy())

    def _scene_rough(self, s: int) -> bool:
        """Scene s runs the rough law (a frictionless scene may share a rough-compiled ensemble: f_t = 0)."""
        return bool(self.rough and self.contact[s].rough)

    def state(self, k: int, reuse=False) -> dict:
        """Host copies of scene k's state in particle-id order (angular velocity in the space frame, computed
        on the host from L; ``reuse``: see StateFrames._scene_rows)."""
        out = self._scene_rows(k, reuse)
        a0, n_k = int(self.starts[k]), int(self.sizes[k])
        w = np.zeros((n_k, 3), self.dtype)
        omega_from_angm(out["orientation"], out.pop("angm"), self._inv_i_h[a0:a0 + n_k], self.dtype(0.5), w)
        out["angular_velocity"] = w
        return {key: out[key] for key in ("position", "velocity", "angular_velocity", "orientation")}


class CudaEllipsoidBackend(CudaSceneBackend):
    """One ellipsoid scene on the GPU (K = 1 of :class:`CudaEllipsoidEnsemble`), with the interface of
    :class:`engine.shapes.spheroid.cpu_backend.CpuEllipsoidBackend`."""

    ensemble_class = CudaEllipsoidEnsemble

    def __init__(self, system: EllipsoidSystem, contact: ContactParams):
        super().__init__(system, contact)

    def omega(self) -> np.ndarray:
        """Space-frame angular velocities in id order (rad/s)."""
        return self.e.state(0)["angular_velocity"]
