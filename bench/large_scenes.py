"""Large sphere scenes on one GPU: their device memory against the prediction, and their start drawn on the device.

    python -m bench large_scenes memory --n 8388608 134217728 1000000000 --precision float32 float64 --steps 1000
    python -m bench large_scenes memory --n 1000000000 --snapshots 1 --orientations off --out-dir /data
    python -m bench large_scenes start --n 2097152 8388608 --phi 0.008 0.058 0.2

``memory``: per case (rough spheres, e_n = e_t = 0.8, phi = 0.058 unless ``--phi``, no snapshots, records every
t_end/200, ``--steps`` cooling steps, no thermalisation, the spec's start or ``--start``) the predicted peak (B per
particle; the list slots per particle it assumes, engine/loops/cuda_memory.py); ``--snapshots K`` frames (the spec's
``orientations`` from ``--orientations``), with the result file written under ``--out-dir`` and its size, the
seconds of the snapshot stops and the process's peak host memory (ru_maxrss; a frame of more than FRAME_PIECE_ROWS
particles is written in pieces, engine/output/pieces.py); the allocator's peak of live device
bytes during the run (a Numba memory-manager plugin that counts what is allocated and released; pending deallocations are
flushed at once, NUMBA_CUDA_MAX_PENDING_DEALLOCS_COUNT = 1); the process's peak as nvidia-smi sees it (context
included); the arrays the ensemble holds at the end (``device_allocations``) and the list slots reached; the loop's
Cundall number. A spec the prediction refuses is reported with the refusal's text and how long it took.

``start``: the random start (engine/setup/cell_rsa.py) drawn on the device (engine/loops/cuda_start.py ``draw_start``,
float64 positions, the sphere's three streams) for each N and phi, best of ``--reps`` after one untimed draw (the
kernels' load), with the rounds it took; for N <= ``--check-max`` the host's draw of the same start and whether the
centres are equal bit for bit (the streams equal to rounding), and the smallest centre distance over sigma.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
import weakref

os.environ.setdefault("NUMBA_CUDA_MAX_PENDING_DEALLOCS_COUNT", "1")


class _Peak:
    live = 0
    peak = 0
    lock = threading.Lock()

    @classmethod
    def add(cls, n: int) -> None:
        with cls.lock:
            cls.live += n
            cls.peak = max(cls.peak, cls.live)

    @classmethod
    def reset(cls) -> None:
        with cls.lock:
            cls.peak = cls.live


def _install_counter() -> bool:
    """A memory-manager plugin that counts live device bytes (allocations minus released ones)."""
    from numba import cuda
    from numba.cuda.cudadrv.driver import NumbaCUDAMemoryManager

    class Counting(NumbaCUDAMemoryManager):
        def memalloc(self, size):
            ptr = super().memalloc(size)
            _Peak.add(int(size))
            weakref.finalize(ptr, _Peak.add, -int(size))
            return ptr

    try:
        cuda.set_memory_manager(Counting)
        return True
    except Exception as exc:  # noqa: BLE001
        print(f"no counting memory manager: {exc}", file=sys.stderr)
        return False


class _SmiPeak:
    """This process's peak device memory as nvidia-smi reports it (polled every 50 ms)."""

    def __init__(self):
        self.peak = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._poll, daemon=True)
        self._t.start()

    def _poll(self):
        pid = str(os.getpid())
        while not self._stop.is_set():
            try:
                out = subprocess.run(["nvidia-smi", "--query-compute-apps=pid,used_memory",
                                      "--format=csv,noheader,nounits"], capture_output=True, text=True,
                                     timeout=5).stdout
                for line in out.splitlines():
                    p, mib = [x.strip() for x in line.split(",")]
                    if p == pid:
                        self.peak = max(self.peak, int(mib) * 2**20)
            except Exception:  # noqa: BLE001
                pass
            self._stop.wait(0.05)

    def stop(self) -> int:
        self._stop.set()
        self._t.join()
        return self.peak


