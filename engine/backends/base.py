"""What every backend receives and returns: the system (state arrays in id order) and contact constants.

The shared types (:class:`SphereSystem`, :class:`EllipsoidSystem`, :class:`ContactParams`) and the cell count
rule (:func:`cell_grid`) are defined in engine/loops/system.py and named here too; this module owns the GPU
probe (:func:`cuda_available`). It imports no concrete backend (the factory is engine/backends/registry.py).
A backend is constructed from a :class:`SphereSystem` (host arrays) and a :class:`ContactParams` and implements
engine.backends.protocol.Backend; host copies happen only in ``observe``/``state``/``contacts`` (output steps).
"""

from __future__ import annotations

import os
import sys
import threading
from typing import Optional

from engine.loops.system import ContactParams, EllipsoidSystem, SphereSystem, cell_grid

__all__ = ["ContactParams", "EllipsoidSystem", "SphereSystem", "cell_grid", "cuda_available", "nvidia_driver",
           "no_nvidia_driver"]


#: the answer of the GPU probe in this process (None: not asked yet); a GPU does not come or go while it runs
_cuda_answer: Optional[bool] = None
_cuda_lock = threading.Lock()


#: what a loaded NVIDIA kernel driver creates on Linux (/dev/dxg: WSL's GPU device)
NVIDIA_DRIVER_PATHS = ("/proc/driver/nvidia", "/dev/nvidiactl", "/dev/dxg")


def nvidia_driver() -> bool:
    """An NVIDIA driver is loaded here (Linux, or WSL's GPU device)."""
    return any(os.path.exists(p) for p in NVIDIA_DRIVER_PATHS)


def no_nvidia_driver() -> bool:
    """Linux without a loaded NVIDIA driver: no CUDA GPU can be used, which :func:`cuda_available` then answers
    without importing numba-cuda (0.2 s of a CPU job's set-up). Other systems: False (ask numba-cuda)."""
    return sys.platform.startswith("linux") and not nvidia_driver()


def gpu_total_memory() -> Optional[int]:
    """Bytes of memory of the first GPU this process sees (CUDA_VISIBLE_DEVICES' first entry, else GPU 0), read
    with nvidia-smi so that no CUDA context is made; None when it cannot be read."""
    import subprocess

    first = os.environ.get("CUDA_VISIBLE_DEVICES", "0").split(",")[0].strip() or "0"
    try:
        out = subprocess.run(["nvidia-smi", f"--id={first}", "--query-gpu=memory.total",
                              "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=10, check=True).stdout
        return int(float(out.split()[0]) * 2**20)    # MiB
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return None


def cuda_available() -> bool:
    """True when a real CUDA GPU can be used (the simulator does not count).

    Asked once per process: the first call imports numba.cuda and starts the CUDA driver; a call from a
    second thread while the first is under way waits for its answer (engine/driver/startup.py asks from a
    background thread while the job's host thread places particles).
    """
    global _cuda_answer
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" or no_nvidia_driver():
        return False
    with _cuda_lock:
        if _cuda_answer is None:
            try:
                from engine.numba_support.numba_import import coverage_hidden

                with coverage_hidden():
                    from numba import cuda
                _cuda_answer = bool(cuda.is_available())
            except Exception:  # numba-cuda missing or no driver
                _cuda_answer = False
        return _cuda_answer
