"""The shared time-loop machinery that every shape's host classes subclass and call: the CPU loop (cpu.py,
cpu_shared.py), the CUDA ensemble base and its parts (cuda_ensemble.py and the cuda_*.py modules), the status
codes (status.py) and the host-side types (system.py).

Layering (tests/test_imports.py): a shape package (engine/shapes/<pkg>/) builds on this package and never imports
engine.backends; this package imports neither a shape package nor the shape registry engine.shapes (a shape's
classes pass their kernels and device functions in) and, of engine.backends,
only the interfaces (engine/backends/protocol.py) and the types module (engine/backends/base.py); engine.backends
(interfaces, factories, ensembles) imports no shape package.
"""
