"""Host-side helpers the CUDA backends share and none owns (engine/loops/cuda_ensemble.py and its parts, cuda_listmodes.py).

Kept apart so that cuda_listmodes.py (the CPU-built list modes, which cuda.py loads) does not import
cuda.py back.
"""

from __future__ import annotations


def copy_device(dst, src, stream) -> None:
    """Device-to-device copy of equal-shape arrays on ``stream`` (no host round trip)."""
    dst.copy_to_device(src, stream=stream)
