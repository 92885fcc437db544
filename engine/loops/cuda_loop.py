"""The one CUDA time loop: kick-drift, forces, closing half kick, the many-steps cooperative kernel and the
observe reduction, built once for every particle shape and specialised at compile time by the shape's device
functions (engine/shapes/<shape>/device.py, ``make_cuda``; the interface is in engine/shapes/sphere/device.py),
which the shape's backend passes to :func:`kernels`.

This module owns the step skeleton (which phase runs when, the shared translation v += F/m hk, x += v dt
wrapped, the displacement and speed maxima that decide a list rebuild, the per-particle force accumulation
over the full Verlet list, the blow-up and overlap checks, the grid syncs of the cooperative loop, the block
reduction of the observables); a shape brings its rotation step, its pair evaluator (contact geometry and
force law) and its observables. Layout, per-scene tables, status words and the neighbour-list kernels are
engine/loops/cuda_kernels.py's; the physics stays in engine/physics/ (njit functions every backend calls).

Kernel arguments (device arrays, particle index fastest), the same for every shape:
    kick_drift(n, first, exact, pos, vel, spin, quat, force, torque, hot, inv_m, spin_inv, x_ref, ids, sc, spd,
               spf, spi, status, step, ext)
    forces(n, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, nbr, nn, hist, ids, sc, spd, spf, spi,
           status, step, ext)
    forces_kick_drift(n, par, exact, pos, pos_out, vel, vel_out, spin, quat, rad, inv_m, f_old, f_new, torque,
                      hot, spin_inv, x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step, ext)
                                                         (only for a shape with ``FUSABLE``)
    half_kick(n, vel, spin, force, torque, inv_m, spin_inv, sc, spd, spi)
    settle(n, spin, quat, sc, spd, spi, step, ext)       (only for a shape with ``settle_one``)
    run_steps(n, nmax, first, skip_kick, thr, pos, vel, spin, quat, f0, f1, torque, hot, inv_m, spin_inv, rad,
              x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0, ext)
    run_steps_fused(n, nmax, first, thr, pos, pos_b, vel, vel_b, spin, spin_b, quat, f0, f1, torque, hot, inv_m,
                    spin_inv, rad, x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0, ext)
                                                         (only for a shape with ``MULTISTEP_FUSABLE``)
    observe(pos, vel, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, spi, ext, acc)
    forces_observe(n, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, spin_inv, nbr, nn, hist, ids, sc,
                   spd, spf, spi, status, step, ext, obs_rad, mass, inertia, acc, row)
                                                         (only for a shape with ``OBSERVES_AFTER_FORCES``; one scene)
    forces_observe_kick_drift(<forces_kick_drift's arguments>, obs_rad, mass, inertia, acc, row)
                                                         (only for a shape with ``FUSABLE``; one scene)
``spin`` is the rotational state the torque kicks (spheres: angular velocity; spheroids: angular momentum),
``rad`` the list radius, ``ext`` a tuple of the shape's own arrays; f_old/f_new (f0/f1) are the double buffer
of the forces (a shape that does not read other particles' old forces gets the same array twice). ``hot`` (uint8,
N) says which particles' force buffers hold something other than zero (``SKIP_COLD``, below): bit 0, the force or
torque of the last force pass was not zero; bit 1, that of the pass before; bit 2, the velocity may differ from the
other half of the fused step's double buffer (``KEEP_VELOCITY``, below); 0xFF when the buffers were written outside
the force passes (allocation, a rebuild's permutation): every pass writes them, every kick reads them.
``exact`` = 0: kick_drift does not read x_ref and reports no displacement, only the speeds (the host bounds the
displacements by the sum of max |v| dt, engine/loops/cuda_stepping.py). With one scene (``spi`` of one row) no
kernel reads ``sc``: every particle is in scene 0.
"""

from __future__ import annotations

import numpy as np
from numba import cuda
from numba.cuda import types as ct

from engine.loops import cuda_kernels as L
from engine.loops.cuda_cache import SIM, cache_kernels
from engine.loops.cuda_kernels import (D_BOX, D_DT, D_HP, D_IM0, D_INVBOX, F_LIM2INV, F_OVL, F_V2F, I_ACTIVE,
                                          I_N, I_START, NSS, S_D2, S_D2B, S_D2C, S_RUN_DONE, S_RUN_REBUILD, S_V2,
                                          S_V2B, SS0, SS_BAD_ID, SS_OVL, SS_OVL_ID)
from engine.physics.contact import min_image
from engine.physics.integrate import drift_wrap, kick

_cache: dict = {}

#: True: a force pass stores a particle's force and torque only where they are not zero or were not at either of
#: the two previous passes (the double buffer's other half and the torque then still hold the zeros they need),
#: and marks in ``hot`` whether they are; the kick-drift reads the force and torque of a particle only where
#: ``hot`` says they are not zero. Most of a dilute gas is out of contact at any step: 24 bytes a particle-step of
#: stores (float32, rough) and as many of loads are saved for 2 bytes of flags. The buffers hold the same numbers
#: as with every store made (a force summed from +0.0 is never -0.0), so the trajectory is the same bits.
#: False: every pass stores, every kick reads (bench/e2e.py --off skip_cold, the tests' reference).
SKIP_COLD = True

