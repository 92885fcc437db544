"""Verlet lists built on the CPU for the GPU time loop: the execution modes of Skorych & Dosta (2022) §3.

Three ways to get the GPU its neighbour list (``list_mode``):

``"gpu"``            the list is built on the GPU (sorted cells or multigrid levels; the default mode of
                     :mod:`engine.loops.cuda_ensemble`).
``"cpu-sequential"`` Skorych & Dosta (2022) Fig. 1A: when a particle has moved L_v/2 the GPU stops, positions go to the
                     host (A5), the CPU builds the list with all its threads (A1, :mod:`engine.neighbours.multigrid`),
                     it goes to the GPU (A2) and the GPU integrates until the next L_v/2 (A3, A4).
``"cpu-pipelined"``  Skorych & Dosta (2022) Fig. 1B: when a particle has moved L_v/4 (B3) the positions are copied
                     (B4) and a CPU thread builds the next list (B5) while the GPU keeps integrating
                     with the current one (B6, B7); at the L_v/2 limit the host waits for the thread
                     (B8), checks the new list a posteriori against Eq. 2 with the positions it was built
                     from (B9, B10), uploads it (B11) and at once starts the next build from the current
                     positions (B12) while the GPU integrates with the new list (B13, B14). A list that
                     fails the check (or overflows its stride) restarts the semi-parallel stage: a
                     synchronous build from the current positions (B1).
``"auto"``           starts on the GPU list and measures; after a few stages one CPU build runs in the
                     background on a copy of the positions (the GPU does not wait) and gives tau_CPU;
                     with the measured tau_GPU (integration time per stage), the GPU build time and the
                     transfer time tau_exch the three modes are predicted per step (Eqs. 5-8:
                     sequential tau_GPU + tau_CPU + tau_exch, pipelined max(tau_GPU, 2 tau_CPU) +
                     2 tau_exch, GPU tau_GPU + tau_build); a CPU mode predicted faster is tried for a few
                     stages and kept only if its *measured* time per step beats the GPU list's. The
                     prediction is repeated every ``REPROBE`` stages (q changes as a gas cools).
                     The probe and a trial cost time (pinned buffers, the builder's set-up, the CPU
                     build beside the GPU's driver thread, stages in a slower mode), so ``auto`` probes
                     only when what is left of the run could repay them: at least
                     ``MIN_STAGES_LEFT`` stages (a trial of TRIAL_STAGES stages and the probe repaid by a
                     SWITCH_MARGIN gain) and ``MIN_WALL_LEFT_S`` seconds. The steps left are the
                     ensemble's: the driver's horizon (``CudaEnsemble.plan``) or the current
                     ``advance`` call's end, whichever is later.

The CPU modes keep the particle order of the device fixed (the GPU mode re-sorts at its rebuilds), so
a list built from a position snapshot stays valid for the slots it names. History carry-over is the GPU
path's: the slots that must keep history go to the compact store before the new list arrives and are
matched by the GPU builds' ``fill_history`` kernel (:mod:`engine.loops.cuda_kernels`).

Measured per stage (``stats``): mode, steps, tau_GPU (s of integration), tau_CPU (s of CPU build),
tau_exch (s of position download + list upload), tau_build (s of GPU build), waits and restarts; q and
G_max (Eqs. 5, 9) from the means. One scene only (K = 1).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from numba import cuda

from engine.loops import cuda_kernels as K
from engine.loops.cuda_device import copy_device as _copy
from engine.loops.cuda_memory import FIRST_STRIDE, grown_stride

MODES = ("gpu", "cpu-sequential", "cpu-pipelined", "auto")
#: stages of the GPU list measured before the first prediction, stages a candidate mode is tried, and
#: stages between two predictions
WARM_STAGES, TRIAL_STAGES, REPROBE = 3, 4, 64
#: a CPU mode is tried only when predicted this much faster per step than the GPU list: switching costs
#: the builder set-up and a trial, and within a few per cent the modes tie in run-to-run noise
SWITCH_MARGIN = 0.05
#: what must be left of a run before auto probes (module docstring): stages and wall seconds
MIN_STAGES_LEFT = int((1 + TRIAL_STAGES) / SWITCH_MARGIN)
MIN_WALL_LEFT_S = 10.0


def g_max(q: float) -> float:
    """Largest gain of the pipelined over the sequential mode for q = tau_CPU/tau_GPU (Skorych & Dosta 2022, Eq. 9)."""
    return q if q <= 0.5 else (1.0 - q) / (2.0 * q)


class HostLists:
    """CPU-built Verlet lists for one scene of a :class:`~engine.loops.cuda_ensemble.CudaEnsembleBase` (spheres)."""

    def __init__(self, ens, mode: str):
        if mode not in MODES:
            raise ValueError(f"list_mode = {mode!r} is not one of {', '.join(MODES)}")
        if ens.n_scenes != 1:
            raise ValueError(f"list_mode = {mode!r} needs one scene; an ensemble of {ens.n_scenes} builds "
                             "its lists on the GPU (list_mode = 'gpu')")
        self.ens = ens
        self.requested = mode
        self.mode = "gpu" if mode == "auto" else mode
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="demq-list")
        self.pending = None      # future of a CPU build: (need, tau_cpu)
        self.pending_kind = None  # "list" (to be used) or "probe" (timing only)
        self.stages = []          # one dict per stage (see module docstring)
        self.restarts = 0
        self.decisions = []       # (steps_done, mode, predicted s/step per mode)
        self._stage_t0 = time.perf_counter()
        self._stage_step0 = ens.steps_done
        self._stage_extra = {}
        self._probe = None        # last background CPU build timing: (tau_cpu, tau_down)
        self._probe_down = 0.0
        self._trial = None        # (mode, stage index where the trial started)
        self._next_probe = WARM_STAGES
        self.builder = None
        self._host = None
        self._uploaded_slots = ens.n      # the list slots of the last upload (predict: the exchange's bytes)
        self.snap = None
        if self.mode != "gpu":
            self._enter_cpu_mode()

    # ---- buffers ------------------------------------------------------------------------------------

    def _enter_cpu_mode(self) -> None:
        """Fix the slot order (no permutation from now on: the attached lists' history is filled unpermuted,
        ``_fill_history(False)``) and set the builder up for it."""
        self._prepare()

    def _prepare(self) -> None:
        """Builder (radii in the current slot order), pinned host buffers and the device snapshot."""
        from engine.neighbours.multigrid import MultigridBuilder, grid_levels

        ens = self.ens
        st = ens.stream
        r = (ens.radius1.copy_to_host(stream=st) if not ens.uniform
             else np.full(ens.n, ens.spd_h[0, K.D_R0], ens.dtype))
        st.synchronize()
        r = np.asarray(r, ens.dtype)
        if self.builder is not None and self.builder.n == ens.n:
            # the same particles in another slot order (the GPU list re-sorts): new radii, same levels
            self.builder.set_radius(r)
            return
        skin = float(ens.contact[0].skin)
        levels = (ens.levels[0] if ens.multigrid else
                  grid_levels(float(ens.box[0]), ens.n, float(r.min()), float(r.max()), skin, max_levels=1))
        self.builder = MultigridBuilder(float(ens.box[0]), r, levels, skin=skin)
        self._alloc_host(FIRST_STRIDE if self._host is None else self._host["nbr"].shape[0])
        if self.snap is None:
            self.snap = cuda.device_array((3, ens.n), ens.pos_dtype, stream=st)

    def _alloc_host(self, max_nb: int) -> None:
        """Pinned host buffers: the positions, the list of ``max_nb`` slots a particle as the host builder fills it
        (its rows are packed for the device on upload, :meth:`_install`), its counts and the rows' offsets."""
        n = self.ens.n
        if self._host is None or self._host["nbr"].shape[0] != max_nb:
            pos = self._host["pos"] if self._host is not None else cuda.pinned_array((3, n), self.ens.pos_dtype)
            self._host = {"pos": pos, "nbr": cuda.pinned_array((max_nb, n), np.int32),
                          "nn": cuda.pinned_array(n, np.int32), "rows": cuda.pinned_array(n + 1, np.int32)}

    # ---- the three pieces of a CPU build ------------------------------------------------------------

    def _download(self) -> float:
        """Positions to the host (A5 / B4 / B9); returns the seconds taken."""
        t0 = time.perf_counter()
        self.ens.pos.copy_to_host(self._host["pos"], stream=self.ens.stream)
        self.ens.stream.synchronize()
        return time.perf_counter() - t0

    def _cpu_build(self, beside_gpu: bool = False) -> tuple:
        """The CPU build of the host positions into the host list; beside_gpu (the builder thread, while
        the GPU integrates): one core is left to the thread that drives the GPU."""
        all_ = numba.config.NUMBA_NUM_THREADS
        numba.set_num_threads(max(1, all_ - 1) if beside_gpu else all_)  # per calling thread
        t0 = time.perf_counter()
        h = self._host
        need = self.builder.build(h["pos"].T, h["nbr"].T, h["nn"])
        return need, time.perf_counter() - t0

    def _install(self, snapshot_dev) -> float:
        """Upload the host list (A2 / B11), attach the history kept in the compact store (the caller has
        compacted the outgoing list), x_ref = the positions the list was built from."""
        ens = self.ens
        st = ens.stream
        t0 = time.perf_counter()
        h = self._host
        # the rows' history slots, back to back in particle order (the device builds hand them out instead)
        rows, counts = h["rows"], h["nn"]
        for s in np.flatnonzero(~ens.active):     # an inactive scene's rows are empty, as a device build leaves them
            counts[ens.starts[s]:ens.starts[s] + ens.sizes[s]] = 0
        slots = int(counts.sum(dtype=np.int64))
        rows[0] = 0
        np.cumsum(counts, out=rows[1:])
        stride = h["nbr"].shape[0]
        packed = h["nbr"].T[np.arange(stride)[None, :] < counts[:, None]]     # rows in particle order
        ens._list_room(slots)
        self._uploaded_slots = slots
        if slots:
            ens.nbr[:slots].copy_to_device(packed, stream=st)
        ens.nn.copy_to_device(rows, stream=st)
        st.synchronize()
        t_up = time.perf_counter() - t0
        ens._fill_history(False)
        if ens.x_ref.dtype == snapshot_dev.dtype:
            _copy(ens.x_ref, snapshot_dev, st)
        else:       # a float32 x_ref beside float64 positions (cuda_memory.xref_dtype)
            K.cast_rows[ens._grid(ens.n)](snapshot_dev, ens.x_ref)
        ens.builds += 1
        return t_up

    def _grow(self, need: int) -> None:
        """A list that did not fit the host buffers' rows: wider ones (the device list is sized on upload)."""
        self._alloc_host(grown_stride(need))

    def _sync_build(self) -> dict:
        """Sequential build from the current positions (A5, A1, A2 / B1, B2); the outgoing list's history
        is compacted first, once, before any growth of the list."""
        self.ens._compact()
        t_down = self._download()
        need, t_cpu = self._cpu_build()
        while need > self._host["nbr"].shape[0]:
            self._grow(need)
            need, t2 = self._cpu_build()
            t_cpu += t2
        _copy(self.snap, self.ens.pos, self.ens.stream)
        t_up = self._install(self.snap)
        return {"tau_cpu": t_cpu, "tau_exch": t_down + t_up}

    def _launch(self, kind: str) -> float:
        """Snapshot the positions (device copy + host copy) and start a CPU build in the thread."""
        _copy(self.snap, self.ens.pos, self.ens.stream)
        t_down = self._download()
        self.pending = self.pool.submit(self._cpu_build, True)
        self.pending_kind = kind
        return t_down

    # ---- hooks called by the ensemble's time loop ------------------------------------------------------

    def exit_threshold(self) -> float:
        """run_steps exit threshold: 1/4 (the L_v/4 signal) while a pipelined build is due, else 1."""
        return 0.25 if (self.mode == "cpu-pipelined" and self.pending is None) else 1.0

    def signal(self) -> None:
        """A particle has moved L_v/4 since the current list's positions (B3): start the next build (B4)."""
        if self.mode == "cpu-pipelined" and self.pending is None:
            self._stage_extra["tau_exch"] = self._stage_extra.get("tau_exch", 0.0) + self._launch("list")

    def rebuild(self) -> None:
        """The L_v/2 limit: a new list by the current mode; the stage's timings recorded."""
        t_end = time.perf_counter()
        ens = self.ens
        rec = {"mode": self.mode, "steps": ens.steps_done - self._stage_step0,
               "tau_gpu": t_end - self._stage_t0, "tau_cpu": 0.0, "tau_exch": 0.0, "tau_build": 0.0,
               "wait": 0.0, "restart": False}
        for key, v in self._stage_extra.items():
            rec[key] += v
        self._stage_extra = {}
        if self.mode == "gpu":
            t0 = time.perf_counter()
            if self.pending is not None and self.pending.done():
                self._take_probe()
            ens._gpu_rebuild()
            rec["tau_build"] = time.perf_counter() - t0
        elif self.mode == "cpu-sequential":
            rec.update(self._sync_build())
        else:
            rec.update(self._pipelined(rec))
        rec["wall"] = time.perf_counter() - self._stage_t0
        self.stages.append(rec)
        self._stage_t0 = time.perf_counter()
        self._stage_step0 = ens.steps_done
        if self.requested == "auto":
            self._auto()

    def _pipelined(self, rec: dict) -> dict:
        ens = self.ens
        if self.pending is None or self.pending_kind != "list":
            self._drop_pending()
            out = self._sync_build()       # semi-parallel stage start (B1, B2)
            out["restart"] = len(self.stages) > 0
            self.restarts += int(out["restart"])
            return out
        t0 = time.perf_counter()
        need, t_cpu = self.pending.result()        # B8
        wait = time.perf_counter() - t0
        self.pending = None
        ens._set_status(K.S_CHECK, 0.0)
        ens.kl["check_snapshot"][ens._grid(ens.n)](ens.n, ens.pos, self.snap, ens.sc, ens.spd, ens.spf, ens.spi,
                                                   ens.status)
        h = ens._read_status_now()                  # B9, B10
        if h[K.S_CHECK] >= 1.0 or need > self._host["nbr"].shape[0]:
            out = self._sync_build()               # grows the list itself when it does not fit
            out["tau_cpu"] += t_cpu
            out.update(wait=wait, restart=True)
            self.restarts += 1
            return out
        ens._compact()
        t_up = self._install(self.snap)             # B11 (x_ref = the snapshot the list was built from)
        t_down = self._launch("list")               # B12: the next list from the current positions
        return {"tau_cpu": t_cpu, "tau_exch": t_up + t_down, "wait": wait}

    def _drop_pending(self) -> None:
        if self.pending is not None:
            self.pending.result()
            self.pending = None

    # ---- automatic choice ---------------------------------------------------------------------------------

    def _take_probe(self) -> None:
        need, t_cpu = self.pending.result()
        self.pending = None
        self._probe = (t_cpu, self._probe_down)

    def _means(self, mode: str, last: int = 8) -> dict | None:
        rows = [r for r in self.stages if r["mode"] == mode and r["steps"] > 0][-last:]
        if not rows:
            return None
        steps = sum(r["steps"] for r in rows)
        return {k: sum(r[k] for r in rows) / len(rows) for k in ("tau_gpu", "tau_cpu", "tau_exch", "tau_build",
                                                                  "wall")} | {"per_step": sum(
                                                                      r["wall"] for r in rows) / steps}

    def predict(self) -> dict | None:
        """Seconds per step of each mode from the GPU-list stages and the background CPU build."""
        g = self._means("gpu")
        if g is None or self._probe is None:
            return None
        t_cpu, t_down = self._probe
        ens = self.ens
        list_bytes = self._uploaded_slots * 4 + ens.n * 8
        pos_bytes = 3 * ens.n * np.dtype(ens.pos_dtype).itemsize
        t_exch = t_down * (1.0 + list_bytes / pos_bytes)
        steps = max(1.0, np.mean([r["steps"] for r in self.stages if r["mode"] == "gpu"][-8:]))
        t_gpu = g["tau_gpu"]
        return {"gpu": g["per_step"], "cpu-sequential": (t_gpu + t_cpu + t_exch) / steps,
                "cpu-pipelined": (max(t_gpu, 2.0 * t_cpu) + 2.0 * t_exch) / steps,
                "q": t_cpu / t_gpu if t_gpu > 0 else float("inf")}

    def _auto(self) -> None:
        n_st = len(self.stages)
        if self._trial is not None:
            mode, start = self._trial
            if n_st - start >= TRIAL_STAGES:
                tried = self._means(mode, TRIAL_STAGES)
                g = self._means("gpu")
                keep = tried is not None and g is not None and tried["per_step"] < g["per_step"]
                self.decisions.append((self.ens.steps_done, mode if keep else "gpu",
                                       {"measured " + mode: tried and tried["per_step"],
                                        "measured gpu": g and g["per_step"]}))
                if not keep:
                    self._switch("gpu")
                self._trial = None
                self._next_probe = n_st + REPROBE
            return
        if self.mode != "gpu":
            return
        if n_st >= self._next_probe and self.pending is None:
            if not self._worth_probing():
                self._next_probe = n_st + REPROBE
                return
            # timing only: the GPU list stays; radii in the slot order of this moment (the GPU re-sorts)
            self._prepare()
            self._probe_down = self._launch("probe")
            self._next_probe = n_st + REPROBE
            return
        if self._probe is not None:
            p = self.predict()
            self._probe = None
            if p is None:
                return
            best = min(("cpu-sequential", "cpu-pipelined"), key=lambda m: p[m])
            if p[best] > (1.0 - SWITCH_MARGIN) * p["gpu"]:
                best = "gpu"
            self.decisions.append((self.ens.steps_done, best, p))
            if best != "gpu":
                self._switch(best)
                self._trial = (best, len(self.stages))

    def _worth_probing(self) -> bool:
        """Whether the rest of the run is long enough to repay a probe and a trial (module docstring)."""
        g = self._means("gpu")
        left = self.ens.steps_left()
        if g is None or left is None:
            return False
        steps_per_stage = max(1.0, float(np.mean([r["steps"] for r in self.stages if r["mode"] == "gpu"][-8:])))
        stages_left = left / steps_per_stage
        if stages_left >= MIN_STAGES_LEFT and left * g["per_step"] >= MIN_WALL_LEFT_S:
            return True
        if not any("skipped probe" in str(d[2]) for d in self.decisions):
            self.decisions.append((self.ens.steps_done, "gpu", {"skipped probe: steps left": int(left),
                                                                "stages left": round(stages_left, 1)}))
        return False

    def _switch(self, mode: str) -> None:
        self._drop_pending()
        self.mode = mode
        if mode != "gpu":
            self._enter_cpu_mode()

    # ---- summary ------------------------------------------------------------------------------------------

    def summary(self) -> dict:
        """Means per mode of tau_GPU, tau_CPU, tau_exch per stage (s), and q = tau_CPU/tau_GPU of that
        mode's stages with G_max(q) (Skorych & Dosta 2022, Eqs. 5, 9; the paper's q is the sequential mode's)."""
        out = {"requested": self.requested, "final_mode": self.mode, "stages": len(self.stages),
               "restarts": self.restarts, "decisions": self.decisions}
        for mode in ("gpu", "cpu-sequential", "cpu-pipelined"):
            m = self._means(mode, last=10 ** 9)
            if m is None:
                continue
            if mode != "gpu" and m["tau_gpu"] > 0:
                m["q"] = m["tau_cpu"] / m["tau_gpu"]
                m["g_max"] = g_max(m["q"])
            out[mode] = m
        return out

    def close(self) -> None:
        self._drop_pending()
        self.pool.shutdown(wait=True)
