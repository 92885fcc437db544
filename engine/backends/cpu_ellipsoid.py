"""CPU backend for frictionless ellipsoids (paper 003): the same layout and interface as CpuBackend.

- Neighbour lists, cells and list copies are those of engine/backends/cpu.py with the bounding-sphere
  radius (largest semi-axis) as the particle radius: the Verlet list holds the pairs whose bounding
  spheres come within the skin, and the force loop runs the Perram-Wertheim contact
  (engine/physics/ellipsoid.py) only for pairs whose bounding spheres overlap (the cheap broad phase),
  behind two exact screens for pairs not in contact at the previous step (ellipsoid_pair_screened: the plane
  normal to the centre line, and the PW iteration stopped at the first iterate with F > 1 + margin). A
  screened pair stores -inf as its gap; when a contact starts right after a screened step the gap of that step
  is evaluated from the state before the step (pos_prev, quat_prev), so every result is the one without the
  screens, bit for bit (tests/engine/test_ellipsoid_screen.py).
- Each pair is evaluated with the lower id as "A" in both partners' loops, so F_ji = -F_ij to the last
  bit without atomics (the full list evaluates each pair twice, as the sphere backend does).
- Rotation: space-frame angular momentum L kicked by the torque, quaternions by Fincham's leap-frog with
  the body-frame angular velocity I^-1 R^T L (engine/physics/rotation.py: fincham_quat_step_body),
  renormalised every step. Predicted end-of-step velocities and angular velocities feed the dashpot.
- List slot layout as in cpu.py (cpu_shared.SLOT = 5); slots 3 and 4 hold the overlap and the dashpot force of the
  previous step (contact start/end corrections; slot 3 = -inf: screened), slots 0-2 are unused
  (frictionless).
- Everything cache=True; the loop is compiled whole (no Python per step).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

import engine.jitcache  # noqa: F401  (before any cache=True kernel: keys the disk cache by source)

from engine.backends.base import ContactParams, EllipsoidSystem, cell_grid
from engine.backends.cpu import bin_particles, build_list, copy_list, half_kick
from engine.backends.cpu_shared import SLOT, collect_springs, cpu_name, restore_springs, worst_overlap
from engine.backends.status import BAD_VALUE, OK, OVERFLOW, OVERLAP, instability_error
from engine.physics.contact import contact_elastic_energy, min_image
from engine.physics.ellipsoid import PAIR_NEEDS_PREV, ellipsoid_contact, ellipsoid_pair_screened
from engine.physics.integrate import drift_wrap, kick
from engine.physics.sonine import DOF_ROTATION_SPHEROID, sonine_sums
from engine.physics.rotation import angular_momentum, body_omega, fincham_quat_step_body, space_omega

#: Newton tolerance on the Perram-Wertheim lambda per precision (bench/RESULTS.md, issue 4 section).
PW_TOL = {"float64": 1e-15, "float32": 1e-7}
#: relative margin of the exact disjointness screens before/inside the Perram-Wertheim solve
#: (engine.physics.ellipsoid.ellipsoid_contact_screened; far above the rounding of F in each precision, so the
#: screens change no result: tests/engine/test_ellipsoid_screen.py); a negative value disables them
PW_SCREEN = {"float64": 1e-9, "float32": 1e-3}


@numba.njit(parallel=True, cache=True)
def kick_drift_ell(pos, vel, angm, quat, force, torque, inv_m, inv_i, x_ref, vel_p, omega_p, pos_prev, quat_prev,
                   hk, dt, box, inv_box, half, chunk_disp, chunk_bad):
    """v += F/m hk, L += tau hk, x += v dt (wrapped), q by Fincham; predicted v and w at t + dt; the
    positions and orientations before the step kept in pos_prev, quat_prev (for a contact that starts after
    a screened step, engine.physics.ellipsoid.ellipsoid_pair_screened)."""
    hp = dt * half
    n = pos.shape[0]
    nch = chunk_disp.shape[0]
    for c in prange(nch):
        i0 = c * n // nch
        i1 = (c + 1) * n // nch
        m = 0.0
        bad = -1
        for i in range(i0, i1):
            im = inv_m[i]
            for k in range(4):
                quat_prev[i, k] = quat[i, k]
            for k in range(3):
                pos_prev[i, k] = pos[i, k]
                v = kick(vel[i, k], force[i, k], im, hk)
                vel[i, k] = v
                vel_p[i, k] = kick(v, force[i, k], im, hp)
                pos[i, k] = drift_wrap(pos[i, k], v, dt, box, inv_box)
            lx = angm[i, 0] + torque[i, 0] * hk
            ly = angm[i, 1] + torque[i, 1] * hk
            lz = angm[i, 2] + torque[i, 2] * hk
            angm[i, 0] = lx
            angm[i, 1] = ly
            angm[i, 2] = lz
            i1_, i2_, i3_ = inv_i[i, 0], inv_i[i, 1], inv_i[i, 2]
            q0, q1, q2, q3 = fincham_quat_step_body(
                quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3],
                lx - torque[i, 0] * hp, ly - torque[i, 1] * hp, lz - torque[i, 2] * hp, lx, ly, lz,
                i1_, i2_, i3_, dt, half)
            quat[i, 0] = q0
            quat[i, 1] = q1
            quat[i, 2] = q2
            quat[i, 3] = q3
            wx, wy, wz = space_omega(q0, q1, q2, q3, lx + torque[i, 0] * hp, ly + torque[i, 1] * hp,
                                     lz + torque[i, 2] * hp, i1_, i2_, i3_, half)
            omega_p[i, 0] = wx
            omega_p[i, 1] = wy
            omega_p[i, 2] = wz
            dx = min_image(pos[i, 0] - x_ref[i, 0], box, inv_box, half)
            dy = min_image(pos[i, 1] - x_ref[i, 1], box, inv_box, half)
            dz = min_image(pos[i, 2] - x_ref[i, 2], box, inv_box, half)
            d2 = dx * dx + dy * dy + dz * dz
            if not (d2 < 1e300) or not (abs(vel[i, 0]) + abs(vel[i, 1]) + abs(vel[i, 2]) < 1e300) \
                    or not (abs(lx) + abs(ly) + abs(lz) < 1e300) or not (abs(q0) <= 1.5):
                if bad < 0:
                    bad = i
            elif d2 > m:
                m = d2
        chunk_disp[c] = m
        chunk_bad[c] = bad


@numba.njit(parallel=True, cache=True)
def compute_forces_ell(pos, vel_p, omega_p, quat, axes, bound, inv_m, nbr, nn, hist, force, torque, box,
                       inv_box, half, k_n, gn_coef, dt, tol, margin, screened_gap, pos_prev, quat_prev, chunk_ovl,
                       chunk_ovl_idx):
    """Contact forces and torques on every particle from its list; overlap/dashpot history updated.

    Pairs proven disjoint by the exact screens (margin >= 0) store screened_gap (-inf) as their gap; a contact that
    starts right after such a step gets the previous gap evaluated from pos_prev/quat_prev (see
    engine.physics.ellipsoid.ellipsoid_pair_screened). Records per chunk the largest overlap relative to
    the smallest semi-axis (stability guard).
    """
    n = pos.shape[0]
    nch = chunk_ovl.shape[0]
    for c in prange(nch):
        i0 = c * n // nch
        i1 = (c + 1) * n // nch
        worst = 0.0
        worst_i = -1
        for i in range(i0, i1):
            fx = 0.0
            fy = 0.0
            fz = 0.0
            tx = 0.0
            ty = 0.0
            tz = 0.0
            for kk in range(nn[i]):
                j = nbr[i, kk]
                a = i if i < j else j
                b = j if i < j else i
                rx = min_image(pos[b, 0] - pos[a, 0], box, inv_box, half)
                ry = min_image(pos[b, 1] - pos[a, 1], box, inv_box, half)
                rz = min_image(pos[b, 2] - pos[a, 2], box, inv_box, half)
                rc = bound[a] + bound[b]
                d2 = rx * rx + ry * ry + rz * rz
                if d2 >= rc * rc and hist[i, kk, 3] <= 0:
                    hist[i, kk, 3] = rc - math.sqrt(d2)     # negative: no contact possible
                    hist[i, kk, 4] = 0
                    continue
                m12 = 1 / (inv_m[a] + inv_m[b])
                d_prev = hist[i, kk, 3]
                for _ in range(2):
                    g = ellipsoid_pair_screened(
                        rx, ry, rz, quat[a, 0], quat[a, 1], quat[a, 2], quat[a, 3],
                        axes[a, 0], axes[a, 1], axes[a, 2],
                        quat[b, 0], quat[b, 1], quat[b, 2], quat[b, 3],
                        axes[b, 0], axes[b, 1], axes[b, 2],
                        vel_p[b, 0] - vel_p[a, 0], vel_p[b, 1] - vel_p[a, 1], vel_p[b, 2] - vel_p[a, 2],
                        omega_p[a, 0], omega_p[a, 1], omega_p[a, 2],
                        omega_p[b, 0], omega_p[b, 1], omega_p[b, 2],
                        d_prev, hist[i, kk, 4], m12, k_n, gn_coef * math.sqrt(m12), dt, tol, margin,
                        screened_gap, half)
                    if g[11] != PAIR_NEEDS_PREV:
                        break
                    # a contact starts after a screened step: the gap of that step, from its state
                    d_prev = ellipsoid_contact(
                        min_image(pos_prev[b, 0] - pos_prev[a, 0], box, inv_box, half),
                        min_image(pos_prev[b, 1] - pos_prev[a, 1], box, inv_box, half),
                        min_image(pos_prev[b, 2] - pos_prev[a, 2], box, inv_box, half),
                        quat_prev[a, 0], quat_prev[a, 1], quat_prev[a, 2], quat_prev[a, 3],
                        axes[a, 0], axes[a, 1], axes[a, 2],
                        quat_prev[b, 0], quat_prev[b, 1], quat_prev[b, 2], quat_prev[b, 3],
                        axes[b, 0], axes[b, 1], axes[b, 2], tol, half)[2]
                if i == a:
                    fx += g[0]
                    fy += g[1]
                    fz += g[2]
                    tx += g[3]
                    ty += g[4]
                    tz += g[5]
                else:
                    fx -= g[0]
                    fy -= g[1]
                    fz -= g[2]
                    tx += g[6]
                    ty += g[7]
                    tz += g[8]
                delta = g[9]
                hist[i, kk, 3] = delta
                hist[i, kk, 4] = g[10]
                if delta > 0:
                    ov = delta / min(min(axes[a, 1], axes[a, 2]), min(axes[b, 1], axes[b, 2]))
                    if ov > worst:
                        worst = ov
                        worst_i = i
            force[i, 0] = fx
            force[i, 1] = fy
            force[i, 2] = fz
            torque[i, 0] = tx
            torque[i, 1] = ty
            torque[i, 2] = tz
        chunk_ovl[c] = worst
        chunk_ovl_idx[c] = worst_i


@numba.njit(cache=True)
def run_steps_ell(nsteps, pos, vel, angm, quat, force, torque, inv_m, inv_i, unit, axes, bound, x_ref, vel_p,
                  omega_p, pos_prev, quat_prev, nbr, nn, hist, nbr_new, nn_new, hist_new,
                  nc, inv_cell, cell_start, cell_list, cell_of, cursor,
                  box, inv_box, half, dt, skin, k_n, gn_coef, tol, margin, screened_gap, overlap_limit, chunk_a,
                  chunk_b):
    """Advance up to nsteps steps; velocities and L synchronous on entry and exit (see cpu.run_steps)."""
    builds = 0
    if nsteps <= 0:
        return OK, 0, -1, 0.0, builds
    limit2 = (skin * half) * (skin * half)
    for s in range(nsteps):
        hk = dt * half if s == 0 else dt
        kick_drift_ell(pos, vel, angm, quat, force, torque, inv_m, inv_i, x_ref, vel_p, omega_p, pos_prev,
                       quat_prev, hk, dt, box, inv_box, half, chunk_a, chunk_b)
        for c in range(chunk_b.shape[0]):
            if chunk_b[c] >= 0:
                return BAD_VALUE, s, chunk_b[c], 0.0, builds
        disp2 = 0.0
        for c in range(chunk_a.shape[0]):
            if chunk_a[c] > disp2:
                disp2 = chunk_a[c]
        if disp2 > limit2:
            bin_particles(pos, nc, inv_cell, cell_start, cell_list, cell_of, cursor)
            build_list(pos, bound, skin, box, inv_box, half, nc, cell_start, cell_list, cell_of,
                       nbr, nn, hist, nbr_new, nn_new, hist_new, x_ref)
            builds += 1
            need = 0
            for i in range(nn_new.shape[0]):
                if nn_new[i] > need:
                    need = nn_new[i]
            if need > nbr_new.shape[1]:
                return OVERFLOW, s, -1, float(need), builds
            copy_list(nbr_new, nn_new, hist_new, nbr, nn, hist)
        compute_forces_ell(pos, vel_p, omega_p, quat, axes, bound, inv_m, nbr, nn, hist, force, torque, box,
                           inv_box, half, k_n, gn_coef, dt, tol, margin, screened_gap, pos_prev, quat_prev, chunk_a,
                           chunk_b)
        worst, who = worst_overlap(chunk_a, chunk_b)
        if worst > overlap_limit:
            return OVERLAP, s, who, worst, builds
    half_kick(vel, angm, force, torque, inv_m, unit, dt * half)
    return OK, nsteps, -1, 0.0, builds


@numba.njit(cache=True)
def observe_ell(vel, angm, quat, mass, inv_i, nn, hist, half, k_n_val):
    """(E_tr, E_rot, E_rot of the two axes perpendicular to body x, contacts, elastic energy,
    max overlap (m), P_x, P_y, P_z, S_tr2, S_rot2, S_x): the last three are the Sonine moments
    sum e_tr,i^2, sum e_perp,i^2 and sum e_tr,i e_perp,i (J^2) with e_perp,i the energy of the two active
    rotational dof (engine/physics/sonine.py, d = 2)."""
    n = vel.shape[0]
    e_tr = 0.0
    e_rot = 0.0
    e_perp = 0.0
    contacts = 0
    e_spring = 0.0
    worst = 0.0
    px = 0.0
    py = 0.0
    pz = 0.0
    s_tr2 = 0.0
    s_rot2 = 0.0
    s_x = 0.0
    for i in range(n):
        m = mass[i]
        e_tr += 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        et_i = 0.5 * m * (vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2)
        px += m * vel[i, 0]
        py += m * vel[i, 1]
        pz += m * vel[i, 2]
        wb = body_omega(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], angm[i, 0], angm[i, 1], angm[i, 2],
                        inv_i[i, 0], inv_i[i, 1], inv_i[i, 2], half)
        e1 = 0.5 * wb[0] * wb[0] / inv_i[i, 0]
        ep = 0.5 * (wb[1] * wb[1] / inv_i[i, 1] + wb[2] * wb[2] / inv_i[i, 2])
        e_rot += e1 + ep
        e_perp += ep
        s_tr2 += et_i * et_i
        s_rot2 += ep * ep
        s_x += et_i * ep
        for kk in range(nn[i]):
            d = hist[i, kk, 3]
            if d > 0:
                contacts += 1
                # each pair appears in both partners' lists; frictionless: no tangential spring
                e_spring += 0.5 * contact_elastic_energy(d, 0.0, 0.0, 0.0, k_n_val, 0.0, 0.5)
                worst = max(worst, d)
    return e_tr, e_rot, e_perp, contacts // 2, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x


@numba.njit(cache=True)
def omega_from_angm(quat, angm, inv_i, half, out):
    for i in range(quat.shape[0]):
        w = space_omega(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], angm[i, 0], angm[i, 1], angm[i, 2],
                        inv_i[i, 0], inv_i[i, 1], inv_i[i, 2], half)
        out[i, 0] = w[0]
        out[i, 1] = w[1]
        out[i, 2] = w[2]


@numba.njit(cache=True)
def angm_from_omega(quat, omega, inertia, half, out):
    for i in range(quat.shape[0]):
        L = angular_momentum(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], omega[i, 0], omega[i, 1],
                             omega[i, 2], inertia[i, 0], inertia[i, 1], inertia[i, 2], half)
        out[i, 0] = L[0]
        out[i, 1] = L[1]
        out[i, 2] = L[2]


class CpuEllipsoidBackend:
    """The CPU time loop for frictionless ellipsoids; interface of :class:`engine.backends.cpu.CpuBackend`."""

    name = "cpu"

    def __init__(self, system: EllipsoidSystem, contact: ContactParams):
        if contact.k_t is not None or contact.friction not in (None, 0.0):
            raise ValueError("the ellipsoid backend is frictionless (paper 003): k_t must be None")
        self.dtype = np.float64 if contact.precision == "float64" else np.float32
        dt_ = self.dtype
        n = system.n
        self.n = n
        self.box = float(system.box_length)

        def arr(x):
            return np.array(x, dtype=dt_, order="C", copy=True)

        self.pos = arr(system.position)
        self.vel = arr(system.velocity)
        self.quat = arr(np.asarray(system.orientation) / np.linalg.norm(system.orientation, axis=1)[:, None])
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
        self.device = cpu_name()
        self.steps_done = 0
        self.builds = 0
        threads = numba.get_num_threads()
        nch = max(1, min(n, 8 * threads))
        self.chunk_a = np.zeros(nch, np.float64)
        self.chunk_b = np.zeros(nch, np.int64)
        self._setup_cells(float(np.max(self.bound)), contact.skin)
        self._alloc_lists(8)
        self.set_contact(contact)
        self._prime(system)

    # ---- set-up (as CpuBackend) ------------------------------------------------------------------

    def _setup_cells(self, rmax: float, skin: float) -> None:
        self.nc = nc = cell_grid(self.box, self.n, rmax, skin)
        self.inv_cell = nc / self.box
        self.cell_start = np.zeros(nc**3 + 1, np.int64)
        self.cursor = np.zeros(nc**3, np.int64)
        self.cell_list = np.zeros(self.n, np.int64)
        self.cell_of = np.zeros(self.n, np.int64)

    def _alloc_lists(self, max_nb: int) -> None:
        n, dt_ = self.n, self.dtype
        self.max_nb = max_nb
        self.nbr = np.zeros((n, max_nb), np.int32)
        self.nn = np.zeros(n, np.int32)
        self.hist = np.zeros((n, max_nb, SLOT), dt_)
        self.nbr_new = np.zeros_like(self.nbr)
        self.nn_new = np.zeros_like(self.nn)
        self.hist_new = np.zeros_like(self.hist)

    def _grow_lists(self, need: int) -> None:
        old = (self.nbr, self.nn, self.hist)
        self._alloc_lists(int(math.ceil(max(need, 2 * self.max_nb) / 4.0)) * 4)
        copy_list(old[0], old[1], old[2], self.nbr, self.nn, self.hist)

    def set_contact(self, contact: ContactParams) -> None:
        """Switch contact constants (thermalisation -> cooling); keeps lists and contact history."""
        if contact.k_t is not None:
            raise ValueError("the ellipsoid backend is frictionless (paper 003): k_t must be None")
        self.contact = contact
        c = self.dtype
        self.k_n = c(contact.k_n)
        self.gn_coef = c(contact.gamma_n_coef)
        self.dt = c(contact.dt)
        self.skin = c(contact.skin)
        self.box_c = c(self.box)
        self.inv_box = c(1.0 / self.box)
        self.tol = c(PW_TOL[contact.precision])
        self.margin = c(PW_SCREEN[contact.precision])
        self.screened_gap = c(-np.inf)
        self.overlap_limit = float(contact.overlap_limit)

    def _build(self) -> None:
        while True:
            bin_particles(self.pos, self.nc, self.inv_cell, self.cell_start, self.cell_list, self.cell_of,
                          self.cursor)
            build_list(self.pos, self.bound, self.skin, self.box_c, self.inv_box, self.half, self.nc,
                       self.cell_start, self.cell_list, self.cell_of, self.nbr, self.nn, self.hist,
                       self.nbr_new, self.nn_new, self.hist_new, self.x_ref)
            need = int(self.nn_new.max()) if self.n else 0
            if need <= self.max_nb:
                break
            self._grow_lists(need)
        copy_list(self.nbr_new, self.nn_new, self.hist_new, self.nbr, self.nn, self.hist)
        self.builds += 1

    def _prime(self, system: EllipsoidSystem) -> None:
        self._build()
        # a fresh list holds bounding-sphere overlaps in slot 3; no contact history at t = 0
        self.hist[:, :, 3] = np.minimum(self.hist[:, :, 3], 0)
        if system.contact_pairs is not None and len(system.contact_pairs):
            restore_springs(self.nbr, self.nn, self.hist, np.asarray(system.contact_pairs, np.int64),
                            np.asarray(system.contact_springs, self.dtype))
        self._forces()

    def _forces(self) -> None:
        compute_forces_ell(self.pos, self.vel_p, self.omega_p, self.quat, self.axes, self.bound, self.inv_m,
                           self.nbr, self.nn, self.hist, self.force, self.torque, self.box_c, self.inv_box,
                           self.half, self.k_n, self.gn_coef, self.dt, self.tol, self.margin, self.screened_gap,
                           self.pos_prev, self.quat_prev, self.chunk_a, self.chunk_b)

    # ---- time loop ---------------------------------------------------------------------------------

    def warmup(self) -> None:
        self.advance(0, _compile_only=True)

    def advance(self, nsteps: int, _compile_only: bool = False) -> None:
        """Advance nsteps steps; raises InstabilityError naming the step, the particle and the cause."""
        left = int(nsteps)
        while left > 0 or _compile_only:
            _compile_only = False
            status, done, who, value, builds = run_steps_ell(
                left, self.pos, self.vel, self.angm, self.quat, self.force, self.torque, self.inv_m,
                self.inv_i, self.unit, self.axes, self.bound, self.x_ref, self.vel_p, self.omega_p,
                self.pos_prev, self.quat_prev, self.nbr, self.nn, self.hist, self.nbr_new, self.nn_new, self.hist_new,
                self.nc,
                self.inv_cell, self.cell_start, self.cell_list, self.cell_of, self.cursor, self.box_c,
                self.inv_box, self.half, self.dt, self.skin, self.k_n, self.gn_coef, self.tol, self.margin,
                self.screened_gap, self.overlap_limit, self.chunk_a, self.chunk_b)
            self.builds += builds
            if status == OK:
                self.steps_done += done
                return
            step = self.steps_done + done
            if status == OVERFLOW:
                self._grow_lists(int(value))
                self._build()
                self._forces()
                half_kick(self.vel, self.angm, self.force, self.torque, self.inv_m, self.unit,
                          self.dt * self.half)
                self.steps_done += done + 1
                left -= done + 1
                continue
            self.steps_done = step
            raise instability_error(status, step, int(who), value, self)

    # ---- host copies (output steps only) -----------------------------------------------------------

    def observe(self) -> dict:
        e_tr, e_rot, e_perp, contacts, e_spring, worst, px, py, pz, s_tr2, s_rot2, s_x = observe_ell(
            self.vel, self.angm, self.quat, self.mass, self.inv_i, self.nn, self.hist, self.half,
            float(self.k_n))
        bmin = float(np.min(self.axes))
        return {"kinetic_energy_translational": float(e_tr), "kinetic_energy_rotational": float(e_rot),
                "kinetic_energy_rotational_active": float(e_perp), "rotational_dof": 2,
                "contacts": int(contacts), "elastic_energy": float(e_spring),
                "max_overlap": float(worst) / bmin, "momentum": (float(px), float(py), float(pz)),
                **sonine_sums(s_tr2, s_rot2, s_x, DOF_ROTATION_SPHEROID)}

    def omega(self) -> np.ndarray:
        out = np.zeros((self.n, 3), self.dtype)
        omega_from_angm(self.quat, self.angm, self.inv_i, self.half, out)
        return out

    def state(self) -> dict:
        """Copies of the state arrays in id order (angular velocity in the space frame)."""
        return {"position": self.pos.copy(), "velocity": self.vel.copy(),
                "angular_velocity": self.omega(), "orientation": self.quat.copy()}

    def contacts(self):
        """(pairs (M,2), slots (M,5)) of the list slots in contact (overlap, dashpot force in 3, 4)."""
        return collect_springs(self.pos, self.bound, self.nbr, self.nn, self.hist, self.box_c,
                               self.inv_box, self.half)
