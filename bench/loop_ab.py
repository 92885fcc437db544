"""Side-by-side loop variants of one case (JAX-MD scenes, 1M scene, 256 packed scenes, 1M rough spheroids).

In one warm process (kernels compiled by a 20-step run of each variant first), each repetition runs every variant
once, in turn, on the same case (bench/vs_jaxmd.py's scene and spec: no thermalisation, no snapshots), and
prints one JSON line per run: the loop and end-to-end Cundall numbers and the neighbour-list builds. A variant is
``default`` or a ``+``-joined list of: bench/e2e.py ``--off`` switch names (e.g. ``launch_cache``,
``displacement_bound``), ``multistep_on`` (the many-steps-per-launch loop forced for a large scene), ``blocks=B``
(every force kernel compiled for B blocks per SM: engine/loops/cuda_loop.py FORCES_BLOCKS_PER_SM; ``blocks=0``: none
compiled with launch bounds), ``observe_blocks=B`` (the same for the force passes that also sum a record's
observables: OBSERVE_BLOCKS_PER_SM), ``kick_blocks=B`` (the same for the kick-drift kernel: KICK_DRIFT_BLOCKS_PER_SM),
``gc_off`` (Python's cyclic garbage collector off during the run), ``skin=L`` (every scene's ``verlet_skin``, radii:
the default skin rule against others on the same gas),
``own_scratch`` (a rebuild's scratch in arrays of its own, not lent by the list and the force buffer:
engine/loops/cuda_rebuild.py LEND_SCRATCH). For the cost of one piece of machinery inside the loop, without the
fresh-process noise of bench/e2e.py. ``--rebuild-parts`` also times each list rebuild's parts and kernels with CUDA
events (:class:`RebuildParts`) and prints their device ms per rebuild and the rebuilds' share of the loop;
``--host-parts`` the host's microseconds a step in the loop's launches (by kernel), status copy, its wait, failed-scene
check and rebuilds (:class:`HostParts`).

    python -m bench loop_ab --cases elastic-2M-f64 elastic-8M-f32 --variants launch_cache default multistep_on
    python -m bench loop_ab --cases rough-2M-f64 --variants default blocks=2 blocks=3
    python -m bench loop_ab --cases elastic-1M-f64 packed-256x4096-f64 --variants default gc_off --start random

Cases: :data:`JAXMD_CASES` (bench/vs_jaxmd.py's gas at phi = 0.058, or ``--phi``) and :data:`EXTRA` (one 1M-sphere
scene, 256 or 64 packed scenes of 4096 at the same sphere size and ``--phi``; 1M rough spheroids). For several scenes
the loop figure is N x steps over the ensemble's loop seconds. Compare one scene with packed scenes at the same
``--start`` (by default both start random: a sphere scene of 2^20 or more from the random start placed in parallel;
spheroids on the lattice, whose list stays nearly empty over a short run).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


#: (module, setting) -> the engine's value of every bench.e2e switch, as this process first found it
_DEFAULTS: dict = {}


def apply(variant: str, default_blocks) -> None:
    """Put every switch back on and the kernels' launch bounds to the engine's ``default_blocks`` (the force,
    observing and kick-drift tables), then turn off those the variant names (bench.e2e.SWITCHES) and set its
    ``blocks=B``, ``observe_blocks=B`` and ``kick_blocks=B``."""
    import gc
    import importlib

    from bench.e2e import SWITCHES, switch_off
    import engine.loops.cuda_ensemble as ensemble
    import engine.loops.cuda_loop as loop
    import engine.loops.cuda_rebuild as rebuild

    for module, setting, _ in SWITCHES.values():
        mod = importlib.import_module(module)
        setattr(mod, setting, _DEFAULTS.setdefault((module, setting), getattr(mod, setting)))
    loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM = default_blocks
    rebuild.LEND_SCRATCH = True
    gc.enable()
    off = []
    for part in ([] if variant == "default" else variant.split("+")):
        if part == "gc_off":
            gc.disable()
        elif part == "multistep_on":
            ensemble.MULTISTEP = True
        elif part == "own_scratch":
            rebuild.LEND_SCRATCH = False
        elif part.startswith("blocks="):
            b = int(part.split("=", 1)[1])
            loop.FORCES_BLOCKS_PER_SM = {"*": b} if b > 0 else None
        elif part.startswith("observe_blocks="):
            b = int(part.split("=", 1)[1])
            loop.OBSERVE_BLOCKS_PER_SM = {"*": b} if b > 0 else None
        elif part.startswith("skin="):
            pass                                    # a spec field: variant_skin, read where the specs are made
        elif part.startswith("kick_blocks="):
            b = int(part.split("=", 1)[1])
            loop.KICK_DRIFT_BLOCKS_PER_SM = {"*": b} if b > 0 else None
        else:
            off.append(part)
    switch_off(off)


def variant_skin(variant: str):
    """The ``skin=L`` of a variant (radii, a float), or None: the engine's default skin."""
    for part in ([] if variant == "default" else variant.split("+")):
        if part.startswith("skin="):
            return float(part.split("=", 1)[1])
    return None


