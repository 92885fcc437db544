"""The two interfaces the driver (engine/driver/simulate.py) talks to: :class:`Backend` (one scene) and
:class:`Ensemble` (K scenes advanced together). Every concrete class implements its interface in full: what a class
cannot do (hand out reused state buffers, build lists on the host) it gets as the explicit default of
the base class below, never by the driver probing for a method. tests/engine/test_protocol.py checks every
concrete class against these bases (no abstract method left, the same parameters).

Single backends (engine/shapes/<shape>/cpu_backend.py, the one-scene CUDA adapters
``CudaBackend``) are what :class:`~engine.backends.ensemble.SerialEnsemble` advances one after another; the packed
CUDA ensembles (subclasses of engine.loops.cuda_ensemble.CudaEnsembleBase) are ensembles themselves.
"""

from __future__ import annotations

import abc
from typing import ClassVar, Mapping

from engine.loops.system import ContactParams


class Backend(abc.ABC):
    """One scene: its state, contact constants and time loop.

    Attributes every backend sets: ``name`` ('cpu', 'cuda'), ``device`` (what runs it, in words), ``builds``
    (neighbour-list builds so far), ``steps_done``.
    """

    name: ClassVar[str]
    device: str
    builds: int

    @abc.abstractmethod
    def set_contact(self, contact: ContactParams) -> None:
        """Switch the contact constants (thermalisation -> cooling); keeps lists and springs."""

    @abc.abstractmethod
    def warmup(self) -> None:
        """Compile (or load) the kernels of the current contact constants without advancing."""

    @abc.abstractmethod
    def advance(self, nsteps: int) -> None:
        """Advance nsteps steps; InstabilityError naming the step, the particle and the cause when it blows up."""

    @abc.abstractmethod
    def observe(self) -> dict:
        """The observables of the current state (energies, contacts, overlap, momentum, moments)."""

    @abc.abstractmethod
    def state(self, reuse=False) -> dict:
        """Host copies of the state arrays in particle-id order. ``reuse`` (True or a buffer slot number): the
        arrays may be host buffers that the next call with the same slot overwrites (backends that keep no such
        buffers return copies)."""

    @abc.abstractmethod
    def contacts(self) -> tuple:
        """(pairs (M, 2) int64 ids, history (M, words)) of the list slots in contact."""

    def plan(self, steps: int) -> None:
        """The run goes on for about ``steps`` more steps (the CUDA auto list mode weighs a probe against it).
        Default: not used."""

    def list_info(self) -> dict:
        """Extra run attributes about where the Verlet lists were built (CUDA's host-built list modes). Default:
        none."""
        return {}


class Ensemble(abc.ABC):
    """K independent scenes advanced together (engine/backends/ensemble.py's module docstring).

    Scene indices are the positions of the systems given to the constructor and never change. Attributes every
    ensemble sets: ``name``, ``device``, ``n_scenes``, ``builds`` (neighbour-list builds of all scenes so far).
    """

    name: str
    device: str
    n_scenes: int
    builds: int
    #: True where :meth:`advance_each` advances each scene by its own number of steps (then the driver advances
    #: every scene in exactly the chunks a lone run uses); False: all scenes move together (:meth:`advance`)
    independent_steps: ClassVar[bool] = False
    #: True where one :meth:`observe` of every scene costs about what one scene's does (packed ensembles): the
    #: driver then observes once per round and shares the result between the scenes that stop in it
    shares_observation: ClassVar[bool] = False

    @abc.abstractmethod
    def set_contact(self, k: int, contact: ContactParams) -> None:
        """Contact constants of scene k (thermalisation -> cooling switch)."""

    @abc.abstractmethod
    def warmup(self) -> None:
        """Compile (or load) the kernels for the current contact constants."""

    @abc.abstractmethod
    def advance(self, nsteps: int) -> dict:
        """Advance every active scene by nsteps; {k: error} of the scenes that blew up (deactivated; the others
        complete the nsteps)."""

    @abc.abstractmethod
    def deactivate(self, k: int) -> None:
        """A finished / cancelled / failed scene drops out; it is never advanced again."""

    @abc.abstractmethod
    def observe(self) -> list:
        """Per scene the keys of a single backend's observe(); None for an inactive scene."""

    @abc.abstractmethod
    def state(self, k: int, reuse=False) -> dict:
        """Host copies of scene k's state (``reuse``: see :meth:`Backend.state`)."""

    @abc.abstractmethod
    def contacts(self, k: int) -> tuple:
        """Scene k's contacts as :meth:`Backend.contacts`."""

    def set_contacts(self, contacts: Mapping[int, ContactParams]) -> None:
        """:meth:`set_contact` for several scenes ({scene: contact}); a packed ensemble uploads its tables once."""
        for k, contact in contacts.items():
            self.set_contact(k, contact)

    def advance_each(self, steps: Mapping[int, int]) -> dict:
        """Advance scene k by steps[k]. Default (``independent_steps`` False): every active scene by the same
        count, so the counts given must be equal."""
        counts = {int(n) for n in steps.values() if n > 0}
        if len(counts) > 1:
            raise ValueError(f"{type(self).__name__} advances its scenes together; got different step counts "
                             f"{sorted(counts)}")
        return self.advance(counts.pop()) if counts else {}

    def advance_observing(self, nsteps: int, at) -> tuple:
        """Advance every active scene nsteps steps and observe them after each count of steps in ``at`` (increasing,
        the last one nsteps): ({k: error} of the scenes that blew up, [:meth:`observe` after each count]). Afterwards
        :meth:`observe` answers the last. Default: :meth:`advance` to each count, then :meth:`observe`."""
        check_observation_steps(nsteps, at)
        failed, out, done = {}, [], 0
        for k in at:
            failed.update(self.advance(k - done))
            done = k
            out.append(self.observe())
        return failed, out

    def observes_in_loop(self) -> bool:
        """True where :meth:`advance_observing` sums the observables inside the time loop, so that advancing through
        several records in one call saves the host's stops (one-scene CUDA ensembles of smooth spheres); the driver
        then does (engine/driver/simulate.py). Default: False."""
        return False

    def deactivate_many(self, ks) -> None:
        """Several scenes drop out at once (a packed ensemble does it in one device round trip)."""
        for k in ks:
            self.deactivate(k)

    def observe_scene(self, k: int) -> dict:
        """Scene k's observables (default: from :meth:`observe`)."""
        return self.observe()[k]

    def plan(self, steps: int) -> None:
        """The run goes on for about ``steps`` more steps (see :meth:`Backend.plan`). Default: not used."""

    def scene_builds(self, k: int) -> int:
        """Neighbour-list builds of scene k. Default: the ensemble's count (scenes rebuilt together)."""
        return self.builds

    def scene_info(self, k: int) -> dict:
        """Extra run attributes of scene k for its result file (where a CUDA run built its Verlet lists). Default:
        none."""
        return {}


def check_observation_steps(nsteps: int, at) -> None:
    """ValueError unless the observation steps ``at`` of :meth:`Ensemble.advance_observing` increase from at least 1
    to exactly nsteps."""
    at = [int(k) for k in at]
    if not at or at[0] < 1 or at[-1] != int(nsteps) or any(b <= a for a, b in zip(at, at[1:])):
        raise ValueError(f"observation steps {at} must increase from 1 or more to nsteps = {nsteps}")
