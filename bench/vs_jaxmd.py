"""demq (CUDA) against JAX-MD on the same sphere gas, side by side on one GPU.

    python -m bench.vs_jaxmd                                   # every case, on a GPU host, from a repo checkout
    python -m bench.vs_jaxmd --cases elastic-2M-f64 --steps-scale 0.1
    python -m bench.vs_jaxmd --quick --backend cpu             # smoke run: N = 4096, 3000 steps, on the CPU

The scene: phi = 0.058 in a periodic 2 m cube, k_n = 1e8 N/m, density 2000 kg/m^3, velocity_rms = 2 m/s,
dt = t_c/50; the radius a, the mass m = rho (4/3) pi a^3 and dt come from demq's own ``engine.setup.params.derive``.
dt is rounded to the nearest float32 (relative change < 6e-8) and given to both codes as the spec's ``dt``:
``jax_md.simulate.velocity_verlet`` casts its dt to float32 even with x64 enabled, so only such a dt is the same
step on both sides. Both start from demq's start of the spec (``engine.setup.scene.initial_spheres``, drawn on the host
for JAX-MD; a GPU job of demq draws the same start on the device, equal to rounding): JAX-MD gets its positions,
wrapped into [0, L), and the momenta m v. At the cases' N (2^21 and more) demq's default start is the fcc lattice
with random displacements, whose first contacts come late; --quick (N = 4096) starts from the random equilibrium
start, with contacts from the first step. demq's ``collisions`` in the JSON counts those of each run.

JAX-MD: ``energy.soft_sphere_neighbor_list`` with alpha = 2, sigma = 2a, epsilon = k_n sigma^2. Its pair energy
U = epsilon/alpha (1 - r/sigma)^alpha (r < sigma) gives the force -dU/dr = epsilon/sigma (1 - r/sigma)
= k_n (sigma - r) = k_n delta, demq's elastic normal spring with overlap delta = 2a - r (and U = k_n delta^2/2,
demq's ``elastic_energy``). The constants go in as arrays of the working dtype (``jax_md.util.maybe_downcast``
makes Python floats float32 even with x64). ``space.periodic(L)``, ``simulate.nve`` (velocity Verlet, as demq)
with mass m; the list (cutoff sigma, ``dr_threshold`` = skin, ``capacity_multiplier`` 1.25) is updated every step
inside one jit-compiled ``lax.fori_loop``. A list that overflowed (``did_buffer_overflow`` after the warm-up or
the timed run) is reallocated with 1.5 x the capacity multiplier and the whole run repeated (the lattice start
has few neighbours, so a list sized from it can overflow once contacts come); only the last attempt is timed.
Each list format (Dense, OrderedSparse) and skin (0.8 a, 1.6 a) runs in its own process; the table shows the
best. float64 cases enable ``jax_enable_x64``; JAX may take 95 % of the GPU memory (XLA_PYTHON_CLIENT_MEM_FRACTION).

demq: ``engine.run`` with e_n = 1, e_t = -1 (elastic, frictionless: no dashpot, no tangential spring, so its
contact-event corrections vanish and both sides integrate the same equations), thermalization 0, snapshots 0,
its default skin and records; t_end = steps x dt. The rough cases (e_n = e_t = 0.8) run demq alone and are
compared with JAX-MD's frictionless rate at the same N and precision. --quick also compares the final states
particle by particle (demq then writes one snapshot): they agree to rounding (7e-15 radii, 1e-12 v_rms).

Timed: "loop" = demq's RunSummary.loop_s (the time loop) / JAX-MD's timed ``fori_loop`` call (after a compile
and a 10-step warm-up, ended by ``block_until_ready``); "end-to-end" = the whole ``engine.run`` call (in the fresh
process; "warm": the same job run again in that process, as a worker that has run a job before runs it) / JAX-MD
from the host start to the result on the host (upload, list allocation, compile, warm-up, timed run; the start
function, demq's, is not counted; JAX's persistent compilation cache stays off, so it includes the XLA compile:
``first_call_s`` in the JSON). Before each demq case, a 10-step run of the same scene in its own process fills
the Numba cache (``--no-warmup`` skips it), so demq's end-to-end time loads its kernels (``timings``).
Cundall number = N x steps / seconds. Every run is a fresh process. Results: a table on stdout, results.json,
results.md and each run's log in --out.

JAX-MD on an offline host with jax (jaxlib, numpy, scipy, ml_dtypes, opt_einsum): ``import jax_md`` also imports
flax, optax, treescope, rich, pygments, msgpack, PyYAML, cloudpickle, etils, absl-py, jraph, e3nn-jax, sympy,
mpmath, attrs and ml_collections (not pymatgen, which its metadata asks for). Carry only what the host lacks, and
keep the flax that came with its jax: a flax release built for another jax fails at ``import jax_md`` (flax.nnx
reads jax internals that move between releases). On the GPU image of 2026-11-28 (jax 0.11.2 with flax 0.12.10,
optax, treescope and the rest installed) four wheels are missing: ``pip download --no-deps --only-binary=:all:
--platform any -d .whl/jaxmd jax-md==0.2.29 jraph e3nn-jax ml-collections``; install them beside the others
(``pip install --no-index --no-deps --target DIR .whl/jaxmd/*.whl``). Without JAX-MD the bench runs demq alone.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if __name__ == "__main__":
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from engine.setup.params import derive  # noqa: E402  (does not import numba)
from engine.setup.spec import SimulationSpec  # noqa: E402

SCENE = dict(volume_fraction=0.058, box_length=2.0, stiffness=1.0e8, density=2000.0, velocity_rms=2.0)
#: name -> (N, precision, steps, rough); a rough case is compared with the elastic JAX-MD run of its N and precision
CASES = {
    "elastic-2M-f64": (2_097_152, "float64", 2000, False),
    "elastic-8M-f32": (8_388_608, "float32", 1000, False),
    "elastic-8M-f64": (8_388_608, "float64", 1000, False),
    "rough-2M-f64": (2_097_152, "float64", 2000, True),
    "rough-8M-f32": (8_388_608, "float32", 1000, True),
}
QUICK_N, QUICK_STEPS = 4096, 3000
FORMATS = ("Dense", "OrderedSparse")
SKINS = (0.8, 1.6)          # JAX-MD dr_threshold in radii
WARMUP_STEPS = 10
CAPACITY_MULTIPLIER = 1.25
JAXMD_MISSING = ("jax_md is not importable here ({error}): JAX-MD runs are skipped and demq runs alone. "
                 "To install it offline, see the end of this script's docstring (python -m pydoc bench.vs_jaxmd)")


def case_spec(n: int, precision: str, steps: int, rough: bool, backend: str, seed: int = 1,
              snapshots: int = 0) -> SimulationSpec:
    """The spec of a case: the module's scene, t_end = steps x dt, no thermalisation, no snapshots (the state
    check of --quick: one, at the end)."""
    contact = dict(e_n=0.8, e_t=0.8) if rough else dict(e_n=1.0, e_t=-1.0)
    base = dict(n_particles=n, precision=precision, thermalization=0.0, snapshots=snapshots, backend=backend,
                seed=seed, **SCENE, **contact)
    dt = float(np.float32(derive(SimulationSpec(**base)).dt))    # JAX-MD steps with a float32 dt (module doc)
    return SimulationSpec(**base, dt=dt, t_end=steps * dt)


def jaxmd_constants(spec: SimulationSpec) -> dict:
    """JAX-MD soft-sphere constants equal to demq's elastic spring (module doc): SI units."""
    p = derive(spec)
    sigma = 2.0 * p.radius
    return {"radius": p.radius, "sigma": sigma, "epsilon": p.k_n * sigma**2, "alpha": 2.0, "mass": p.mass,
            "dt": p.dt, "box": spec.box_length}


