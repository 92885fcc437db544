"""Host-side helpers the CUDA backends share and none owns (engine/loops/cuda_ensemble.py and its parts,
cuda_listmodes.py).

Kept apart so that cuda_listmodes.py (the CPU-built list modes, which cuda.py loads) does not import
cuda.py back.
"""

from __future__ import annotations

from engine.loops.cuda_cache import SIM


def copy_device(dst, src, stream) -> None:
    """Device-to-device copy of equal-shape contiguous arrays on ``stream`` (no host round trip): through the driver
    call itself on a GPU (engine.numba_support.numba_internals.async_copy_device), numba-cuda's copy under the
    simulator."""
    if SIM:
        dst.copy_to_device(src, stream=stream)
        return
    from engine.numba_support.numba_internals import async_copy_device

    async_copy_device(dst, src, stream)
