"""demq (CUDA) against JAX-MD at its best on the same colliding equilibrium gas, side by side on one GPU.

    python -m bench vs_jaxmd                                    # the default cases, on a GPU host, from a checkout
    python -m bench vs_jaxmd --cases elastic-2M-f64-phi0.058 --steps-scale 0.5
    python -m bench vs_jaxmd --quick --backend cpu --cases elastic-2M-f64-phi0.058 elastic-2M-f64-phi0.2  # N = 4096

On an H200 (the image's jax 0.11.2; jax-md 0.2.29 and the three wheels it lacks carried in .whl/jaxmd, see the end
of this docstring), the default set in one device call (--budget-s: no new (N, phi) group starts after 400 s; the
groups run 2M before 8M):

    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/jaxmd/*.whl
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
    python3 -m bench vs_jaxmd --out /tmp/vs_jaxmd > $OUT/vs_jaxmd.log 2>&1
    cp /tmp/vs_jaxmd/results.json /tmp/vs_jaxmd/results.md $OUT/; tar czf $OUT/logs.tgz -C /tmp/vs_jaxmd logs

The gas: phi = 0.058 and 0.2 in a periodic 2 m cube, k_n = 1e8 N/m, density 2000 kg/m^3, velocity_rms = 2 m/s,
dt = t_c/50 (demq's ``engine.setup.params.derive``), rounded to the nearest float32 (relative change < 6e-8) and given
to both codes as the spec's ``dt``: ``jax_md.simulate.velocity_verlet`` casts its dt to float32 even with x64. Both
codes start from demq's random start (``start = "random"``: random sequential addition, RSA, with Maxwellian
velocities and spins; engine/setup/start_kind.py) at every N, with no thermalisation: a homogeneous gas at equilibrium
speeds whose pair correlation at contact is RSA's, 1 + (5/3) phi against Carnahan-Starling's 1 + (5/2) phi + O(phi^2)
(at phi = 0.2 the collision rate starts about a quarter below Enskog's and relaxes within about one collision; the
table's Enskog figure says what a relaxed gas would give). demq draws it inside ``engine.run`` (on the host: RSA is
sequential, about 3 s per million spheres at phi = 0.058 and 6 s at 0.2 on a 2-core VM); the JAX-MD process gets
the same arrays, saved by the demq process of its N and phi.

Collisions per particle in the timed window: demq's count of contacts begun (the ``collisions`` observable,
2 x pairs / N), next to Enskog's omega_E x steps x dt (``derive(spec).collision_rate0``, Carnahan-Starling g). For
JAX-MD an estimate: the pairs overlapping in its final state (2 x pairs / N: contacts in progress per particle) times
window / t_c, t_c = pi sqrt(m/(2 k_n)) the head-on contact time (oblique contacts of a linear spring are shorter, so
it runs low; one snapshot, so it is noisy at small N).

JAX-MD: ``energy.soft_sphere_neighbor_list`` with alpha = 2, sigma = 2a, epsilon = k_n sigma^2. Its pair energy
U = epsilon/alpha (1 - r/sigma)^alpha (r < sigma) gives the force -dU/dr = epsilon/sigma (1 - r/sigma)
= k_n (sigma - r) = k_n delta, demq's elastic normal spring with overlap delta = 2a - r (and U = k_n delta^2/2,
demq's ``elastic_energy``). The constants go in as arrays of the working dtype (``jax_md.util.maybe_downcast``
makes Python floats float32 even with x64). ``space.periodic(L)``, ``simulate.nve`` (velocity Verlet, as demq) with
mass m. At its best:

- the particles are renumbered in cell order (:func:`cell_order`: the cells of JAX-MD's own cell list, edge
  >= sigma + 0.4 a) before they are handed to it, so that its gathers of neighbours are local (the RSA start is
  numbered in placement order, random in space);
- the list is updated as JAX-MD users update it: ``nbrs.update`` every step inside a jit-compiled
  ``lax.fori_loop`` of CHUNK steps (a static trip count; the timed run queues steps / CHUNK calls and waits once),
  overflow checked after the run, the list then reallocated with 1.5 x the capacity multiplier and the run repeated
  (only the last attempt is timed);
- the configuration is searched (:func:`search_plan`) over the list format (Dense, Sparse, OrderedSparse), the skin
  (``dr_threshold``, radii) and ``capacity_multiplier``: every format at skin 0.4 a, then the neighbouring skins for
  the best format (one more step outward while an edge wins), then the other capacities. A trial compiles, runs one
  chunk, times one chunk whose first step is made to rebuild the list and two plain chunks after it (t_step per
  step; t_rebuild = the first chunk less a plain one), and predicts N / (t_step + t_rebuild / k), k = (skin/2) /
  (v_max dt) the steps between rebuilds that the fastest particle allows (:func:`predicted_cundall`). The best
  prediction is then timed properly, from the start, over the case's steps. A (phi, precision) searched at one N is
  not searched again at a larger N (the 8M float64 cases reuse the 2M float64 winner; --search-every searches each).

float64 runs enable ``jax_enable_x64``; JAX may take 95 % of the GPU memory.

demq: ``engine.run`` with e_n = 1, e_t = -1 (elastic, frictionless: no dashpot, no tangential spring, so both sides
integrate the same equations), thermalization 0, snapshots 0, its default skin and records; t_end = steps x dt.
The rough cases (e_n = e_t = 0.8, without and with the Coulomb cap mu = 0.5, the spec's ``friction``) run demq alone
and are compared with JAX-MD's frictionless best at the same N, phi and precision. The demq cases of one (N, phi)
run in one process, each twice: "loop" = RunSummary.loop_s of the second run; "warm whole job" = the second
``engine.run`` call (CUDA context, kernels and buffer pools ready, as a worker that has run a job before gives it)
with its start taken from the process's first draw (:class:`StartMemo`: as JAX-MD's figures leave the start's
making out; the draw's own seconds are ``start_draw_s``, the table's bracket). The first run of each case (its
kernels compiled or loaded from the disk cache; the start drawn, in the first case of the process) is in the JSON.
A full garbage collection runs before each run, outside the clock, as ``timeit`` keeps collections out of its loop:
a process that has just compiled holds ~0.9 million objects, and a full pass over them, due at some later
allocation, took 0.2-0.4 s (H200 host, 8M float32): as long as the extra time of the one slow loop (0.29 s) and
the one slow warm build (0.23 s) of two device calls without it.
--quick compares the final states particle by particle (demq then writes one snapshot): they agree to rounding.

Cundall number = N x steps / seconds. Results: a table on stdout, results.json, results.md and each process's log
in --out.

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
import dataclasses
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
if __name__ == "__main__":
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from engine.setup.params import derive  # noqa: E402  (does not import numba)
from engine.setup.spec import SimulationSpec  # noqa: E402

SCENE = dict(box_length=2.0, stiffness=1.0e8, density=2000.0, velocity_rms=2.0)
VOLUME_FRACTIONS = (0.058, 0.2)
#: Coulomb friction coefficient of the rough cases with the cap on (Hidalgo et al. 2013's mu)
FRICTION_CAP = 0.5
#: contact -> spec fields
CONTACTS = {"elastic": dict(e_n=1.0, e_t=-1.0), "rough": dict(e_n=0.8, e_t=0.8),
            "rough-coulomb": dict(e_n=0.8, e_t=0.8, friction=FRICTION_CAP)}


class Case(NamedTuple):
    n: int
    precision: str
    steps: int       # a multiple of CHUNK: each timed loop ~1-3 s on an H200
    contact: str     # a CONTACTS key; a rough case is compared with the elastic JAX-MD run of its N, phi, precision
    phi: float


SIZES = {"2M-f64": (2_097_152, "float64", 6000), "8M-f32": (8_388_608, "float32", 3000),
         "8M-f64": (8_388_608, "float64", 2000)}
CASES = {f"{contact}-{size}-phi{phi:g}": Case(n, precision, steps, contact, phi)
         for contact in CONTACTS for phi in VOLUME_FRACTIONS for size, (n, precision, steps) in SIZES.items()}
#: what fits one device call: every elastic case, the rough ones at 2M float64 (8M float32 on request)
DEFAULT_CASES = [k for k, c in CASES.items() if c.contact == "elastic" or (c.n, c.precision) == (2_097_152, "float64")]
QUICK_N, QUICK_STEPS = 4096, 3000
CHUNK = 100                 # steps per jit-compiled fori_loop call (static trip count)
FORMATS = ("Dense", "Sparse", "OrderedSparse")
SKINS = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6)     # JAX-MD dr_threshold in radii; the search starts at START_SKIN
CAPACITIES = (1.25, 1.1)         # capacity_multiplier: the first for the format/skin search, then the others
START_SKIN = 0.4
JAXMD_MISSING = ("jax_md is not importable here ({error}): JAX-MD runs are skipped and demq runs alone. "
                 "To install it offline, see the end of this script's docstring (python -m pydoc bench.vs_jaxmd)")


def case_spec(case: Case, backend: str, seed: int = 1, snapshots: int = 0, steps=None) -> SimulationSpec:
    """The spec of a case: the module's gas from demq's random start, t_end = steps x dt, no thermalisation, no
    snapshots (the state check of --quick: one, at the end)."""
    base = dict(n_particles=case.n, precision=case.precision, volume_fraction=case.phi, start="random",
                thermalization=0.0, snapshots=snapshots, backend=backend, seed=seed, **SCENE, **CONTACTS[case.contact])
    dt = float(np.float32(derive(SimulationSpec(**base)).dt))    # JAX-MD steps with a float32 dt (module doc)
    return SimulationSpec(**base, dt=dt, t_end=(case.steps if steps is None else steps) * dt)


def jaxmd_constants(spec: SimulationSpec) -> dict:
    """JAX-MD soft-sphere constants equal to demq's elastic spring (module doc): SI units."""
    p = derive(spec)
    sigma = 2.0 * p.radius
    return {"radius": p.radius, "sigma": sigma, "epsilon": p.k_n * sigma**2, "alpha": 2.0, "mass": p.mass,
            "dt": p.dt, "box": spec.box_length, "contact_time": p.contact_time}


