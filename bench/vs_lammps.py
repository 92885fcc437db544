"""demq (CPU) against LAMMPS ``gran/hooke/history`` on the same scene, side by side in one run.

    python -m bench vs_lammps --n 4096 32768 --steps 20000 3000 --threads 1 --pairs 3 --out DIR

The scene: the Hidalgo et al. (2013) radius of the default spec (a = 1.55 cm, engine/setup/params.py ``derive``),
velocity_rms = 3 m/s, e_n = e_t = 0.8, k_n = 1e8 N/m, density 2000 kg/m^3, no Coulomb limit
(friction = null); phi = 0.008 at N = 4096 and 0.058 above (``--phi`` overrides); the box grows with N so that
the radius stays the default one. No thermalisation (``thermalization = 0``), so both codes start from the
SAME state: demq's default start (``start = null``: the random, equilibrium-gas placement of engine/setup/start_kind.py
at these sizes; ``--start`` overrides, recorded as ``start`` in each row), drawn by engine/setup/scene.py
``initial_spheres`` (positions, velocities, spins), is written into the LAMMPS data file in id order, and both
integrate the dissipative gas from there for the same number of steps.

LAMMPS, with its units (``units si``; pair_gran docs: F_n = k_n delta n - m_eff gamma_n v_n,
F_t = -(k_t Delta s_t + m_eff gamma_t v_t), m_eff = m_i m_j/(m_i + m_j)):
- ``Kn`` = demq k_n (N/m);
- ``gamma_n`` = demq gamma_n / m12 (1/s): demq's gamma_n (kg/s, Hidalgo et al. 2013, params.py) is a force per
  velocity, LAMMPS's is per unit effective mass; equal spheres, so m_eff = m12 for every pair;
- ``Kt`` = demq k_t (Hidalgo et al. 2013, Eq. 4, N/m), ``gamma_t`` = 0 with dampflag 0 (no tangential damping);
- ``xmu`` = 1e4, the largest LAMMPS accepts (friction effectively off, as demq's default friction = null);
- ``timestep`` = demq dt (t_c/50), ``neighbor`` skin of one radius (``--lammps-skin``, in radii),
  ``neigh_modify delay 0 every 10 check yes``, ``fix nve/sphere``, no gravity, periodic cube; LAMMPS's own
  default spatial sort of the atoms (``atom_modify sort``: every 1000 steps).
demq runs its own default skin (``verlet_skin: null``, recorded in the JSON).

What is timed: demq through the public path ``engine.run`` (default snapshots, records every t_end/200,
t_end = steps x dt), on the CPU backend with ``--threads`` Numba threads. "loop" is RunSummary.loop_s (the
time loop); "end-to-end" is the wall clock around the whole ``engine.run`` call (placement, first list,
compile or cache load, output file). A tiny warm-up run first fills the Numba cache (``--no-warmup`` skips
it). LAMMPS runs ``lmp -in`` (``--threads 2``: ``mpirun -np 2``); "loop" is its "Loop time of X", and
"end-to-end" the wall clock around the ``lmp`` process. Cundall number = N x steps / seconds.

Each N runs ``--pairs`` side-by-side pairs (default 3: demq, then LAMMPS, on the same start). A row reports the
median over the pairs of each code's loop Cundall number and of the pair ratio demq / LAMMPS, and the spread of
each code's runs, max / min - 1 (identical runs: only the machine makes them differ). Each run also records what
the machine did meanwhile: its CPU seconds (``cpu_s``: the demq process's, or the LAMMPS child's) against its wall
seconds, and the seconds the hypervisor gave the host's CPUs to other guests (``steal_s``, the "steal" column of
/proc/stat over all CPUs; None where there is none): a run slow in wall time but not in CPU time was descheduled; one
slow in CPU time too ran on a slower or busier CPU.

``--co-runner MB`` asks how much a busy neighbour costs each code: the bench pins itself (and so LAMMPS, its child)
to one CPU and starts a process on the other CPUs that streams over MB megabytes without pause (NumPy ``a += 1``:
each pass reads and writes the whole array, taking the shared last-level cache and memory bandwidth), for the whole
comparison; ``co_runner_mb`` in each row says it ran.
Without ``lmp`` on PATH the bench says so and runs demq alone.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":   # Numba reads NUMBA_NUM_THREADS once, at import: set it before engine imports
    _t = [a for a in sys.argv[1:] if a.startswith("--threads")]
    if _t:
        _v = _t[0].split("=", 1)[1] if "=" in _t[0] else sys.argv[sys.argv.index(_t[0]) + 1]
        os.environ.setdefault("NUMBA_NUM_THREADS", _v)
    else:
        os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.setup.params import derive  # noqa: E402  (does not import numba)
from engine.setup.spec import SimulationSpec  # noqa: E402

#: LAMMPS refuses xmu > 1e4 (pair_gran settings); with it the Coulomb limit never bites in this gas.
LAMMPS_XMU = 1.0e4
VELOCITY_RMS = 3.0
LOOP_RE = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms")


def default_radius() -> float:
    """Radius of the default spec (Hidalgo et al. 2013: N = 4096, phi = 0.008, L = 2 m), in m."""
    return derive(SimulationSpec()).radius


def default_phi(n: int) -> float:
    """The densities: 0.008 at N = 4096 (Hidalgo et al. 2013), 0.058 for the larger gases."""
    return 0.008 if n <= 4096 else 0.058


def scene_spec(n: int, phi: float, steps: int, seed: int = 1, skin: float | None = None,
               start: str | None = None) -> SimulationSpec:
    """The spec of the compared scene: default radius, box from N and phi, t_end = steps x dt; ``skin``: demq's
    verlet_skin in radii (None: its default); ``start``: the placement (None: demq's default, module doc)."""
    a = default_radius()
    box = (n * 4.0 / 3.0 * math.pi * a**3 / phi) ** (1.0 / 3.0)
    base = dict(n_particles=n, volume_fraction=phi, box_length=box, velocity_rms=VELOCITY_RMS, e_n=0.8, e_t=0.8,
                stiffness=1.0e8, density=2000.0, thermalization=0.0, backend="cpu", seed=seed, verlet_skin=skin,
                start=start)
    dt = derive(SimulationSpec(**base)).dt
    return SimulationSpec(**base, t_end=steps * dt)


def lammps_params(spec: SimulationSpec, skin_radii: float = 1.0) -> dict:
    """LAMMPS gran/hooke/history constants (SI) equivalent to demq's derived ones (module doc)."""
    p = derive(spec)
    return {"kn": p.k_n, "kt": p.k_t, "gamma_n": p.gamma_n / p.m12, "gamma_t": 0.0, "xmu": LAMMPS_XMU,
            "dampflag": 0, "dt": p.dt, "skin": skin_radii * p.radius, "radius": p.radius,
            "density": spec.density, "box_length": spec.box_length}


def write_data(path: Path, system) -> None:
    """LAMMPS data file (atom_style sphere) of a demq SphereSystem: positions wrapped into [0, L)."""
    L = system.box_length
    n = len(system.mass)
    pos = system.position % L
    lines = ["LAMMPS data file written by bench/vs_lammps.py (demq initial_spheres)", "",
             f"{n} atoms", "1 atom types", "",
             f"0 {L!r} xlo xhi", f"0 {L!r} ylo yhi", f"0 {L!r} zlo zhi", "", "Atoms # sphere", ""]
    for i in range(n):
        r = float(system.radius[i])
        rho = float(system.mass[i]) / (4.0 / 3.0 * math.pi * r**3)
        x, y, z = (float(c) for c in pos[i])
        lines.append(f"{i + 1} 1 {2.0 * r!r} {rho!r} {x!r} {y!r} {z!r}")
    lines += ["", "Velocities", ""]
    for i in range(n):
        v = system.velocity[i]
        w = system.angular_velocity[i]
        lines.append(f"{i + 1} {float(v[0])!r} {float(v[1])!r} {float(v[2])!r} "
                     f"{float(w[0])!r} {float(w[1])!r} {float(w[2])!r}")
    path.write_text("\n".join(lines) + "\n")


def lammps_input(prm: dict, steps: int, data_file: str = "data.lmp", thermo_every: int = 5000) -> str:
    """The LAMMPS input script of the scene (module doc)."""
    return "\n".join([
        "# bench/vs_lammps.py: same scene as demq",
        "units si",
        "atom_style sphere",
        "boundary p p p",
        "comm_modify vel yes",
        f"read_data {data_file}",
        f"neighbor {prm['skin']!r} bin",
        "neigh_modify delay 0 every 10 check yes",
        f"pair_style gran/hooke/history {prm['kn']!r} {prm['kt']!r} {prm['gamma_n']!r} {prm['gamma_t']!r} "
        f"{prm['xmu']!r} {prm['dampflag']}",
        "pair_coeff * *",
        f"timestep {prm['dt']!r}",
        "fix 1 all nve/sphere",
        "compute ket all ke",
        "compute ker all erotate/sphere",
        "thermo_style custom step c_ket c_ker",
        "thermo_modify norm no",
        f"thermo {max(1, min(thermo_every, steps))}",
        f"run {steps}",
        "",
    ])


def lammps_command(threads: int) -> list:
    """``lmp`` (1 rank) or ``mpirun -np k lmp``; None when lmp (or mpirun for k > 1) is missing."""
    lmp = shutil.which("lmp")
    if lmp is None:
        return None
    if threads == 1:
        return [lmp]
    mpirun = shutil.which("mpirun")
    if mpirun is None:
        return None
    extra = ["--allow-run-as-root"] if hasattr(os, "geteuid") and os.geteuid() == 0 else []
    return [mpirun, *extra, "-np", str(threads), lmp]


def host_steal_s() -> float | None:
    """Seconds the hypervisor has given this host's CPUs to other guests since boot, summed over the CPUs (the
    "steal" field of /proc/stat's first line, in clock ticks), or None where /proc/stat has no such field."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def _steal_since(start: float | None) -> float | None:
    now = host_steal_s()
    return None if start is None or now is None else round(now - start, 3)


def run_lammps(workdir: Path, threads: int, n: int, steps: int) -> dict:
    """Run ``in.lammps`` in ``workdir``; loop and end-to-end Cundall numbers, version, final energies."""
    cmd = lammps_command(threads)
    if cmd is None:
        return {"available": False, "reason": "lmp not on PATH" if shutil.which("lmp") is None
                else "mpirun not on PATH (needed for --threads > 1)"}
    env = dict(os.environ, OMP_NUM_THREADS="1")
    steal0 = host_steal_s()
    child0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([*cmd, "-in", "in.lammps", "-log", "log.lammps", "-screen", "none"], cwd=workdir,
                          env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    child1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (child1.ru_utime + child1.ru_stime) - (child0.ru_utime + child0.ru_stime)
    steal = _steal_since(steal0)
    log = (workdir / "log.lammps").read_text() if (workdir / "log.lammps").exists() else ""
    m = LOOP_RE.search(log)
    if proc.returncode != 0 or m is None:
        raise RuntimeError(f"LAMMPS failed (rc {proc.returncode}): {(proc.stdout + proc.stderr)[-2000:]}\n"
                           f"{log[-2000:]}")
    loop, procs, lsteps, atoms = float(m.group(1)), int(m.group(2)), int(m.group(3)), int(m.group(4))
    if lsteps != steps or atoms != n:
        raise RuntimeError(f"LAMMPS ran {lsteps} steps with {atoms} atoms, expected {steps} and {n}")
    version = re.search(r"LAMMPS \(([^)]*)\)", log)
    thermo = [ln.split() for ln in log.splitlines() if re.match(rf"\s*{steps}\s+\S+\s+\S+\s*$", ln)]
    return {"available": True, "command": " ".join([*cmd, "-in", "in.lammps"]), "procs": procs,
            "version": version.group(1) if version else "?", "loop_s": loop, "wall_s": wall,
            "cundall_loop": n * steps / loop, "cundall_end_to_end": n * steps / wall, "cpu_s": round(cpu, 3),
            "steal_s": steal, "ke_translational_end": float(thermo[-1][1]) if thermo else None,
            "ke_rotational_end": float(thermo[-1][2]) if thermo else None}


def run_demq(spec: SimulationSpec, threads: int, workdir: Path) -> dict:
    """engine.run on the CPU backend with ``threads`` Numba threads: loop and end-to-end Cundall numbers."""
    import h5py
    import numba

    from engine import run

    if threads > numba.config.NUMBA_NUM_THREADS:
        raise SystemExit(f"--threads {threads} > NUMBA_NUM_THREADS = {numba.config.NUMBA_NUM_THREADS}; "
                         "set NUMBA_NUM_THREADS before starting the bench")
    numba.set_num_threads(threads)
    out = workdir / "demq.h5"
    steal0 = host_steal_s()
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    s = run(spec, out, backend="cpu")
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    steal = _steal_since(steal0)
    with h5py.File(out, "r") as f:
        ket = float(f["observables/kinetic_energy_translational/value"][-1])
        ker = float(f["observables/kinetic_energy_rotational/value"][-1])
        builds = int(f["parameters"].attrs["neighbour_builds"])
    out.unlink()
    n = spec.n_particles
    return {"threads": numba.get_num_threads(), "steps": s.steps, "loop_s": s.loop_s, "wall_s": wall,
            "cundall_loop": s.cundall, "cundall_end_to_end": n * s.steps / wall,
            "builds": builds, "cpu_s": round(cpu, 3), "steal_s": steal, "timings": s.extra.get("timings"),
            "skin_m": derive(spec).skin,
            "ke_translational_end": ket, "ke_rotational_end": ker}


#: the co-runner's loop: one array of argv[1] MB, read and written in whole passes until the process is killed
CO_RUNNER_CODE = "import sys, numpy as np\na = np.ones(int(sys.argv[1]) << 17)\nwhile True:\n    a += 1.0\n"


@contextlib.contextmanager
def co_runner(megabytes: int):
    """Pin this process to its first allowed CPU and stream over ``megabytes`` MB on the others meanwhile
    (:data:`CO_RUNNER_CODE`); yields the co-runner's process. Needs two CPUs."""
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < 2:
        raise SystemExit(f"--co-runner needs two CPUs; this process may use {len(allowed)}")
    own, others = {allowed[0]}, set(allowed[1:])
    proc = subprocess.Popen([sys.executable, "-c", CO_RUNNER_CODE, str(int(megabytes))])
    try:
        os.sched_setaffinity(proc.pid, others)
        os.sched_setaffinity(0, own)
        yield proc
    finally:
        proc.kill()
        proc.wait()
        os.sched_setaffinity(0, set(allowed))


def _machine_txt(r: dict) -> str:
    """A run's wall and CPU seconds and the host's steal over it, for the pair lines."""
    steal = "" if r["steal_s"] is None else f", host steal {r['steal_s']:.2f} s"
    return f"wall {r['wall_s']:.2f} s, CPU {r['cpu_s']:.2f} s{steal}"


def spread(values) -> float:
    """max / min - 1 of a code's identical runs (0: all equal)."""
    return max(values) / min(values) - 1.0


def compare(n: int, phi: float, steps: int, threads: int, skin_radii: float, out_dir, seed: int = 1,
            demq_skin: float | None = None, pairs: int = 3, start: str | None = None) -> dict:
    """``pairs`` side-by-side runs (demq, then LAMMPS, from demq's start written as the LAMMPS data file); a row
    with the medians of the Cundall numbers and of the pair ratios, and each code's spread."""
    from engine.setup.scene import initial_spheres
    from engine.setup.start_kind import start_protocol

    spec = scene_spec(n, phi, steps, seed, demq_skin, start)
    prm = lammps_params(spec, skin_radii)
    demq_runs, lammps_runs = [], []
    with tempfile.TemporaryDirectory(prefix="vs_lammps_") as tmp:
        work = Path(tmp)
        write_data(work / "data.lmp", initial_spheres(spec, derive(spec)))
        (work / "in.lammps").write_text(lammps_input(prm, steps))
        for k in range(pairs):
            demq = run_demq(spec, threads, work)
            if demq["steps"] != steps:
                raise RuntimeError(f"demq ran {demq['steps']} steps, expected {steps}")
            lmp = run_lammps(work, threads, n, steps)
            demq_runs.append(demq)
            lammps_runs.append(lmp)
            ratio = f", ratio x{demq['cundall_loop'] / lmp['cundall_loop']:.2f}" if lmp.get("available") else ""
            lm_txt = f", LAMMPS loop {lmp['cundall_loop']:.3g}" if lmp.get("available") else ""
            print(f"  N={n} pair {k + 1}/{pairs}: demq loop {demq['cundall_loop']:.3g} ({demq['builds']} builds; "
                  f"{_machine_txt(demq)}){lm_txt}{ratio}"
                  + (f" (LAMMPS {_machine_txt(lmp)})" if lmp.get("available") else ""), flush=True)
        if out_dir is not None:
            tag = f"n{n}_t{threads}"
            shutil.copy(work / "in.lammps", Path(out_dir) / f"in.{tag}.lammps")
            if (work / "log.lammps").exists():
                shutil.copy(work / "log.lammps", Path(out_dir) / f"log.{tag}.lammps")
    demq_loop = [d["cundall_loop"] for d in demq_runs]
    row = {"n": n, "phi": phi, "steps": steps, "threads": threads, "start": start_protocol(spec), "pairs": pairs,
           "spec": json.loads(spec.model_dump_json()), "lammps_params": prm, "demq_runs": demq_runs,
           "lammps_runs": lammps_runs, "demq_loop_median": statistics.median(demq_loop),
           "demq_end_to_end_median": statistics.median(d["cundall_end_to_end"] for d in demq_runs),
           "demq_spread": spread(demq_loop), "lammps": {"available": lammps_runs[0].get("available", False)},
           "ratio_loop": None}
    if row["lammps"]["available"]:
        lammps_loop = [m["cundall_loop"] for m in lammps_runs]
        row.update(lammps_loop_median=statistics.median(lammps_loop), lammps_spread=spread(lammps_loop),
                   lammps_end_to_end_median=statistics.median(m["cundall_end_to_end"] for m in lammps_runs),
                   ratios_loop=[d / m for d, m in zip(demq_loop, lammps_loop)])
        row["ratio_loop"] = statistics.median(row["ratios_loop"])
    else:
        row["lammps"]["reason"] = lammps_runs[0]["reason"]
    return row


def table(rows) -> str:
    """Markdown table of the comparison rows (medians over the pairs; spread = max / min - 1)."""
    head = ("| N | φ | start | steps | threads | demq loop | demq spread | demq end-to-end | LAMMPS loop | "
            "LAMMPS spread | demq / LAMMPS (loop) |\n|---|---|---|---|---|---|---|---|---|---|---|")
    out = [head]
    for r in rows:
        lmp = r["lammps"]["available"]
        lo = f"{r['lammps_loop_median']:.3g}" if lmp else "—"
        ls = f"{100 * r['lammps_spread']:.1f} %" if lmp else "—"
        ra = f"×{r['ratio_loop']:.2f}" if lmp else "—"
        out.append(f"| {r['n']} | {r['phi']:g} | {r['start']} | {r['steps']} | {r['threads']} | "
                   f"{r['demq_loop_median']:.3g} | {100 * r['demq_spread']:.1f} % | "
                   f"{r['demq_end_to_end_median']:.3g} | {lo} | {ls} | {ra} |")
    return "\n".join(out)


def machine() -> dict:
    model = "?"
    try:
        for ln in Path("/proc/cpuinfo").read_text().splitlines():
            if ln.startswith("model name"):
                model = ln.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"nproc": os.cpu_count(), "cpu": model, "python": platform.python_version(),
            "numba_num_threads_env": os.environ.get("NUMBA_NUM_THREADS")}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[4096, 32768])
    ap.add_argument("--phi", type=float, default=None, help="volume fraction (default 0.008 at N <= 4096, else 0.058)")
    ap.add_argument("--steps", type=int, nargs="+", default=[3000],
                    help="steps per run: one value for every N, or one per --n")
    ap.add_argument("--threads", type=int, choices=(1, 2), default=1,
                    help="demq Numba threads and LAMMPS MPI ranks")
    ap.add_argument("--lammps-skin", type=float, default=1.0, help="LAMMPS neighbor skin in radii")
    ap.add_argument("--demq-skin", type=float, default=None,
                    help="demq's verlet_skin in radii (default: the spec's default for the backend and density)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pairs", type=int, default=3, help="side-by-side runs per N (medians and spreads over them)")
    ap.add_argument("--start", choices=("random", "lattice"), default=None,
                    help="demq's placement (default: the spec's default, the random gas at these sizes)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the tiny run that fills the Numba cache")
    ap.add_argument("--co-runner", type=int, default=0, metavar="MB",
                    help="stream over MB megabytes on the other CPUs meanwhile, this bench pinned to one (0: none)")
    ap.add_argument("--out", default=None, help="folder for LAMMPS inputs and logs, results.json, results.md")
    a = ap.parse_args(argv)
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
    if shutil.which("lmp") is None:
        print("lmp not found on PATH (Debian: apt-get install lammps): running demq alone", flush=True)
    if not a.no_warmup:
        with tempfile.TemporaryDirectory(prefix="vs_lammps_warm_") as tmp:
            run_demq(scene_spec(256, 0.008, 20), a.threads, Path(tmp))
    if len(a.steps) not in (1, len(a.n)):
        ap.error(f"--steps: give one value or one per --n ({len(a.n)}), got {len(a.steps)}")
    steps = a.steps * len(a.n) if len(a.steps) == 1 else a.steps
    if a.co_runner and a.threads != 1:
        ap.error("--co-runner pins the bench to one CPU: use it with --threads 1")
    rows = []
    for n, k in zip(a.n, steps):
        phi = a.phi if a.phi is not None else default_phi(n)
        with co_runner(a.co_runner) if a.co_runner else contextlib.nullcontext():
            r = compare(n, phi, k, a.threads, a.lammps_skin, a.out, a.seed, a.demq_skin, a.pairs, a.start)
        r["co_runner_mb"] = a.co_runner
        rows.append(r)
        lmp_txt = (f"LAMMPS loop {r['lammps_loop_median']:.3g}, demq/LAMMPS x{r['ratio_loop']:.2f}"
                   if r["lammps"]["available"] else f"LAMMPS not run ({r['lammps']['reason']})")
        beside = f" beside a {a.co_runner} MB co-runner" if a.co_runner else ""
        print(f"N={n} phi={phi:g} start={r['start']} steps={k}{beside}, median of {a.pairs}: demq loop "
              f"{r['demq_loop_median']:.3g} (spread {100 * r['demq_spread']:.1f} %, end-to-end "
              f"{r['demq_end_to_end_median']:.3g}), {lmp_txt}", flush=True)
    md = table(rows)
    print(md)
    if a.out:
        info = {"command": "python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
                "machine": machine(), "rows": rows}
        Path(a.out, f"results_t{a.threads}.json").write_text(json.dumps(info, indent=1))
        Path(a.out, f"results_t{a.threads}.md").write_text(md + "\n")
    return rows


if __name__ == "__main__":
    main()
