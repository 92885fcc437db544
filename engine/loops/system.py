"""The host-side types every backend receives: the system (state arrays in id order) and the contact constants.

:class:`SphereSystem`, :class:`EllipsoidSystem` (host arrays, SI units), :class:`ContactParams` and the cell
count rule :func:`cell_grid`. A neutral module (engine/loops/): shape packages, the shared machinery and the
backends all import it; engine.backends.base re-exports these names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar, Optional

import numpy as np


def rows_equal(a) -> bool:
    """Whether every row of ``a`` (axis 0) equals its first: True at once for an empty array or a broadcast view
    along axis 0 (stride 0: one row stored), otherwise by comparing them."""
    a = np.asarray(a)
    return a.shape[0] == 0 or a.strides[0] == 0 or bool(np.all(a == a[0]))


@dataclass
class SphereSystem:
    """Host-side state of N spheres in a periodic cube, SI units, rows in particle-id order.

    position (N,3) m in [0, L); velocity (N,3) m/s; angular_velocity (N,3) rad/s (space frame);
    orientation (N,4) unit quaternions (w,x,y,z), body -> space; radius, mass, inertia (N,) m, kg, kg m^2 (a
    one-size start may hold them as read-only broadcast views of one value: :func:`rows_equal` reads that without
    scanning).
    contact_pairs (M,2) int64 ids (i, j) and contact_springs (M,3) m: tangential springs of contacts
    carried over from a checkpoint (both orderings present); empty for a fresh start.
    draw: a large start still to be drawn on the GPU (engine.setup.scene.StartDraw; the GPU backend draws it when it is
    built, engine/loops/cuda_start.py); position, velocity, angular_velocity and orientation are then None.
    Only the CUDA backend takes such a system (engine.setup.scene.drawn_on_host gives the arrays).
    """

    #: the shape (engine/shapes/ registry key) whose plug-in runs this system
    shape: ClassVar[str] = "sphere"
    box_length: float
    position: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    orientation: np.ndarray
    radius: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    contact_pairs: Optional[np.ndarray] = None
    contact_springs: Optional[np.ndarray] = None
    draw: Optional[object] = None

    @property
    def n(self) -> int:
        return self.draw.n if self.position is None else self.position.shape[0]


@dataclass
class EllipsoidSystem:
    """Host-side state of N ellipsoids (Rubio-Largo et al. 2015), SI units, rows in particle-id order.

    As :class:`SphereSystem`, with semi_axes (N,3) m (a, b, c along the body axes x, y, z; prolate
    spheroids: a >= b = c) and inertia (N,3) kg m^2, the principal moments about the body axes.
    angular_velocity is in the space frame. contact_pairs/contact_springs: contact slots carried over
    from a checkpoint (overlap and dashpot force in columns 3, 4), empty for a fresh start. draw: as
    :class:`SphereSystem`'s (a large start drawn by the GPU backend; the state arrays are then None).
    """

    shape: ClassVar[str] = "ellipsoid"
    box_length: float
    position: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    orientation: np.ndarray
    semi_axes: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    contact_pairs: Optional[np.ndarray] = None
    contact_springs: Optional[np.ndarray] = None
    draw: Optional[object] = None

    @property
    def n(self) -> int:
        return self.draw.n if self.position is None else self.position.shape[0]


@dataclass(frozen=True)
class ContactParams:
    """Contact constants and numerics. k_t = None: smooth (no tangential force, no torque).

    friction = None: no Coulomb limit. gamma_n of a pair is gamma_n_coef * sqrt(m12) (kg/s).
    orientation: integrate quaternions (only needed for output or non-spherical shapes).
    """

    k_n: float
    gamma_n_coef: float
    k_t: Optional[float]
    friction: Optional[float]
    dt: float
    skin: float
    precision: str = "float64"
    orientation: bool = True
    overlap_limit: float = 0.05
    #: where a CUDA backend builds the Verlet list: 'gpu', 'cpu-sequential', 'cpu-pipelined', 'auto'
    #: (Skorych & Dosta 2022, §3; engine/loops/cuda_listmodes.py); the CPU backend always builds on the CPU
    list_mode: str = "gpu"

    @property
    def rough(self) -> bool:
        return self.k_t is not None

    def with_(self, **kw) -> "ContactParams":
        return replace(self, **kw)


def cell_grid(box: float, n: int, rmax: float, skin: float) -> int:
    """Cells per box edge for the neighbour build: edge >= 2 a_max + L_v (Skorych & Dosta 2022), at most ~(2N)^(1/3).

    Very dilute scenes would otherwise spend memory and build time on empty cells; cells may be larger
    than the cutoff, never smaller. Every backend bins with this so they order neighbours alike.
    """
    cutoff = 2.0 * rmax + skin
    nc = max(1, int(box / cutoff))
    nc = max(1, min(nc, int(round((2.0 * n) ** (1.0 / 3.0))) + 1))
    while nc > 1 and box / nc < cutoff:
        nc -= 1
    return nc


#: the cooperative many-steps-per-launch loop is used up to this many particles (all scenes together), the
#: per-phase loop above: measured on an H200 (bench/gpu_ensemble.py) 10x faster at 4096 and 2x at 2^18 (64 packed
#: scenes; 2026-11-21, when a per-phase step cost the host about 170 us); at 2^20 the per-phase loop is the faster one
#: on an H100 (bench/loop_ab.py --variants default multistep, docs/performance.md "Packed ensembles": one scene x1.4
#: rough, x1.75 elastic, x1.3 rough spheroids; 256 packed scenes x1.7 rough, x2.2 elastic), and at 2^19 on an H200
#: (2026-11-30, one scene, float64, phi = 0.058: x1.7 elastic, x1.8 rough; bench/loop_ab.py --cases elastic-2M-f64
#: rough-2M-f64 --n 524288 --variants multistep_on default): a grid of co-resident blocks loops over many particles
#: per thread. Below 2^19 see the next two.
MULTISTEP_MAX_PARTICLES = (1 << 19) - 1
#: ... and from this many particles the per-phase loop for one scene of spheres filling at least PER_PHASE_DENSE_PHI of
#: the volume: the more neighbours a particle has, the longer each phase keeps the GPU busy against the per-phase loop's
#: fixed host work a step, while the many-steps loop runs its phases on the co-resident blocks alone. H200, 2026-11-30,
#: 2^18 spheres, float64 unless named, two runs each, per phase against many steps (bench/loop_ab.py --n 262144 --phi
#: PHI --variants default multistep): phi = 0.2 elastic x1.25, x1.37, rough x1.01, x1.25, float32 elastic x1.47, x0.95,
#: rough x1.15, x1.00; phi = 0.15 elastic x1.43, x1.00, rough x1.23, x1.36; phi = 0.1 elastic x0.99, x1.14, rough x0.84,
#: x0.79; phi = 0.058 elastic x0.96, x0.96, rough x0.67, x0.78. At 2^17 and phi = 0.2 the many-steps loop still wins
#: (elastic x0.88, x0.84, rough x0.60, x0.88); so it does for 64 packed rough scenes of 4096 at phi = 0.2 (x0.71, x0.81
#: per phase; elastic x1.27, x1.19): packs keep the size rule.
PER_PHASE_DENSE_PARTICLES = 1 << 18
PER_PHASE_DENSE_PHI = 0.15


def many_steps_loop(n: int, volume_fraction: Optional[float] = None) -> bool:
    """Whether a CUDA ensemble of ``n`` particles (all its scenes) runs the cooperative many-steps loop rather than
    the per-phase loop: up to MULTISTEP_MAX_PARTICLES, except from PER_PHASE_DENSE_PARTICLES on for one scene of
    spheres at a ``volume_fraction`` (None: not known, several scenes, or not spheres) of at least
    PER_PHASE_DENSE_PHI."""
    if n > MULTISTEP_MAX_PARTICLES:
        return False
    dense = volume_fraction is not None and volume_fraction >= PER_PHASE_DENSE_PHI
    return not (dense and n >= PER_PHASE_DENSE_PARTICLES)


def ensemble_many_steps_loop(systems) -> bool:
    """:func:`many_steps_loop` of the scenes ``systems`` packed into one CUDA ensemble: the volume fraction counts for
    one scene only (packed rough scenes ran slower per phase), and is summed only where it decides (a mixture's radii
    are summed one by one)."""
    n = sum(s.n for s in systems)
    near = len(systems) == 1 and PER_PHASE_DENSE_PARTICLES <= n <= MULTISTEP_MAX_PARTICLES
    return many_steps_loop(n, sphere_volume_fraction(systems[0]) if near else None)


def sphere_volume_fraction(system) -> Optional[float]:
    """The volume fraction of a scene of spheres (its spheres' volume over its box's), None for another shape."""
    if system.shape != "sphere":
        return None
    r = np.asarray(system.radius, np.float64)
    cubes = len(r) * float(r[0]) ** 3 if len(r) and rows_equal(r) else float(np.sum(r ** 3))
    return 4.0 / 3.0 * math.pi * cubes / float(system.box_length) ** 3