def run_demq(job: dict) -> dict:
    """One demq case through ``engine.run``: loop and end-to-end Cundall numbers, final energies."""
    import h5py

    from engine import run

    spec = SimulationSpec(**job["spec"])
    with tempfile.TemporaryDirectory(prefix="vs_jaxmd_") as tmp:
        out = Path(tmp) / "demq.h5"
        t0 = time.perf_counter()
        s = run(spec, out, backend=spec.backend)
        wall = time.perf_counter() - t0
        with h5py.File(out, "r") as f:
            ke, el = (float(f[f"observables/{k}/value"][-1])
                      for k in ("kinetic_energy_translational", "elastic_energy"))
            collisions = int(f["observables/collisions/value"][-1])
            if job.get("state_out"):      # the final snapshot (the spec then asks for one)
                np.savez(job["state_out"], position=f["particles/all/position/value"][-1],
                         velocity=f["particles/all/velocity/value"][-1])
        # the same job again in this process: a warm worker's figure (CUDA context, kernels and buffers' pools
        # ready), still the whole engine.run call
        t0 = time.perf_counter()
        run(spec, Path(tmp) / "demq_warm.h5", backend=spec.backend)
        wall_warm = time.perf_counter() - t0
    n = spec.n_particles
    return {"backend": s.backend, "device": s.device, "steps": s.steps, "loop_s": s.loop_s, "wall_s": wall,
            "wall_warm_s": wall_warm, "cundall_loop": s.cundall, "cundall_end_to_end": n * s.steps / wall,
            "cundall_end_to_end_warm": n * s.steps / wall_warm, "timings": s.extra.get("timings"),
            "skin_m": derive(spec).skin, "ke_translational_end": ke, "elastic_energy_end": el,
            "collisions": collisions}


