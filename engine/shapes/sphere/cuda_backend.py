"""The sphere's CUDA host side: :class:`CudaEnsemble`, K sphere scenes on the GPU, and :class:`CudaBackend`, one
of them behind the single Backend interface.

The machinery (tables, lists, time loop, records, state copies) is the shared
:class:`engine.loops.cuda_ensemble.CudaEnsembleBase`; this module owns only what is the sphere's own: its state
arrays (space-frame angular velocity, scalar radius, mass and inertia; per particle only when a scene's spheres
differ, else in the scene's constants), a large start drawn on the device (engine/loops/cuda_start.py), the lazy
orientations' marks and the collision counter (engine/shapes/sphere/device.py), the orientation switch of the
specialisation, and the observables. An ensemble that neither tracks orientations nor has its state read (no
snapshots, no checkpoints: ``reads_state`` False), or whose scenes want none (their spec's ``orientations`` false),
holds no orientations and no marks on the device (a sphere's orientation changes nothing else; 24 B a particle in
float32, 40 in float64). Its Verlet list may be built on the host for a lone scene (Skorych & Dosta 2022, §3).
A large scene's state is copied out in pieces for a snapshot (:meth:`state_pieces`).
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops import cuda_loop
from engine.loops.cuda_ensemble import TPB, CudaEnsembleBase, CudaSceneBackend
from engine.loops.system import rows_equal
from engine.physics.sonine import DOF_ROTATION_SPHERE, sonine_sums
from engine.setup.precision import state_dtype
from engine.shapes import device as shape_device   # the device module of this class's shape (a subclass's own)
from engine.shapes.sphere import device as SC


class CudaEnsemble(CudaEnsembleBase):
    """K scenes of spheres advanced together on the GPU (engine/loops/cuda_ensemble.py).

    All scenes share the precision; everything else (N, box, contact constants, dt, skin, rough or
    smooth, Coulomb, orientation) is per scene.
    """

    shape = "sphere"
    host_lists = True
    _view_names = ("radius1", "inv_m1", "inv_i1", "mass1", "inertia1")
    _NOBS = SC.NOBS

    def _upload_particles(self, systems) -> None:
        """Sphere state and constants on the device (uniform scenes keep their constants in spd)."""
        dt_, n = self.dtype, self.n
        #: orientations (and their marks) on the device: tracked, or the state is read and some scene wants them (see
        #: the module docstring)
        self.orientations_held = any(c.orientation for c in self.contact) or (
            self.reads_state and self.orientations_wanted)
        rad, mass, inertia = (self._cat(arrays)[:, 0] for arrays in (
            [s.radius for s in systems], [s.mass for s in systems], [s.inertia for s in systems]))
        uniform = [rows_equal(s.radius) and rows_equal(s.mass) and rows_equal(s.inertia) for s in systems]
        self.uniform = all(uniform)
        self._rmax = [0.0 if not s.n else float(s.radius[0]) if u else float(np.max(s.radius))
                      for s, u in zip(systems, uniform)]
        self._scene0 = [(rad[i], mass[i], inertia[i]) if s_n else (0, 0, 0)
                        for i, s_n in zip(self.starts, self.sizes)]
        up, cat = self._up, self._cat
        if any(s.draw is not None for s in systems):
            self._draw_starts(systems)
        else:
            self.pos = up(cat([s.position for s in systems]), 3, self.pos_dtype)
            self.vel = up(cat([s.velocity for s in systems]), 3)
            self.omega = up(cat([s.angular_velocity for s in systems]), 3)
            self.quat = up(cat([s.orientation for s in systems]), 4) if self.orientations_held else \
                self._no_orientations()
        self.f_cur = self._zeros((3, n), dt_)
        self.f_nxt = cuda.device_array((3, n), dt_, stream=self.stream)
        self._alt = None     # the fused step's other halves of pos and vel (_fused_out)
        self._alt_spin = None  # and of omega, for the fused many-steps kernel (_multistep_out)
        self.torque = self._zeros((3, n), dt_)
        # the step from which each sphere's orientation turns are pending (lazy orientations, shapes/sphere/device.py)
        self.q_last = self._zeros(n if self.orientations_held else 1, np.int64)
        # the contacts each sphere has begun (the collisions observable; shapes/sphere/device.py pair; int32: a sphere
        # begins thousands of contacts in the longest runs, 2^31 is far beyond any)
        self.begun = self._zeros(n, np.int32)
        if self.uniform:
            dummy = cuda.device_array((1, 1), dt_, stream=self.stream)
            self.radius = self.inv_m = self.inv_i = self.mass = self.inertia = dummy
            self._per_particle = ()
        else:
            self.radius = up(rad, 1)
            self.mass = up(mass, 1)
            self.inertia = up(inertia, 1)
            self.inv_m = up((1.0 / mass.astype(dt_)).astype(dt_), 1)
            self.inv_i = up((1.0 / inertia.astype(dt_)).astype(dt_), 1)
            self._per_particle = (self.radius, self.mass, self.inertia, self.inv_m, self.inv_i)

    def _no_orientations(self):
        """The stand-in for the orientations an ensemble does not hold: a (4, 1) array of the state's type, which
        kernels compiled without orientations never read."""
        return cuda.device_array((4, 1), self.dtype, stream=self.stream)

    def _permuted_arrays(self) -> tuple:
        """The device arrays permuted into cell order at a rebuild, besides the per-particle constants."""
        return (self.pos, self.vel, self.omega) + ((self.quat,) if self.orientations_held else ()) + (self.f_cur,)

    def _permuted_i64(self) -> tuple:
        """The integer device arrays (N) permuted with them (spheres: the lazy orientations' marks, int64, the
        contacts begun, int32)."""
        return (self.q_last, self.begun) if self.orientations_held else (self.begun,)

    def state_arrays(self) -> dict:
        """{state key: device array (rows, N, particle index fastest)} that :meth:`_scene_rows` copies out
        (spheres: the space-frame angular velocity itself; the orientations where held)."""
        arrays = {"position": self.pos, "velocity": self.vel, "angular_velocity": self.omega}
        if self.orientations_held:
            arrays["orientation"] = self.quat
        return arrays

    def state(self, k: int, reuse=False) -> dict:
        """Host copies of scene k's state in particle-id order; where the orientations are not held, the identity
        quaternion stands for each (nothing reads them: no snapshots, no checkpoints, none tracked)."""
        out = super().state(k, reuse)
        if not self.orientations_held:
            q = np.zeros((int(self.sizes[k]), 4), self.dtype)
            q[:, 0] = 1.0
            out["orientation"] = q
        return out

    def state_pieces(self, k: int, rows: int):
        """Scene k's state in particle-id order in pieces of ``rows`` particles (StateFrames._state_pieces): the
        snapshot of a large scene (engine/output/writers/snapshots.py). The orientations only where held."""
        return self._state_pieces(k, rows)

    def _draw_starts(self, systems) -> None:
        """pos, vel, omega, quat of scenes of which some hold a start to draw on the device
        (engine.setup.scene.StartDraw: engine/loops/cuda_start.py); the others' host arrays go up into their columns."""
        from engine.loops.cuda_start import SPHERE_TARGETS, draw_start

        n, st = self.n, self.stream
        self.pos = cuda.device_array((3, n), self.pos_dtype, stream=st)
        held = self.orientations_held
        made = {}

        def target(name: str, rows: int):
            """The state array ``name``, made at its first use: after the first random start's cells are freed
            (they and the positions are the start's peak, engine/loops/cuda_memory.py predict_sphere_device)."""
            def get():
                if name not in made:
                    made[name] = cuda.device_array((rows, n), self.dtype, stream=st)
                return made[name]
            return get

        targets = {"vel": target("vel", 3), "omega": target("omega", 3), "quat": target("quat", 4)}
        for sy, col0 in zip(systems, self.starts):
            if sy.draw is not None:     # (the orientation stream is left undrawn where none are held)
                draw_start(sy.draw, int(col0), self.pos, {k: targets[a] for k, a in SPHERE_TARGETS.items()
                                                          if held or a != "quat"}, st, self.max_blocks)
            else:
                pairs = [(sy.position, "pos"), (sy.velocity, "vel"), (sy.angular_velocity, "omega")]
                for a, name in pairs + ([(sy.orientation, "quat")] if held else []):
                    self._up_into(a, self.pos if name == "pos" else targets[name](), int(col0))
        self.vel, self.omega = targets["vel"](), targets["omega"]()
        self.quat = targets["quat"]() if held else self._no_orientations()
        if self.reads_state:
            self._prepare_frame_slot()     # (its staging made after the start's peak)

    def _scene_constants(self, s: int) -> None:
        """Scene s's particle constants in spd (used when its particles are uniform)."""
        c = self.dtype
        r0, m0, i0 = self._scene0[s]
        self.spd_h[s, [K.D_R0, K.D_M0, K.D_I0]] = [c(r0), c(m0), c(i0)]
        self.spd_h[s, K.D_IM0] = (1.0 / np.array([m0 or 1.0], c))[0]
        self.spd_h[s, K.D_II0] = (1.0 / np.array([i0 or 1.0], c))[0]

    def _views(self) -> None:
        """1-D views of the per-particle constants (kept as (1, N) rows for the permutation)."""
        self.radius1, self.inv_m1, self.inv_i1 = self.radius[0], self.inv_m[0], self.inv_i[0]
        self.mass1, self.inertia1 = self.mass[0], self.inertia[0]

    @staticmethod
    def kernel_flags(contacts) -> tuple:
        """The kernels' compile-time switches (rough, Coulomb cap, orientations) for scenes of ``contacts``."""
        rough = any(c.k_t is not None for c in contacts)
        return rough, rough and any(c.friction is not None for c in contacts), any(c.orientation for c in contacts)

    @classmethod
    def prepare_kernels(cls, contacts: tuple) -> None:
        for c in contacts:
            cuda_loop.kernels(cls.shape, state_dtype(c.precision), cls.kernel_flags([c]), True, TPB,
                              shape_device(cls.shape))

    def _specialise(self) -> None:
        act = [c for c, a in zip(self.contact, self.active) if a] or self.contact
        rough, coulomb, orient = self.kernel_flags(act)
        if orient and not self.orientations_held:
            raise RuntimeError("orientations switched on in an ensemble made without them (reads_state False or "
                               "orientations False, and no scene tracking orientations): make it with both True")
        if orient and not self._orient:
            # orientations tracked from now on: nothing is pending from the steps run without them
            self.q_last.copy_to_device(np.full(self.n, self.steps_done, np.int64), stream=self.stream)
        self._orient = orient
        self._torque_stored = rough      # the force passes store every particle's torque (after a rebuild)
        self.k = cuda_loop.kernels(self.shape, self.dtype, (rough, coulomb, orient), self.uniform, self.tpb,
                                   shape_device(self.shape))
        self._coop_blocks = None

    def _torque_rewritten(self) -> bool:
        """A lone scene of rough spheres: its next force pass stores every sphere's torque after a rebuild (an
        ensemble's stopped scenes are skipped by the force passes: their torque is left as it is)."""
        return self._torque_stored and self.n_scenes == 1

    def _prime(self, systems) -> None:
        """First list build (restoring checkpointed springs) and forces at t = 0."""
        self._rebuild()
        for s, sy in enumerate(systems):
            if sy.contact_pairs is not None and len(sy.contact_pairs):
                self._restore_springs(self.starts[s] + np.asarray(sy.contact_pairs, np.int64),
                                      np.asarray(sy.contact_springs, np.float64))
        self._forces(step=0)
        self.f_cur, self.f_nxt = self.f_nxt, self.f_cur
        # scenes that already fail at t = 0 (overlapping start): reported by the first advance
        self._pending = self._collect(self._read_status_now())

    def _fused_out(self) -> tuple:
        """The other halves of the fused step's double buffer (made at the first fused launch): positions and
        velocities (only smooth spheres fuse: their spins never change in the loop)."""
        if self._alt is None:
            st = self.stream
            self._alt = (cuda.device_array(self.pos.shape, self.pos.dtype, stream=st),
                         cuda.device_array(self.vel.shape, self.vel.dtype, stream=st))
        return self._alt

    def _swap_fused(self) -> None:
        (self.pos, self.vel), self._alt = self._alt, (self.pos, self.vel)

    def _multistep_out(self) -> tuple:
        """The other halves of the fused many-steps kernel's double buffer: positions and velocities (those of
        :meth:`_fused_out`) and angular velocities (made at first use)."""
        if self._alt_spin is None:
            self._alt_spin = cuda.device_array(self.omega.shape, self.omega.dtype, stream=self.stream)
        return self._fused_out() + (self._alt_spin,)

    def _swap_multistep(self) -> None:
        self._swap_fused()
        self.omega, self._alt_spin = self._alt_spin, self.omega

    def _step_arrays(self) -> tuple:
        """(spin, spin_inv, list radius, ext) of the time loop's kernels (engine/loops/cuda_loop.py):
        spheres: the angular velocity, 1/I, the radius, (the lazy orientations' marks, the contacts begun)."""
        return self.omega, self.inv_i1, self.radius1, (self.q_last, self.begun)

    def _observe_args(self) -> tuple:
        """observe(pos, vel, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, spi, ext) (cuda_loop)."""
        return (self.pos, self.vel, self.omega, self.quat, self.radius1, self.mass1, self.inertia1, self.nbr,
                self.nn, self.hist, self.spd, self.spf, self.spi, self._step_arrays()[3])

    def _observables(self, s: int, r: list) -> dict:
        """Scene s's observables from its observe sums r (engine/shapes/sphere/device.py: observe_one)."""
        return {"kinetic_energy_translational": r[0], "kinetic_energy_rotational": r[1],
                "contacts": int(round(r[2])) // 2, "elastic_energy": r[3],
                "max_overlap": r[SC.O_MAX], "momentum": (r[4], r[5], r[6]),
                "collisions": int(round(r[SC.O_COLL])) // 2,
                **sonine_sums(r[SC.O_TR2], r[SC.O_ROT2], r[SC.O_X], DOF_ROTATION_SPHERE)}


class CudaBackend(CudaSceneBackend):
    """One sphere scene on the GPU (K = 1 of :class:`CudaEnsemble`), with the interface of
    :class:`engine.shapes.sphere.cpu_backend.CpuBackend`."""

    ensemble_class = CudaEnsemble
