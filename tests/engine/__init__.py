"""Tests of engine/: spec, physics, backends (CPU; CUDA under the simulator), driver."""