class RebuildParts:
    """CUDA events around a GPU list rebuild's parts (engine/loops/cuda_rebuild.py ``ListBuilds``): the kept
    history's compaction, the sort and permutation, the build's two passes with their scan and slot count
    (``build``: the rest), and the new list's history; device milliseconds per rebuild (the stream's time
    between the events: kernels, and the gaps where the GPU waits on the host's launches and status reads) and
    host milliseconds per rebuild, over the rebuilds of one run's time loop; and each kernel launched inside a
    rebuild, by name (``kernels``: device ms per rebuild, the gaps between launches excluded). A diagnostic: the
    events stay in the loop."""

    PARTS = ("_compact", "_sort_and_permute", "_fill_history")

    def __init__(self):
        self.marks: list = []
        self.host_s: list = []
        self.launches: list = []        # (rebuild index, kernel name, events) of the launches inside rebuilds
        self._depth = 0
        self._saved: dict = {}
        self._saved_launch = None

    def __enter__(self):
        import engine.loops.cuda_launch as launch
        import engine.loops.cuda_rebuild as rebuild
        from engine.loops.cuda_cache import SIM
        from numba import cuda

        event = (lambda: cuda.event()) if SIM else (lambda: cuda.event(timing=True))  # noqa: E731
        cls = rebuild.ListBuilds
        self._saved = {name: getattr(cls, name) for name in self.PARTS + ("_gpu_rebuild",)}
        timer = self

        def wrap(name, fn):
            def timed(ens, *a, **k):
                e0 = event()
                e0.record(ens.stream)
                t0 = time.perf_counter()
                timer._depth += 1
                try:
                    out = fn(ens, *a, **k)
                finally:
                    timer._depth -= 1
                e1 = event()
                e1.record(ens.stream)
                if name == "_gpu_rebuild":
                    timer.host_s.append(time.perf_counter() - t0)
                timer.marks.append((name, e0, e1))
                return out
            return timed

        saved_launch = self._saved_launch = launch.LaunchCache.launch

        def timed_launch(cache, name, dispatcher, config, args):
            if not timer._depth:
                return saved_launch(cache, name, dispatcher, config, args)
            e0 = event()
            e0.record(config[2])
            saved_launch(cache, name, dispatcher, config, args)
            e1 = event()
            e1.record(config[2])
            timer.launches.append((len(timer.host_s), name, e0, e1))

        for name, fn in self._saved.items():
            setattr(cls, name, wrap(name, fn))
        launch.LaunchCache.launch = timed_launch
        return self

    def __exit__(self, *exc):
        import engine.loops.cuda_launch as launch
        import engine.loops.cuda_rebuild as rebuild

        for name, fn in self._saved.items():
            setattr(rebuild.ListBuilds, name, fn)
        launch.LaunchCache.launch = self._saved_launch
        return False

    def summary(self) -> dict:
        """{part: device ms per rebuild} with ``build`` (the whole less the timed parts), ``rebuild`` (the whole),
        ``host_ms`` and ``rebuilds``, over the rebuilds inside the time loop: the first, the job's first list (built
        before the loop), is left out."""
        groups, group = [], []
        for mark in self.marks:          # a rebuild's parts end before it does
            group.append(mark)
            if mark[0] == "_gpu_rebuild":
                groups.append(group)
                group = []
        total: dict = {}
        for name, e0, e1 in (m for g in groups[1:] for m in g):
            e1.synchronize()
            total[name] = total.get(name, 0.0) + e0.elapsed_time(e1)
        n = len(groups) - 1
        if n <= 0:
            return {"rebuilds": 0}
        out = {name.strip("_"): round(total.get(name, 0.0) / n, 3) for name in self.PARTS}
        out["rebuild"] = round(total["_gpu_rebuild"] / n, 3)
        out["build"] = round(out["rebuild"] - sum(out[p.strip("_")] for p in self.PARTS), 3)
        out["host_ms"] = round(1e3 * sum(self.host_s[1:]) / n, 3)
        out["rebuilds"] = n
        kernels: dict = {}
        for index, name, e0, e1 in self.launches:
            if index >= 1:
                e1.synchronize()
                kernel = name.split("/")[0]          # gather_rows/<array>/<part>: one kernel
                kernels[kernel] = kernels.get(kernel, 0.0) + e0.elapsed_time(e1) / n
        out["kernels"] = {k: round(v, 3) for k, v in sorted(kernels.items(), key=lambda kv: -kv[1])}
        return out