#: True (with SKIP_COLD): the fused force-and-kick-drift pass stores a velocity component into the other half of the
#: double buffer only where that half may not hold the same number already (``hot`` bit 2) or the component is kicked
#: by a force that is not zero. Bit 2 is kept so: a fused pass sets it where its force is not zero (the halves then
#: differ by the kick) and clears it elsewhere (they hold the same velocity); any other force pass sets it where its
#: force is not zero and leaves it set where it was (the in-place kicks after such a pass, the next call's first
#: kick-drift and the closing half kick, change a velocity only where that force is not zero); 0xFF sets it. Most of
#: a dilute gas is under no force: up to 12 bytes (float32) a particle-step are saved. A kick by a zero force,
#: v = u + 0, is the number u, so the trajectory is the same bits (a velocity of -0.0 may be kept where the store would
#: make it +0.0; a position never differs). False: every velocity stored (bench/e2e.py --off keep_velocity).
KEEP_VELOCITY = True

#: blocks of the force kernel (and of the fused force-and-kick-drift kernel) each SM must hold, by (shape,
#: precision, shape flags) or "*" (its launch bounds: the compiler keeps the registers to 65536 / (TPB x blocks)
#: and spills the rest); a specialisation not named is
#: left to the compiler. Set where it measurably pays (docs/performance.md, "GPU: the time loop"): smooth
#: float64 spheres, 96 registers and 2 blocks of 256 threads left alone, run their force kernel with 3 blocks
#: (80 registers, 20 bytes spilled on the rare contact path) 5 % faster on an H100; smooth float32 spheres, whose
#: fused kernel takes 72 registers (3 blocks, 35 % of the warps active), with 4 blocks: the 8M-sphere loop 14 %
#: faster on an H200 (bench loop_ab --variants default blocks=4); rough float32 spheres (80 registers left alone,
#: 34 % of the warps active) with 4 blocks: the 8M-sphere loop 8-10 % faster on an H200 at phi = 0.058 and 7 % at
#: phi = 0.2 (bench loop_ab --cases rough-8M-f32 --variants default blocks=4 blocks=5: 5 blocks lose), in mixed
#: precision (which shares the float32 key) 21 % (rough-8M-mixed against blocks=0); with a Coulomb cap 27 %
#: (coulomb-8M-f32). Rough float64 spheres are held to 2 blocks: their force kernel, left alone, took 130 registers
#: with the ``hot`` flags (one block of 256 threads an SM: 11 % of the warps active, the kernel 1.7 times as long on
#: an H200; bench step_bytes --cases rough-2M-f64); with a Coulomb cap the 2M-sphere loop is 42 % faster at 2 blocks
#: than left alone (coulomb-2M-f64). Spheroids are left alone: forced to 2 or 3 blocks their 1M rough loop ran 2.8
#: and 4.7 times as long (spheroids-rough-1M-f64).
#: None: no launch bounds anywhere (bench loop_ab's variants).
FORCES_BLOCKS_PER_SM: dict | None = {("sphere", "<f8", (False, False, False)): 3,
                                     ("sphere", "<f8", (False, False, True)): 3,
                                     ("sphere", "<f4", (False, False, False)): 4,
                                     ("sphere", "<f4", (False, False, True)): 4,
                                     ("sphere", "<f4", (True, False, False)): 4,
                                     ("sphere", "<f4", (True, False, True)): 4,
                                     ("sphere", "<f4", (True, True, False)): 4,
                                     ("sphere", "<f4", (True, True, True)): 4,
                                     ("sphere", "<f8", (True, False, False)): 2,
                                     ("sphere", "<f8", (True, False, True)): 2,
                                     ("sphere", "<f8", (True, True, False)): 2,
                                     ("sphere", "<f8", (True, True, True)): 2}

#: Blocks of 256 threads per SM that the force passes which also sum a record's observables (forces_observe,
#: forces_observe_kick_drift) are compiled for, keyed as FORCES_BLOCKS_PER_SM; absent or None: left to the
#: compiler. Smooth spheres, left alone, take 123 registers (float32: 2 blocks, 25 % of the warps active); with 3
#: blocks the 8M-sphere loop with 200 records is 6 % (float32) and 14 % (float64) faster on an H200 (bench loop_ab
#: --variants default observe_blocks=3 observe_blocks=4; 4 blocks gained less). Rough float64 spheres, 170 registers
#: left alone (one block), with 2 blocks: the 2M-sphere loop with 200 records 6 % faster on an H200 (7.82e9 against
#: 7.37e9, bench loop_ab --cases rough-2M-f64 --variants default observe_blocks=2). Rough float32 spheres, with the
#: list's history in packed rows, left alone, lost a block: the 8M-sphere loop with 200 records at 1.00e10; with 3
#: blocks 1.19e10, with 2 1.17e10 (H200, bench loop_ab --cases rough-8M-f32 --variants default observe_blocks=2
#: observe_blocks=3).
OBSERVE_BLOCKS_PER_SM: dict | None = {("sphere", "<f8", (False, False, False)): 3,
                                      ("sphere", "<f8", (False, False, True)): 3,
                                      ("sphere", "<f4", (False, False, False)): 3,
                                      ("sphere", "<f4", (False, False, True)): 3,
                                      ("sphere", "<f4", (True, False, False)): 3,
                                      ("sphere", "<f4", (True, False, True)): 3,
                                      ("sphere", "<f8", (True, False, False)): 2,
                                      ("sphere", "<f8", (True, False, True)): 2}


