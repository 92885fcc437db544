"""The warm-up (jobs/warm.py, `demq warm`): every kernel specialisation compiled into numba's disk cache before the
first job, so that a job in a fresh process compiles nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jobs.warm import PRECISIONS, specialisations

ROOT = Path(__file__).resolve().parents[2]

#: a job unlike the warm-up's tiny scene in every run-time value (N, phi, e_n, friction, thermalisation, output),
#: of a specialisation the warm-up covers (CPU, sphere, float64, rough with friction, one size); the probe also
#: loads a large start's functions (engine.setup.scene.load_parallel_start), as a job of 10^5 spheres would
JOB = {"n_particles": 300, "volume_fraction": 0.08, "box_length": 0.8, "e_n": 0.7, "e_t": 0.5, "friction": 0.3,
       "t_end": 0.003, "thermalization": 0.5, "snapshots": 2, "seed": 5, "backend": "cpu", "precision": "float64"}

PROBE = r"""
import json, sys, tempfile
from numba.core import event
compiled = []
class Listener(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)
    def on_end(self, ev):
        pass
event.register("numba:compile", Listener())
from engine.setup.params import derive
from engine.setup.scene import load_parallel_start
from engine.driver.simulate import run
from engine.setup.spec import SimulationSpec
spec = SimulationSpec.model_validate(json.loads(sys.argv[1]))
summary = run(spec, tempfile.mkdtemp() + "/job.h5")
load_parallel_start(spec, derive(spec))
print(json.dumps({"compiled": compiled, "compile_s": summary.extra["timings"]["compile"]}))
"""


def test_specialisations_are_every_variant_the_engine_accepts():
    sp = specialisations(["cpu", "cuda"])
    names = {s.name() for s in sp}
    # spheres: 3 precisions x 3 contact laws x (one size, species); spheroids refuse species and mixed precision
    assert len([s for s in sp if s.shape == "sphere"]) == 2 * len(PRECISIONS) * 3 * 2
    assert len([s for s in sp if s.shape == "ellipsoid"]) == 2 * 2 * 3
    assert {"cpu/sphere/mixed/friction/species", "cuda/ellipsoid/float32/smooth/uniform"} <= names
    assert not any(s.shape == "ellipsoid" and (s.sizes == "species" or s.precision == "mixed") for s in sp)
    assert [s.name() for s in specialisations(["cpu"], ["sphere"], ["float32"])] == [
        f"cpu/sphere/float32/{law}/{sizes}" for law in ("rough", "smooth", "friction")
        for sizes in ("uniform", "species")]


def _env(cache: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache), "NUMBA_NUM_THREADS": "1"}


@pytest.mark.heavy   # compiles six kernels into an empty cache: about a minute on 2 cores
def test_warm_fills_the_cache_so_that_a_job_in_a_fresh_process_compiles_nothing(tmp_path):
    cache = tmp_path / "numba-cache"   # empty: everything the job needs must come from the warm-up
    warm = [sys.executable, "-m", "service.cli", "warm", "--backend", "cpu", "--shape", "sphere",
            "--precision", "float64"]
    first = subprocess.run(warm, cwd=ROOT, env=_env(cache), capture_output=True, text=True, timeout=1800)
    assert first.returncode == 0, first.stderr[-3000:]
    line = first.stdout.strip().splitlines()[-1]
    assert line.startswith("warm: 6 kernels in ") and "failed" not in line, line
    assert int(line.split("(")[1].split()[0]) > 0      # it compiled (an empty cache)

    # the small job's time loop (no parallel regions) and a larger one's (parallel regions: engine/loops/cpu.py
    # SERIAL_LOOP_BELOW), each in a fresh process
    for job in (JOB, {**JOB, "n_particles": 2048, "box_length": 1.6}):
        probe = subprocess.run([sys.executable, "-c", PROBE, json.dumps(job)], cwd=ROOT, env=_env(cache),
                               capture_output=True, text=True, timeout=600)
        assert probe.returncode == 0, probe.stderr[-3000:]
        got = json.loads(probe.stdout.strip().splitlines()[-1])
        assert got["compiled"] == [], job   # every function the job called was loaded from the warm-up's cache

    again = subprocess.run(warm, cwd=ROOT, env=_env(cache), capture_output=True, text=True, timeout=1800)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "(0 functions compiled" in again.stdout, again.stdout


def test_warm_in_a_process_of_its_own_reports_and_a_stop_ends_it():
    """The worker's form: the warm-up in a spawned process (the worker holds no compiled code, no GPU context);
    its report comes back; a worker stopping meanwhile ends it (no report)."""
    import threading

    from jobs.warm import warm_in_process

    report = warm_in_process(["cpu"], shapes=["sphere"], precisions=["float64"])
    assert report is not None and report.kernels == 6 and not report.failed
    assert report.line().startswith("warm: 6 kernels in ")
    stop = threading.Event()
    stop.set()
    assert warm_in_process(["cpu"], stop=stop) is None


@pytest.mark.heavy   # compiles twelve CPU specialisations in two processes: about two minutes on 2 cores
def test_a_warm_up_in_several_processes_leaves_every_specialisation_loadable(tmp_path):
    """The parallel form (a host of many cores): two spawned processes compile the float64 and float32 groups, then
    the last pass in this process loads all twelve from the cache; a second warm-up compiles nothing."""
    code = ("import json, sys; from jobs.warm import warm; r = warm(['cpu'], ['sphere'], ['float64', 'float32'], "
            "processes=2); print(json.dumps([r.kernels, r.compiled, r.failed]))")
    runs = []
    for _ in range(2):
        p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=_env(tmp_path / "numba-cache"),
                           capture_output=True, text=True, timeout=1800)
        assert p.returncode == 0, p.stderr[-3000:]
        runs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    (kernels, compiled, failed), again = runs
    assert kernels == 12 and failed == [] and compiled > 0, runs[0]
    assert again == [12, 0, []], again


def test_the_warm_up_runs_in_one_process_on_a_small_machine(monkeypatch):
    import jobs.warm as w

    monkeypatch.setattr(w.os, "cpu_count", lambda: 2)
    assert w.warm_processes(48) == 1
    monkeypatch.setattr(w.os, "cpu_count", lambda: 16)
    assert w.warm_processes(48) == 8 and w.warm_processes(3) == 3


def _state(pid: int) -> str:
    """The process state letter of ``pid`` (R running, S sleeping, T stopped, ...), from /proc."""
    text = Path(f"/proc/{pid}/stat").read_text()
    return text[text.rindex(")") + 2]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc (Linux)")
def test_a_background_warm_up_leads_its_own_low_priority_group_that_pauses_resumes_and_closes(tmp_path):
    """The worker's form (jobs/worker.py): the warm-up beside the claims, in a process group of its own at nice 19,
    stopped (SIGSTOP) while a claim runs, let go again after it, killed with its group when the worker stops."""
    import time

    from jobs.warm import BackgroundWarmUp

    warm_up = BackgroundWarmUp(["cpu"], shapes=["sphere"], precisions=["float32"])
    pid = warm_up._proc.pid
    try:
        deadline = time.monotonic() + 30
        while os.getpgid(pid) != pid or os.getpriority(os.PRIO_PROCESS, pid) != 19:
            assert time.monotonic() < deadline, "the warm-up process formed no group of its own at nice 19"
            time.sleep(0.05)
        assert os.getpgid(pid) != os.getpgid(0)   # a worker's signals to its group never reach the worker
        warm_up.pause()
        assert warm_up.paused
        deadline = time.monotonic() + 10
        while _state(pid) != "T":
            assert time.monotonic() < deadline, "the paused warm-up did not stop"
            time.sleep(0.05)
        time.sleep(0.3)
        assert _state(pid) == "T" and warm_up.running and warm_up.poll(0) is None
        warm_up.resume()
        assert not warm_up.paused
        deadline = time.monotonic() + 10
        while _state(pid) == "T":
            assert time.monotonic() < deadline, "the resumed warm-up stayed stopped"
            time.sleep(0.05)
    finally:
        warm_up.pause()
        warm_up.close()   # from the paused state: SIGKILL to the group ends it too
    assert not warm_up.running and not warm_up._proc.is_alive()
