"""Cundall number of the CUDA ellipsoid backend against N and precision, and its ratio to spheres (the
must-show 5), plus the ensemble rows K x 4096 ellipsoids.

Scene: the Rubio-Largo et al. (2015) gas -- frictionless prolate spheroids, elongation xi = 2, phi = 0.058, e_n = 0.9,
the engine's contact constants for that spec (engine.setup.params.derive: k_n, gamma_n, dt = t_c/50, skin), box edge
2 m x (N/4096)^(1/3) (the particle size of Hidalgo et al. 2013, as engine/validation/hcs_ellipsoids.py), v_rms = 3.5 m/s
and spins about the two axes perpendicular to the symmetry axis at the same temperature. Placement: uniformly random
centres and orientations, every overlapping ellipsoid (Perram-Wertheim W_0 < 1, the engine's own test) redrawn
until none is left -- a random gas in which bounding spheres overlap as often as in the thermalised gas (about
one pair per particle; a lattice start has none, and the force kernel would then never run the contact
function). Cundall number = N x steps / wall s of ``advance`` after compilation, placement and the first list
build, median of ``--reps`` runs (bench/gpu_scaling.py's ``measure``, which also profiles the phases).

Spheres at the same N are measured in the same process with bench/gpu_scaling.py's scene and ``measure``
(rough spheres, Coulomb friction, rotation: the sphere rows of docs/performance.md), and the ratio ellipsoid/sphere is
reported per N and precision.

    python -m bench gpu_ellipsoid_scaling
    python -m bench gpu_ellipsoid_scaling --n 2097152 --precision float64 --no-ensemble   # the target row
    python -m bench gpu_ellipsoid_scaling --budget-s 200   # start no new row after 200 s (rows by priority)
    python -m bench gpu_ellipsoid_scaling --n 2097152 16777216 --no-ensemble --spheres-last --controls

``--controls`` adds float64 rows at N = 2 097 152 with the exact screens before the Perram-Wertheim solve
switched off (engine.shapes.spheroid.cpu_backend.PW_SCREEN < 0: the code path before the screens) and with the PW
tolerance 1e-10 instead of 1e-15, measured in the same process as the default row.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np
from numba import prange

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import out_dir  # noqa: E402
from bench import gpu_scaling  # noqa: E402
from engine.physics.ellipsoid import ellipsoid_overlap_pw, plane_separated, shape_matrix_inverse  # noqa: E402

XI = 2.0
PHI = 0.058
E_N = (0.9, 0.95, 0.98)


# ---- placement: a random ellipsoid gas ---------------------------------------------------------------

@numba.njit(parallel=True, cache=True)
def _flag_overlaps(pos, quat, a, b, box, nc, cell_start, cell_list, moved, bad):
    """bad[i] = particle i (moved in the last pass) overlaps a particle that stays (a kept one, or a moved
    one with a lower index): centre distance < 2a and Perram-Wertheim W_0 < 1 + 1e-6."""
    n = pos.shape[0]
    inv_cell = nc / box
    rc2 = 4.0 * a * a
    for i in prange(n):
        bad[i] = False
        if not moved[i]:
            continue
        cx = min(int(pos[i, 0] * inv_cell), nc - 1)
        cy = min(int(pos[i, 1] * inv_cell), nc - 1)
        cz = min(int(pos[i, 2] * inv_cell), nc - 1)
        for ox in range(-1, 2):
            for oy in range(-1, 2):
                for oz in range(-1, 2):
                    c = (((cx + ox) % nc) * nc + (cy + oy) % nc) * nc + (cz + oz) % nc
                    for s in range(cell_start[c], cell_start[c + 1]):
                        j = cell_list[s]
                        if j == i or (moved[j] and j > i):
                            continue
                        dx = pos[j, 0] - pos[i, 0]
                        dy = pos[j, 1] - pos[i, 1]
                        dz = pos[j, 2] - pos[i, 2]
                        dx -= box * np.round(dx / box)
                        dy -= box * np.round(dy / box)
                        dz -= box * np.round(dz / box)
                        if dx * dx + dy * dy + dz * dz >= rc2:
                            continue
                        # exact screen first (bench speed only): a plane normal to the centre line separating
                        # the pair scaled by 1 + 2e-6 proves W_0 > 1 + 2e-6, so the pair is not flagged anyway
                        ia = shape_matrix_inverse(quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3], a, b, b, 0.5)
                        ib = shape_matrix_inverse(quat[j, 0], quat[j, 1], quat[j, 2], quat[j, 3], a, b, b, 0.5)
                        if plane_separated(ia[0], ia[1], ia[2], ia[3], ia[4], ia[5], ib[0], ib[1], ib[2], ib[3],
                                           ib[4], ib[5], dx, dy, dz, 2e-6, 0.5):
                            continue
                        w0 = ellipsoid_overlap_pw(dx, dy, dz, quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3],
                                                  a, b, b, quat[j, 0], quat[j, 1], quat[j, 2], quat[j, 3], a, b, b,
                                                  1e-12, 0.5)[1]
                        if w0 < 1.0 + 1e-6:
                            bad[i] = True
                            break
                    if bad[i]:
                        break
                if bad[i]:
                    break


def _unit_quats(rng, k):
    q = rng.normal(size=(k, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@numba.njit(cache=True)
def _bin_cells(pos, box, nc, cell_start, cell_list):
    """Counting sort of the particles by cell (stable: index order within a cell), O(N)."""
    n = pos.shape[0]
    inv_cell = nc / box
    cid = np.empty(n, np.int64)
    cell_start[:] = 0
    for i in range(n):
        cx = min(int(pos[i, 0] * inv_cell), nc - 1)
        cy = min(int(pos[i, 1] * inv_cell), nc - 1)
        cz = min(int(pos[i, 2] * inv_cell), nc - 1)
        c = (cx * nc + cy) * nc + cz
        cid[i] = c
        cell_start[c + 1] += 1
    for c in range(nc * nc * nc):
        cell_start[c + 1] += cell_start[c]
    fill = cell_start[:-1].copy()
    for i in range(n):
        c = cid[i]
        cell_list[fill[c]] = i
        fill[c] += 1


def place_gas(n, box, a, b, rng, max_passes=200):
    """Random centres and orientations of n spheroids (semi-axes a, b, b) in a periodic box, none overlapping."""
    pos = rng.uniform(0.0, box, size=(n, 3))
    quat = _unit_quats(rng, n)
    moved = np.ones(n, np.bool_)
    bad = np.zeros(n, np.bool_)
    nc = max(1, int(box / (2.0 * a)))
    cell_start = np.zeros(nc ** 3 + 1, np.int64)
    cell_list = np.zeros(n, np.int64)
    for _ in range(max_passes):
        _bin_cells(pos, box, nc, cell_start, cell_list)
        _flag_overlaps(pos, quat, a, b, box, nc, cell_start, cell_list, moved, bad)
        k = int(bad.sum())
        if k == 0:
            return pos, quat
        pos[bad] = rng.uniform(0.0, box, size=(k, 3))
        quat[bad] = _unit_quats(rng, k)
        moved[:] = bad
    raise RuntimeError(f"place_gas: overlaps left after {max_passes} passes")


_placed: dict = {}


def ellipsoid_gas(n, phi, precision, seed=1, xi=XI, e_n=0.9):
    """(EllipsoidSystem, ContactParams) of the Rubio-Largo et al. (2015) gas (module docstring); placement cached per
    (n, phi, seed, xi) so both precisions start from the same configuration."""
    from engine.backends.base import EllipsoidSystem
    from engine.setup.params import derive
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(shape="ellipsoid", elongation=xi, n_particles=n, volume_fraction=phi,
                          box_length=2.0 * (n / 4096) ** (1 / 3), e_n=e_n, e_t=-1.0, velocity_rms=3.5, seed=seed,
                          precision=precision, snapshots=0)
    p = derive(spec)
    a, b, _ = p.semi_axes
    key = (n, phi, seed, xi)
    if key not in _placed:
        rng = np.random.default_rng(seed)
        pos, quat = place_gas(n, spec.box_length, a, b, rng)
        vel = rng.normal(size=(n, 3))
        vel -= vel.mean(0)
        vel *= spec.velocity_rms / math.sqrt(np.mean(np.sum(vel * vel, 1)))
        i_perp = p.inertia[1]
        w_b = rng.normal(size=(n, 2))
        w_b *= spec.velocity_rms * math.sqrt(p.mass / (3.0 * i_perp)) / math.sqrt(np.mean(w_b * w_b))
        w, x, y, z = quat.T
        e2 = np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)
        e3 = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1)
        omega = w_b[:, :1] * e2 + w_b[:, 1:] * e3
        _placed[key] = (pos, vel, omega, quat)
    pos, vel, omega, quat = _placed[key]
    system = EllipsoidSystem(box_length=spec.box_length, position=pos, velocity=vel, angular_velocity=omega,
                             orientation=quat, semi_axes=np.broadcast_to(np.asarray(p.semi_axes, float), (n, 3)),
                             mass=np.broadcast_to(np.float64(p.mass), (n,)),
                             inertia=np.broadcast_to(np.asarray(p.inertia, float), (n, 3)))
    return system, contact_params(spec, p, thermalization=False)


# ---- rows -------------------------------------------------------------------------------------------

#: control variants of an ellipsoid row: (PW_SCREEN, PW_TOL) overrides for the row's precision
VARIANTS = {"default": (None, None), "noscreen": (-1.0, None), "tol1e-10": (None, 1e-10)}


def measure_scaling(n, precision, reps, target_s, shape, variant="default"):
    from engine.shapes.spheroid import cpu_backend as cpu_ellipsoid
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    if shape == "ellipsoid":
        screen, tol = VARIANTS[variant]
        saved = (cpu_ellipsoid.PW_SCREEN[precision], cpu_ellipsoid.PW_TOL[precision])
        try:
            if screen is not None:
                cpu_ellipsoid.PW_SCREEN[precision] = screen
            if tol is not None:
                cpu_ellipsoid.PW_TOL[precision] = tol
            r = gpu_scaling.measure(n, PHI, precision, reps, target_s, make=ellipsoid_gas,
                                    backend=CudaEllipsoidBackend)
            r.update(variant=variant, pw_screen=cpu_ellipsoid.PW_SCREEN[precision],
                     pw_tol=cpu_ellipsoid.PW_TOL[precision])
        finally:
            cpu_ellipsoid.PW_SCREEN[precision], cpu_ellipsoid.PW_TOL[precision] = saved
    else:
        r = gpu_scaling.measure(n, PHI, precision, reps, target_s)
    r["shape"] = shape
    return r


def measure_ensemble(k, precision, multistep, reps, target_s, n=4096):
    """K scenes of n ellipsoids (xi = 2, own seed, e_n cycling 0.9/0.95/0.98) in one CudaEllipsoidEnsemble."""
    from numba import cuda

    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble

    t0 = time.perf_counter()
    made = [ellipsoid_gas(n, PHI, precision, seed=1000 + s, e_n=E_N[s % 3]) for s in range(k)]
    free0 = cuda.current_context().get_memory_info()[0]
    ens = CudaEllipsoidEnsemble([m[0] for m in made], [m[1] for m in made])
    if multistep is not None:
        ens.multistep = multistep
    ens.warmup()
    cuda.synchronize()
    free1 = cuda.current_context().get_memory_info()[0]
    setup = time.perf_counter() - t0
    ens.advance(10)
    t = time.perf_counter()
    ens.advance(50)
    per = (time.perf_counter() - t) / 50
    steps = int(max(20, min(50000, target_s / per)))
    runs = []
    b0, l0 = ens.builds, ens.launches
    for _ in range(reps):
        t = time.perf_counter()
        failed = ens.advance(steps)
        runs.append(k * n * steps / (time.perf_counter() - t))
        assert not failed, failed
    obs = ens.observe()
    row = dict(shape="ellipsoid-ensemble", k=k, n=n, phi=PHI, precision=precision,
               loop="multistep" if ens.multistep else "per-phase", steps=steps, reps=reps,
               cundall_aggregate=float(np.median(runs)), cundall_runs=runs,
               us_per_step=1e6 * k * n / float(np.median(runs)),
               builds_per_step=(ens.builds - b0) / (reps * steps), launches_per_step=(ens.launches - l0) / (reps * steps),
               bytes_per_particle_meminfo=(free0 - free1) / (k * n),
               contacts_per_particle=sum(o["contacts"] for o in obs) / (k * n), setup_s=setup)
    del ens
    return row


def plan(ns, precisions, ks, ensemble, spheres_last=False, controls=False):
    """Rows in priority order: the target row (float64 at 2^21) first, then float64 by N, float32 by N,
    then the ensemble rows; each ellipsoid row is followed by its sphere row (spheres_last: all sphere rows
    after all ellipsoid rows; controls: the float64 2^21 control variants right after the target row)."""
    order = []
    first = [(p, n) for p in precisions for n in ns if (p, n) == ("float64", 2097152)]
    rest = [(p, n) for p in precisions for n in ns if (p, n) not in first]
    spheres = []
    for p, n in first + rest:
        order.append(("ellipsoid", p, n))
        if controls and (p, n) == ("float64", 2097152):
            order += [("ellipsoid:noscreen", p, n), ("ellipsoid:tol1e-10", p, n)]
        (spheres if spheres_last else order).append(("sphere", p, n))
    order += spheres
    if ensemble:
        for p in precisions:
            for k in ks:
                order.append(("ensemble", p, k))
    return order


def table(rows, info) -> str:
    out = [f"{info['gpu']}: ellipsoids xi = {XI}, phi = {PHI} (the gas of Rubio-Largo et al. 2015); spheres: rough, "
           "Coulomb, rotation",
           "", "| precision | N | ellipsoids: Cundall (median) | loop | KD | rebuild | forces | B/particle | max_nb | "
           "contacts/particle | spheres: Cundall | ratio ell/sph |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    sph = {(r["precision"], r["n"]): r for r in rows if r.get("shape") == "sphere" and "error" not in r}
    for r in rows:
        if r.get("shape") != "ellipsoid":
            continue
        if r.get("variant", "default") != "default":
            r = dict(r, precision=f"{r['precision']} ({r['variant']})")
        if "error" in r:
            out.append(f"| {r['precision']} | {r['n']} | ERROR {r['error'][:80]} |")
            continue
        f = r["frac"]
        s = sph.get((r["precision"].split(" ")[0], r["n"]))
        ratio = f"{r['cundall_median'] / s['cundall_median']:.2f}" if s else "-"
        sc = f"{s['cundall_median']:.3g}" if s else "-"
        out.append(f"| {r['precision']} | {r['n']} | {r['cundall_median']:.3g} | {r['loop']} | {f['kick_drift']:.2f} | "
                   f"{f['rebuild']:.2f} | {f['forces']:.2f} | {r['bytes_per_particle_meminfo']:.0f} | {r['max_nb']} | "
                   f"{r['contacts_per_particle']:.2g} | {sc} | {ratio} |")
    ens = [r for r in rows if r.get("shape") == "ellipsoid-ensemble"]
    if ens:
        out += ["", "| precision | K x 4096 ellipsoids | loop | aggregate Cundall | us/step | builds/step | B/particle |",
                "|---|---|---|---|---|---|---|"]
        for r in ens:
            if "error" in r:
                out.append(f"| {r['precision']} | {r['k']} | ERROR {r['error'][:80]} |")
                continue
            out.append(f"| {r['precision']} | {r['k']} | {r['loop']} | {r['cundall_aggregate']:.3g} | "
                       f"{r['us_per_step']:.1f} | {r['builds_per_step']:.3f} | {r['bytes_per_particle_meminfo']:.0f} |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="*", default=[4096, 32768, 262144, 2097152, 16777216])
    ap.add_argument("--precision", nargs="*", default=["float64", "float32"])
    ap.add_argument("--k", type=int, nargs="*", default=[1, 16, 64, 256, 1024])
    ap.add_argument("--no-ensemble", action="store_true")
    ap.add_argument("--no-spheres", action="store_true")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--target-s", type=float, default=0.4)
    ap.add_argument("--budget-s", type=float, default=None, help="start no new row after this many seconds")
    ap.add_argument("--spheres-last", action="store_true", help="sphere rows after all ellipsoid rows")
    ap.add_argument("--controls", action="store_true", help="float64 2^21 rows without the screens / with tol 1e-10")
    ap.add_argument("--out", default=None, help="folder for gpu_ellipsoid_scaling.json (rewritten after every "
                    "row) and .md (default ./bench-out/gpu_ellipsoid_scaling/)")
    args = ap.parse_args()
    out_path = out_dir(args.out, "gpu_ellipsoid_scaling") / "gpu_ellipsoid_scaling.json"
    from numba import cuda

    t_start = time.perf_counter()
    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else dev.name
    info = dict(gpu=name, date=time.strftime("%Y-%m-%d"), numba=numba.__version__, numpy=np.__version__,
                python=platform.python_version(), total_mem=cuda.current_context().get_memory_info()[1],
                xi=XI, phi=PHI, cmd=" ".join(sys.argv))
    print(json.dumps(info), flush=True)
    rows, skipped = [], []
    for kind, prec, n in plan(args.n, args.precision, args.k, not args.no_ensemble, args.spheres_last, args.controls):
        kind, _, variant = kind.partition(":")
        if kind == "sphere" and args.no_spheres:
            continue
        if args.budget_s is not None and time.perf_counter() - t_start > args.budget_s:
            skipped.append(f"{kind}{':' + variant if variant else ''} {prec} {n}")
            continue
        try:
            if kind == "ensemble":
                r = measure_ensemble(n, prec, None, args.reps, args.target_s)
            else:
                r = measure_scaling(n, prec, args.reps, args.target_s, kind, variant or "default")
        except Exception as e:  # report and go on
            r = dict(shape="ellipsoid-ensemble" if kind == "ensemble" else kind, precision=prec,
                     **({"k": n} if kind == "ensemble" else {"n": n}), variant=variant or "default",
                     error=repr(e)[:300])
        r["elapsed_s"] = time.perf_counter() - t_start
        rows.append(r)
        print(json.dumps(r), flush=True)
        out_path.write_text(json.dumps(dict(info=info, rows=rows, skipped=skipped), indent=1))
    out_path.write_text(json.dumps(dict(info=info, rows=rows, skipped=skipped), indent=1))
    md = table(rows, info)
    if skipped:
        md += "\n\nNot measured (time budget): " + ", ".join(skipped)
    print("\n" + md)
    out_path.with_suffix(".md").write_text(md + "\n")


if __name__ == "__main__":
    sys.exit(main())