def case(n: int, precision: str, phi: float, steps: int, start=None, snapshots: int = 0, orientations: bool = True,
         out_dir=None) -> dict:
    import engine
    from engine.errors import SpecError
    from engine.loops import cuda_ensemble
    from engine.loops.cuda_memory import release_unreferenced, device_allocations, predict_sphere_device
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=n, volume_fraction=phi, e_n=0.8, e_t=0.8, precision=precision,
                          backend="cuda", snapshots=snapshots, orientations=orientations, thermalization=0,
                          start=start)
    spec = spec.model_copy(update={"t_end": steps * derive(spec).dt})
    pred = predict_sphere_device(spec, derive(spec), reads_state=snapshots > 0)
    kept = []
    init = cuda_ensemble.CudaEnsembleBase.__init__

    def keep(self, *a, **k):
        kept.append(self)
        init(self, *a, **k)

    row = dict(n=n, precision=precision, phi=phi, steps=steps, start=start or "default", snapshots=snapshots,
               orientations=orientations,
               predicted_B_per_particle=pred.peak_bytes / n,
               predicted_loop_B=pred.loop_bytes / n, predicted_start_B=pred.start_bytes / n,
               predicted_slots_per_particle=pred.slots / n)
    cuda_ensemble.CudaEnsembleBase.__init__ = keep
    release_unreferenced()     # the earlier cases' arrays freed first: none may be released during this one
    _Peak.reset()
    base = _Peak.live
    smi = _SmiPeak()
    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
            s = engine.run(spec, os.path.join(tmp, "out.h5"))
            row.update(loop_cundall=s.cundall, loop_s=s.loop_s, job_s=s.job_wall_s,
                       snapshots_s=s.extra["timings"]["snapshots"], close_s=s.extra["timings"]["close"],
                       file_GB=os.path.getsize(s.output) / 1e9,
                       host_peak_GB=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9)
            if snapshots:
                import h5py

                with h5py.File(s.output) as f:
                    part = f["particles/all"]
                    row["frames"] = {k: list(part[k]["value"].shape) for k in part
                                     if isinstance(part[k], h5py.Group) and "value" in part[k]}
    except SpecError as exc:
        row.update(refused=str(exc), refused_after_s=time.perf_counter() - t0)
    finally:
        cuda_ensemble.CudaEnsembleBase.__init__ = init
    row["smi_peak_B_per_particle"] = smi.stop() / n
    row["allocator_peak_B_per_particle"] = (_Peak.peak - base) / n
    if kept and "refused" not in row:     # (a refused spec's only ensemble is the start-up thread's stand-in)
        e = kept[-1]
        found = device_allocations(e)
        row.update(slots_per_particle=e.nbr.shape[0] / n, held_B_per_particle=sum(found.values()) / n,
                   held_by_array={k: round(v / n, 2) for k, v in sorted(found.items(), key=lambda kv: -kv[1])[:16]},
                   predicted_by_array={k: round(v / n, 2) for k, v in sorted(pred.table.items(),
                                                                              key=lambda kv: -kv[1])[:16]})
    kept.clear()
    if "allocator_peak_B_per_particle" in row and not row.get("refused"):
        row["predicted_over_allocator_peak"] = row["predicted_B_per_particle"] / row["allocator_peak_B_per_particle"]
    return row


def start_case(n: int, phi: float, reps: int, check_max: int) -> dict:
    import numpy as np
    from numba import cuda

    from engine.loops.cuda_start import draw_start
    from engine.analysis.pairs import periodic_pairs
    from engine.setup.params import derive
    from engine.setup.scene import StartDraw, parallel_start_streams
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=n, volume_fraction=phi, backend="cuda", seed=1)
    p = derive(spec)
    streams, radius = parallel_start_streams(spec, p)
    d = StartDraw.of(n, spec.seed, streams, spec.box_length, radius, "random")
    stream = cuda.stream()
    pos = cuda.device_array((3, n), np.float64, stream=stream)
    dsts = {k: cuda.device_array((dim, n), np.float64, stream=stream) for k, dim, _ in d.streams}
    times = []
    for _ in range(reps + 1):
        stream.synchronize()
        t0 = time.perf_counter()
        draw_start(d, 0, pos, dsts, stream)
        stream.synchronize()
        times.append(time.perf_counter() - t0)
    row = dict(n=n, phi=phi, cells=d.rsa.nc ** 3, first_s=times[0], best_s=min(times[1:]))
    if n <= check_max:
        t0 = time.perf_counter()
        pos_h, arrays_h = d.on_host()
        row["host_s"] = time.perf_counter() - t0
        pos_d = pos.copy_to_host().T
        row["centres_equal"] = bool(np.array_equal(pos_d, pos_h))
        row["streams_max_rel_diff"] = max(float(np.max(np.abs(dsts[k].copy_to_host().T - a))) / max(
            1e-300, float(np.max(np.abs(a)))) for (k, _, _), a in zip(d.streams, arrays_h))
        close = periodic_pairs(pos_h, spec.box_length, 2.0 * radius * 1.001)
        r = pos_h[close[:, 1]] - pos_h[close[:, 0]]
        r -= spec.box_length * np.round(r / spec.box_length)
        row["min_distance_over_sigma"] = float(np.sqrt((r * r).sum(1)).min() / (2 * radius)) if len(r) else None
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["memory", "start"])
    ap.add_argument("--n", type=int, nargs="+", default=[8388608])
    ap.add_argument("--precision", nargs="+", default=["float32"])
    ap.add_argument("--phi", type=float, nargs="+", default=[0.058])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--start", choices=["random", "lattice"], default=None,
                    help="memory: the spec's start (default: the spec's own)")
    ap.add_argument("--reps", type=int, default=3, help="start: timed draws after the first")
    ap.add_argument("--check-max", type=int, default=2097152, help="start: largest N drawn on the host too")
    ap.add_argument("--snapshots", type=int, default=0, help="memory: snapshot frames (the spec's snapshots)")
    ap.add_argument("--orientations", choices=["on", "off"], default="on", help="memory: the spec's orientations")
    ap.add_argument("--out-dir", default=None, help="memory: where the result files are written (a temporary "
                                                    "directory there; default: the system's)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    if args.what == "memory":
        counting = _install_counter()
        for prec in args.precision:
            for n in args.n:
                r = case(n, prec, args.phi[0], args.steps, args.start, args.snapshots, args.orientations == "on",
                         args.out_dir)
                r["allocator_counted"] = counting
                rows.append(r)
                print(json.dumps(r), flush=True)
    else:
        for phi in args.phi:
            for n in args.n:
                r = start_case(n, phi, args.reps, args.check_max)
                rows.append(r)
                print(json.dumps(r), flush=True)
    if args.out:
        with open(os.path.join(args.out, f"large_scenes_{args.what}.json"), "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