def run_jaxmd(job: dict) -> dict:
    """One JAX-MD configuration (list format, skin) of a case: Cundall numbers, final energies."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.95")   # the GPU is JAX's alone (default 0.75)
    import jax

    if job["spec"]["precision"] == "float64":
        jax.config.update("jax_enable_x64", True)       # before any array exists
    import jax.numpy as jnp
    from jax import lax
    from jax_md import energy, partition, simulate, space

    from engine.setup.scene import initial_spheres

    spec = SimulationSpec(**job["spec"])
    c = jaxmd_constants(spec)
    system = initial_spheres(spec, derive(spec))
    dtype = np.float64 if spec.precision == "float64" else np.float32
    pos_host = np.asarray(system.position % c["box"], dtype)
    mom_host = np.asarray(c["mass"] * system.velocity, dtype)
    steps, fmt = job["steps"], getattr(partition.NeighborListFormat, job["format"])
    displacement, shift = space.periodic(c["box"])

    def stepper(apply_fn):
        @jax.jit
        def advance(state, nbrs, n_steps):
            def step(_, carry):
                st, nb = carry
                nb = nb.update(st.position)               # rebuilt only when a particle moved half the skin
                return apply_fn(st, neighbor=nb), nb
            return lax.fori_loop(0, n_steps, step, (state, nbrs))
        return advance

    multiplier, reallocations = CAPACITY_MULTIPLIER, 0
    while True:
        # arrays of the working dtype: jax_md.util.maybe_downcast turns Python floats into float32 even with x64
        neighbor_fn, energy_fn = energy.soft_sphere_neighbor_list(
            displacement, c["box"], sigma=jnp.asarray(c["sigma"], dtype), epsilon=jnp.asarray(c["epsilon"], dtype),
            alpha=jnp.asarray(c["alpha"], dtype), dr_threshold=jnp.asarray(job["skin_radii"] * c["radius"], dtype),
            format=fmt, capacity_multiplier=multiplier)
        init_fn, apply_fn = simulate.nve(energy_fn, shift, c["dt"])
        advance = stepper(apply_fn)
        t0 = time.perf_counter()
        pos, mom = jnp.asarray(pos_host), jnp.asarray(mom_host)
        nbrs = neighbor_fn.allocate(pos)
        state = init_fn(jax.random.PRNGKey(0), pos, 0.0, mass=c["mass"], momenta=mom, neighbor=nbrs)
        warm_state, warm_nbrs = advance(state, nbrs, WARMUP_STEPS)      # compiles; the step count is traced
        jax.block_until_ready(warm_state.position)
        t1 = time.perf_counter()
        end_state, end_nbrs = advance(state, nbrs, steps)
        jax.block_until_ready(end_state.position)
        t2 = time.perf_counter()
        ke = float(0.5 * jnp.sum(end_state.momentum**2) / c["mass"])
        t3 = time.perf_counter()
        if not (bool(warm_nbrs.did_buffer_overflow) or bool(end_nbrs.did_buffer_overflow)):
            break
        multiplier, reallocations = multiplier * 1.5, reallocations + 1
    if job.get("state_out"):
        np.savez(job["state_out"], position=np.asarray(end_state.position),
                 velocity=np.asarray(end_state.momentum) / c["mass"])
    n = spec.n_particles
    return {"format": job["format"], "skin_radii": job["skin_radii"], "steps": steps, "loop_s": t2 - t1,
            "wall_s": t3 - t0, "first_call_s": t1 - t0, "cundall_loop": n * steps / (t2 - t1),
            "cundall_end_to_end": n * steps / (t3 - t0), "capacity_multiplier": multiplier,
            "reallocations": reallocations, "list_shape": list(end_nbrs.idx.shape),
            "ke_translational_end": ke, "elastic_energy_end": float(energy_fn(end_state.position, neighbor=end_nbrs)),
            "jax": jax.__version__, "device": str(jax.devices()[0]), "constants": c}


def in_fresh_process(job: dict, log_dir: Path) -> dict:
    """Run ``job`` (side 'demq' or 'jaxmd') in a child process of this module; its result, or the error it died of."""
    with tempfile.TemporaryDirectory(prefix="vs_jaxmd_job_") as tmp:
        result = Path(tmp) / "result.json"
        cmd = [sys.executable, "-m", "bench.vs_jaxmd", "--one-case", json.dumps(job), "--result", str(result)]
        tag = job["side"] + "_" + "_".join(str(job[k]) for k in ("name", "format", "skin_radii") if k in job)
        with open(log_dir / f"{tag}.log", "w") as log:
            proc = subprocess.run(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        if proc.returncode == 0 and result.exists():
            return json.loads(result.read_text())
    tail = (log_dir / f"{tag}.log").read_text()[-1500:]
    return {"error": f"exit status {proc.returncode}", "log_tail": tail}


def jaxmd_available() -> tuple[bool, str]:
    """Whether this Python imports the JAX-MD modules the bench needs; the versions, or the import error."""
    code = ("import jax; from importlib.metadata import version; "
            "from jax_md import energy, partition, simulate, space; "
            "print(f'jax {jax.__version__}, jax-md {version(\"jax-md\")}, "
            "{jax.default_backend()}: {jax.devices()[0]}')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if proc.returncode == 0:
        return True, proc.stdout.strip()
    return False, (proc.stderr.strip().splitlines() or ["?"])[-1]


def state_difference(spec: SimulationSpec, demq_file: Path, jaxmd_files: list) -> dict:
    """Largest per-particle differences between demq's final state and every JAX-MD run's (positions by minimum
    image, in m and in radii; velocities in m/s and relative to velocity_rms)."""
    ref, box, radius = np.load(demq_file), spec.box_length, derive(spec).radius
    dx, dv = 0.0, 0.0
    for path in jaxmd_files:
        other = np.load(path)
        d = ref["position"] - other["position"]
        dx = max(dx, float(np.abs(d - box * np.round(d / box)).max()))
        dv = max(dv, float(np.abs(ref["velocity"] - other["velocity"]).max()))
    return {"max_position_diff_m": dx, "max_position_diff_radii": dx / radius, "max_velocity_diff": dv,
            "max_velocity_diff_rel": dv / spec.velocity_rms, "jaxmd_runs_compared": len(jaxmd_files)}


def best(runs: list, key: str):
    ok = [r for r in runs if "error" not in r]
    return max(ok, key=lambda r: r[key]) if ok else None


def compare(names, backend: str, scale: float, quick: bool, formats, skins, seed: int, log_dir: Path,
            with_jaxmd: bool, warmup: bool = True) -> list:
    """Run the cases (demq once each, JAX-MD once per N, precision and steps, every format x skin); the rows."""
    jax_runs, rows = {}, []
    states = Path(tempfile.mkdtemp(prefix="vs_jaxmd_states_"))
    for name in names:
        n, precision, steps, rough = CASES[name]
        n, steps = (QUICK_N, QUICK_STEPS) if quick else (n, steps)
        steps = max(1, int(round(steps * scale)))
        check = quick and not rough             # compare the final states particle by particle
        spec = case_spec(n, precision, steps, rough, backend, seed, snapshots=1 if check else 0)
        job = {"side": "demq", "name": name, "spec": json.loads(spec.model_dump_json())}
        if warmup:      # the same scene for a few steps: fills the Numba cache with this case's kernels
            warm = case_spec(n, precision, WARMUP_STEPS, rough, backend, seed, snapshots=spec.snapshots)
            in_fresh_process({**job, "name": f"{name}-warmup", "spec": json.loads(warm.model_dump_json())}, log_dir)
        demq = in_fresh_process({**job, "state_out": str(states / f"demq_{name}.npz")} if check else job, log_dir)
        key = (n, precision, steps)
        if with_jaxmd and key not in jax_runs:
            elastic = json.loads(case_spec(n, precision, steps, False, backend, seed).model_dump_json())
            jobs = [{"side": "jaxmd", "name": f"{n}_{precision}", "spec": elastic, "steps": steps, "format": f,
                     "skin_radii": s,
                     "state_out": str(states / f"jaxmd_{n}_{precision}_{f}_{s}.npz") if quick else None}
                    for f in formats for s in skins]
            jax_runs[key] = [(in_fresh_process(j, log_dir), j["state_out"]) for j in jobs]
        runs = [r for r, _ in jax_runs.get(key, [])]
        loop, e2e = best(runs, "cundall_loop"), best(runs, "cundall_end_to_end")
        row = {"case": name, "n": n, "precision": precision, "steps": steps, "rough": rough,
               "spec": json.loads(spec.model_dump_json()), "demq": demq, "jaxmd_runs": runs,
               "jaxmd_best_loop": loop, "jaxmd_best_end_to_end": e2e}
        if "error" not in demq and loop is not None:
            row["ratio_loop"] = demq["cundall_loop"] / loop["cundall_loop"]
            row["ratio_end_to_end"] = demq["cundall_end_to_end"] / e2e["cundall_end_to_end"]
            # the must-show of the comparison: demq's whole job against JAX-MD's loop alone
            row["ratio_end_to_end_vs_loop"] = demq["cundall_end_to_end"] / loop["cundall_loop"]
            row["ratio_warm_end_to_end_vs_loop"] = demq["cundall_end_to_end_warm"] / loop["cundall_loop"]
            if not rough:      # same start, same equations: relative difference of the final energies
                row["ke_rel_diff"] = abs(demq["ke_translational_end"] / loop["ke_translational_end"] - 1.0)
        if check and "error" not in demq and loop is not None:
            done = [f for r, f in jax_runs[key] if "error" not in r]
            row["state_difference"] = state_difference(spec, states / f"demq_{name}.npz", done)
        rows.append(row)
        print(row_line(row), flush=True)
    shutil.rmtree(states)
    return rows


def row_line(r: dict) -> str:
    d, j = r["demq"], r["jaxmd_best_loop"]
    demq = (f"demq {d['cundall_loop']:.3g} (e2e {d['cundall_end_to_end']:.3g}, warm "
            f"{d['cundall_end_to_end_warm']:.3g})") if "error" not in d \
        else f"demq FAILED ({d['error']})"
    jax = (f"JAX-MD {j['cundall_loop']:.3g} ({j['format']}, skin {j['skin_radii']} a)" if j
           else "JAX-MD not run" if not r["jaxmd_runs"] else "JAX-MD FAILED (every configuration)")
    line = f"{r['case']}: N={r['n']} {r['precision']} {r['steps']} steps: {demq}; {jax}"
    if "state_difference" in r:
        sd = r["state_difference"]
        line += (f"; final states differ by <= {sd['max_position_diff_radii']:.2g} radii, "
                 f"{sd['max_velocity_diff_rel']:.2g} v_rms ({d['collisions']} collisions)")
    return line


def table(rows: list) -> str:
    """Markdown table: Cundall numbers (particle-steps per second) and demq / JAX-MD ratios."""
    out = ["| case | N | precision | steps | demq loop | demq end-to-end (fresh / warm process) | JAX-MD loop (best) | "
           "JAX-MD end-to-end (best) | demq / JAX-MD loop | demq end-to-end (fresh / warm) / JAX-MD loop |",
           "|---|---|---|---|---|---|---|---|---|---|"]

    def num(x, k):
        return f"{x[k]:.3g}" if x and "error" not in x else "—"

    for r in rows:
        jl, je = r["jaxmd_best_loop"], r["jaxmd_best_end_to_end"]
        jl_txt = f"{num(jl, 'cundall_loop')} ({jl['format']}, {jl['skin_radii']} a)" if jl else "—"
        ratios = [f"×{r[k]:.2f}" if k in r else "—"
                  for k in ("ratio_loop", "ratio_end_to_end_vs_loop", "ratio_warm_end_to_end_vs_loop")]
        out.append(f"| {r['case']}{' (vs elastic JAX-MD)' if r['rough'] else ''} | {r['n']} | {r['precision']} | "
                   f"{r['steps']} | {num(r['demq'], 'cundall_loop')} | {num(r['demq'], 'cundall_end_to_end')} / "
                   f"{num(r['demq'], 'cundall_end_to_end_warm')} | {jl_txt} | {num(je, 'cundall_end_to_end')} | "
                   f"{ratios[0]} | {ratios[1]} / {ratios[2]} |")
    return "\n".join(out)


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    ap.add_argument("--steps-scale", type=float, default=1.0, help="multiply every case's steps (quick checks)")
    ap.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS), help="JAX-MD list formats")
    ap.add_argument("--skins", nargs="+", type=float, default=list(SKINS), help="JAX-MD skins in radii")
    ap.add_argument("--quick", action="store_true", help=f"N = {QUICK_N}, {QUICK_STEPS} steps (smoke run)")
    ap.add_argument("--backend", choices=("cuda", "cpu"), default="cuda", help="demq's backend (cpu: smoke runs only)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-warmup", action="store_true", help="skip demq's short runs that fill the Numba cache")
    ap.add_argument("--out", default="bench-out/vs_jaxmd", help="folder for results.json, results.md, logs")
    ap.add_argument("--one-case", help=argparse.SUPPRESS)      # child process: one JSON job ...
    ap.add_argument("--result", help=argparse.SUPPRESS)        # ... and where its result goes
    a = ap.parse_args(argv)
    if a.one_case:
        job = json.loads(a.one_case)
        result = run_demq(job) if job["side"] == "demq" else run_jaxmd(job)
        Path(a.result).write_text(json.dumps(result))
        return [result]
    if not a.steps_scale > 0:
        ap.error(f"--steps-scale must be > 0, got {a.steps_scale}")
    out = Path(a.out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    with_jaxmd, jax_info = jaxmd_available()
    print(f"JAX-MD: {jax_info}" if with_jaxmd else JAXMD_MISSING.format(error=jax_info), flush=True)
    if with_jaxmd and a.backend == "cuda" and "gpu" not in jax_info:
        print("WARNING: JAX runs on the CPU here (no CUDA jaxlib?): the JAX-MD numbers are not GPU numbers", flush=True)
    rows = compare(a.cases, a.backend, a.steps_scale, a.quick, a.formats, a.skins, a.seed, out / "logs", with_jaxmd,
                   warmup=not a.no_warmup)
    md = table(rows)
    print(md)
    args = argv if argv is not None else sys.argv[1:]
    info = {"command": " ".join([sys.executable, "-m", "bench.vs_jaxmd", *args]),
            "jaxmd": jax_info if with_jaxmd else None, "rows": rows}
    (out / "results.json").write_text(json.dumps(info, indent=1))
    (out / "results.md").write_text(md + "\n")
    return rows


if __name__ == "__main__":
    main()
