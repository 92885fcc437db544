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
state and per-scene constants on the device, the arrays it hands to the kernels, its observables, and a large start
drawn on the device (:func:`draw_ellipsoid_start`: engine/loops/cuda_start.py's draws, then :func:`start_rows`).
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
from engine.loops.cuda_cache import cache_kernels
from engine.loops.cuda_ensemble import CudaEnsembleBase, CudaSceneBackend
from engine.physics.rotation import angular_momentum, quat_unit, space_omega
from engine.setup.scene import _space_spin
from engine.physics.sonine import sonine_sums
from engine.shapes import device as shape_device   # the device module of this class's shape (a subclass's own)
from engine.shapes.spheroid import device as CE

#: the spheroid columns of spd (engine/shapes/spheroid/device.py: offsets from the common K.ND)
E_A, E_B, E_C, E_II1, E_II2, E_II3, E_TOL, E_BMIN, E_SCR, E_FT = (K.ND + c for c in range(CE.NCOL))


def _host_rows(orient, omega, inertia_c, inv_i, half) -> tuple:
    """(unit quaternions, space-frame L, predicted spin) in the working precision from float64 orientations and
    space-frame spins, exactly as CpuEllipsoidBackend builds them."""
    dt_ = inertia_c.dtype
    n = orient.shape[0]
    quat = np.empty((n, 4), dt_)
    unit_quaternions(np.ascontiguousarray(orient), quat)
    angm = np.empty((n, 3), dt_)        # every row written by the loops below
    angm_from_omega(quat, np.ascontiguousarray(omega.astype(dt_, copy=False)), inertia_c, half, angm)
    omega_p = np.empty((n, 3), dt_)
    omega_from_angm(quat, angm, inv_i, half, omega_p)
    return quat, angm, omega_p


@cuda.jit
def start_rows(q64, w_b, w_a, rough, col0, count, i1, i2, i3, ii1, ii2, ii3, half, quat, angm, omega_p):
    """Columns [col0, col0 + count) of a start drawn on the device: from its float64 orientations q64 and body-axis
    spins (w_b about e2, e3; w_a about e1 when ``rough``) the space-frame spin (engine.setup.scene._space_spin), and as
    :func:`_host_rows` the unit quaternion, L and the predicted spin in the working precision (a value is cast by
    storing it; omega_p holds the spin until L is taken). Principal moments i and their inverses ii: the scene's."""
    for i in range(cuda.grid(1), count, cuda.gridsize(1)):
        c = col0 + i
        g0, g1, g2, g3 = q64[0, c], q64[1, c], q64[2, c], q64[3, c]
        wa = w_a[0, c] if rough else 0.0
        ox, oy, oz = _space_spin(g0, g1, g2, g3, w_b[0, c], w_b[1, c], wa, rough)
        u0, u1, u2, u3 = quat_unit(g0, g1, g2, g3)
        quat[0, c], quat[1, c], quat[2, c], quat[3, c] = u0, u1, u2, u3
        omega_p[0, c], omega_p[1, c], omega_p[2, c] = ox, oy, oz
        q0, q1, q2, q3 = quat[0, c], quat[1, c], quat[2, c], quat[3, c]
        lx, ly, lz = angular_momentum(q0, q1, q2, q3, omega_p[0, c], omega_p[1, c], omega_p[2, c], i1, i2, i3, half)
        angm[0, c], angm[1, c], angm[2, c] = lx, ly, lz
        lx, ly, lz = angm[0, c], angm[1, c], angm[2, c]
        omega_p[0, c], omega_p[1, c], omega_p[2, c] = space_omega(q0, q1, q2, q3, lx, ly, lz, ii1, ii2, ii3, half)


cache_kernels({"start_rows": start_rows}, ("spheroid_start",))


def draw_ellipsoid_start(d, col0: int, pos, vel, angm, omega_p, quat, inertia_row, inv_i_row, half, stream,
                         cap: int = 1 << 14) -> None:
    """Draw the ellipsoid start ``d`` (engine.setup.scene.StartDraw: the lattice's or the random one's) into columns
    [col0, col0 + n) of the device state: engine/loops/cuda_start.py's draws (velocities into vel, orientations and
    body-axis spins into float64 scratch), then :func:`start_rows`. ``inertia_row``, ``inv_i_row``: the scene's
    principal moments and their inverses in the working precision."""
    from engine.loops.cuda_start import draw_start
    from engine.setup.scene import STREAM_QUATERNION, STREAM_SPIN, STREAM_SPIN_AXIS, STREAM_VELOCITY, is_rough_draw

    n = vel.shape[1]
    rough = is_rough_draw(d.streams)
    q64 = cuda.device_array((4, n), np.float64, stream=stream)
    w_b = cuda.device_array((2, n), np.float64, stream=stream)
    w_a = cuda.device_array((1, n if rough else 0), np.float64, stream=stream)
    dsts = {STREAM_VELOCITY: vel, STREAM_SPIN: w_b, STREAM_SPIN_AXIS: w_a, STREAM_QUATERNION: q64}
    draw_start(d, col0, pos, {k: dsts[k] for k, _, _ in d.streams}, stream, cap,
               quat=q64 if d.rsa is not None else None)
    blocks = max(1, min(cap, (d.n + 255) // 256))
    start_rows[blocks, 256, stream](q64, w_b, w_a, rough, np.int64(col0), np.int64(d.n), *inertia_row, *inv_i_row,
                                    half, quat, angm, omega_p)


def load_device_start(dtype, placements=("lattice", "random")) -> None:
    """Load (or compile) every kernel of a device-drawn spheroid start in the working precision ``dtype``, for the
    argument types a job's start calls them with: a start of 64 rough spheroids of each of ``placements``
    ("lattice", "random"), discarded (the GPU start-up thread, engine/driver/startup.py)."""
    from engine.setup.params import derive
    from engine.setup.scene import StartDraw, parallel_start_streams
    from engine.setup.spec import SimulationSpec

    stream = cuda.stream()
    half = dtype(0.5)
    for start in placements:
        spec = SimulationSpec(shape="ellipsoid", elongation=2.0, n_particles=64, start=start)
        p = derive(spec)
        a, b = p.semi_axes[0], p.semi_axes[1]
        d = StartDraw.of(64, 0, parallel_start_streams(spec, p)[0], spec.box_length, a, start,
                         (a, b) if start == "random" else ())
        rows = [cuda.device_array((k, 64), dtype, stream=stream) for k in (3, 3, 3, 3, 4)]
        inertia = np.asarray(p.inertia, dtype)
        draw_ellipsoid_start(d, 0, *rows, inertia, (1.0 / inertia).astype(dtype), half, stream)
    stream.synchronize()


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

    def __init__(self, systems: list, contacts: list, reads_state: bool = True, orientations: bool = True):
        for k, s in enumerate(systems):
            if not isinstance(s, EllipsoidSystem):
                raise TypeError(f"scene {k}: CudaEllipsoidEnsemble needs EllipsoidSystem scenes, "
                                f"got {type(s).__name__}")
        # rough contacts keep the spring and the contact's k_t: 6 history words (engine/shapes/spheroid/device.py)
        self.hist_words = SLOT_ROUGH if any(c.rough for c in contacts) else K.HW
        super().__init__(systems, contacts, reads_state)   # a spheroid always holds its orientation

    # ---- set-up (hooks of CudaEnsembleBase) -------------------------------------------------------------

    def _upload_particles(self, systems) -> None:
        """State (L from the angular velocity, as the CPU backend does) and constants on the device; a start still
        to be drawn (``system.draw``) is drawn into its columns on the device (:func:`draw_ellipsoid_start`)."""
        dt_, n, s = self.dtype, self.n, self.stream
        half = dt_(0.5)
        cat = self._cat
        axes = cat([sy.semi_axes for sy in systems])
        mass = cat([sy.mass for sy in systems])[:, 0]
        inertia = cat([sy.inertia for sy in systems])
        self.uniform = all(sy.n == 0 or (np.all(sy.semi_axes == sy.semi_axes[0]) and np.all(sy.mass == sy.mass[0])
                                         and np.all(sy.inertia == sy.inertia[0])) for sy in systems)
        self._rmax = [float(np.max(sy.semi_axes)) if sy.n else 0.0 for sy in systems]
        axes_c = axes.astype(dt_, copy=False)
        inertia_c = np.ascontiguousarray(inertia.astype(dt_, copy=False))
        inv_i = (1.0 / inertia_c).astype(dt_, copy=False)
        inv_m = (1.0 / mass.astype(dt_)).astype(dt_)
        self._inv_i_h = inv_i
        self._bmin = [float(np.min(axes_c[a:a + m])) if m else 1.0 for a, m in zip(self.starts, self.sizes)]
        self._scene0 = [(axes_c[a], mass[a], inertia_c[a]) if m else (np.ones(3, dt_), 1.0, np.ones(3, dt_))
                        for a, m in zip(self.starts, self.sizes)]
        if any(sy.draw is not None for sy in systems):
            self._draw_starts(systems, inertia_c, inv_i, half)
        else:
            up = self._up
            quat, angm, omega_p = _host_rows(cat([sy.orientation for sy in systems]),
                                             cat([sy.angular_velocity for sy in systems]), inertia_c, inv_i, half)
            self.pos = up(cat([sy.position for sy in systems]), 3)
            self.vel = up(cat([sy.velocity for sy in systems]), 3)
            self.angm = up(angm, 3)
            self.omega_p = up(omega_p, 3)
            self.quat = up(quat, 4)
        self.vel_p = self._copy(self.vel)
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

    def _draw_starts(self, systems, inertia_c, inv_i, half) -> None:
        """pos, vel, angm, omega_p, quat of scenes of which some hold a start to draw on the device; the others'
        host rows go up into their columns."""
        n, st, dt_ = self.n, self.stream, self.dtype
        self.pos, self.vel, self.angm, self.omega_p = (cuda.device_array((3, n), dt_, stream=st) for _ in range(4))
        self.quat = cuda.device_array((4, n), dt_, stream=st)
        if self.reads_state:
            self._prepare_frame_slot()     # beside the draws
        for sy, col0, m in zip(systems, self.starts, self.sizes):
            a = int(col0)
            if sy.draw is not None:
                draw_ellipsoid_start(sy.draw, a, self.pos, self.vel, self.angm, self.omega_p, self.quat,
                                     inertia_c[a], inv_i[a], half, st, self.max_blocks)
                continue
            quat, angm, omega_p = _host_rows(np.asarray(sy.orientation, np.float64),
                                             np.asarray(sy.angular_velocity, np.float64), inertia_c[a:a + m],
                                             inv_i[a:a + m], half)
            for rows, dst in ((sy.position, self.pos), (sy.velocity, self.vel), (angm, self.angm),
                              (omega_p, self.omega_p), (quat, self.quat)):
                self._up_into(rows, dst, a)

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