#: Blocks of 256 threads per SM the per-phase kick-drift kernel (``kick_drift``: rough spheres run it every step,
#: smooth ones fuse it into the force pass) is compiled for, keyed as FORCES_BLOCKS_PER_SM; absent or None: left to
#: the compiler. Rough spheres with 4 (H200, bench loop_ab --cases rough-8M-mixed rough-2M-f64 --variants default
#: kick_blocks=4): mixed precision 5 % faster (its kick-drift holds float64 positions beside float32 velocities),
#: float64 2 % (with a Coulomb cap too: coulomb-2M-f64); float32 takes 64 registers anyway (6 and 8 blocks lost 10
#: and 27 %).
KICK_DRIFT_BLOCKS_PER_SM: dict | None = {("sphere", "<f4", (True, False, False)): 4,
                                         ("sphere", "<f4", (True, False, True)): 4,
                                         ("sphere", "<f8", (True, False, False)): 4,
                                         ("sphere", "<f8", (True, False, True)): 4,
                                         ("sphere", "<f8", (True, True, False)): 4,
                                         ("sphere", "<f8", (True, True, True)): 4}


def kernels(shape: str, dtype, flags: tuple, uniform: bool, tpb: int, device) -> dict:
    """The kernel set of one shape and specialisation (cached): the neighbour-list kernels of
    cuda_kernels.grid_kernels, the time loop of this module and the shape's own kernels. ``flags``: the shape's
    compile-time switches in the order of its ``FLAGS``; ``device``: the shape's device module (its
    ``make_cuda``), which the caller passes in: this module names no shape and no shape registry."""
    flags = tuple(bool(f) for f in flags)
    key = (shape, np.dtype(dtype).str, flags, uniform, tpb, force_blocks(shape, dtype, flags),
           observe_blocks(shape, dtype, flags), bool(SKIP_COLD), kick_drift_blocks(shape, dtype, flags),
           bool(SKIP_COLD and KEEP_VELOCITY))
    if key not in _cache:
        dt = np.dtype(dtype).type
        parts = device.make_cuda(L, dt, uniform, tpb, *key[2])
        k = dict(L.grid_kernels(dtype, uniform, tpb))
        k.update(cache_kernels(_make(parts, dt, uniform, tpb, key[5], key[6], key[7], key[8], key[9]),
                               ("loop",) + key[:2] + tuple(map(str, key[2:]))))
        k.update(cache_kernels(dict(parts.kernels), ("own",) + key[:2] + tuple(map(str, key[2:]))))
        _cache[key] = k
    return _cache[key]


def force_blocks(shape: str, dtype, flags: tuple):
    """Blocks per SM the force kernels are compiled for (:data:`FORCES_BLOCKS_PER_SM`), or None."""
    return _blocks(FORCES_BLOCKS_PER_SM, shape, dtype, flags)


def observe_blocks(shape: str, dtype, flags: tuple):
    """Blocks per SM the force passes that sum a record are compiled for (:data:`OBSERVE_BLOCKS_PER_SM`), or None."""
    return _blocks(OBSERVE_BLOCKS_PER_SM, shape, dtype, flags)


def kick_drift_blocks(shape: str, dtype, flags: tuple):
    """Blocks per SM the kick-drift kernel is compiled for (:data:`KICK_DRIFT_BLOCKS_PER_SM`), or None."""
    return _blocks(KICK_DRIFT_BLOCKS_PER_SM, shape, dtype, flags)


def _blocks(table: dict | None, shape: str, dtype, flags: tuple):
    """The entry of ``table`` for this specialisation (or its "*" entry), or None: no table, no entry, or the CUDA
    simulator, whose jit takes no launch bounds."""
    if not table or SIM:
        return None
    return table.get((shape, np.dtype(dtype).str, flags), table.get("*"))


