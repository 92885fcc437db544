"""demq engine: DEM of granular gases (rough spheres, smooth spheroids) on the CPU and the GPU.

Usable alone::

    from engine import SimulationSpec, run
    summary = run(SimulationSpec(n_particles=512, t_end=0.01), "out.h5")
"""

from engine.errors import BackendUnavailable, Cancelled, EngineError, InstabilityError, SpecError
from engine.setup.spec import SimulationSpec, load_spec
from engine.version import __version__


def run(*args, **kwargs):
    """Run a spec and write its HDF5 result; see :func:`engine.driver.simulate.run`."""
    from engine.driver.simulate import run as _run

    return _run(*args, **kwargs)


def run_ensemble(*args, **kwargs):
    """Run several specs as one ensemble, one HDF5 result each; see :func:`engine.driver.ensemble.run_ensemble`."""
    from engine.driver.ensemble import run_ensemble as _run_ensemble

    return _run_ensemble(*args, **kwargs)


__all__ = ["SimulationSpec", "load_spec", "run", "run_ensemble", "EngineError", "SpecError", "InstabilityError",
           "Cancelled", "BackendUnavailable", "__version__"]
