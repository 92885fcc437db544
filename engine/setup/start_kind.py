"""Which start a spec gets, how it is drawn, and how much thermalisation it needs (engine/setup/scene.py draws it;
no numba here: engine/driver/startup.py asks before numba is imported). docs/physics.md §5 explains the protocols.

Two protocols place the particles (``spec.start``):

- ``"random"``: uniform random non-overlapping positions by random sequential addition (RSA). At the
  densities of a granular gas this is close to the equilibrium hard-sphere gas: its pair correlation at
  contact is g_RSA(sigma) ~ 1 + (5/3) phi against the Carnahan-Starling value 1 + (5/2) phi + O(phi^2).
  With Maxwellian velocities and spins it needs no thermalisation where that difference is small.
- ``"lattice"``: the sites of an fcc lattice with a random displacement each (the protocol of the rough-sphere
  cooling papers), which must be melted by ``thermalization`` collisions per particle of elastic dynamics.

``spec.start = null`` picks ``"random"`` wherever RSA is cheap (one-size particles of a shape whose trait
``RANDOM_START`` says so, spheres and spheroids, whose bounding spheres' volume fraction phi xi^2 is at most
RANDOM_MAX_VOLUME_FRACTION, at any N: from PARALLEL_START_MIN particles on it is placed in parallel,
engine/setup/cell_rsa.py, which places every spheroid start; every species spec), ``"lattice"`` otherwise (denser
gases).
``spec.thermalization = null`` is what that start needs (:func:`thermalization_collisions`).
"""

from __future__ import annotations


from engine.setup.scales import species_table
from engine.shapes import traits

#: one-size starts of at least this many particles are drawn in parallel (engine/setup/scene.py's docstring)
PARALLEL_START_MIN = 1 << 20
SEQUENTIAL_GENERATOR = "numpy-pcg64"
PARALLEL_GENERATOR = "splitmix64-counter"
#: a random start of at least PARALLEL_START_MIN one-size spheres: random sequential addition in cell rounds from
#: the same counter-based draws (engine/setup/cell_rsa.py), on the host or the GPU alike
PARALLEL_RSA_GENERATOR = "splitmix64-cell-rsa"
#: False: large starts are drawn on the host even for a GPU job (bench/e2e.py ``--off device_start`` sets it, for
#: A/B timings)
DEVICE_START = True

RANDOM = "random"
LATTICE = "lattice"
#: densest random (RSA) start: RSA jams near phi = 0.38 and slows down long before
RANDOM_MAX_VOLUME_FRACTION = 0.30
#: thermalisation of a lattice start, collisions per particle (melts the lattice: docs/physics.md §5)
LATTICE_THERMALIZATION = 1.0
#: a random start of at most this volume fraction is already an equilibrium gas: its g(sigma) is within
#: 1.5 % of Carnahan-Starling, and the difference relaxes within a small fraction of a collision
RANDOM_EQUILIBRIUM_MAX_VOLUME_FRACTION = 0.02
#: (volume fraction up to which, collisions per particle) that relax a random start's contact structure,
#: measured (docs/physics.md §5): the RSA deficit in g(sigma) is gone after ~0.1 collisions at phi = 0.058-0.1
#: (0.25 keeps a factor of two), and needs about one collision at phi = 0.2
RANDOM_RELAXATION = ((RANDOM_EQUILIBRIUM_MAX_VOLUME_FRACTION, 0.0), (0.1, 0.25), (RANDOM_MAX_VOLUME_FRACTION, 1.0))


def start_protocol(spec) -> str:
    """The placement a spec gets: its own ``start``, or for ``start = null`` "random" where RSA is cheap and
    "lattice" elsewhere (module docstring)."""
    if spec.start is not None:
        return spec.start
    if species_table(spec) is not None:
        return RANDOM
    if traits(spec.shape).RANDOM_START and spec.volume_fraction * spec.elongation ** 2 <= RANDOM_MAX_VOLUME_FRACTION:
        return RANDOM
    return LATTICE


def thermalization_collisions(spec) -> float:
    """Collisions per particle of elastic dynamics run before t = 0: the spec's own ``thermalization``, or for
    null what its start needs: none for a random start that is already an equilibrium gas, a short relaxation
    of a denser one's contact structure, and one collision to melt a lattice."""
    if spec.thermalization is not None:
        return float(spec.thermalization)
    if start_protocol(spec) == LATTICE:
        return LATTICE_THERMALIZATION
    return next(collisions for phi, collisions in RANDOM_RELAXATION if spec.volume_fraction <= phi)


def start_generator(spec) -> str:
    """Which generator draws a spec's start: the sequential NumPy one, or for N >= PARALLEL_START_MIN one-size
    particles the parallel counter-based one: the lattice protocol's, or a random start's random sequential addition
    in cell rounds (species starts are sequential RSA at any N). A smaller random spheroid start draws its velocities
    and spins from NumPy and its centres and orientations by the same cell rounds on one thread."""
    if species_table(spec) is not None or spec.n_particles < PARALLEL_START_MIN:
        return SEQUENTIAL_GENERATOR
    return PARALLEL_GENERATOR if start_protocol(spec) == LATTICE else PARALLEL_RSA_GENERATOR


def device_start(spec) -> bool:
    """Whether a GPU job of ``spec`` draws its start on the device (engine/loops/cuda_start.py): a large one-size
    start of spheres or spheroids (a parallel generator's), unless :data:`DEVICE_START` is False."""
    return DEVICE_START and start_generator(spec) in (PARALLEL_GENERATOR, PARALLEL_RSA_GENERATOR)
