"""Work on a large array in pieces on a few threads (the output path of large scenes).

NumPy releases the GIL in its array loops, so a per-piece function made of NumPy calls (a finite check, a strided
write that faults pages in) runs on up to 8 cores at once. One pool per process, started on first use.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

#: elements per piece (16 MB of float64)
PIECE = 1 << 21
#: a frame of more particles is copied off the GPU and written in pieces of this many particles, each one chunk of
#: its dataset (engine/output/writers/snapshots.py): neither the device's staging buffer nor the host holds the
#: whole frame (a billion float32 spheres: 36 GB a frame)
FRAME_PIECE_ROWS = 1 << 24

_lock = threading.Lock()
_pool = None


def map_pieces(a: np.ndarray, fn: Callable[[np.ndarray], object], piece: int = PIECE) -> list:
    """[fn(p) for p in the pieces of a's flat view] (``a`` must be contiguous for ``fn`` to write into it); pieces
    of about ``piece`` elements, on the pool's threads; an array of one piece on the caller's thread."""
    global _pool
    flat = a.reshape(-1)
    count = -(-flat.size // max(1, piece))
    if count <= 1:
        return [fn(flat)]
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1), thread_name_prefix="demq-pieces")
    return list(_pool.map(fn, np.array_split(flat, count)))