class HostParts:
    """Host microseconds a step of a run's time loop in the pieces of the GPU loop's host work: each kernel launch by
    name (engine/loops/cuda_launch.py ``LaunchCache.launch``: the cache's key and look-up and the launch call, ``go``
    the direct driver call within them), the status copy (``_status_copy``), the wait for it (``_wait_status``: the
    GPU's time where the host waits on it), the failed-scene check (``_collect``) and the list rebuilds
    (``_rebuild``, their waits included), each summed over the whole run (its set-up's launches and first list
    included) and divided by its steps. A diagnostic: each timed call costs the host about half a microsecond more."""

    METHODS = ("_status_copy", "_wait_status", "_collect", "_rebuild")

    def __init__(self):
        self.seconds: dict = {}
        self._saved: list = []

    def _add(self, name: str, t0: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def _timed(self, label: str, fn):
        timer = self

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                timer._add(label, t0)
        return timed

    def _patch(self, owner, name: str, fn) -> None:
        self._saved.append((owner, name, owner.__dict__.get(name)))
        setattr(owner, name, fn)

    def __enter__(self):
        import engine.loops.cuda_ensemble as ensemble
        import engine.loops.cuda_launch as launch
        import engine.numba_support.numba_internals as internals

        base = ensemble.CudaEnsembleBase
        for name in self.METHODS:
            self._patch(base, name, self._timed(name, getattr(base, name)))
        saved_launch = launch.LaunchCache.launch
        timer = self

        def timed_launch(cache, name, dispatcher, config, args):
            t0 = time.perf_counter()
            try:
                return saved_launch(cache, name, dispatcher, config, args)
            finally:
                timer._add("launch:" + name.split("/")[0], t0)

        self._patch(launch.LaunchCache, "launch", timed_launch)
        saved_direct = internals.direct_launch

        def timed_direct(*a, **k):
            go = saved_direct(*a, **k)
            return self._timed("go", go) if callable(go) else go

        self._patch(internals, "direct_launch", timed_direct)
        return self

    def __exit__(self, *exc):
        for owner, name, fn in reversed(self._saved):
            if fn is None:
                delattr(owner, name)
            else:
                setattr(owner, name, fn)
        self._saved = []
        return False

    def summary(self, steps: int) -> dict:
        """{piece: host µs a step} over ``steps`` steps, the largest first."""
        return {k: round(1e6 * v / max(1, steps), 2) for k, v in sorted(self.seconds.items(), key=lambda kv: -kv[1])}


#: the JAX-MD scene's cases (bench/vs_jaxmd.py's gas at phi = 0.058, its start left to the engine unless --start):
#: name -> (N, precision, steps, contact)
JAXMD_CASES = {"elastic-2M-f64": (2_097_152, "float64", 2000, "elastic"),
               "elastic-8M-f32": (8_388_608, "float32", 1000, "elastic"),
               "elastic-8M-f64": (8_388_608, "float64", 1000, "elastic"),
               "rough-2M-f64": (2_097_152, "float64", 2000, "rough"),
               "rough-8M-f32": (8_388_608, "float32", 1000, "rough"),
               "rough-8M-mixed": (8_388_608, "mixed", 1000, "rough"),
               "coulomb-2M-f64": (2_097_152, "float64", 2000, "rough-coulomb"),
               "coulomb-8M-f32": (8_388_608, "float32", 1000, "rough-coulomb")}
#: cases beyond those: name -> (scenes, N per scene, precision, steps, contact); the JAX-MD scene
#: (phi = 0.058, k_n = 1e8, rho = 2000, v_rms = 2) at its sphere size (box 2 m x (N / 2^21)^(1/3)), elastic or
#: rough (e_n = e_t = 0.8), and the rough spheroids of the spheroid papers (xi = 2, phi = 0.05, e_n = e_t = 0.8)
EXTRA = {
    "elastic-1M-f64": (1, 1 << 20, "float64", 20_000, "elastic"),
    "rough-1M-f64": (1, 1 << 20, "float64", 20_000, "rough"),
    "packed-256x4096-f64": (256, 4096, "float64", 20_000, "elastic"),
    "packed-rough-256x4096-f64": (256, 4096, "float64", 20_000, "rough"),
    "packed-64x4096-f64": (64, 4096, "float64", 20_000, "elastic"),
    "packed-rough-64x4096-f64": (64, 4096, "float64", 20_000, "rough"),
    "spheroids-rough-1M-f64": (1, 1 << 20, "float64", 2000, "spheroid"),
}


def extra_specs(case: str, steps: int, backend: str, start=None, phi: float = 0.058) -> list:
    """The specs of an EXTRA case (one per scene, own seeds), t_end = steps x dt exactly; ``start``: the spec's start
    protocol (None: the engine's choice by size, which differs between one 1M scene and 4096-sphere scenes); ``phi``:
    the sphere cases' volume fraction (in the same box: larger spheres)."""
    from bench.vs_jaxmd import SCENE
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    k, n, precision, _, contact = EXTRA[case]
    base = dict(SCENE, volume_fraction=phi, n_particles=n, precision=precision,
                thermalization=0.0, snapshots=0, backend=backend,
                box_length=SCENE["box_length"] * (n / 2**21) ** (1 / 3), start=start)
    if contact == "elastic":
        base.update(e_n=1.0, e_t=-1.0)
    elif contact == "rough":
        base.update(e_n=0.8, e_t=0.8)
    else:
        base.update(shape="ellipsoid", elongation=2.0, volume_fraction=0.05, e_n=0.8, e_t=0.8)
    out = []
    for seed in range(1, k + 1):
        spec = SimulationSpec(**base, seed=seed)
        dt = derive(spec).dt
        out.append(SimulationSpec(**base, seed=seed, dt=dt, t_end=steps * dt))
    return out


def case_specs(case: str, steps: int, backend: str = "cuda", phi: float = 0.058, n=None, velocity_rms=None,
               start=None, skin=None) -> list:
    """The specs of ``case`` (one per scene) over ``steps`` steps: a JAX-MD case at volume fraction ``phi``, with
    ``n`` particles at the same sphere size (the box scaled as N^(1/3), so the same dt) and rms speed
    ``velocity_rms`` (m/s) where given; ``start``: every scene's start protocol (None: the engine's choice by size);
    ``skin``: every scene's ``verlet_skin`` (radii; None: the default rule)."""
    from bench.vs_jaxmd import Case, case_spec

    if case in EXTRA:
        specs = extra_specs(case, steps, backend, start, phi)
    else:
        n0, precision, _, contact = JAXMD_CASES[case]
        specs = [case_spec(Case(n0, precision, steps, contact, phi), backend)]
        if n is not None:
            specs = [type(s)(**dict(s.model_dump(), n_particles=n, box_length=s.box_length * (n / n0) ** (1 / 3)))
                     for s in specs]
        if velocity_rms is not None:        # dt depends on the contact, not the speed
            specs = [type(s)(**dict(s.model_dump(), velocity_rms=velocity_rms)) for s in specs]
        specs = [type(s)(**dict(s.model_dump(), start=start)) for s in specs]
    if skin is not None:
        specs = [type(s)(**dict(s.model_dump(), verlet_skin=skin)) for s in specs]
    return specs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", choices=list(JAXMD_CASES) + list(EXTRA), default=["elastic-2M-f64"])
    ap.add_argument("--variants", nargs="+", default=["launch_cache", "default"])
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--backend", choices=("cuda", "cpu"), default="cuda")
    ap.add_argument("--steps-scale", type=float, default=1.0)
    ap.add_argument("--phi", type=float, default=0.058, help="volume fraction of the sphere cases (default 0.058)")
    ap.add_argument("--n", type=int, default=None,
                    help="particles of the JAX-MD cases instead of theirs, at the same sphere size (the box scaled as "
                         "N^(1/3)): the same gas at another N")
    ap.add_argument("--velocity-rms", type=float, default=None,
                    help="the JAX-MD cases' rms speed (m/s) instead of theirs: the same gas moving faster a step")
    ap.add_argument("--start", choices=("lattice", "random"), default=None,
                    help="every scene's start protocol (default: the engine's choice: random for spheres up to "
                         "phi = 0.3, the lattice for spheroids)")
    ap.add_argument("--rebuild-parts", action="store_true",
                    help="time each GPU list rebuild's parts with CUDA events (RebuildParts) and print device ms per "
                         "rebuild and the rebuilds' share of the loop")
    ap.add_argument("--host-parts", action="store_true",
                    help="time the host's work a step of the GPU loop (HostParts: launches by kernel, status copy, "
                         "its wait, the failed-scene check, rebuilds) and print host µs a step")
    args = ap.parse_args(argv)
    import h5py

    import engine.loops.cuda_loop as loop
    from engine import run, run_ensemble
    from engine.setup.start_kind import start_protocol

    default_blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM

    def specs_of(case: str, steps: int, variant: str) -> list:
        return case_specs(case, steps, args.backend, phi=args.phi, n=args.n, velocity_rms=args.velocity_rms,
                          start=args.start, skin=variant_skin(variant))

    def run_case(specs: list, tmp: Path) -> tuple:
        """(summaries, wall s): one scene through engine.run, several through one run_ensemble."""
        t0 = time.perf_counter()
        if len(specs) == 1:
            out = [run(specs[0], tmp / "run.h5", backend=args.backend)]
        else:
            out = run_ensemble(specs, [tmp / f"run{k}.h5" for k in range(len(specs))], backend=args.backend)
        wall = time.perf_counter() - t0
        for s in out:
            if isinstance(s, BaseException):
                raise s
        return out, wall

    with tempfile.TemporaryDirectory(prefix="loop_ab_") as tmp:
        tmp = Path(tmp)
        for case in args.cases:
            steps = EXTRA[case][3] if case in EXTRA else JAXMD_CASES[case][2]
            steps = max(1, int(steps * args.steps_scale))
            for v in args.variants:
                apply(v, default_blocks)
                run_case(specs_of(case, 20, v), tmp)
            for rep in range(args.reps):
                for v in args.variants:
                    apply(v, default_blocks)
                    specs = specs_of(case, steps, v)
                    timer = RebuildParts() if args.rebuild_parts else contextlib.nullcontext()
                    host = HostParts() if args.host_parts else contextlib.nullcontext()
                    with timer, host:
                        summaries, wall = run_case(specs, tmp)
                    n = sum(sp.n_particles for sp in specs)
                    loop_s = max(s.loop_s for s in summaries)
                    steps_done = summaries[0].steps
                    with h5py.File(summaries[0].output, "r") as f:
                        builds = int(f["parameters"].attrs["neighbour_builds"])
                        skin_radii = round(float(f["parameters"].attrs["verlet_skin"]), 4)
                    extra = {}
                    if args.rebuild_parts:
                        parts = timer.summary()
                        extra = {"rebuild_ms": parts, "rebuild_share": round(
                            parts.get("rebuild", 0.0) * parts["rebuilds"] / (1e3 * loop_s), 4)}
                    if args.host_parts:
                        extra["host_us_per_step"] = host.summary(steps_done)
                    print(json.dumps({"case": case, "phi": specs[0].volume_fraction, "variant": v, "rep": rep,
                                      "device": summaries[0].device,
                                      "scenes": len(specs), "n": n, "start": start_protocol(specs[0]),
                                      "steps": steps_done, "list_builds": builds,
                                      "skin_radii": skin_radii,
                                      "loop_s": round(loop_s, 4), "wall_s": round(wall, 3),
                                      "cundall_loop": float(f"{n * steps_done / loop_s:.3e}"),
                                      "cundall_end_to_end": float(f"{n * steps_done / wall:.3e}"), **extra}),
                          flush=True)
    apply("default", default_blocks)
    return 0


if __name__ == "__main__":
    sys.exit(main())
