"""Run time against error for every numerical knob of the engine.

Knobs (all through the public spec / backend parameters; nothing here changes an engine default):

- time step dt = t_c/k, k in DT_FRACTIONS (spec field ``dt``, in seconds; the spec refuses dt > t_c/10);
- precision float64 / float32 / mixed (spec ``precision``; mixed = float64 positions, float32 state,
  engine/setup/precision.py; sphere scenes only: the ellipsoid rows run float64 and float32);
- Verlet skin L_v in radii (spec ``verlet_skin``; its default depends on the backend and the volume
  fraction, engine.setup.params.default_verlet_skin): cost only, in the cooling gas and in a sweep over volume
  fractions, where the default rule's skin at each phi is compared with the fastest;
- rebuild policy: the engine has exactly one (rebuild when a particle has moved more than L_v/2,
  engine/loops/cpu.py run_steps); there is no switch, so no rows;
- ellipsoids: the contact algorithm. The spec exposes none: the engine always runs the Perram-Wertheim
  (PW) maximisation by safeguarded Newton. Its iteration tolerance (engine.shapes.spheroid.cpu_backend.PW_TOL,
  a run-time argument of the kernel) is varied here by this bench only; the Delta/P overlap test of
  Rubio-Largo et al. (2015), which the engine does not use, is measured beside it as an overlap classifier.

Scenes and errors (references in brackets):

- ``collisions``: K independent pairs of spheres (half head-on, half at 10 deg, sticking), impact speeds
  giving peak overlaps log-uniform in 0.2 % ... 2 % of the radius and contact starts at every phase of a
  step. Errors: max |e_n - e_n,nominal| over the head-on pairs [exact: the dashpot is built for it] and
  max |e_t - e_t,ref| over the oblique pairs [the same pair at float64, dt = t_c/200; the analytic
  e_t,eff of Hidalgo et al. (2013) Eq. 4 misses O(delta/a) lever-arm terms, docs/physics.md, so its offset is
  listed separately].
- ``elastic_smooth`` / ``elastic_rough``: elastic gas (e_n = 1; smooth e_t = -1, rough e_t = 1). The error
  of a knob is the energy error it adds per collision, measured without seed noise on a sample of binary
  collisions drawn from the gas's own collision statistics (flux-weighted Maxwellian relative speeds,
  impact parameters uniform over the collision disc, spins at the gas's rotational temperature, contact
  starts at every phase of a step): RMS over the sample of dE / (6 T) (6 T = the mean energy of two gas
  particles). Smooth: against exact conservation. Rough: against the same collisions at float64,
  dt = t_c/200, because the Eq.-4 spring itself loses energy at any dt (the spring is not back at zero when
  a contact ends); that loss (the model's, the same at t_c/800) is reported beside it. The gas runs
  (N spheres, several seeds) give the cost and the accumulated drift E(t_end)/E(0) - 1, which the pair
  sample predicts (mean C <eps>, spread sqrt(2 C / N) sd(eps) after C collisions per particle).
- ``cooling``: rough gas e_n = e_t = 0.8 after an elastic thermalisation, max over t of |T/T0 / ref - 1|
  and the same for R/T0 [float64, dt = t_c/200 run of the same seed]; and the largest deviation from
  Luding's ODE with e_t,eff [engine/analysis/theory.py]. Chaos floor: the same reference at dt = t_c/180 and t_c/190
  (a 5-10 % change of an already converged dt) decorrelates the trajectory; deviations below it are noise.
- ``ellipsoid``: contact geometry on random overlapping pairs against the longdouble oracle
  (tests/engine/test_ellipsoid_oracle.py, the sample of the one-off study bench/ellipsoid_geometry_accuracy.py):
  max |delta - delta_ref| and max normal error; the cost is the Cundall number of a small elastic
  ellipsoid gas at the same precision and tolerance, whose energy drift is a second error column.

Cost: the Cundall number N x steps / wall s of the time loop (engine/driver/simulate.py; compilation excluded,
median of ``reps`` runs). A step costs about the same at every dt, but a coarser dt covers more
simulated time per step, so the Pareto fronts use the throughput Cundall x dt / t_c (particle-contact-
times simulated per wall second); the tables give both.

Pareto front (:func:`dominates`): row q dominates row p when q is not measurably more expensive and is
demonstrably more accurate, or equally accurate and measurably cheaper. Throughputs differ when more than
TIME_NOISE apart (the run-to-run scatter); errors within ERROR_TIE (relative) are the same; errors further
apart but within SIGMAS combined standard errors of their seed means are unresolved (neither row beats the
other through them; the verdict names them). Errors below a scene's floor (the cooling gas's trajectory-
chaos floor) count as the floor. The front: every row that no other row demonstrably beats.

Output: REPORT.md, accuracy.png, summary.json in --out DIR (default ./bench-out/accuracy/).

    PYTHONPATH=. NUMBA_NUM_THREADS=1 python -m bench accuracy [--quick] [--backend cuda] [--threads 1]
    python -m bench accuracy [--quick] [--backend cpu|cuda] [-o DIR]
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import statistics
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bench import out_dir as bench_out


DT_FRACTIONS = (10, 20, 35, 50, 100, 200)
PRECISIONS = ("float64", "float32", "mixed")
#: the ellipsoid contact solver's precisions (no mixed variant: engine/setup/precision.py)
ELLIPSOID_PRECISIONS = ("float64", "float32")
SKINS = (0.1, 0.2, 0.4, 0.8, 1.6)
PW_TOLS = {"float64": (1e-15, 1e-13, 1e-12, 1e-10, 1e-8, 1e-6), "float32": (1e-7, 1e-6, 1e-5, 1e-4)}
#: engine defaults (engine/setup/params.py: dt = t_c/50; engine/setup/spec.py: float64, verlet_skin = 0.4;
#: engine/shapes/spheroid/cpu_backend.py: PW_TOL)
#: "skin" is the backend's default at the gas scenes' phi (engine.setup.params.default_verlet_skin), set by main() per
#: report; analyse() takes the skin the default rows ran at from summary.json ("default_skin").
DEFAULT = {"dt_fraction": 50, "precision": "float64", "skin": 0.4}
DEFAULT_PW_TOL = {"float64": 1e-15, "float32": 1e-7}
#: Cooling chaos floor: the float64 reference repeated at these dt (converged to ~1e-5 in e_n).
FLOOR_FRACTIONS = (180, 190)
#: Two costs closer than this are a tie: repeated runs on the shared 2-core VM scatter by about +-15 %
#: (docs/performance.md, CPU spheres).
TIME_NOISE = 0.15
#: Two errors within this relative distance are a tie (the same physics to rounding).
ERROR_TIE = 0.05
#: ... and within this many combined standard errors of their seed means (fronts).
SIGMAS = 2.0
#: Finer reference of the rough elastic pairs: the model's own loss at t_c/800 against t_c/200.
FINE_FRACTION = 800

COLLISION_REPS = 7     # timed runs per collision row in the full variant (each lasts only milliseconds)
E_N_LOW = 0.3          # second restitution of the collision scene (head-on pairs)
RADIUS = 0.01          # m, every sphere scene (ellipsoids: volume-equivalent radius)
DENSITY = 2000.0       # kg/m^3
K_N = 1.0e8            # N/m
OVERLAP = 0.01         # typical head-on overlap sqrt(2) v_rms / omega_0 of the gas scenes, in radii


@dataclass
class Size:
    """Scene sizes of one report variant."""

    gas_n: int = 2048           # spheres in the elastic and cooling gases
    phi: float = 0.1
    collisions: float = 3.0     # collisions per particle of the cooling and elastic runs
    thermalization: float = 1.0
    pairs: int = 512            # collision scene: pairs
    ell_n: int = 128            # ellipsoid gas
    ell_collisions: float = 1.0
    ell_xi: float = 2.0
    ell_phi: float = 0.05       # bounding spheres (radius a) fill 0.05 xi^2 ~ 0.2: room on the start lattice
    oracle: int = 2000          # oracle pairs for the ellipsoid geometry
    reps: int = 3               # timed repetitions (median)
    seeds: tuple = (0, 1, 2)    # gases: drift / deviation averaged over these seeds (timing from the first)
    gas_pairs: int = 512        # elastic scenes: binary collisions drawn from the gas's collision statistics
    sweep_n: int = 4096         # skin sweep: spheres per run, volume fractions, skins, timed steps
    sweep_phis: tuple = (0.008, 0.1, 0.3)
    sweep_skins: tuple = (0.2, 0.4, 0.8, 1.2)
    sweep_steps: int = 3000
    dt_fractions: tuple = DT_FRACTIONS
    skins: tuple = SKINS
    pw_tols: dict = field(default_factory=lambda: dict(PW_TOLS))


SIZES = {
    "full": Size(),
    "quick": Size(gas_n=1024, collisions=1.5, thermalization=0.5, pairs=128, ell_n=64, ell_collisions=0.5,
                  oracle=500, reps=1, seeds=(0,), gas_pairs=128, sweep_n=2048, sweep_phis=(0.1, 0.3),
                  sweep_skins=(0.4, 0.8), sweep_steps=1500, skins=(0.2, 0.4, 0.8),
                  pw_tols={"float64": (1e-15, 1e-12, 1e-8), "float32": (1e-7, 1e-5)}),
    "tiny": Size(gas_n=256, collisions=0.6, thermalization=0.3, pairs=32, ell_n=64, ell_collisions=0.2,
                 oracle=200, reps=1, seeds=(0,), gas_pairs=32, sweep_n=512, sweep_phis=(0.1,),
                 sweep_skins=(0.4, 0.8), sweep_steps=300, dt_fractions=(10, 50, 200), skins=(0.4, 0.8),
                 pw_tols={"float64": (1e-15,), "float32": (1e-7,)}),
}


# ---- helpers ---------------------------------------------------------------------------------------

def machine(backend: str, device: str | None = None) -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba

    info = {"cpu": cpu, "cores": os.cpu_count(), "numba_threads": numba.get_num_threads(),
            "numba": numba.__version__, "numpy": np.__version__, "python": platform.python_version(),
            "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "backend": backend, "date": time.strftime("%Y-%m-%d")}
    if device:
        info["device"] = device
    return info


def box_for(n: int, phi: float, radius: float = RADIUS) -> float:
    return (4.0 * math.pi * n * radius**3 / (3.0 * phi)) ** (1.0 / 3.0)


def gas_spec(size: Size, *, dt_fraction, precision, skin, e_n, e_t, collisions, thermalization, backend,
             seed=0, shape="sphere", n=None, records=60, steps=None):
    """A periodic gas with typical head-on overlap OVERLAP radii running `collisions` per particle
    (or `steps` time steps)."""
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    n = n or (size.ell_n if shape == "ellipsoid" else size.gas_n)
    xi = size.ell_xi if shape == "ellipsoid" else 1.0
    phi = size.ell_phi if shape == "ellipsoid" else size.phi
    fields = dict(shape=shape, n_particles=n, volume_fraction=phi, box_length=box_for(n, phi),
                  e_n=e_n, e_t=e_t, elongation=xi, stiffness=K_N, density=DENSITY, snapshots=0,
                  precision=precision, seed=seed, backend=backend, verlet_skin=skin, overlap_limit=0.2,
                  thermalization=thermalization, friction=None)
    probe = SimulationSpec.model_construct(**{**SimulationSpec.model_construct().__dict__, **fields,
                                              "velocity_rms": 1.0, "dt": None})
    p = derive(probe)
    v = OVERLAP * p.radius_min * p.omega0 / math.sqrt(2.0)
    probe = SimulationSpec.model_construct(**{**probe.__dict__, "velocity_rms": v})
    p = derive(probe)
    t_end = collisions / p.collision_rate0 if steps is None else steps * p.contact_time / dt_fraction
    return SimulationSpec(**{**fields, "velocity_rms": v, "t_end": t_end, "dt": p.contact_time / dt_fraction,
                             "output_interval": t_end / records})


def run_gas(spec, backend: str, reps: int, tmp: Path) -> dict:
    """Run a spec `reps` times; series of the first run, median Cundall number."""
    from engine.output.h5md import read_parameters, read_series
    from engine.driver.simulate import run

    path = tmp / "gas.h5"
    cund, device, out = [], None, None
    for r in range(max(1, reps)):
        s = run(spec, path, backend=backend)
        cund.append(s.cundall)
        device = s.device
        if r == 0:
            names = ("kinetic_energy_translational", "kinetic_energy_rotational", "elastic_energy",
                     "temperature_translational", "temperature_rotational", "max_overlap")
            out = {k: read_series(path, k) for k in names}
            par = read_parameters(path)
            out["parameters"] = {k: par[k] for k in ("radius", "number_density", "mass", "contact_time", "dt")}
            out["steps"] = s.steps
    out["cundall"] = float(statistics.median(cund))
    out["cundall_runs"] = [float(c) for c in cund]
    out["device"] = device
    return out


def energy_drift(series: dict) -> float:
    e = (series["kinetic_energy_translational"]["value"] + series["kinetic_energy_rotational"]["value"]
         + series["elastic_energy"]["value"])
    return float(np.max(np.abs(e / e[0] - 1.0)))


def throughput(cundall: float, dt_fraction: float) -> float:
    """Particle-contact-times simulated per wall second: Cundall x dt / t_c."""
    return cundall / dt_fraction


# ---- scene 1: binary collisions --------------------------------------------------------------------

def collision_scene(size: Size, seed: int = 7):
    """Pairs on a lattice (spacing 8 a): positions, velocities, and per-pair (angle, v_rel)."""
    from engine.setup.params import Q_SPHERE

    rng = np.random.default_rng(seed)
    k = size.pairs
    a = RADIUS
    m = DENSITY * 4.0 / 3.0 * math.pi * a**3
    omega0 = math.sqrt(K_N / (0.5 * m))
    side = int(math.ceil(k ** (1.0 / 3.0)))
    spacing = 8.0 * a
    box = side * spacing
    depth = np.exp(rng.uniform(math.log(0.002), math.log(0.02), size=k))   # peak overlap / a
    speed = depth * a * omega0
    angle = np.where(np.arange(k) % 2 == 0, 0.0, math.radians(10.0))
    phase = rng.uniform(size=k)            # contact start anywhere inside a step
    pos = np.zeros((2 * k, 3))
    vel = np.zeros((2 * k, 3))
    for p in range(k):
        c = (np.array([p % side, (p // side) % side, p // side**2]) + 0.5) * spacing
        v = speed[p] * np.array([math.cos(angle[p]), math.sin(angle[p]), 0.0])
        gap = 1e-3 * a + phase[p] * speed[p] * math.cos(angle[p]) * (math.pi / omega0) / 10.0
        pos[2 * p] = c - np.array([a + gap / 2, 0, 0])
        pos[2 * p + 1] = c + np.array([a + gap / 2, 0, 0])
        vel[2 * p] = v / 2
        vel[2 * p + 1] = -v / 2
    approach = float(np.max(1.2e-3 * a / (speed * np.cos(angle))) + (math.pi / omega0) / 10)
    return dict(box=box, pos=pos, vel=vel, angle=angle, speed=speed, mass=m, inertia=Q_SPHERE * m * a * a,
                omega0=omega0, tc=math.pi / omega0, approach=approach, duration=approach + 3.0 * math.pi / omega0)


def run_pairs(scene: dict, *, dt_fraction: int, precision: str, backend: str, reps: int, e_n: float,
              e_t: float) -> dict:
    """Run a pair scene (positions, velocities, optional spins) for its ``duration``: final state, Cundall."""
    from engine.backends.base import ContactParams, SphereSystem
    from engine.backends.registry import make_backend
    from engine.setup.params import gamma_n_from_restitution, k_t_paper

    k2 = scene["pos"].shape[0]
    m12 = 0.5 * scene["mass"]
    dt = scene["tc"] / dt_fraction
    params = ContactParams(k_n=K_N, gamma_n_coef=gamma_n_from_restitution(e_n, K_N, m12) / math.sqrt(m12),
                           k_t=None if e_t <= -1.0 else k_t_paper(e_t, K_N), friction=None, dt=dt,
                           skin=DEFAULT["skin"] * RADIUS, precision=precision, orientation=False, overlap_limit=0.5)
    steps = int(scene["duration"] / dt) + 1
    omega = scene.get("omega", np.zeros((k2, 3)))
    cund, st, device = [], None, None
    for _ in range(max(1, reps)):
        system = SphereSystem(scene["box"], scene["pos"].copy(), scene["vel"].copy(), omega.copy(),
                              np.tile([1.0, 0, 0, 0], (k2, 1)), np.full(k2, RADIUS), np.full(k2, scene["mass"]),
                              np.full(k2, scene["inertia"]))
        be = make_backend(backend, system, params)
        be.warmup()
        t0 = time.perf_counter()
        be.advance(steps)
        st = be.state()          # includes the device -> host copy (once, at the end)
        wall = time.perf_counter() - t0
        cund.append(k2 * steps / wall)
        device = be.device
    return {"velocity": np.asarray(st["velocity"], np.float64),
            "angular_velocity": np.asarray(st["angular_velocity"], np.float64),
            "position": np.asarray(st["position"], np.float64),
            "cundall": float(statistics.median(cund)), "cundall_runs": cund, "device": device, "steps": steps}


def run_collisions(scene: dict, *, dt_fraction: int, precision: str, backend: str, reps: int,
                   e_n: float = 0.8, e_t: float = 0.8) -> dict:
    k2 = scene["pos"].shape[0]
    r = run_pairs(scene, dt_fraction=dt_fraction, precision=precision, backend=backend, reps=reps, e_n=e_n, e_t=e_t)
    v, w = r["velocity"], r["angular_velocity"]
    n_hat = np.array([-1.0, 0.0, 0.0])
    e_meas = np.zeros(k2 // 2)
    for p in range(k2 // 2):
        g0 = scene["vel"][2 * p] - scene["vel"][2 * p + 1]
        g1 = v[2 * p] - v[2 * p + 1] - RADIUS * np.cross(w[2 * p] + w[2 * p + 1], n_hat)
        if scene["angle"][p] == 0.0:
            e_meas[p] = -g1.dot(n_hat) / g0.dot(n_hat)
        else:
            gt0 = g0 - g0.dot(n_hat) * n_hat
            gt1 = g1 - g1.dot(n_hat) * n_hat
            e_meas[p] = -gt1.dot(gt0) / gt0.dot(gt0)
    return {"e": e_meas, "cundall": r["cundall"], "cundall_runs": r["cundall_runs"], "device": r["device"],
            "steps": r["steps"]}


def gas_pair_scene(size: Size, seed: int = 11) -> dict:
    """Binary collisions drawn from the collision statistics of the elastic gas scenes (gas_spec).

    The gas starts Maxwellian at velocity_rms = OVERLAP a omega_0 / sqrt(2) with equal rotational and
    translational temperatures T, and stays so (elastic). Collisions of relative speed g happen at a rate
    proportional to g times the relative-velocity Maxwellian, so g^2 / (4 sigma_v^2) ~ Gamma(2) (sigma_v
    the per-component velocity spread); the impact parameter b is uniform over the disc of radius 2a
    (b / 2a = sqrt(U)); spins are Gaussian at the temperature T; the touching time is uniform over one
    t_c/10 step, so every dt meets every contact phase. Pairs sit on a lattice of spacing 6 a (box
    comparable to the gas's), their centres of mass at rest.
    """
    from engine.setup.params import Q_SPHERE

    rng = np.random.default_rng(seed)
    k = size.gas_pairs
    a = RADIUS
    m = DENSITY * 4.0 / 3.0 * math.pi * a**3
    inertia = Q_SPHERE * m * a * a
    omega0 = math.sqrt(K_N / (0.5 * m))
    tc = math.pi / omega0
    sigma_v = OVERLAP * a * omega0 / math.sqrt(2.0) / math.sqrt(3.0)
    g = 2.0 * sigma_v * np.sqrt(rng.gamma(2.0, 1.0, size=k))
    beta = np.sqrt(rng.uniform(size=k))
    t_touch = (2.0 + rng.uniform(size=k)) * tc / 10.0
    omega = rng.normal(scale=sigma_v * math.sqrt(m / inertia), size=(2 * k, 3))
    side = int(math.ceil(k ** (1.0 / 3.0)))
    spacing = 6.0 * a
    pos = np.zeros((2 * k, 3))
    vel = np.zeros((2 * k, 3))
    for p in range(k):
        c = (np.array([p % side, (p // side) % side, p // side**2]) + 0.5) * spacing
        gvec = np.array([g[p], 0.0, 0.0])
        r_touch = 2.0 * a * np.array([-math.sqrt(1.0 - beta[p] ** 2), beta[p], 0.0])   # r = x1 - x2, r.g < 0
        r0 = r_touch - gvec * t_touch[p]
        pos[2 * p], pos[2 * p + 1] = c + r0 / 2, c - r0 / 2
        vel[2 * p], vel[2 * p + 1] = gvec / 2, -gvec / 2
    return dict(box=side * spacing, pos=pos, vel=vel, omega=omega, mass=m, inertia=inertia, omega0=omega0, tc=tc,
                duration=float(np.max(t_touch)) + 2.5 * tc, temperature=m * sigma_v**2)


def pair_energy(scene: dict, *, dt_fraction: int, precision: str, backend: str, e_t: float, reps: int = 1) -> dict:
    """Per collision of a gas pair scene: eps = dE / (6 T); also whether every pair separated again."""
    r = run_pairs(scene, dt_fraction=dt_fraction, precision=precision, backend=backend, reps=reps, e_n=1.0, e_t=e_t)
    m, inertia = scene["mass"], scene["inertia"]

    def energy(v, w):
        e = 0.5 * m * np.sum(v * v, axis=1) + 0.5 * inertia * np.sum(w * w, axis=1)
        return e[0::2] + e[1::2]

    d = r["position"][0::2] - r["position"][1::2]
    d -= scene["box"] * np.round(d / scene["box"])
    apart = bool(np.all(np.sqrt(np.sum(d * d, axis=1)) > 2.0 * RADIUS))
    de = energy(r["velocity"], r["angular_velocity"]) - energy(scene["vel"], scene["omega"])
    return {"eps": de / (6.0 * scene["temperature"]), "apart": apart, "device": r["device"], "steps": r["steps"]}


def build_collisions(size: Size, backend: str, reps: int, log) -> dict:
    from engine.setup.params import e_t_effective

    scene = collision_scene(size)
    head = scene["angle"] == 0.0
    e_n, e_t = 0.8, 0.8
    e_t_eff = e_t_effective(e_n, e_t)
    ref = run_collisions(scene, dt_fraction=max(DT_FRACTIONS), precision="float64", backend=backend, reps=1)
    rows = []
    for prec in PRECISIONS:
        for frac in size.dt_fractions:
            # a pair run lasts milliseconds: time it COLLISION_REPS times in the full variant (median)
            creps = COLLISION_REPS if reps >= 3 else reps
            r = ref if (prec == "float64" and frac == max(DT_FRACTIONS) and creps <= 1) else \
                run_collisions(scene, dt_fraction=frac, precision=prec, backend=backend, reps=creps)
            err_n = float(np.max(np.abs(r["e"][head] - e_n)))
            err_t = float(np.max(np.abs(r["e"][~head] - ref["e"][~head])))
            err_t_an = float(np.max(np.abs(r["e"][~head] - e_t_eff)))
            # strong damping: the dashpot's O(dt^2) error grows as e_n falls (head-on pairs only)
            low = run_collisions(scene, dt_fraction=frac, precision=prec, backend=backend, reps=1, e_n=E_N_LOW)
            err_low = float(np.max(np.abs(low["e"][head] - E_N_LOW)))
            rows.append({"scene": "collisions", "dt_fraction": frac, "precision": prec, "skin": DEFAULT["skin"],
                         "cundall": r["cundall"], "throughput": throughput(r["cundall"], frac),
                         "err_e_n": err_n, "err_e_n_low": err_low, "err_e_t": err_t, "err_e_t_analytic": err_t_an,
                         "error": max(err_n, err_low, err_t), "device": r["device"], "steps": r["steps"]})
            log(f"collisions dt=t_c/{frac} {prec}: |de_n| {err_n:.2e} (e_n = {E_N_LOW}: {err_low:.2e}) "
                f"|de_t| {err_t:.2e} Cundall {r['cundall']:.3g}")
    return {"rows": rows, "pairs": size.pairs, "e_t_effective": e_t_eff,
            "ref_e_t_offset": float(np.max(np.abs(ref["e"][~head] - e_t_eff))),
            "ref_e_n_error": float(np.max(np.abs(ref["e"][head] - e_n))),
            "depth_range": [float(np.min(scene["speed"]) / scene["omega0"] / RADIUS),
                            float(np.max(scene["speed"]) / scene["omega0"] / RADIUS)],
            "box": scene["box"], "device": ref["device"]}


# ---- scenes 2 and 3: elastic drift and cooling -----------------------------------------------------

def _knob_grid(size: Size):
    """(dt_fraction, precision, skin) of the dt x precision grid and the skin row at the defaults."""
    grid = [(f, p, DEFAULT["skin"]) for p in PRECISIONS for f in size.dt_fractions]
    grid += [(DEFAULT["dt_fraction"], DEFAULT["precision"], s) for s in size.skins if s != DEFAULT["skin"]]
    return grid


def _mean_se(x) -> tuple[float, float]:
    x = np.asarray(x, float)
    return float(np.mean(x)), (float(np.std(x, ddof=1) / math.sqrt(x.size)) if x.size > 1 else 0.0)


def energy_end(series: dict) -> float:
    """Signed E(t_end)/E(0) - 1 of a run (E = E_tr + E_rot + E_el)."""
    e = (series["kinetic_energy_translational"]["value"] + series["kinetic_energy_rotational"]["value"]
         + series["elastic_energy"]["value"])
    return float(e[-1] / e[0] - 1.0)


def build_elastic(size: Size, backend: str, reps: int, tmp: Path, log, e_t: float, pairs: dict) -> dict:
    """Elastic gas, smooth (e_t = -1: the integrator alone) or rough (e_n = e_t = 1).

    Error of a row: RMS over the gas pair sample of the energy error per collision eps = dE/(6T) (smooth:
    against exact conservation; rough: minus the same collision at float64, t_c/200, i.e. the part dt and
    precision add to the model's own loss). Cost and the accumulated drift: the gas runs (seeds).
    """
    rough = e_t > 0
    name = "elastic_rough" if rough else "elastic_smooth"
    ref_frac = max(DT_FRACTIONS)
    c, n = size.collisions, size.gas_n
    ref = pair_energy(pairs, dt_fraction=ref_frac, precision="float64", backend=backend, e_t=e_t)
    rows = []
    for prec in PRECISIONS:
        for frac in size.dt_fractions:
            pe = ref if (prec == "float64" and frac == ref_frac) else \
                pair_energy(pairs, dt_fraction=frac, precision=prec, backend=backend, e_t=e_t)
            eps = pe["eps"]
            d = eps - ref["eps"] if rough else eps
            ends, maxes, timings = [], [], []
            for k, seed in enumerate(size.seeds):
                spec = gas_spec(size, dt_fraction=frac, precision=prec, skin=DEFAULT["skin"], e_n=1.0, e_t=e_t,
                                seed=seed, collisions=c, thermalization=0.0, backend=backend)
                g = run_gas(spec, backend, reps if k == 0 else 1, tmp)
                if k == 0:
                    first = g
                ends.append(energy_end(g))
                maxes.append(energy_drift(g))
                timings += g["cundall_runs"]     # every seed runs the same N and steps: one timing sample each
            cund = float(statistics.median(timings))
            end, end_se = _mean_se(ends)
            mx, mx_se = _mean_se(maxes)
            rows.append({"scene": name, "dt_fraction": frac, "precision": prec, "skin": DEFAULT["skin"],
                         "cundall": cund, "cundall_runs": timings, "throughput": throughput(cund, frac),
                         "error": float(np.sqrt(np.mean(d * d))), "error_se": 0.0, "err_mean": float(np.mean(d)),
                         "eps_mean": float(np.mean(eps)), "eps_sd": float(np.std(eps)),
                         "pred_drift": c * float(np.mean(eps)), "pred_sd": math.sqrt(2.0 * c / n) * float(np.std(eps)),
                         "pred_dt_drift": c * float(np.mean(d)), "pairs_apart": pe["apart"],
                         "gas_end": end, "gas_end_se": end_se, "gas_end_seeds": ends, "gas_max": mx,
                         "gas_max_se": mx_se, "steps": first["steps"], "device": first["device"],
                         "max_overlap": float(np.max(first["max_overlap"]["value"]))})
            log(f"{name} dt=t_c/{frac} {prec}: per-collision error rms {rows[-1]['error']:.2e} (mean "
                f"{rows[-1]['err_mean']:+.1e}); gas E_end/E0-1 {end:+.2e} +- {end_se:.1e}, max {mx:.2e}; "
                f"Cundall {cund:.3g}")
    out = {"rows": rows, "spec": spec.model_dump(), "pairs": size.gas_pairs}
    if rough:   # the model's own loss: the same collisions at t_c/200 and t_c/800
        fine = pair_energy(pairs, dt_fraction=FINE_FRACTION, precision="float64", backend=backend, e_t=e_t)
        out["model_loss"] = {"eps_ref": float(np.mean(ref["eps"])), "eps_fine": float(np.mean(fine["eps"])),
                             "pred_drift": c * float(np.mean(ref["eps"])),
                             "fine_vs_ref_rms": float(np.sqrt(np.mean((fine["eps"] - ref["eps"]) ** 2)))}
        log(f"{name} model loss per collision: t_c/{ref_frac} {out['model_loss']['eps_ref']:.2e}, "
            f"t_c/{FINE_FRACTION} {out['model_loss']['eps_fine']:.2e}")
    return out


def _curves(g: dict):
    t = g["temperature_translational"]["time"]
    tt = g["temperature_translational"]["value"]
    rr = g["temperature_rotational"]["value"]
    return t, tt / tt[0], rr / tt[0]


def _dev_from(g: dict, ref: dict) -> float:
    t, T, R = _curves(g)
    tr, Tr, Rr = _curves(ref)
    grid = tr[tr <= min(t[-1], tr[-1])]
    dT = np.abs(np.interp(grid, t, T) / np.interp(grid, tr, Tr) - 1.0)
    dR = np.abs(np.interp(grid, t, R) / np.interp(grid, tr, Rr) - 1.0)
    return float(max(dT.max(), dR.max()))


def _tau_curves(g: dict, spec):
    """tau, T/T0, R/T0 of one run (tau = (2/3) G T0^1/2 t with its own measured T0)."""
    from engine.analysis.theory import tau_factor

    t, T, R = _curves(g)
    par = g["parameters"]
    t0 = float(g["temperature_translational"]["value"][0])
    k = tau_factor(float(par["radius"]), float(par["number_density"]), float(par["mass"]), spec.volume_fraction, t0)
    return k * t, T, R


def _dev_ode(runs: list, spec) -> tuple[float, float, float]:
    """max |T/T_ODE - 1|, |R/R_ODE - 1| of the seed-mean curves (Luding's ODE with e_t,eff from R(0)/T(0))."""
    from engine.setup.params import e_t_effective
    from engine.analysis.theory import luding_ode

    curves = [_tau_curves(g, spec) for g in runs]
    tau = curves[0][0]
    tau = tau[tau <= min(c[0][-1] for c in curves)]
    T = np.mean([np.interp(tau, c[0], c[1]) for c in curves], axis=0)
    R = np.mean([np.interp(tau, c[0], c[2]) for c in curves], axis=0)
    Tth, Rth = luding_ode(spec.e_n, e_t_effective(spec.e_n, spec.e_t), tau, 1.0, float(R[0]))
    return float(np.max(np.abs(T / Tth - 1))), float(np.max(np.abs(R / Rth - 1))), float(tau[-1])


def _summary(g: dict) -> dict:
    """What the cooling scene keeps of a run (the curves and the cost)."""
    keep = ("temperature_translational", "temperature_rotational", "parameters", "cundall", "cundall_runs", "steps",
            "device", "max_overlap")
    return {k: g[k] for k in keep}


def build_cooling(size: Size, backend: str, reps: int, tmp: Path, log) -> dict:
    """Cooling curves per knob against a float64 t_c/200 reference of the same seed, averaged over seeds."""
    common = dict(e_n=0.8, e_t=0.8, collisions=size.collisions, thermalization=size.thermalization,
                  backend=backend)
    ref_frac = max(DT_FRACTIONS)
    ref_spec = gas_spec(size, dt_fraction=ref_frac, precision="float64", skin=DEFAULT["skin"], **common)
    refs, floors = {}, []
    for k, seed in enumerate(size.seeds):
        refs[seed] = _summary(run_gas(gas_spec(size, dt_fraction=ref_frac, precision="float64", skin=DEFAULT["skin"],
                                               seed=seed, **common), backend, reps if k == 0 else 1, tmp))
        for f in FLOOR_FRACTIONS:
            g = run_gas(gas_spec(size, dt_fraction=f, precision="float64", skin=DEFAULT["skin"], seed=seed, **common),
                        backend, 1, tmp)
            floors.append(_dev_from(g, refs[seed]))
    floor = float(np.mean(floors))
    log(f"cooling reference t_c/{ref_frac}: Cundall {refs[size.seeds[0]]['cundall']:.3g}; chaos floor "
        f"(t_c/{', /'.join(map(str, FLOOR_FRACTIONS))} x seeds) {', '.join(_e(x) for x in floors)}")
    rows = []
    for frac, prec, skin in _knob_grid(size):
        devs, runs = [], []
        for k, seed in enumerate(size.seeds):
            if frac == ref_frac and prec == "float64" and skin == DEFAULT["skin"]:
                g = refs[seed]
            else:
                g = _summary(run_gas(gas_spec(size, dt_fraction=frac, precision=prec, skin=skin, seed=seed, **common),
                                     backend, reps if k == 0 else 1, tmp))
            devs.append(_dev_from(g, refs[seed]))
            runs.append(g)
        dev = float(np.mean(devs))
        se = float(np.std(devs, ddof=1) / math.sqrt(len(devs))) if len(devs) > 1 else 0.0
        dT, dR, tau_end = _dev_ode(runs, ref_spec)
        g = runs[0]
        timings = [c for r in runs for c in r["cundall_runs"]]   # same N and steps for every seed
        cund = float(statistics.median(timings))
        rows.append({"scene": "cooling", "dt_fraction": frac, "precision": prec, "skin": skin,
                     "cundall": cund, "cundall_runs": timings, "throughput": throughput(cund, frac), "error": dev,
                     "error_se": se, "error_seeds": devs, "err_ode_T": dT, "err_ode_R": dR, "err_ode": max(dT, dR),
                     "tau_end": tau_end, "steps": g["steps"], "device": g["device"],
                     "max_overlap": float(max(np.max(r["max_overlap"]["value"]) for r in runs))})
        log(f"cooling dt=t_c/{frac} {prec} skin {skin}: vs ref {dev:.2e} +- {se:.1e}, vs ODE T {dT:.2e} "
            f"R {dR:.2e}, Cundall {cund:.3g}")
    return {"rows": rows, "floor": floor, "floors": floors, "spec": ref_spec.model_dump()}


# ---- skin sweep: the Verlet skin's cost over volume fractions ----------------------------------------

def build_skin_sweep(size: Size, backend: str, reps: int, tmp: Path, log) -> dict:
    """Cundall number against the Verlet skin at several volume fractions (cost only: the skin moves no
    trajectory). Rough e_n = e_t = 0.8 gas, dt = t_c/50, float64, orientation off, typical overlap OVERLAP,
    the same lattice start for every skin, ``size.sweep_steps`` steps (several list rebuilds at every skin),
    median of ``reps`` timed ``advance`` calls (compilation and the first list build excluded, one
    observables reduction at the end, as bench/specialisation.py times)."""
    from engine.backends.registry import make_backend
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params
    from engine.setup.params import default_verlet_skin

    rows = []
    for phi in size.sweep_phis:
        rule = default_verlet_skin(backend, "sphere", phi)      # one extra row where it is not a swept skin
        skins = sorted(set(size.sweep_skins) | {rule})
        spec = gas_spec(replace(size, phi=phi), dt_fraction=DEFAULT["dt_fraction"], precision=DEFAULT["precision"],
                        skin=DEFAULT["skin"], e_n=0.8, e_t=0.8, collisions=0.0, thermalization=0.0, backend=backend,
                        n=size.sweep_n, records=2, steps=size.sweep_steps)
        p = derive(spec)
        system = initial_spheres(spec, p)
        base = contact_params(spec, p, thermalization=False).with_(orientation=False)
        for skin in skins:
            contact = base.with_(skin=skin * p.radius)
            runs, device = [], None
            for _ in range(max(1, reps)):
                be = make_backend(backend, system, contact)
                be.warmup()
                t0 = time.perf_counter()
                be.advance(size.sweep_steps)
                be.observe()                 # synchronises a GPU backend
                runs.append(system.n * size.sweep_steps / (time.perf_counter() - t0))
                device = be.device
            rows.append({"phi": phi, "skin": skin, "cundall": float(statistics.median(runs)), "cundall_runs": runs,
                         "n": size.sweep_n, "steps": size.sweep_steps, "device": device,
                         "builds": int(getattr(be, "builds", -1))})
            log(f"skin sweep phi={phi} L_v={skin:.3g}a: Cundall {rows[-1]['cundall']:.3g} "
                f"({rows[-1]['builds']} builds)")
    sweep_flags(rows)
    return {"rows": rows}


def sweep_flags(rows: list) -> None:
    """vs_fastest and fastest (within TIME_NOISE of the fastest skin: the cost front) of every sweep row."""
    for phi in {r["phi"] for r in rows}:
        sub = [r for r in rows if r["phi"] == phi]
        best = max(r["cundall"] for r in sub)
        for r in sub:
            r["vs_fastest"] = r["cundall"] / best
            r["fastest"] = r["cundall"] >= best * (1.0 - TIME_NOISE)    # within the timing noise of the fastest


def sweep_default_row(rows: list, phi: float, backend: str):
    """(rule's skin, the row compared, exact?) at ``phi``: the row at the default rule's own skin
    (engine.setup.params.default_verlet_skin), else the nearest swept skin (in log L_v)."""
    from engine.setup.params import default_verlet_skin

    want = default_verlet_skin(backend, "sphere", phi)
    sub = [r for r in rows if r["phi"] == phi]
    exact = [r for r in sub if math.isclose(r["skin"], want, rel_tol=1e-9)]
    if exact:
        return want, exact[0], True
    return want, min(sub, key=lambda r: abs(math.log(r["skin"] / want))), False


# ---- scene 4: ellipsoids ---------------------------------------------------------------------------

def _timed_batch(fn, reps=3):
    best = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best.append(time.perf_counter() - t0)
    return statistics.median(best)


@functools.cache
def paper_batch_kernel():
    """An njit loop of the Delta/P disjointness test of Rubio-Largo et al. (2015)
    (engine.physics.ellipsoid.paper_disjoint) over a batch of pairs: (r, qa, aa, qb, ab, half, out)."""
    import numba

    from engine.physics.ellipsoid import paper_disjoint

    @numba.njit
    def paper_batch(r, qa, aa, qb, ab, half, out):
        for k in range(r.shape[0]):
            out[k] = paper_disjoint(r[k, 0], r[k, 1], r[k, 2], qa[k, 0], qa[k, 1], qa[k, 2], qa[k, 3],
                                    aa[k, 0], aa[k, 1], aa[k, 2], qb[k, 0], qb[k, 1], qb[k, 2], qb[k, 3],
                                    ab[k, 0], ab[k, 1], ab[k, 2], half)

    return paper_batch


def build_ellipsoid(size: Size, reps: int, tmp: Path, log) -> dict:
    """Geometry error against the oracle and ellipsoid-gas cost, per precision and PW tolerance (CPU)."""
    from engine.shapes.spheroid import cpu_backend as cpu_ellipsoid
    from tests.engine.test_ellipsoid_geometry import H, contact_batch, errors
    from tests.engine.test_ellipsoid_oracle import random_overlapping

    paper_batch = paper_batch_kernel()
    data = random_overlapping(size.oracle, seed=2024)
    k = size.oracle
    tile = max(1, 20000 // k)              # time the kernel on >= 2e4 evaluations
    rows, paper_rows = [], []
    saved = dict(cpu_ellipsoid.PW_TOL)
    try:
        for prec in ELLIPSOID_PRECISIONS:
            dtype = np.float64 if prec == "float64" else np.float32

            def c(x, dtype=dtype):
                return np.ascontiguousarray(np.asarray(x, dtype=dtype))

            arrs = [c(data[key]) for key in ("r", "qa", "axes_a", "qb", "axes_b")]
            big = [np.ascontiguousarray(np.tile(a, (tile, 1))) for a in arrs]
            for tol in size.pw_tols[prec]:
                out = np.zeros((k, 9), dtype)
                contact_batch(*arrs, dtype(tol), dtype(H), out)
                ed, en, ec = errors(data, out)
                bigout = np.zeros((k * tile, 9), dtype)
                contact_batch(*big, dtype(tol), dtype(H), bigout)   # compile/warm
                sec = _timed_batch(lambda: contact_batch(*big, dtype(tol), dtype(H), bigout))
                cpu_ellipsoid.PW_TOL[prec] = tol
                spec = gas_spec(size, dt_fraction=DEFAULT["dt_fraction"], precision=prec, skin=DEFAULT["skin"],
                                e_n=1.0, e_t=-1.0, collisions=size.ell_collisions, thermalization=0.0,
                                backend="cpu", shape="ellipsoid")
                g = run_gas(spec, "cpu", reps, tmp)
                rows.append({"scene": "ellipsoid", "precision": prec, "pw_tol": tol,
                             "dt_fraction": DEFAULT["dt_fraction"], "skin": DEFAULT["skin"],
                             "err_delta_max": float(ed.max()), "err_delta_p99": float(np.percentile(ed, 99)),
                             "err_normal_max": float(en.max()), "err_point_max": float(ec.max()),
                             "nan": int(np.isnan(out).sum()), "missed": int(np.sum(out[:, 0] >= 1)),
                             "pairs_per_s": k * tile / sec, "cundall": g["cundall"],
                             "throughput": throughput(g["cundall"], DEFAULT["dt_fraction"]),
                             "drift": energy_drift(g), "error": float(max(ed.max(), en.max(), ec.max())),
                             "device": g["device"],
                             "steps": g["steps"]})
                log(f"ellipsoid {prec} tol {tol:g}: |d delta| {ed.max():.2e} b, |d n| {en.max():.2e}, "
                    f"|d C| {ec.max():.2e}, "
                    f"{k * tile / sec:.3g} pairs/s, gas Cundall {g['cundall']:.3g}, drift {energy_drift(g):.2e}")
                cpu_ellipsoid.PW_TOL[prec] = saved[prec]
            pd = np.zeros(k * tile, np.bool_)
            paper_batch(*big, dtype(0.5), pd)
            sec = _timed_batch(lambda: paper_batch(*big, dtype(0.5), pd))
            paper_rows.append({"precision": prec, "called_disjoint": int(pd[:k].sum()), "pairs": k,
                               "pairs_per_s": k * tile / sec})
    finally:
        cpu_ellipsoid.PW_TOL.update(saved)
    return {"rows": rows, "paper": paper_rows, "spec": spec.model_dump(),
            "delta_range": [float(np.min(np.asarray(data["delta"], float))),
                            float(np.max(np.asarray(data["delta"], float)))]}


# ---- Pareto fronts ---------------------------------------------------------------------------------

def dominates(q: dict, p: dict, floor: float = 0.0, sigmas: float = SIGMAS) -> bool:
    """q is demonstrably at least as good as p and better in one respect.

    Errors closer than ERROR_TIE (relative) are the same (deterministic rows, or the same trajectory to
    rounding): then the measurably cheaper row wins. Errors further apart but within ``sigmas`` combined
    standard errors of their seed means (``error_se``) are unresolved: the measurement cannot tell which is
    more accurate, so neither dominates the other through them. Otherwise the smaller error is better.
    q dominates p when q is not measurably more expensive (TIME_NOISE) and either has a resolved smaller
    error or the same error at a measurably lower cost. Errors below ``floor`` count as the floor.
    """
    eq, ep = max(q["error"], floor), max(p["error"], floor)
    same = abs(eq - ep) <= ERROR_TIE * max(eq, ep)
    noise = sigmas * math.hypot(q.get("error_se", 0.0), p.get("error_se", 0.0))
    better = ep - eq > max(ERROR_TIE * max(eq, ep), noise)
    not_dearer = q["throughput"] >= p["throughput"] * (1.0 - TIME_NOISE)
    cheaper = q["throughput"] > p["throughput"] * (1.0 + TIME_NOISE)
    return not_dearer and (better or (same and cheaper))


def unresolved(q: dict, p: dict, floor: float = 0.0, sigmas: float = SIGMAS) -> bool:
    """q is measurably cheaper than p and their errors differ, but by less than the seed scatter resolves."""
    eq, ep = max(q["error"], floor), max(p["error"], floor)
    noise = sigmas * math.hypot(q.get("error_se", 0.0), p.get("error_se", 0.0))
    return (q["throughput"] > p["throughput"] * (1.0 + TIME_NOISE)
            and ERROR_TIE * max(eq, ep) < abs(eq - ep) <= noise)


def pareto(rows: list, floor: float = 0.0) -> list:
    """Marks each row with `on_front` and, if off it, `dominated_by` (labels); returns the front.

    Also `unresolved_with`: the cheaper rows whose errors the seed scatter cannot rank against this row's.
    """
    for p in rows:
        by = [q for q in rows if q is not p and dominates(q, p, floor)]
        p["on_front"] = not by
        p["dominated_by"] = [label(q) for q in by]
        p["unresolved_with"] = [label(q) for q in rows if q is not p and unresolved(q, p, floor)]
    return sorted([r for r in rows if r["on_front"]], key=lambda r: r["throughput"])


def label(r: dict) -> str:
    s = f"t_c/{r['dt_fraction']} {r['precision']}"
    if r.get("pw_tol") is not None:
        return f"{r['precision']} tol {r['pw_tol']:g}"
    if r.get("skin", DEFAULT["skin"]) != DEFAULT["skin"]:
        s += f" L_v={r['skin']:g}a"
    return s


def is_default(r: dict) -> bool:
    if r.get("pw_tol") is not None:
        return r["precision"] == DEFAULT["precision"] and r["pw_tol"] == DEFAULT_PW_TOL[r["precision"]]
    return (r["dt_fraction"] == DEFAULT["dt_fraction"] and r["precision"] == DEFAULT["precision"]
            and r.get("skin", DEFAULT["skin"]) == DEFAULT["skin"])


# ---- report ----------------------------------------------------------------------------------------

TITLES = {
    "collisions": "binary collisions: max |de_n| (e_n = 0.8, 0.3), |de_t|",
    "elastic_smooth": "elastic smooth gas (e_t = -1): energy error per collision (RMS)",
    "elastic_rough": "elastic rough gas (e_n = e_t = 1): energy error per collision added by dt (RMS)",
    "cooling": "cooling: deviation from float64 t_c/200",
    "ellipsoid": "ellipsoid geometry vs oracle (CPU)",
}


def _kind(r: dict) -> str:
    if r.get("pw_tol") is not None:
        return "tol"
    if r.get("skin", DEFAULT["skin"]) != DEFAULT["skin"]:
        return "skin"
    return "dt"


def plot(panels: list, path: Path, backend: str = "cpu") -> None:
    from engine.optional import require_matplotlib

    require_matplotlib("the accuracy report's figure")
    import matplotlib.pyplot as plt

    cols = 3
    rows_n = int(math.ceil(len(panels) / cols))
    fig, axes = plt.subplots(rows_n, cols, figsize=(5.4 * cols, 4.3 * rows_n), squeeze=False)
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    for ax, (title, rows, ykey, ylabel, floor) in zip(axes.ravel(), panels):
        if ykey == "sweep":     # Cundall number against the skin, one line per volume fraction
            for k, phi in enumerate(sorted({r["phi"] for r in rows})):
                sub = sorted([r for r in rows if r["phi"] == phi], key=lambda r: r["skin"])
                ax.plot([r["skin"] for r in sub], [r["cundall"] for r in sub], "o-", color=f"C{k}",
                        label=f"phi = {phi:g}")
                d = sweep_default_row(rows, phi, backend)[1]
                ax.plot([d["skin"]], [d["cundall"]], "*", ms=11, color="red", zorder=5,
                        label="default (engine rule)" if k == 0 else None)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("Verlet skin L_v / a", fontsize=8)
            ax.set_ylabel(ylabel, fontsize=8)
            ax.set_title(title, fontsize=9)
            ax.legend(fontsize=6)
            continue
        pos = [r[ykey] for r in rows if r[ykey] > 0]
        ymin = (min(pos) / 3.0) if pos else 1e-18     # a zero error (the reference itself) is drawn here

        def yv(r, ymin=ymin):
            return max(r[ykey], ymin)
        for prec, mk in (("float64", "o"), ("float32", "s"), ("mixed", "^")):
            for kind, color in (("dt", "C0"), ("skin", "C2"), ("tol", "C4")):
                pts = [r for r in rows if r["precision"] == prec and _kind(r) == kind]
                if pts:
                    ax.scatter([r["throughput"] for r in pts], [yv(r) for r in pts], marker=mk,
                               facecolors=color if prec == "float64" else "none", edgecolors=color, s=36,
                               label=f"{kind} ({prec})")
                    if ykey == "error" and any(r.get("error_se") for r in pts):
                        ax.errorbar([r["throughput"] for r in pts], [r[ykey] for r in pts],
                                    yerr=[2 * r.get("error_se", 0.0) for r in pts], fmt="none", ecolor=color, lw=0.8)
        if ykey == "error":
            front = sorted([r for r in rows if r.get("on_front")], key=lambda r: r["throughput"])
            if front:
                ax.plot([r["throughput"] for r in front], [max(yv(r), floor) for r in front], "k-", lw=1.2,
                        marker="x", ms=9, label="Pareto front (errors below the floor drawn at it)")
        for r in rows:
            y = yv(r)
            if is_default(r):
                ax.scatter([r["throughput"]], [y], marker="*", s=200, color="red", zorder=5, label="default")
            if _kind(r) == "dt":
                ax.annotate(f"/{r['dt_fraction']}", (r["throughput"], y), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
            elif _kind(r) == "tol":
                ax.annotate(f"{r['pw_tol']:g}", (r["throughput"], y), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        if floor:
            ax.axhline(floor, color="grey", ls=":", lw=1, label="floor")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("throughput = Cundall x dt/t_c (particle t_c / s)", fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _e(x) -> str:
    return f"{x:.2e}"


def _front_cell(r: dict) -> str:
    s = "yes" if r["on_front"] else "no"
    return s + (" (default)" if is_default(r) else "")


def verdict(rows: list, scene: str, floor: float = 0.0) -> str:
    d = [r for r in rows if is_default(r)]
    if not d:
        return f"- {scene}: the default is not among this variant's rows."
    d = d[0]
    if d["on_front"]:
        text = f"- **{scene}**: the default ({label(d)}) is on the Pareto front"
    else:
        text = (f"- **{scene}**: the default ({label(d)}) is **not** on the Pareto front: dominated by "
                f"{', '.join(d['dominated_by'])}")
        if floor and d["error"] <= floor * (1.0 + ERROR_TIE):
            text += " (its error is at this scene's chaos floor: the rows below it tie, and the cheaper ones win)"
    if d.get("unresolved_with"):
        text += (f"; the seed scatter does not rank it against the cheaper {', '.join(d['unresolved_with'])} "
                 "(errors within two standard errors), so this scene alone does not decide between them")
    return text + "."


def skin_verdict(sweep: dict, backend: str) -> str:
    """The default rule's skin against the fastest at every swept phi (front: within TIME_NOISE)."""
    rows = sweep["rows"]
    parts, ok = [], True
    for phi in sorted({r["phi"] for r in rows}):
        want, d, exact = sweep_default_row(rows, phi, backend)
        best = max((q for q in rows if q["phi"] == phi), key=lambda q: q["cundall"])
        name = f"L_v = {want:.3g} a" if exact else f"L_v = {want:.3g} a, nearest swept skin {d['skin']:g} a"
        parts.append(f"phi = {phi:g}: {name}, x{d['vs_fastest']:.2f} of the fastest (L_v = {best['skin']:g} a)"
                     + ("" if d["fastest"] else " **off the front**"))
        ok = ok and d["fastest"]
    head = ("is on the cost front (within the timing noise of the fastest skin) at every swept volume fraction"
            if ok else "is **not** on the cost front (within the timing noise of the fastest skin) at every swept "
            "volume fraction")
    return ("- **skin** (cost only): the default, which depends on phi (engine.setup.params.default_verlet_skin), "
            f"{head} "
            f"({'; '.join(parts)}).")


def _pm(x, se) -> str:
    return f"{x:+.2e} +- {se:.1e}" if se else f"{x:+.2e}"


def _gas_table(rows: list, extra: tuple = ()) -> list:
    head = "| dt | precision | skin L_v/a | error | " + "".join(f"{h} | " for h, _ in extra) + \
        "Cundall | throughput | steps | front |"
    out = [head, "|" + "---|" * (8 + len(extra))]
    for r in rows:
        se = f" +- {r['error_se']:.1e}" if r.get("error_se") else ""
        out.append(f"| t_c/{r['dt_fraction']} | {r['precision']} | {r['skin']:g} | {_e(r['error'])}{se} | "
                   + "".join(f"{fn(r)} | " for _, fn in extra)
                   + f"{r['cundall']:.3g} | {r['throughput']:.3g} | {r['steps']} | {_front_cell(r)} |")
    return out


def _elastic_table(block: dict, rough: bool) -> list:
    rows = block["rows"]
    if not rough:
        out = ["| dt | precision | error = RMS of eps | mean of eps | pairs predict gas E_end/E0 - 1 | "
               "gas E_end/E0 - 1 | gas max abs(E/E0 - 1) | Cundall | throughput | steps | front |",
               "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            out.append(f"| t_c/{r['dt_fraction']} | {r['precision']} | {_e(r['error'])} | {r['err_mean']:+.2e} | "
                       f"{r['pred_drift']:+.1e} +- {r['pred_sd']:.1e} | {_pm(r['gas_end'], r['gas_end_se'])} | "
                       f"{_e(r['gas_max'])} | {r['cundall']:.3g} | {r['throughput']:.3g} | {r['steps']} | "
                       f"{_front_cell(r)} |")
        return out
    ref = [r for r in rows if r["dt_fraction"] == max(DT_FRACTIONS) and r["precision"] == "float64"]
    out = ["| dt | precision | error = RMS of the dt part of eps | its mean | dt part: pairs predict | "
           "dt part: gas (E_end minus the t_c/200 gas's) | gas E_end/E0 - 1 | Cundall | throughput | steps | front |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        gas = "-"
        if ref:
            g0 = ref[0]
            gas = _pm(r["gas_end"] - g0["gas_end"], math.hypot(r["gas_end_se"], g0["gas_end_se"])) \
                if r is not g0 else "0"
        out.append(f"| t_c/{r['dt_fraction']} | {r['precision']} | {_e(r['error'])} | {r['err_mean']:+.2e} | "
                   f"{r['pred_dt_drift']:+.1e} | {gas} | {_pm(r['gas_end'], r['gas_end_se'])} | "
                   f"{r['cundall']:.3g} | {r['throughput']:.3g} | {r['steps']} | {_front_cell(r)} |")
    return out


FRONT_RULE = ("**Pareto front**: row q dominates row p when q is not measurably more expensive and is demonstrably "
              "more accurate, or equally accurate and measurably cheaper. Costs: throughputs more than {t} % apart "
              "differ (the run-to-run scatter of the shared 2-core development VM). Errors within {e} % of each "
              "other are the same (deterministic rows; the skin rows, which run the same trajectory); errors "
              "further apart but within {s:g} combined standard errors of their seed means (the cooling rows, "
              "averaged over seeds) are *unresolved*: the measurement cannot tell which row is more accurate, so "
              "neither dominates the other, and the verdict names such cheaper rows; beyond that the smaller error "
              "is better. The collision errors and the elastic scenes' pair-sample errors are deterministic (no "
              "seed noise). Errors below a scene's floor (the cooling gas's trajectory-chaos floor) count as the "
              "floor. The front is every row that no other row demonstrably beats: a front with error bars.")


def _model_loss_text(block: dict, c: float) -> str:
    """The rough elastic model's own loss: isolated collisions (pairs) against the gas at t_c/200."""
    ml = block.get("model_loss")
    if not ml:
        return ""
    text = (f"The model's loss per isolated collision: <eps> = {ml['eps_ref']:.2e} at t_c/200 and "
            f"{ml['eps_fine']:.2e} at t_c/{FINE_FRACTION} (per-collision RMS difference {ml['fine_vs_ref_rms']:.1e}: "
            f"no dt effect), which predicts {ml['pred_drift']:+.1e} over {c} collisions per particle. ")
    ref = [r for r in block["rows"] if r["dt_fraction"] == max(DT_FRACTIONS) and r["precision"] == "float64"]
    if ref and ml["pred_drift"] < 0:
        g, se = ref[0]["gas_end"], ref[0]["gas_end_se"]
        ratio = g / ml["pred_drift"]
        text += f"The gas at t_c/200 ends at {_pm(g, se)}, x{ratio:.2g} of that"
        if g < ml["pred_drift"] - 2.0 * se and ratio > 2.0:
            text += ("; the excess is not in the sample of isolated pairs, and no dt error either (the gas column "
                     "barely moves between t_c/50 and t_c/200, as the pairs predict): collisions in a gas are not "
                     "all isolated pairs, and a sphere that touches a third one during a contact leaves springs "
                     "that are not back at zero when the contacts end")
        text += ". "
    return text


def write_report(out: Path, res: dict, cmd: str, wall: float) -> str:
    m = res["machine"]
    sc = res["scenes"]
    dev = m.get("device") or m["cpu"]
    size = res["size"]
    L = ["# Accuracy against cost", "",
         f"Command: `{cmd}` ({res['variant']} variant), {wall / 60:.1f} min wall in all.",
         f"Machine: backend **{m['backend']}** on **{dev}**; host CPU {m['cpu']} ({m['cores']} cores), "
         f"{m['numba_threads']} Numba thread(s), load average {m['load_average']:.2f} at the start; "
         f"numba {m['numba']}, numpy {m['numpy']}, Python {m['python']}; {m['date']}.", "",
         "**Cost** is the Cundall number (N x steps / wall s of the time loop, compilation excluded, output "
         f"records included; median of {res['reps']} run(s) of seed 0, plus one run of each further seed where a "
         "scene averages over seeds). A step costs about the same at any dt, so the "
         "fronts are drawn against the **throughput = Cundall x dt/t_c** (particle-contact-times simulated per "
         "wall second: what a fixed stretch of simulated time costs); the tables give both.", "",
         FRONT_RULE.format(t=int(100 * TIME_NOISE), e=int(100 * ERROR_TIE), s=SIGMAS), "",
         "**Knobs that do not exist in the engine**: the rebuild policy (one rule: rebuild when a particle has "
         "moved more than L_v/2; no switch, so no rows) and the ellipsoid contact algorithm (the spec exposes "
         "none; the engine always uses the Perram-Wertheim (PW) maximisation; this bench varies its Newton "
         "tolerance and measures the Delta/P test of Rubio-Largo et al. (2015) as a classifier only).", "",
         "![accuracy against cost](accuracy.png)", "",
         f"## Verdict on the defaults (dt = t_c/50, float64, L_v = {DEFAULT['skin']:g} a on this backend at the "
         f"gas scenes' phi = {size['phi']:g}; PW tolerance 1e-15)", ""]
    if res.get("rule_skin") is not None and not math.isclose(res["rule_skin"], DEFAULT["skin"], rel_tol=1e-9):
        L += [f"Note: the gas scenes ran at L_v = {DEFAULT['skin']:g} a, the default when they were measured; the "
              f"default at phi = {size['phi']:g} is now {res['rule_skin']:.3g} a "
              "(engine.setup.params.default_verlet_skin). "
              "The skin moves no trajectory, so their errors are the default's; its cost: the cooling rows' skins.",
              ""]
    for name in sc:
        if name == "skin_sweep":
            L.append(skin_verdict(sc[name], m["backend"]))
        else:
            L.append(verdict(sc[name]["rows"], name, sc[name].get("floor", 0.0)))
    L += ["", *res["advice"], ""]

    col = sc["collisions"]
    L += ["## Binary collisions", "",
          f"{col['pairs']} pairs (half head-on, half at 10 deg and sticking), a = {RADIUS} m, k_n = {K_N:g} N/m, "
          f"rho = {DENSITY:g} kg/m^3, e_n = e_t = 0.8, peak overlaps {col['depth_range'][0]:.2g}-"
          f"{col['depth_range'][1]:.2g} a, contact starts spread over a step, lattice box {col['box']:.3g} m. "
          f"Error = max(abs(de_n), abs(de_n at e_n = {E_N_LOW}), abs(de_t)): de_n against the nominal e_n (exact for "
          f"this dashpot; the head-on pairs are run again with e_n = {E_N_LOW}, where the dashpot's dt error is "
          "larger); de_t "
          "against the same pairs at float64, t_c/200, because the analytic e_t,eff = "
          f"{col['e_t_effective']:.5f} (Hidalgo et al. 2013, Eq. 4, docs/physics.md) neglects O(delta/a) lever-arm and "
          f"normal-rotation terms: the reference differs from it by {_e(col['ref_e_t_offset'])} (e_n: "
          f"{_e(col['ref_e_n_error'])}). Cost: the pair scene itself (all pairs in contact a third of the run; "
          f"median of {COLLISION_REPS if res['reps'] >= 3 else res['reps']} runs of a few ms each).",
          "", f"| dt | precision | max abs(de_n), e_n = 0.8 | max abs(de_n), e_n = {E_N_LOW} | max abs(de_t) vs ref | "
          "max abs(e_t - e_t,eff) | Cundall | throughput | front |", "|---|---|---|---|---|---|---|---|---|"]
    for r in col["rows"]:
        L.append(f"| t_c/{r['dt_fraction']} | {r['precision']} | {_e(r['err_e_n'])} | {_e(r['err_e_n_low'])} | "
                 f"{_e(r['err_e_t'])} | "
                 f"{_e(r['err_e_t_analytic'])} | {r['cundall']:.3g} | {r['throughput']:.3g} | {_front_cell(r)} |")

    es = sc["elastic_smooth"]["spec"]
    er = sc["elastic_rough"]
    c = size["collisions"]
    apart = all(r["pairs_apart"] for k in ("elastic_smooth", "elastic_rough") for r in sc[k]["rows"])
    L += ["", "## Elastic gas: energy error", "",
          f"Gas: N = {es['n_particles']}, phi = {es['volume_fraction']}, typical head-on overlap {OVERLAP:g} a, "
          f"{c} collisions per particle from a Maxwellian start at equal translational and rotational "
          f"temperatures T (no thermalisation), {RADIUS} m spheres, seeds {', '.join(map(str, size['seeds']))}. "
          "Its run-level drift E(t_end)/E(0) - 1 (E = E_tr + E_rot + E_el) is a sum of per-collision errors of "
          "both signs, so one run says little about a knob (the seed scatter is as large as the dt effect "
          "between neighbouring dt). **Error of a row**: the energy error per collision, eps = dE/(6T) (6T: the "
          f"mean energy of two gas particles), on {sc['elastic_smooth']['pairs']} binary collisions drawn from "
          "this gas's own collision statistics (relative speed g with g^2/(4 sigma_v^2) ~ Gamma(2), the "
          "flux-weighted Maxwellian; impact parameter uniform over the collision disc; Gaussian spins at T; "
          "touching time uniform over a t_c/10 step), run by the same backend at every dt and precision: the "
          "same collisions at every row, no seed noise. RMS over the sample; the mean is the systematic part. "
          "The pairs predict the gas drift after C collisions per particle as C <eps> +- sqrt(2C/N) sd(eps) "
          f"(mean +- spread of one run); every pair had separated at the end of its run: {apart}.", "",
          "**Smooth** (e_n = 1, e_t = -1): eps against exact conservation (integrator and contact-event "
          "corrections alone).", "", *_elastic_table(sc["elastic_smooth"], rough=False), "",
          "**Rough** (e_n = e_t = 1, as the accuracy study asks): the Eq.-4 spring loses energy at any dt (it is back "
          "at zero at the end of a contact only for delta << a, a normal that does not turn and an isolated "
          "pair, docs/physics.md): the model's own loss, not a knob's error. The error of a row is therefore "
          "the part of eps that dt and precision add: eps minus eps of the same collision at float64, "
          "t_c/200. "
          + _model_loss_text(er, c)
          + "The dt part the pairs predict for the gas, C times its mean, is what the gas shows: its end "
            "energy minus that of the t_c/200 gas of the same seeds (+- the seed scatter).", "",
          *_elastic_table(er, rough=True)]

    coo = sc["cooling"]
    cs = coo["spec"]
    L += ["", "## Homogeneous cooling", "",
          f"Rough gas e_n = e_t = 0.8: N = {cs['n_particles']}, phi = {cs['volume_fraction']}, typical overlap "
          f"{OVERLAP:g} a, {cs['thermalization']} elastic collisions per particle of thermalisation, then "
          f"{size['collisions']} collisions per particle of cooling (tau_end = {coo['rows'][0]['tau_end']:.2f}). "
          "Error = max over t of abs(T/T0 / ref - 1) and of the same for R/T0, against the float64 t_c/200 run "
          f"of the same seed, averaged over seeds {', '.join(map(str, size['seeds']))} (+- standard error). "
          "**Chaos floor**: the reference repeated at t_c/"
          f"{', t_c/'.join(map(str, FLOOR_FRACTIONS))} (dt changed by 5-10 % where e_n is converged to ~1e-4) "
          f"deviates by {', '.join(_e(x) for x in coo['floors'])} (mean {_e(coo['floor'])}): any perturbation "
          "decorrelates the trajectories, and the deviation it grows into depends on the perturbation only "
          "logarithmically, so this scene ranks dt only coarsely. dev vs ODE: the seed-mean T/T0 and R/T0 "
          "against Luding's ODE with e_t,eff from the measured R(0)/T(0); one run at this N fluctuates by about "
          f"sqrt(2/(3N)) = {math.sqrt(2 / (3 * cs['n_particles'])):.1e} of T, so that column measures the "
          "finite scene (and mean-field theory), not the knob.", "",
          *_gas_table(coo["rows"], (("dev vs ODE (T, R)", lambda r: f"{_e(r['err_ode_T'])}, {_e(r['err_ode_R'])}"),))]

    sw = sc.get("skin_sweep")
    if sw:
        r0 = sw["rows"][0]
        skins = sorted({r["skin"] for r in sw["rows"]})
        from engine.setup.params import DEFAULT_SKIN_FLOOR, DEFAULT_SKIN_MEAN_FREE_PATH, DEFAULT_VERLET_SKIN
        rule = (DEFAULT_VERLET_SKIN["cpu"], DEFAULT_VERLET_SKIN["cuda"], DEFAULT_SKIN_MEAN_FREE_PATH,
                DEFAULT_SKIN_FLOOR)
        L += ["", "## Verlet skin: cost against volume fraction", "",
              f"The skin moves no trajectory (the cooling rows above at every skin agree to rounding), so it is a "
              f"cost-only knob: its front is the fastest skin. Rough gas e_n = e_t = 0.8, dt = t_c/50, float64, "
              f"N = {r0['n']}, typical overlap {OVERLAP:g} a, orientation off, {r0['steps']} steps from the same "
              f"lattice start at every skin (a list is rebuilt when a particle has moved L_v/2), median of "
              f"{res['reps']} timed run(s) of the time loop. Cells: Cundall number (x the fastest skin's at the "
              "same phi; list builds in one run); **bold**: the default at that phi, "
              "engine.setup.params.default_verlet_skin "
              f"(L_max = {rule[0]:g} a CPU, {rule[1]:g} a CUDA while the mean free path lambda = a/(3 sqrt(2) phi "
              f"g(phi)), g the Carnahan-Starling contact value, is at least {rule[2]:g} a; then L_max lambda/"
              f"{rule[2]:g} a, at least {rule[3]:g} a); where the rule's value is "
              "not a swept skin the sweep adds it as a row (rows measured before the rule existed: the nearest "
              "swept skin stands for it and the verdict says so).", "",
              "| phi | default (rule) | " + " | ".join(f"L_v = {k:.3g} a" for k in skins) + " |",
              "|---|---|" + "---|" * len(skins)]
        for phi in sorted({r["phi"] for r in sw["rows"]}):
            want, d, exact = sweep_default_row(sw["rows"], phi, m["backend"])
            by = {r["skin"]: r for r in sw["rows"] if r["phi"] == phi}

            def cell(k, by=by, d=d):
                r = by.get(k)
                if r is None:
                    return "-"
                b = "**" if r is d else ""
                return f"{b}{r['cundall']:.3g} (x{r['vs_fastest']:.2f}; {r.get('builds', '?')}){b}"
            L.append(f"| {phi:g} | {want:.3g} a{'' if exact else ' (nearest swept: ' + format(d['skin'], 'g') + ' a)'}"
                     f" | " + " | ".join(cell(k) for k in skins) + " |")

    ell = sc.get("ellipsoid")
    if ell:
        es = ell["spec"]
        L += ["", "## Ellipsoids (CPU backend)", "",
              f"Geometry: {size['oracle']} random overlapping pairs of the oracle sample (b = 1, xi in [1, 4], "
              f"overlap {ell['delta_range'][0]:.1e}-{ell['delta_range'][1]:.1e} b; seed 2024 as in "
              "the one-off study bench/ellipsoid_geometry_accuracy.py) against the longdouble oracle "
              "(tests/engine/test_ellipsoid_oracle.py). Error = the largest of max abs(delta - delta_ref) (b), "
              "max abs(n - n_ref) (rad) and max abs(C - C_ref) (b): overlap, force direction and lever arm. Cost: the "
              f"Cundall number of an elastic frictionless gas of N = {es['n_particles']} prolate spheroids, "
              f"xi = {es['elongation']}, phi = {es['volume_fraction']}, dt = t_c/50, {size['ell_collisions']} "
              "collisions per particle from the lattice start; its energy drift is the last column. The PW "
              "tolerance is the stop criterion on the Newton step in lambda "
              "(engine.shapes.spheroid.cpu_backend.PW_TOL, set by this bench for the run).", "",
              "| precision | PW tolerance | error | max abs(d delta) (b) | p99 abs(d delta) | max abs(d n) (rad) | "
              "max abs(d C) (b) | NaN | missed overlaps | PW pairs/s | gas Cundall | gas drift | front |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in ell["rows"]:
            L.append(f"| {r['precision']} | {r['pw_tol']:g} | {_e(r['error'])} | {_e(r['err_delta_max'])} | "
                     f"{_e(r['err_delta_p99'])} | {_e(r['err_normal_max'])} | {_e(r['err_point_max'])} | {r['nan']} | "
                     f"{r['missed']} | {r['pairs_per_s']:.3g} | "
                     f"{r['cundall']:.3g} | {_e(r['drift'])} | {_front_cell(r)} |")
        L += ["", "The Delta/P overlap test of Rubio-Largo et al. (2015) on the same pairs (all overlapping), as a "
              "classifier:", "",
              "| precision | overlapping pairs called disjoint | pairs/s |", "|---|---|---|"]
        for r in ell["paper"]:
            L.append(f"| {r['precision']} | {r['called_disjoint']} of {r['pairs']} | {r['pairs_per_s']:.3g} |")
        L += ["", "It misses overlaps (Delta == 0 identically for equal spheres and identical parallel "
              "spheroids), so it is no alternative to PW at any speed; the engine does not offer it."]
    L += ["", "Raw rows, fronts and machine: summary.json (same folder)."]
    text = "\n".join(L) + "\n"
    (out / "REPORT.md").write_text(text)
    return text


def advice(res: dict) -> list:
    """Plain-language reading of the measured rows (numbers from this run only)."""
    sc = res["scenes"]
    d = DEFAULT

    def pick(name, frac, prec="float64", skin=d["skin"]):
        for r in sc[name]["rows"]:
            if r["dt_fraction"] == frac and r["precision"] == prec and r.get("skin", skin) == skin:
                return r
        return None

    out = ["### What the defaults give, and how to trade", ""]
    c, es, er, k = (pick(n, d["dt_fraction"]) for n in ("collisions", "elastic_smooth", "elastic_rough", "cooling"))
    coll = res["size"]["collisions"]
    if c and es and er and k:
        ref_rough = pick("elastic_rough", max(DT_FRACTIONS))
        out.append(
            f"- At the defaults: restitution max abs(de_n) = {_e(c['err_e_n'])} (e_n = 0.8), {_e(c['err_e_n_low'])} "
            f"(e_n = {E_N_LOW}), abs(de_t) = {_e(c['err_e_t'])}; elastic smooth gas: energy error per collision "
            f"{_e(es['error'])} RMS (mean {es['err_mean']:+.1e}), gas drift after {coll} collisions per particle "
            f"{_pm(es['gas_end'], es['gas_end_se'])} (pairs predict {es['pred_drift']:+.1e} +- {es['pred_sd']:.1e}); "
            f"elastic rough gas: dt adds {_e(er['error'])} RMS per collision (predicts {er['pred_dt_drift']:+.1e} "
            f"over {coll} collisions per particle) to the contact model's own loss (gas "
            f"{_pm(ref_rough['gas_end'], ref_rough['gas_end_se'])} at t_c/200); cooling curve within {_e(k['error'])} "
            f"of the t_c/200 reference (chaos floor {_e(sc['cooling']['floor'])}) and {_e(k['err_ode'])} of Luding's "
            f"ODE (N = {sc['cooling']['spec']['n_particles']}).")
        parts = []
        for f in sorted({r["dt_fraction"] for r in sc["collisions"]["rows"]}):
            rc, rs, rr = pick("collisions", f), pick("elastic_smooth", f), pick("elastic_rough", f)
            if rc and rs and rr:
                parts.append(f"t_c/{f}: restitution error {_e(rc['error'])}, smooth {_e(rs['error'])}, rough dt part "
                             f"{_e(rr['error'])}, cost x{es['throughput'] / rs['throughput']:.2g}")
        out.append("- dt trades accuracy for speed (float64; restitution error = worst of e_n = 0.8, e_n = "
                   f"{E_N_LOW} and e_t; smooth / rough: RMS energy error per collision; cost = wall time per "
                   "simulated time relative to the default, from the smooth elastic gas): " + "; ".join(parts) + ".")
        ok = sorted([r for r in sc["collisions"]["rows"] if r["precision"] == "float64" and r["error"] < 1e-3],
                    key=lambda r: -r["throughput"])
        if ok:
            best = ok[0]["dt_fraction"]
            why = ("which is why the default is t_c/50" if best == d["dt_fraction"] else
                   f"so by this criterion the default t_c/{d['dt_fraction']} is not the cheapest choice")
            out.append(f"- The cheapest float64 dt whose worst restitution error stays below 1e-3 (the issue-2 "
                       f"tolerance) down to e_n = {E_N_LOW} is t_c/{best} ({_e(ok[0]['error'])}), {why}.")
    for prec in ("float32", "mixed"):
        c32 = pick("collisions", d["dt_fraction"], prec)
        k32 = pick("cooling", d["dt_fraction"], prec)
        s32 = pick("elastic_smooth", d["dt_fraction"], prec)
        if c and c32 and k and k32 and s32:
            out.append(f"- {prec} at t_c/50: abs(de_n) {_e(c32['err_e_n'])} (float64 {_e(c['err_e_n'])}), at e_n = "
                       f"{E_N_LOW} {_e(c32['err_e_n_low'])} (float64 {_e(c['err_e_n_low'])}); smooth energy error per "
                       f"collision {_e(s32['error'])} (float64 {_e(es['error'])}); cooling-curve error "
                       f"{_e(k32['error'])} (float64 {_e(k['error'])}, chaos floor "
                       f"{_e(sc['cooling'].get('floor', 0))}); "
                       f"Cundall {k32['cundall']:.3g} vs {k['cundall']:.3g} in the cooling gas on this backend.")
    sk = sorted([r for r in sc["cooling"]["rows"] if r["dt_fraction"] == d["dt_fraction"]
                 and r["precision"] == d["precision"]], key=lambda r: r["skin"])
    if len(sk) > 1:
        out.append("- Verlet skin (cooling gas, Cundall): " + ", ".join(f"L_v = {r['skin']:g} a: {r['cundall']:.3g}"
                                                                      for r in sk)
                   + "; the skin changes the cost only (the errors agree to rounding); volume fractions: the skin "
                     "sweep below.")
    return out


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    return str(o)


def set_default_skin(backend: str, phi: float) -> None:
    """The default rows of this report use the backend's default Verlet skin at the gas scenes' phi
    (engine.setup.params.default_verlet_skin)."""
    from engine.setup.params import default_verlet_skin

    DEFAULT["skin"] = default_verlet_skin(backend, "sphere", phi)


def main(out_dir=None, variant: str = "full", backend: str = "cpu", threads: int = 1, n: int | None = None,
         reps: int | None = None, ellipsoids: bool = True, cmd: str | None = None, log=print,
         sweep_n: int | None = None) -> int:
    import numba

    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    size = SIZES[variant]
    set_default_skin(backend, size.phi)
    if n:
        size = replace(size, gas_n=n)
    if sweep_n:
        size = replace(size, sweep_n=sweep_n)
    reps = reps or size.reps
    out = bench_out(out_dir, "accuracy")
    t0 = time.time()
    res = {"variant": variant, "reps": reps, "size": dict(size.__dict__), "machine": machine(backend),
           "default_skin": DEFAULT["skin"]}
    sc = {}
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        sc["collisions"] = build_collisions(size, backend, reps, log)
        pairs = gas_pair_scene(size)
        sc["elastic_smooth"] = build_elastic(size, backend, reps, tmp, log, e_t=-1.0, pairs=pairs)
        sc["elastic_rough"] = build_elastic(size, backend, reps, tmp, log, e_t=1.0, pairs=pairs)
        sc["cooling"] = build_cooling(size, backend, reps, tmp, log)
        sc["skin_sweep"] = build_skin_sweep(size, backend, reps, tmp, log)
        if ellipsoids:
            sc["ellipsoid"] = build_ellipsoid(size, reps, tmp, log)
    res["scenes"] = sc
    if backend != "cpu":
        res["machine"]["device"] = sc["collisions"]["device"]
    res["wall_s"] = time.time() - t0
    flags = {"quick": " --quick", "tiny": " --tiny"}.get(variant, "")
    res["command"] = cmd or f"python -m bench accuracy{flags} --backend {backend}"
    analyse(res, out, log)
    return 0


def analyse(res: dict, out: Path, log=print) -> None:
    """Fronts, verdicts, plot, REPORT.md and summary.json from the measured rows in `res`.

    The default rows are those at the skin they ran at (``default_skin``); the skin sweep's default at each
    phi is the current rule (engine.setup.params.default_verlet_skin), so a re-analysis judges the rule of the code
    it runs with against the stored timings."""
    backend = res["machine"]["backend"]
    set_default_skin(backend, res["size"]["phi"])
    res["rule_skin"] = DEFAULT["skin"]
    DEFAULT["skin"] = res.get("default_skin", DEFAULT["skin"])
    sc = res["scenes"]
    res["fronts"], res["defaults_on_front"] = {}, {}
    for name, block in sc.items():
        if name == "skin_sweep":
            sweep_flags(block["rows"])
            phis = sorted({r["phi"] for r in block["rows"]})
            picks = [sweep_default_row(block["rows"], phi, backend) for phi in phis]
            block["default_rule"] = [{"phi": phi, "rule_skin": want, "row_skin": d["skin"], "exact": exact,
                                      "vs_fastest": d["vs_fastest"], "on_front": d["fastest"]}
                                     for phi, (want, d, exact) in zip(phis, picks)]
            res["defaults_on_front"][name] = all(d["fastest"] for _, d, _ in picks)
            continue
        res["fronts"][name] = [label(r) for r in pareto(block["rows"], block.get("floor", 0.0))]
        res["defaults_on_front"][name] = next((r["on_front"] for r in block["rows"] if is_default(r)), None)
    res["advice"] = advice(res)
    panels = [(TITLES[name], block["rows"], "error", "error", block.get("floor", 0.0)) for name, block in sc.items()
              if name != "skin_sweep"]
    panels.insert(4, ("cooling: deviation from Luding's ODE (no front)", sc["cooling"]["rows"], "err_ode",
                      "max |T/T_ODE - 1|, |R/R_ODE - 1|", 0.0))
    if "skin_sweep" in sc:
        panels.append(("Verlet skin: cost against volume fraction", sc["skin_sweep"]["rows"], "sweep",
                       "Cundall number (particle-steps / s)", 0.0))
    plot(panels, out / "accuracy.png", backend)
    text = write_report(out, res, res["command"], res["wall_s"])
    (out / "summary.json").write_text(json.dumps(res, indent=1, default=_json_default))
    log(text)


def reanalyse(out_dir) -> int:
    """Redo fronts, plot and report from an existing summary.json (no new measurements)."""
    out = Path(out_dir)
    analyse(json.loads((out / "summary.json").read_text()), out)
    return 0


def cli(argv=None) -> int:
    ap = argparse.ArgumentParser(description="accuracy against cost for every numerical knob")
    ap.add_argument("-o", "--out", dest="out_dir", metavar="DIR", default=None,
                    help="report folder (default ./bench-out/accuracy/)")
    ap.add_argument("--quick", action="store_true", help="about one minute on 2 cores (kernel cache warm)")
    ap.add_argument("--tiny", action="store_true", help="smallest scenes (smoke test)")
    ap.add_argument("--backend", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="Numba threads (CPU backend; default 1)")
    ap.add_argument("--n", type=int, default=None, help="spheres in the gas scenes (default 2048; quick 1024)")
    ap.add_argument("--reps", type=int, default=None, help="timed runs per row (median)")
    ap.add_argument("--sweep-n", type=int, default=None, help="spheres per run of the skin sweep (default 4096)")
    ap.add_argument("--no-ellipsoids", action="store_true")
    ap.add_argument("--reanalyse", action="store_true",
                    help="only redo fronts, plot and report from OUT/summary.json (no runs)")
    a = ap.parse_args(argv)
    if a.reanalyse:
        return reanalyse(bench_out(a.out_dir, "accuracy"))
    variant = "tiny" if a.tiny else "quick" if a.quick else "full"
    flags = {"quick": " --quick", "tiny": " --tiny"}.get(variant, "")
    extra = "".join(f" --{k} {v}" for k, v in (("threads", a.threads), ("n", a.n), ("reps", a.reps),
                                                  ("sweep-n", a.sweep_n))
                    if v is not None and not (k == "threads" and v == 1))
    cmd = f"python -m bench accuracy{flags} --backend {a.backend}{extra}" + \
        (" --no-ellipsoids" if a.no_ellipsoids else "")
    return main(a.out_dir, variant, a.backend, a.threads, a.n, a.reps, not a.no_ellipsoids, cmd=cmd,
                sweep_n=a.sweep_n)


if __name__ == "__main__":
    raise SystemExit(cli())