def _make(P, DT, UNIFORM, TPB, FORCE_BLOCKS=None, OBSERVE_BLOCKS=None,  # noqa: C901  (a closure per specialisation)
          SKIP=True, KICK_BLOCKS=None, KEEP=True):
    ZERO = DT(0)
    HALF = DT(0.5)
    WIDEN_REF = DT == np.float64    # x_ref may be float32 beside float64 positions (cuda_memory.xref_dtype)
    BIG = DT(np.finfo(DT).max)
    f64 = np.float64
    SH2 = 2 * TPB
    PREDICTS, TORQUE = P.PREDICTS, P.TORQUE
    translated, rotate, spin_kick = P.translated, P.rotate, P.spin_kick
    particle, pair, observe_one = P.particle, P.pair, P.observe_one
    observes_after_forces = bool(getattr(P, "OBSERVES_AFTER_FORCES", P.FUSABLE))
    observe_after_forces = P.observe_after_forces if observes_after_forces else None

    block_max2, fail = L.device_helpers(TPB)

    scene_of = L.scene_of

    # ---- step phases (device functions shared by the one-step kernels and the multi-step kernel) ------

    @cuda.jit(device=True)
    def translate(k, i, x_old, u, f, xr, exact, im, hk, hp, dt, box, inv_box, pos_out, vel_out, kept, ext):
        """Component k of particle i's translation: v = u + f im hk, x = x_old + v dt wrapped (stored), the
        shape's ``translated`` hook; returns the squared displacement from xr (0 unless ``exact``) and v^2.
        ``kept`` (vel_out holds u already: it is the array u was read from, or the fused pass's other half where
        ``hot`` bit 2 is clear): a kick by f = 0 stores nothing (v = u + 0 is u: the same number, a -0.0 kept), the
        store of a particle under no force (most of a dilute gas) is saved."""
        v = kick(u, f, im, hk)
        if not kept or f != ZERO:
            vel_out[k, i] = v
        translated(k, i, x_old, v, f, im, hp, ext)
        x = drift_wrap(x_old, v, dt, box, inv_box)
        pos_out[k, i] = x
        d = min_image(x - xr, box, inv_box, HALF) if exact else ZERO
        return d * d, v * v

    @cuda.jit(device=True)
    def kick_drift_one(i, first, exact, kept, pos, pos_out, vel, vel_out, spin, quat, fx, fy, fz, torque, torqued,
                       inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi, status, step, ext):
        """v += F/m hk (hk = dt/2 on the first step of a call, else dt; F = (fx, fy, fz)), x += v dt wrapped,
        then the shape's rotation step (``torqued`` False: the torque is zero, not read); returns the normalised
        squared displacement since the build (0 unless ``exact``) and speed (0, 0 for a skipped scene). Reads pos
        and vel, writes pos_out and vel_out (the same arrays, or the other half of the fused kernel's double buffer;
        ``kept``: vel_out holds vel's numbers already, a velocity component under no force is not stored again; a
        skipped scene's particles are copied across). Every read is issued before the first write: one memory
        latency, not one per component (the compiler may not move a read past a write that could alias it)."""
        s = scene_of(i, sc, spi)
        x0 = pos[0, i]
        x1 = pos[1, i]
        x2 = pos[2, i]
        u0 = vel[0, i]
        u1 = vel[1, i]
        u2 = vel[2, i]
        r0 = r1 = r2 = ZERO
        if exact and WIDEN_REF:
            # a float32 x_ref beside float64 positions, widened explicitly: the CUDA simulator's NumPy scalars would
            # otherwise round the displacement to float32 (the GPU's typing widens it anyway)
            r0 = ZERO + x_ref[0, i]
            r1 = ZERO + x_ref[1, i]
            r2 = ZERO + x_ref[2, i]
        elif exact:
            r0 = x_ref[0, i]
            r1 = x_ref[1, i]
            r2 = x_ref[2, i]
        if spi[s, I_ACTIVE] == 0:
            for k in range(3):
                pos_out[k, i] = pos[k, i]
                vel_out[k, i] = vel[k, i]
            return 0.0, 0.0
        dt = spd[s, D_DT]
        if PREDICTS:
            hp = spd[s, D_HP]
            hk = hp if first else dt
        else:
            hk = spd[s, D_HP] if first else dt
            hp = hk
        box = spd[s, D_BOX]
        inv_box = spd[s, D_INVBOX]
        im = spd[s, D_IM0] if UNIFORM else inv_m[i]
        d0, w0 = translate(0, i, x0, u0, fx, r0, exact, im, hk, hp, dt, box, inv_box, pos_out, vel_out,
                           kept, ext)
        d1, w1 = translate(1, i, x1, u1, fy, r1, exact, im, hk, hp, dt, box, inv_box, pos_out, vel_out,
                           kept, ext)
        d2, w2 = translate(2, i, x2, u2, fz, r2, exact, im, hk, hp, dt, box, inv_box, pos_out, vel_out,
                           kept, ext)
        dsp = ZERO + d0 + d1 + d2
        v2 = ZERO + w0 + w1 + w2
        ok = rotate(i, s, spin, quat, torque, torqued, spin_inv, ext, spd, spi, hk, hp, dt, step)
        if not (dsp < BIG) or not (v2 < BIG) or not ok:
            fail(status, spi, s, SS_BAD_ID, ids[i], step)
            return 0.0, 0.0
        return f64(dsp) * spf[s, F_LIM2INV], f64(v2) * spf[s, F_V2F]

    @cuda.jit(device=True)
    def forces_one(i, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, nbr, nn, hist, ids, sc, spd,
                   spf, spi, status, step, ext, fused):
        """Contact forces and torque on particle i from its list (the shape's pair evaluator per slot, summed
        in list order; slots q = nn[i] .. nn[i + 1] - 1 hold the neighbour nbr[q] and its history
        hist[:, q]); per-slot history advanced in place; a scene whose overlap exceeds its limit stops.
        Returns the force (stored in f_new too; zero for a skipped scene), whether force or torque is not zero
        (``hot`` bit 0) and whether the other half of the fused step's velocity buffer held this one's numbers
        before the pass (bit 2 clear, ``KEEP``). The stores are skipped where both are zero and were at the two
        passes before (``SKIP``: f_new, the buffer written two passes ago, and the torque, written one pass ago,
        hold zeros already). ``fused``: the pass kicks with this force into the other half (bit 2 becomes whether
        the force is not zero), else an in-place kick may follow (bit 2 is set where it is not zero)."""
        s = scene_of(i, sc, spi)
        # the particle's own reads are issued before the scene's active flag is known (harmless for a stopped
        # scene, whose slots are then left alone): one memory latency less per particle in a latency-bound kernel
        p = particle(i, s, pos, rad, inv_m, ids, spd)
        h0 = nn[i]          # the row's first history slot, and its count from the next row's (cuda_kernels: the
        m = nn[i + 1] - h0  # list's layout; the two loads share a cache line across the warp)
        was = hot[i] if SKIP else 7
        if spi[s, I_ACTIVE] == 0:
            return ZERO, ZERO, ZERO, False, False
        acc = (ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO)
        for q in range(h0, h0 + m):
            acc = pair(i, q, nbr[q], s, p, acc, pos, vel, spin, quat, rad, inv_m, f_old, hist, ids, ext, spd)
        fx, fy, fz, tx, ty, tz, worst = acc
        now = not (fx == ZERO and fy == ZERO and fz == ZERO)
        if TORQUE:
            now = now or not (tx == ZERO and ty == ZERO and tz == ZERO)
        if now or (was & 3) != 0:
            f_new[0, i] = fx
            f_new[1, i] = fy
            f_new[2, i] = fz
            if TORQUE:
                torque[0, i] = tx
                torque[1, i] = ty
                torque[2, i] = tz
        if SKIP:
            moved = now if fused else (now or (was & 4) != 0)
            flags = (1 if now else 0) | ((was & 1) << 1) | (4 if (moved or not KEEP) else 0)
            if flags != was:
                hot[i] = flags
        w64 = f64(worst)
        if w64 > spf[s, F_OVL]:
            b = SS0 + NSS * s
            cuda.atomic.max(status, b + SS_OVL, w64)
            fail(status, spi, s, SS_OVL_ID, ids[i], step)
        return fx, fy, fz, now, KEEP and (was & 4) == 0

    # ---- one-step kernels (large scenes: launch overhead is negligible) ---------------------------------

    @cuda.jit(device=True)
    def clear_maxima(i0, status):
        """Thread 0 of a force pass resets the per-step maxima, both parities, for the next kick-drift
        (stream-ordered after the status copy of the previous one)."""
        if i0 == 0:
            status[S_D2] = 0.0
            status[S_V2] = 0.0
            status[S_D2B] = 0.0
            status[S_V2B] = 0.0

    @cuda.jit(device=True)
    def clear_other_parity(i0, par, status):
        """Thread 0 of a fused pass of parity ``par`` clears the other parity's maxima for the next launch (the host
        copied them out after the previous one)."""
        if i0 == 0:
            if par == 0:
                status[S_D2B] = 0.0
                status[S_V2B] = 0.0
            else:
                status[S_D2] = 0.0
                status[S_V2] = 0.0

    @cuda.jit(device=True)
    def publish_maxima(sh, md, mv, par, status):
        """The block's largest squared displacement and speed into the status slots of parity ``par``."""
        block_max2(sh, md, mv)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_D2 if par == 0 else S_D2B, sh[0])
            cuda.atomic.max(status, S_V2 if par == 0 else S_V2B, sh[TPB])

    @(cuda.jit(launch_bounds=(TPB, KICK_BLOCKS)) if KICK_BLOCKS else cuda.jit)
    def kick_drift(n, first, exact, pos, vel, spin, quat, force, torque, hot, inv_m, spin_inv, x_ref, ids, sc, spd,
                   spf, spi, status, step, ext):
        sh = cuda.shared.array(SH2, ct.float64)
        md = 0.0
        mv = 0.0
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            # a particle whose last force pass left force and torque zero (hot bit 0 clear): neither is read
            pushed = (hot[i] & 1) != 0 if SKIP else True
            fx = fy = fz = ZERO
            if pushed:
                fx = force[0, i]
                fy = force[1, i]
                fz = force[2, i]
            d2, v2 = kick_drift_one(i, first, exact, True, pos, pos, vel, vel, spin, quat, fx, fy, fz, torque, pushed,
                                    inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi, status, step, ext)
            md = max(md, d2)
            mv = max(mv, v2)
        block_max2(sh, md, mv)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_D2, sh[0])
            cuda.atomic.max(status, S_V2, sh[TPB])

    @(cuda.jit(launch_bounds=(TPB, FORCE_BLOCKS)) if FORCE_BLOCKS else cuda.jit)
    def forces(n, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, nbr, nn, hist, ids, sc, spd, spf,
               spi, status, step, ext):
        i0 = cuda.grid(1)
        clear_maxima(i0, status)
        for i in range(i0, n, cuda.gridsize(1)):
            forces_one(i, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, nbr, nn, hist, ids, sc, spd,
                       spf, spi, status, step, ext, False)

    @(cuda.jit(launch_bounds=(TPB, FORCE_BLOCKS)) if FORCE_BLOCKS else cuda.jit)
    def forces_kick_drift(n, par, exact, pos, pos_out, vel, vel_out, spin, quat, rad, inv_m, f_old, f_new, torque,
                          hot, spin_inv, x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step, ext):
        """The forces of step ``step`` and the kick-drift of step + 1, one pass over the particles (a shape with
        ``FUSABLE``: its pair evaluator reads no neighbour state the kick-drift rewrites but positions and
        velocities). The pair evaluators read the neighbours' positions and velocities of step ``step`` from
        pos, vel while this pass writes step + 1's into pos_out, vel_out: no particle's new state is seen by
        another's forces of the same step, and the trajectory is that of the two kernels forces then
        kick_drift. The maxima go to the status slots of parity ``par`` (S_D2/S_V2 or S_D2B/S_V2B) and the
        other parity's are cleared for the next launch (the host copied them out after the previous launch)."""
        sh = cuda.shared.array(SH2, ct.float64)
        i0 = cuda.grid(1)
        clear_other_parity(i0, par, status)
        md = 0.0
        mv = 0.0
        for i in range(i0, n, cuda.gridsize(1)):
            fx, fy, fz, pushed, kept = forces_one(i, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot,
                                                  nbr, nn, hist, ids, sc, spd, spf, spi, status, step, ext, True)
            d2, v2 = kick_drift_one(i, 0, exact, kept, pos, pos_out, vel, vel_out, spin, quat, fx, fy, fz, torque,
                                    pushed, inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi, status, step + 1, ext)
            md = max(md, d2)
            mv = max(mv, v2)
        publish_maxima(sh, md, mv, par, status)

    @cuda.jit
    def half_kick(n, vel, spin, force, torque, inv_m, spin_inv, sc, spd, spi):
        """Closing half kick (velocities and the rotational state synchronous with positions)."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            s = scene_of(i, sc, spi)
            if spi[s, I_ACTIVE] == 0:
                continue
            hk = spd[s, D_HP]
            im = spd[s, D_IM0] if UNIFORM else inv_m[i]
            for k in range(3):
                vel[k, i] = kick(vel[k, i], force[k, i], im, hk)
            spin_kick(i, s, spin, torque, spin_inv, spd, hk)

    settle_one = P.settle_one

    @cuda.jit
    def settle(n, spin, quat, sc, spd, spi, step, ext):
        """The shape's end-of-call work (``settle_one``: spheres bring their lazy orientations up to date), before
        the closing half kick; launched only when the shape has some."""
        for i in range(cuda.grid(1), n, cuda.gridsize(1)):
            settle_one(i, scene_of(i, sc, spi), spin, quat, ext, spd, spi, step)

    # ---- many steps per launch (small scenes and ensembles: launch overhead paid once per chunk) -------

    @cuda.jit(device=True)
    def begin_run(g, i0, status):
        """The many-steps kernels' start: their status words cleared (by thread 0), then a grid sync."""
        if i0 == 0:
            status[S_D2] = 0.0
            status[S_D2B] = 0.0
            status[S_D2C] = 0.0
            status[S_RUN_DONE] = 0.0
            status[S_RUN_REBUILD] = 0.0
        g.sync()

    @cuda.jit
    def run_steps(n, nmax, first, skip_kick, thr, pos, vel, spin, quat, f0, f1, torque, hot, inv_m, spin_inv, rad,
                  x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0, ext):
        """Up to nmax whole steps in one cooperative launch, the phases separated by grid syncs.

        Stops early, after the drift of a step and before its forces, when a particle has moved more than
        sqrt(thr) L_v/2 since the list build (thr = 1: the rebuild rule; thr = 1/4: the L_v/4 signal of the
        pipelined CPU-list mode): status[S_RUN_REBUILD] = 1 and status[S_RUN_DONE] = the whole steps
        completed (the host rebuilds or starts a CPU build, computes that step's forces and relaunches). Step
        st reads forces from f0 when st is even (f1 when odd) and writes the other buffer. skip_kick = 1: the
        drift of step 0 is already done (the host computes its forces first).
        """
        g = cuda.cg.this_grid()
        sh = cuda.shared.array(SH2, ct.float64)
        i0 = cuda.grid(1)
        stride = cuda.gridsize(1)
        begin_run(g, i0, status)
        done = 0
        for st in range(nmax):
            even = (st & 1) == 0
            slot = S_D2 if even else S_D2B
            if even:
                fa = f0
                fb = f1
            else:
                fa = f1
                fb = f0
            step = step0 + st
            if not (st == 0 and skip_kick != 0):
                if i0 == 0:
                    status[S_D2B if even else S_D2] = 0.0  # the other parity's slot, free until next step
                md = 0.0
                for i in range(i0, n, stride):
                    d2, v2 = kick_drift_one(i, first if st == 0 else 0, 1, True, pos, pos, vel, vel, spin, quat,
                                            fa[0, i], fa[1, i], fa[2, i], torque, True, inv_m, spin_inv, x_ref, ids,
                                            sc, spd, spf, spi, status, step, ext)
                    md = max(md, d2)
                block_max2(sh, md, 0.0)
                if cuda.threadIdx.x == 0:
                    cuda.atomic.max(status, slot, sh[0])
                g.sync()
                if status[slot] > thr:
                    break
            for i in range(i0, n, stride):
                forces_one(i, pos, vel, spin, quat, rad, inv_m, fa, fb, torque, hot, nbr, nn, hist, ids, sc, spd,
                           spf, spi, status, step, ext, False)
            done += 1
            g.sync()
        if i0 == 0:
            status[S_RUN_DONE] = f64(done)
            status[S_RUN_REBUILD] = 1.0 if done < nmax else 0.0

    @cuda.jit(device=True)
    def drift_slot(st):
        """The status slot of the displacement maximum of step st's drift in run_steps_fused (three in rotation)."""
        r = st % 3
        return S_D2 if r == 0 else (S_D2B if r == 1 else S_D2C)

    @cuda.jit
    def run_steps_fused(n, nmax, first, thr, pos, pos_b, vel, vel_b, spin, spin_b, quat, f0, f1, torque, hot, inv_m,
                        spin_inv, rad, x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step0, ext):
        """run_steps with one grid sync a step (a shape with ``MULTISTEP_FUSABLE``): the drift of step 0, then
        for each step st one pass of the forces of st and the drift of st + 1, as cuda_loop's
        ``forces_kick_drift`` does for one step. Positions, velocities and spins are double-buffered: step st's
        state is read from the first half (pos, vel, spin) when st is even and from the second (pos_b, vel_b,
        spin_b) when odd, and the drift of st + 1 writes the other half, so no particle's new state is seen by
        another's forces of the same step and the trajectory is that of run_steps. The launch ends after the
        forces of step nmax - 1, or, like run_steps, after the drift of the first step whose largest displacement
        exceeds the threshold (status[S_RUN_REBUILD] = 1); status[S_RUN_DONE] = the whole steps done; the state
        is then in the half of parity S_RUN_DONE (after an exit) or S_RUN_DONE - 1. The displacement maxima rotate
        through three slots: a slot is cleared one pass before it is written and read after that pass's sync, so
        no thread clears a slot that another may still read; on exit S_D2 holds the exiting drift's maximum."""
        i0 = cuda.grid(1)
        stride = cuda.gridsize(1)
        sh = cuda.shared.array(SH2, ct.float64)
        g = cuda.cg.this_grid()
        begin_run(g, i0, status)
        md = 0.0
        for i in range(i0, n, stride):
            d2, v2 = kick_drift_one(i, first, 1, True, pos, pos, vel, vel, spin, quat, f0[0, i], f0[1, i], f0[2, i],
                                    torque, True, inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi, status, step0, ext)
            md = max(md, d2)
        block_max2(sh, md, 0.0)
        if cuda.threadIdx.x == 0:
            cuda.atomic.max(status, S_D2, sh[0])
        g.sync()
        exit_max = status[S_D2]
        done = 0
        if not (exit_max > thr):
            for st in range(nmax):
                if (st & 1) == 0:
                    fa, fb = f0, f1
                    p_in, p_out, v_in, v_out, w_in, w_out = pos, pos_b, vel, vel_b, spin, spin_b
                else:
                    fa, fb = f1, f0
                    p_in, p_out, v_in, v_out, w_in, w_out = pos_b, pos, vel_b, vel, spin_b, spin
                step = step0 + st
                more = st + 1 < nmax
                slot = drift_slot(st + 1)
                if i0 == 0:
                    status[drift_slot(st + 2)] = 0.0
                md = 0.0
                for i in range(i0, n, stride):
                    # (not ``fused``: this kernel stores every velocity and never runs beside forces_kick_drift)
                    fx, fy, fz, pushed, _ = forces_one(i, p_in, v_in, w_in, quat, rad, inv_m, fa, fb, torque, hot,
                                                       nbr, nn, hist, ids, sc, spd, spf, spi, status, step, ext, False)
                    if more:
                        for k in range(3):
                            w_out[k, i] = w_in[k, i]
                        d2, v2 = kick_drift_one(i, 0, 1, False, p_in, p_out, v_in, v_out, w_out, quat, fx, fy, fz,
                                                torque, pushed, inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi,
                                                status, step + 1, ext)
                        md = max(md, d2)
                done += 1
                if not more:
                    break
                block_max2(sh, md, 0.0)
                if cuda.threadIdx.x == 0:
                    cuda.atomic.max(status, slot, sh[0])
                g.sync()
                exit_max = status[slot]
                if exit_max > thr:
                    break
        if i0 == 0:
            status[S_RUN_DONE] = f64(done)
            status[S_RUN_REBUILD] = 1.0 if done < nmax else 0.0
            status[S_D2] = exit_max

    # ---- observables ----------------------------------------------------------------------------------

    NOBS = P.NOBS
    block_accumulate = L.observe_reducer(TPB, NOBS, P.OBS_MAX)
    SH_OBS = NOBS * TPB

    @cuda.jit
    def observe(pos, vel, spin, quat, rad, mass, inertia, nbr, nn, hist, spd, spf, spi, ext, acc):
        """acc[s] += the shape's observe sums (its ``observe_one``), one slot a maximum; per particle in
        float64, one block row per scene (blockIdx.y = s), reduced per block (observe_reducer): O(blocks)
        atomics, not O(N) on K x NOBS addresses."""
        s = cuda.blockIdx.y
        sh = cuda.shared.array(SH_OBS, ct.float64)
        vals = cuda.local.array(NOBS, ct.float64)
        for q in range(NOBS):
            vals[q] = 0.0
        if spi[s, I_ACTIVE] != 0:
            a0 = spi[s, I_START]
            for li in range(cuda.blockIdx.x * TPB + cuda.threadIdx.x, spi[s, I_N], cuda.gridDim.x * TPB):
                j = a0 + li
                observe_one(j, s, vals, vel[0, j], vel[1, j], vel[2, j], pos, spin, quat, rad, mass, inertia, nbr, nn,
                            hist, spd, spf, ext)
        block_accumulate(sh, vals, acc, s)

    @cuda.jit(device=True)
    def observe_synced(i, vals, fx, fy, fz, pos, vel, spin, quat, inv_m, obs_rad, mass, inertia, nbr, nn, hist, spd,
                       spf, ext, torque, spin_inv):
        """Particle i's observe sums (one scene) from its velocity half a step behind, brought level with the
        positions in registers, v = u + F/m dt/2 (the closing half kick's expression), and not stored; called
        right after particle i's force pass (the shape's ``observe_after_forces``)."""
        im = spd[0, D_IM0] if UNIFORM else inv_m[i]
        hk = spd[0, D_HP]
        observe_after_forces(i, 0, vals, kick(vel[0, i], fx, im, hk), kick(vel[1, i], fy, im, hk),
                             kick(vel[2, i], fz, im, hk), pos, spin, quat, obs_rad, mass, inertia, nbr, nn, hist, spd,
                             spf, ext, torque, spin_inv)

    @(cuda.jit(launch_bounds=(TPB, OBSERVE_BLOCKS)) if OBSERVE_BLOCKS else cuda.jit)
    def forces_observe(n, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, spin_inv, nbr, nn, hist, ids,
                       sc, spd, spf, spi, status, step, ext, obs_rad, mass, inertia, acc, row):
        """The forces of ``step`` (as ``forces``) and, in the same pass, the observe sums of the state they complete
        into acc[row] (as ``observe``): one scene of a shape with ``OBSERVES_AFTER_FORCES`` (its force pass leaves
        the spins alone), velocities and spins half a step behind the positions (:func:`observe_synced`): the state
        stays so, and the next step's kick is a whole one."""
        sh = cuda.shared.array(SH_OBS, ct.float64)
        vals = cuda.local.array(NOBS, ct.float64)
        for q in range(NOBS):
            vals[q] = 0.0
        i0 = cuda.grid(1)
        clear_maxima(i0, status)
        if spi[0, I_ACTIVE] != 0:
            for i in range(i0, n, cuda.gridsize(1)):
                fx, fy, fz, _, _ = forces_one(i, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot, nbr,
                                              nn, hist, ids, sc, spd, spf, spi, status, step, ext, False)
                observe_synced(i, vals, fx, fy, fz, pos, vel, spin, quat, inv_m, obs_rad, mass, inertia, nbr, nn,
                               hist, spd, spf, ext, torque, spin_inv)
        block_accumulate(sh, vals, acc, row)

    @(cuda.jit(launch_bounds=(TPB, OBSERVE_BLOCKS)) if OBSERVE_BLOCKS else cuda.jit)
    def forces_observe_kick_drift(n, par, exact, pos, pos_out, vel, vel_out, spin, quat, rad, inv_m, f_old, f_new,
                                  torque, hot, spin_inv, x_ref, nbr, nn, hist, ids, sc, spd, spf, spi, status, step,
                                  ext, obs_rad, mass, inertia, acc, row):
        """``forces_kick_drift`` with the observe sums of the state its forces complete into acc[row], as
        ``forces_observe`` (one scene): a record inside an advance call costs no pass and no wait of its own."""
        sh = cuda.shared.array(SH2, ct.float64)
        sh_obs = cuda.shared.array(SH_OBS, ct.float64)
        i0 = cuda.grid(1)
        clear_other_parity(i0, par, status)
        vals = cuda.local.array(NOBS, ct.float64)
        for q in range(NOBS):
            vals[q] = 0.0
        md = 0.0
        mv = 0.0
        for i in range(i0, n, cuda.gridsize(1)):
            fx, fy, fz, pushed, kept = forces_one(i, pos, vel, spin, quat, rad, inv_m, f_old, f_new, torque, hot,
                                                  nbr, nn, hist, ids, sc, spd, spf, spi, status, step, ext, True)
            if spi[0, I_ACTIVE] != 0:
                observe_synced(i, vals, fx, fy, fz, pos, vel, spin, quat, inv_m, obs_rad, mass, inertia, nbr, nn,
                               hist, spd, spf, ext, torque, spin_inv)
            d2, v2 = kick_drift_one(i, 0, exact, kept, pos, pos_out, vel, vel_out, spin, quat, fx, fy, fz, torque,
                                    pushed, inv_m, spin_inv, x_ref, ids, sc, spd, spf, spi, status, step + 1, ext)
            md = max(md, d2)
            mv = max(mv, v2)
        publish_maxima(sh, md, mv, par, status)
        block_accumulate(sh_obs, vals, acc, row)

    k = dict(kick_drift=kick_drift, forces=forces, half_kick=half_kick, run_steps=run_steps, observe=observe)
    if P.FUSABLE:
        k["forces_kick_drift"] = forces_kick_drift
        k["forces_observe_kick_drift"] = forces_observe_kick_drift
    if observes_after_forces:
        k["forces_observe"] = forces_observe
    if P.MULTISTEP_FUSABLE:
        k["run_steps_fused"] = run_steps_fused
    if settle_one is not None:
        k["settle"] = settle
    return k
