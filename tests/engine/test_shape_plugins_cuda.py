"""Every registered shape brings the CUDA parts the one CUDA time loop (engine/loops/cuda_loop.py) needs.

The CUDA simulator must be on before numba.cuda is first imported, so the check runs in a child process.
"""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: the names engine/shapes/sphere/device.py's docstring promises (the interface of make_cuda's result)
PARTS = ("PREDICTS", "TORQUE", "NOBS", "OBS_MAX", "translated", "rotate", "spin_kick", "particle", "pair",
         "observe_one", "kernels")


def _child() -> None:
    import numpy as np

    from engine.loops import cuda_kernels, cuda_loop
    from engine.shapes import SHAPES, device

    for name in SHAPES:
        mod = device(name)
        assert isinstance(mod.FLAGS, tuple), name
        for flags in ((False,) * len(mod.FLAGS), (True,) * len(mod.FLAGS)):
            parts = mod.make_cuda(cuda_kernels, np.float64, True, 32, *flags)
            missing = [p for p in PARTS if not hasattr(parts, p)]
            assert not missing, (name, missing)
            assert 0 <= parts.OBS_MAX < parts.NOBS, name
            k = cuda_loop.kernels(name, np.float32, flags, False, 32, mod)
            for kernel in ("kick_drift", "forces", "half_kick", "run_steps", "observe", "build", "compact"):
                assert kernel in k, (name, kernel)
            assert set(parts.kernels) <= set(k), name
    try:
        device("cube")
    except ValueError as e:
        assert "cube" in str(e)
    else:
        raise AssertionError("an unknown shape must be refused")
    print("SHAPES-CUDA-OK")


def test_every_shape_has_its_cuda_parts():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, __file__, "--child"], env=env, cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and "SHAPES-CUDA-OK" in r.stdout, r.stdout + r.stderr


if __name__ == "__main__" and sys.argv[1:] == ["--child"]:
    _child()