# ---- pure helpers (tests/bench/test_vs_jaxmd_smoke.py) -----------------------------------------------------------

def cell_order(position: np.ndarray, box: float, min_cell: float) -> np.ndarray:
    """The permutation that numbers particles in cell order: cells of edge box / floor(box / min_cell) >= min_cell,
    x fastest then y then z (JAX-MD's cell hash), by a stable sort (ties keep their order). ``position`` in m,
    wrapped into [0, box) here."""
    cells = max(1, int(box // min_cell))
    c = np.clip(((np.asarray(position) % box) * (cells / box)).astype(np.int64), 0, cells - 1)
    return np.argsort(c[:, 0] + cells * (c[:, 1] + cells * c[:, 2]), kind="stable")


def collisions_per_particle(contacts_begun: int, n: int) -> float:
    """Collisions per particle of ``contacts_begun`` pair contacts among n particles: each involves two, 2 M / N."""
    return 2.0 * contacts_begun / n


def collisions_from_overlaps(overlapping_pairs: float, n: int, window_s: float, contact_time_s: float) -> float:
    """Collisions per particle over ``window_s`` estimated from the pairs in contact at one instant: contacts in
    progress per particle 2 P / N, each lasting about t_c, so 2 P / N x window / t_c (module doc: runs low)."""
    return 2.0 * overlapping_pairs / n * window_s / contact_time_s


def steps_between_rebuilds(skin_m: float, max_speed: float, dt: float) -> float:
    """Steps until the fastest particle has moved half the skin (JAX-MD's rebuild rule), >= 1."""
    return max(1.0, 0.5 * skin_m / max(max_speed * dt, 1e-300))


def predicted_cundall(n: int, step_s: float, rebuild_s: float, interval_steps: float) -> float:
    """N / (t_step + t_rebuild / k): the Cundall number of a run that rebuilds its list every k steps."""
    return n / (step_s + max(rebuild_s, 0.0) / interval_steps)


def search_plan(formats, skins, capacities, trial) -> tuple:
    """The configuration search (module doc): ``trial(format, skin, capacity)`` -> predicted Cundall number (or None
    when it failed). Every format at the start skin (START_SKIN if in ``skins``, else the middle one) and the first
    capacity; then the neighbouring skins for the best format, one more outward while an edge wins; then the other
    capacities at the best (format, skin). Returns (best (format, skin, capacity), {config: prediction})."""
    skins = sorted(skins)
    seen = {}

    def score(cfg):
        if cfg not in seen:
            seen[cfg] = trial(*cfg)
        return seen[cfg] if seen[cfg] is not None else -math.inf

    def best_of(cfgs):
        return max(cfgs, key=score)

    cap0 = capacities[0]
    k = skins.index(START_SKIN) if START_SKIN in skins else (len(skins) - 1) // 2
    fmt = best_of([(f, skins[k], cap0) for f in formats])[0]
    while True:
        around = [skins[j] for j in (k - 1, k, k + 1) if 0 <= j < len(skins)]
        winner = best_of([(fmt, s, cap0) for s in around])
        j = skins.index(winner[1])
        if j == k:
            break
        k = j
    best = best_of([(fmt, skins[k], c) for c in capacities])
    if score(best) == -math.inf:
        raise RuntimeError(f"every JAX-MD configuration failed: {sorted(seen)}")
    return best, seen


# ---- demq ---------------------------------------------------------------------------------------------------------

class StartMemo:
    """Keeps the starts a process draws (engine.setup.scene.initial_spheres) and hands out copies: the second run of a
    case then takes the start of the first (module doc). Installed by patching engine.setup.scene.initial_spheres, which
    the sphere plug-in looks up at each call."""

    def __init__(self):
        import engine.setup.scene as scene

        self.scene, self.draw = scene, scene.initial_spheres
        self._replaced = scene.initial_spheres      # what close() puts back, whatever ``draw`` is by then
        self.starts, self.draw_s, self.ready = {}, {}, {}
        scene.initial_spheres = self

    @staticmethod
    def key(spec) -> tuple:
        return (spec.n_particles, spec.volume_fraction, spec.box_length, spec.seed, spec.velocity_rms, spec.density,
                spec.start)

    def __call__(self, spec, p, on_device: bool = False):
        key = self.key(spec)
        if key not in self.starts:
            t0 = time.perf_counter()
            # drawn on the host even for a GPU job (whose large start would be drawn on the device: the same
            # centres, engine/setup/cell_rsa.py), so that it can be handed to JAX-MD and to the second run
            self.starts[key] = self.draw(spec, p, False)
            self.draw_s[key] = time.perf_counter() - t0
        ready = self.ready.pop(key, None)
        return ready if ready is not None else self._copy(self.starts[key])

    def prepare(self) -> None:
        """Copies of the starts drawn so far, made now, before a timed run: the run is handed a start as JAX-MD is,
        without the memo's own copying (0.37 s for 8M spheres) in its time."""
        self.ready = {key: self._copy(system) for key, system in self.starts.items()}

    @staticmethod
    def _copy(system):
        return dataclasses.replace(system, **{f.name: np.array(v) for f in dataclasses.fields(system)
                                              if isinstance(v := getattr(system, f.name), np.ndarray)})

    def close(self):
        self.scene.initial_spheres = self._replaced


def run_demq(job: dict) -> dict:
    """Every demq case of one (N, phi) (module doc): per case the first and the second run; saves the start for
    JAX-MD (``start_out``) and, for --quick's check, each elastic case's final state (``state_out``)."""
    import h5py

    from engine import run

    memo = StartMemo()
    results = {}
    try:
        with tempfile.TemporaryDirectory(prefix="vs_jaxmd_") as tmp:
            for name, spec_json in job["specs"].items():
                spec = SimulationSpec(**spec_json)
                try:
                    runs = []
                    for attempt in ("first", "warm"):
                        out = Path(tmp) / f"{attempt}.h5"
                        memo.prepare()
                        # as timeit does for its loop: no collection of the compile's objects inside the clock
                        gc.collect()
                        t0 = time.perf_counter()
                        s = run(spec, out, backend=spec.backend)
                        runs.append((s, time.perf_counter() - t0))
                    (s1, wall1), (s, wall) = runs
                    with h5py.File(out, "r") as f:
                        ke, el = (float(f[f"observables/{k}/value"][-1])
                                  for k in ("kinetic_energy_translational", "elastic_energy"))
                        collisions = int(f["observables/collisions/value"][-1])
                        if job.get("states") and spec.snapshots:
                            np.savez(Path(job["states"]) / f"demq_{name}.npz",
                                     position=f["particles/all/position/value"][-1],
                                     velocity=f["particles/all/velocity/value"][-1])
                    n, p = spec.n_particles, derive(spec)
                    results[name] = {
                        "backend": s.backend, "device": s.device, "steps": s.steps, "loop_s": s.loop_s,
                        "cundall_loop": s.cundall, "wall_warm_s": wall, "cundall_whole_job_warm": n * s.steps / wall,
                        "first_run": {"wall_s": wall1, "loop_s": s1.loop_s, "timings": s1.extra.get("timings")},
                        "timings": s.extra.get("timings"), "skin_m": p.skin, "ke_translational_end": ke,
                        "elastic_energy_end": el, "collisions": collisions,
                        "collisions_per_particle": collisions_per_particle(collisions, n),
                        "enskog_collisions_per_particle": p.collision_rate0 * s.steps * p.dt,
                        "start_draw_s": memo.draw_s[memo.key(spec)]}
                except Exception as e:          # the other cases of the group still run
                    results[name] = {"error": f"{type(e).__name__}: {e}"}
            if job.get("start_out") and memo.starts:
                (system,) = memo.starts.values()
                np.savez(job["start_out"], position=system.position, velocity=system.velocity)
    finally:
        memo.close()
    return results


# ---- JAX-MD -------------------------------------------------------------------------------------------------------

class JaxmdRun:
    """JAX-MD on one (N, phi, precision): the start in cell order on the device, a configuration's compiled chunk."""

    def __init__(self, spec: SimulationSpec, start: dict):
        os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.95")   # the GPU is JAX's alone (default 0.75)
        import jax

        if spec.precision == "float64":
            jax.config.update("jax_enable_x64", True)       # before any array exists
        import jax.numpy as jnp
        from jax_md import space

        self.jax, self.jnp = jax, jnp
        self.spec, self.c = spec, jaxmd_constants(spec)
        self.dtype = np.float64 if spec.precision == "float64" else np.float32
        self.n = spec.n_particles
        box = self.c["box"]
        position = np.asarray(start["position"], np.float64) % box
        velocity = np.asarray(start["velocity"], np.float64)
        self.order = cell_order(position, box, self.c["sigma"] + START_SKIN * self.c["radius"])
        self.pos0 = jnp.asarray(position[self.order].astype(self.dtype))
        self.mom0 = jnp.asarray((self.c["mass"] * velocity[self.order]).astype(self.dtype))
        self.max_speed = float(np.sqrt((velocity**2).sum(axis=1).max()))
        self.displacement, self.shift = space.periodic(box)
        self.built = {}

    def build(self, fmt: str, skin_radii: float, capacity: float):
        """(neighbor_fn, energy_fn, init_fn, chunk) of one configuration, kept: the timed run of a configuration
        the search tried reuses its compiled chunk."""
        key = (fmt, skin_radii, capacity)
        if key in self.built:
            return self.built[key]
        jax, jnp = self.jax, self.jnp
        from jax import lax
        from jax_md import energy, partition, simulate

        c, dt = self.c, self.dtype
        neighbor_fn, energy_fn = energy.soft_sphere_neighbor_list(
            self.displacement, c["box"], sigma=jnp.asarray(c["sigma"], dt), epsilon=jnp.asarray(c["epsilon"], dt),
            alpha=jnp.asarray(c["alpha"], dt), dr_threshold=jnp.asarray(skin_radii * c["radius"], dt),
            format=getattr(partition.NeighborListFormat, fmt), capacity_multiplier=capacity)
        init_fn, apply_fn = simulate.nve(energy_fn, self.shift, c["dt"])
        far = jnp.asarray(0.5 * c["box"], dt)

        @jax.jit
        def advance(state, nbrs, force_rebuild):
            # force_rebuild (a search trial): the reference positions moved half a box, so the first update rebuilds
            nbrs = dataclasses.replace(nbrs, reference_position=jnp.where(
                force_rebuild, nbrs.reference_position + far, nbrs.reference_position))

            def step(_, carry):
                st, nb = carry
                nb = nb.update(st.position)               # rebuilt only when a particle moved half the skin
                return apply_fn(st, neighbor=nb), nb
            return lax.fori_loop(0, CHUNK, step, (state, nbrs))

        self.built[key] = neighbor_fn, energy_fn, init_fn, advance
        return self.built[key]

    def start(self, neighbor_fn, init_fn):
        """The start's state and its freshly allocated list."""
        nbrs = neighbor_fn.allocate(self.pos0)
        state = init_fn(self.jax.random.PRNGKey(0), self.pos0, 0.0, mass=self.c["mass"], momenta=self.mom0,
                        neighbor=nbrs)
        return state, nbrs

    def run_chunks(self, advance, state, nbrs, chunks: int, force_rebuild: bool = False):
        """``chunks`` calls of the compiled chunk (queued, one wait at the end): (state, list, seconds)."""
        flag = self.jnp.asarray(force_rebuild)
        t0 = time.perf_counter()
        for k in range(chunks):
            state, nbrs = advance(state, nbrs, flag if k == 0 else self.jnp.asarray(False))
        self.jax.block_until_ready(state.position)
        return state, nbrs, time.perf_counter() - t0

    def trial(self, fmt: str, skin_radii: float, capacity: float, log: list):
        """One search trial (module doc): the predicted Cundall number; None when the list overflowed or it failed."""
        try:
            neighbor_fn, _, init_fn, advance = self.build(fmt, skin_radii, capacity)
            state, nbrs = self.start(neighbor_fn, init_fn)
            t0 = time.perf_counter()
            state, nbrs, _ = self.run_chunks(advance, state, nbrs, 1)             # compiles
            compile_s = time.perf_counter() - t0
            # the rebuild first: the plain chunks after it see a natural rebuild only if k < 3 CHUNK
            state, nbrs, forced = self.run_chunks(advance, state, nbrs, 1, force_rebuild=True)
            state, nbrs, plain = self.run_chunks(advance, state, nbrs, 2)
            overflow = bool(nbrs.did_buffer_overflow)
        except Exception as e:        # e.g. out of memory, or an index past int32: the search goes on without it
            error = f"{type(e).__name__}: {str(e)[:300]}"
            log.append({"format": fmt, "skin_radii": skin_radii, "capacity": capacity, "error": error})
            print(f"  trial {fmt} skin {skin_radii} a capacity {capacity}: FAILED {error}", flush=True)
            return None
        step_s = plain / (2 * CHUNK)
        rebuild_s = forced - plain / 2
        k = steps_between_rebuilds(skin_radii * self.c["radius"], self.max_speed, self.c["dt"])
        pred = predicted_cundall(self.n, step_s, rebuild_s, k)
        log.append({"format": fmt, "skin_radii": skin_radii, "capacity": capacity, "step_s": step_s,
                    "rebuild_s": rebuild_s, "rebuild_every_steps": k, "predicted_cundall": pred,
                    "compile_s": compile_s, "overflow": overflow, "list_shape": list(nbrs.idx.shape)})
        print(f"  trial {fmt} skin {skin_radii} a capacity {capacity}: step {step_s * 1e3:.3f} ms, rebuild "
              f"{rebuild_s * 1e3:.2f} ms every {k:.0f} steps -> {pred:.3g}{' OVERFLOW' if overflow else ''}",
              flush=True)
        return None if overflow else pred

    def overlapping_pairs(self, position, nbrs, fmt: str) -> int:
        """Pairs closer than sigma in the list (each pair once)."""
        jnp = self.jnp
        idx, n = nbrs.idx, self.n
        if fmt == "Dense":
            other = position[jnp.clip(idx, 0, n - 1)]
            d = self.jax.vmap(self.jax.vmap(self.displacement, (None, 0)))(position, other)
        else:
            d = self.jax.vmap(self.displacement)(position[jnp.clip(idx[0], 0, n - 1)],
                                                 position[jnp.clip(idx[1], 0, n - 1)])
            idx = idx[0]
        hits = int(jnp.sum((jnp.sum(d * d, axis=-1) < self.c["sigma"] ** 2) & (idx < n)))
        return hits if fmt == "OrderedSparse" else hits // 2

    def timed(self, fmt: str, skin_radii: float, capacity: float, steps: int) -> dict:
        """The configuration timed over ``steps`` from the start (module doc: reallocation on overflow)."""
        jnp = self.jnp
        reallocations = 0
        while True:
            t0 = time.perf_counter()
            neighbor_fn, energy_fn, init_fn, advance = self.build(fmt, skin_radii, capacity)
            state0, nbrs0 = self.start(neighbor_fn, init_fn)
            state, nbrs, _ = self.run_chunks(advance, state0, nbrs0, 1)   # compiles (unless the search did) + warms
            t1 = time.perf_counter()
            state, nbrs, loop_s = self.run_chunks(advance, state0, nbrs0, steps // CHUNK)
            if not bool(nbrs.did_buffer_overflow) or reallocations == 3:
                break
            capacity, reallocations = capacity * 1.5, reallocations + 1
        ke = float(0.5 * jnp.sum(state.momentum**2) / self.c["mass"])
        pairs = self.overlapping_pairs(state.position, nbrs, fmt)
        window = steps * self.c["dt"]
        return {"format": fmt, "skin_radii": skin_radii, "capacity_multiplier": capacity, "steps": steps,
                "loop_s": loop_s, "cundall_loop": self.n * steps / loop_s, "setup_and_compile_s": t1 - t0,
                "reallocations": reallocations, "overflow": bool(nbrs.did_buffer_overflow),
                "list_shape": list(nbrs.idx.shape), "ke_translational_end": ke,
                "elastic_energy_end": float(energy_fn(state.position, neighbor=nbrs)),
                "overlapping_pairs_end": pairs,
                "collisions_per_particle_estimate": collisions_from_overlaps(pairs, self.n, window,
                                                                             self.c["contact_time"]),
                "final_state": state}


def run_jaxmd(job: dict) -> dict:
    """JAX-MD on one (N, phi, precision): the search (or the given configuration), then the timed run."""
    spec = SimulationSpec(**job["spec"])
    t0 = time.perf_counter()
    jm = JaxmdRun(spec, np.load(job["start"]))
    prepare_s = time.perf_counter() - t0
    log = []
    if job.get("config"):
        best = tuple(job["config"])
    else:
        best, _ = search_plan(job["formats"], job["skins"], job["capacities"],
                                        lambda f, s, c: jm.trial(f, s, c, log))
    search_s = time.perf_counter() - t0 - prepare_s
    print(f"  best: {best[0]}, skin {best[1]} a, capacity {best[2]}; timing {job['steps']} steps", flush=True)
    result = jm.timed(*best, steps=job["steps"])
    state = result.pop("final_state")
    if job.get("state_out"):          # back in demq's numbering
        inverse = np.argsort(jm.order)
        np.savez(job["state_out"], position=np.asarray(state.position)[inverse],
                 velocity=np.asarray(state.momentum)[inverse] / jm.c["mass"])
    import jax

    return {**result, "searched": not job.get("config"), "trials": log, "prepare_s": prepare_s, "search_s": search_s,
            "jax": jax.__version__, "device": str(jax.devices()[0]), "constants": jm.c}


# ---- the driver ---------------------------------------------------------------------------------------------------

def in_fresh_process(job: dict, log_dir: Path, tag: str) -> dict:
    """Run ``job`` (side 'demq' or 'jaxmd') in a child process of this module; its result, or the error it died of.
    The child's output goes to its log and, line by line, to this process's stdout."""
    with tempfile.TemporaryDirectory(prefix="vs_jaxmd_job_") as tmp:
        result = Path(tmp) / "result.json"
        cmd = [sys.executable, "-m", "bench.vs_jaxmd", "--one-case", json.dumps(job), "--result", str(result)]
        with open(log_dir / f"{tag}.log", "w") as log:
            proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for line in proc.stdout:
                log.write(line)
                if line.startswith("  "):
                    print(line, end="", flush=True)
            proc.wait()
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


def state_difference(spec: SimulationSpec, demq_file: Path, jaxmd_file: Path) -> dict:
    """Largest per-particle differences between demq's final state and JAX-MD's (positions by minimum image, in m
    and in radii; velocities in m/s and relative to velocity_rms)."""
    ref, other, box, radius = np.load(demq_file), np.load(jaxmd_file), spec.box_length, derive(spec).radius
    d = ref["position"] - other["position"]
    dx = float(np.abs(d - box * np.round(d / box)).max())
    dv = float(np.abs(ref["velocity"] - other["velocity"]).max())
    return {"max_position_diff_m": dx, "max_position_diff_radii": dx / radius, "max_velocity_diff": dv,
            "max_velocity_diff_rel": dv / spec.velocity_rms}


def start_groups(names) -> dict:
    """(N, phi) -> the case names that start from that gas, smaller N first, in the order given."""
    groups = {}
    for name in sorted(names, key=lambda k: CASES[k].n):
        groups.setdefault((CASES[name].n, CASES[name].phi), []).append(name)
    return groups


def compare(names, a, log_dir: Path, with_jaxmd: bool) -> list:
    """Run the cases by start group (demq's process, then JAX-MD's per precision); the rows."""
    states = Path(tempfile.mkdtemp(prefix="vs_jaxmd_states_"))
    winners, rows, t_start = {}, [], time.perf_counter()
    for (n_full, phi), group in start_groups(names).items():
        if time.perf_counter() - t_start > a.budget_s:
            print(f"budget of {a.budget_s:g} s spent: skipped {group}", flush=True)
            continue
        cases = {name: CASES[name]._replace(
            n=QUICK_N if a.quick else CASES[name].n,
            steps=max(CHUNK, round(CASES[name].steps * a.steps_scale / CHUNK) * CHUNK) if not a.quick
            else QUICK_STEPS) for name in group}
        specs = {name: case_spec(c, a.backend, a.seed, snapshots=1 if a.quick and c.contact == "elastic" else 0)
                 for name, c in cases.items()}
        start = states / f"start_{n_full}_{phi:g}.npz"
        print(f"demq: {', '.join(group)}", flush=True)
        demq_job = {"side": "demq", "specs": {k: json.loads(s.model_dump_json()) for k, s in specs.items()},
                    "start_out": str(start), "states": str(states)}
        demq = in_fresh_process(demq_job, log_dir, f"demq_{n_full}_{phi:g}")
        jax_runs = {}
        for precision in sorted({c.precision for c in cases.values()}):
            if not with_jaxmd or not start.exists():
                continue
            c = next(c for c in cases.values() if c.precision == precision)
            steps = max(x.steps for x in cases.values() if x.precision == precision)
            elastic = case_spec(c._replace(contact="elastic", steps=steps), a.backend, a.seed)
            config = winners.get((phi, precision)) if not a.search_every else None
            job = {"side": "jaxmd", "spec": json.loads(elastic.model_dump_json()), "start": str(start),
                   "steps": steps, "formats": a.formats, "skins": a.skins, "capacities": a.capacities,
                   "config": config, "state_out": str(states / f"jaxmd_{precision}.npz") if a.quick else None}
            print(f"JAX-MD: N={c.n} phi={phi:g} {precision}, "
                  f"{'configuration of the search at a smaller N: ' + str(config) if config else 'search'}", flush=True)
            r = jax_runs[precision] = in_fresh_process(job, log_dir, f"jaxmd_{n_full}_{phi:g}_{precision}")
            if "error" not in r and r["searched"]:
                winners[(phi, precision)] = [r["format"], r["skin_radii"], r["capacity_multiplier"]]
        for name, c in cases.items():
            d = demq.get(name, demq) if "error" not in demq else demq
            j = jax_runs.get(c.precision)
            row = {"case": name, "n": c.n, "phi": phi, "precision": c.precision, "steps": c.steps,
                   "contact": c.contact, "spec": json.loads(specs[name].model_dump_json()), "demq": d, "jaxmd": j}
            if "error" not in d and j and "error" not in j:
                row["ratio_loop"] = d["cundall_loop"] / j["cundall_loop"]
                row["ratio_whole_job_warm_vs_loop"] = d["cundall_whole_job_warm"] / j["cundall_loop"]
                if c.contact == "elastic":      # same start, same equations: relative difference of the energies
                    row["ke_rel_diff"] = abs(d["ke_translational_end"] / j["ke_translational_end"] - 1.0)
                    if a.quick:
                        row["state_difference"] = state_difference(
                            specs[name], states / f"demq_{name}.npz", states / f"jaxmd_{c.precision}.npz")
            rows.append(row)
            print(row_line(row), flush=True)
        for f in states.glob("*.npz"):
            f.unlink()
    states.rmdir()
    return rows


def row_line(r: dict) -> str:
    d, j = r["demq"], r["jaxmd"]
    demq = (f"demq {d['cundall_loop']:.3g} (warm whole job {d['cundall_whole_job_warm']:.3g}; "
            f"{d['collisions_per_particle']:.3g} collisions/particle, Enskog {d['enskog_collisions_per_particle']:.3g})"
            if "error" not in d else f"demq FAILED ({d['error']})")
    jax = (f"JAX-MD {j['cundall_loop']:.3g} ({config(j)}; ~{j['collisions_per_particle_estimate']:.2g} "
           f"collisions/particle)" if j and "error" not in j
           else "JAX-MD not run" if not j else f"JAX-MD FAILED ({j['error']})")
    line = f"{r['case']}: N={r['n']} phi={r['phi']:g} {r['precision']} {r['steps']} steps: {demq}; {jax}"
    if "state_difference" in r:
        sd = r["state_difference"]
        line += f"; final states differ by <= {sd['max_position_diff_radii']:.2g} radii, " \
                f"{sd['max_velocity_diff_rel']:.2g} v_rms"
    return line


def config(j: dict) -> str:
    return f"{j['format']}, skin {j['skin_radii']:g} a, capacity {j['capacity_multiplier']:.3g}"


def table(rows: list) -> str:
    """Markdown table: Cundall numbers (particle-steps per second) and demq / JAX-MD ratios."""
    out = [("| case | N | φ | precision | steps | collisions/particle: demq (Enskog) / JAX-MD est. | demq loop | "
            "JAX-MD best loop (config) | demq / JAX-MD loop | demq warm whole job (start draw s) | "
            "demq warm whole job / JAX-MD loop |"),
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d, j = r["demq"], r["jaxmd"]
        ok_d, ok_j = "error" not in d, bool(j) and "error" not in j
        coll = (f"{d['collisions_per_particle']:.3g} ({d['enskog_collisions_per_particle']:.3g})" if ok_d else "—") + \
            (f" / {j['collisions_per_particle_estimate']:.2g}" if ok_j else "")
        out.append(
            f"| {r['case']}{' (vs elastic JAX-MD)' if r['contact'] != 'elastic' else ''} | {r['n']} | {r['phi']:g} | "
            f"{r['precision']} | {r['steps']} | {coll} | {d['cundall_loop']:.3g} | "
            if ok_d else f"| {r['case']} | {r['n']} | {r['phi']:g} | {r['precision']} | {r['steps']} | — | — | ")
        out[-1] += (f"{j['cundall_loop']:.3g} ({config(j)}) | " if ok_j else "— | ") + \
            (f"×{r['ratio_loop']:.2f} | " if "ratio_loop" in r else "— | ") + \
            (f"{d['cundall_whole_job_warm']:.3g} ({d['start_draw_s']:.1f}) | " if ok_d else "— | ") + \
            (f"×{r['ratio_whole_job_warm_vs_loop']:.2f} |" if "ratio_loop" in r else "— |")
    return "\n".join(out)


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=DEFAULT_CASES)
    ap.add_argument("--steps-scale", type=float, default=1.0, help="multiply every case's steps (rounded to chunks)")
    ap.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS), help="JAX-MD list formats searched")
    ap.add_argument("--skins", nargs="+", type=float, default=list(SKINS), help="JAX-MD skins searched, in radii")
    ap.add_argument("--capacities", nargs="+", type=float, default=list(CAPACITIES),
                    help="JAX-MD capacity multipliers searched (the first for the format and skin search)")
    ap.add_argument("--search-every", action="store_true", help="search at every N (default: once per phi, precision)")
    ap.add_argument("--quick", action="store_true", help=f"N = {QUICK_N}, {QUICK_STEPS} steps (harness check)")
    ap.add_argument("--backend", choices=("cuda", "cpu"), default="cuda", help="demq's backend (cpu: --quick only)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--budget-s", type=float, default=400.0, help="start no new (N, phi) group after this many s")
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
    if not all(c >= 1.0 for c in a.capacities):
        ap.error(f"--capacities must be >= 1, got {a.capacities}")
    out = Path(a.out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    with_jaxmd, jax_info = jaxmd_available()
    print(f"JAX-MD: {jax_info}" if with_jaxmd else JAXMD_MISSING.format(error=jax_info), flush=True)
    if with_jaxmd and a.backend == "cuda" and "gpu" not in jax_info:
        print("WARNING: JAX runs on the CPU here (no CUDA jaxlib?): the JAX-MD numbers are not GPU numbers", flush=True)
    t0 = time.perf_counter()
    rows = compare(a.cases, a, out / "logs", with_jaxmd)
    md = table(rows)
    print(md)
    print(f"total {time.perf_counter() - t0:.0f} s", flush=True)
    args = argv if argv is not None else sys.argv[1:]
    info = {"command": " ".join([sys.executable, "-m", "bench.vs_jaxmd", *args]),
            "jaxmd": jax_info if with_jaxmd else None, "rows": rows}
    (out / "results.json").write_text(json.dumps(info, indent=1))
    (out / "results.md").write_text(md + "\n")
    return rows


if __name__ == "__main__":
    main()
