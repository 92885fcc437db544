"""Former home of the CUDA backend, kept for the names older code imports from it.

The CUDA machinery is in engine/loops/ (the ensemble base engine/loops/cuda_ensemble.py and its parts), the
sphere's CUDA host side in engine/shapes/sphere/cuda_backend.py, reached here through the shape registry (this
module names no shape package: the layer rule of tests/test_imports.py). New code asks the registry
(``engine.shapes.host(shape).cuda_ensemble()``) or builds ensembles with engine.backends.ensemble.make_ensemble.
"""

from engine.loops.cuda_cache import SIM
from engine.loops.cuda_ensemble import CudaEnsembleBase, CudaSceneBackend
from engine.loops.cuda_frames import PIN_AFTER_FRAMES, PINNED_SLOT_BYTES, _page_locked, _touched_empty
from engine.loops.system import MULTISTEP_MAX_PARTICLES
from engine.shapes import host

#: the sphere's packed ensemble and its one-scene backend (engine/shapes/sphere/cuda_backend.py)
CudaEnsemble = host("sphere").cuda_ensemble()
CudaBackend = host("sphere").cuda_backend()

__all__ = ["SIM", "MULTISTEP_MAX_PARTICLES", "PIN_AFTER_FRAMES", "PINNED_SLOT_BYTES", "CudaEnsembleBase",
           "CudaSceneBackend", "CudaEnsemble", "CudaBackend", "_page_locked", "_touched_empty"]
