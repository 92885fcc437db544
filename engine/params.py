"""Derived parameters of a spec: particle size, mass, inertia, contact constants, time step.

Paper 001 (Hidalgo et al. 2013) and PHYSICS-NOTES §1:
- normal spring-dashpot m12 d''+ gamma_n d' + k_n d = 0, contact ending when the overlap returns to
  zero (rule (a)); t_c = pi sqrt(m12/k_n) (elastic contact time, DESIGN §2);
- gamma_n = sqrt(4 k_n m12 / ((pi/ln(1/e_n))^2 + 1))            (paper 001, text after Eq. 3);
- k_t = k_n q/(1+q) (arccos(-e_t)/pi)^2, q = 2/5                  (paper 001 Eq. 4).
Eq. 4 is exact only for gamma_n = 0: with damping the contact lasts pi/omega instead of pi/omega_0 and
the spring model yields e_t,eff = -cos(arccos(-e_t) sqrt(1 + (ln e_n / pi)^2)) (PHYSICS-NOTES §1.2),
which is what the theory is compared with.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

#: Moment-of-inertia factor of a solid sphere, I = q m a^2.
Q_SPHERE = 0.4


def radius_from_volume_fraction(n: int, phi: float, box_length: float) -> float:
    """Radius in m of N equal spheres that fill a fraction phi of a cube of edge L."""
    return (3.0 * phi * box_length**3 / (4.0 * math.pi * n)) ** (1.0 / 3.0)


def gamma_n_from_restitution(e_n: float, k_n: float, m12: float) -> float:
    """Normal damping gamma_n in kg/s giving restitution e_n (paper 001; exact for rule (a))."""
    if e_n >= 1.0:
        return 0.0
    return math.sqrt(4.0 * k_n * m12 / ((math.pi / math.log(1.0 / e_n)) ** 2 + 1.0))


def k_t_paper(e_t: float, k_n: float, q: float = Q_SPHERE) -> float:
    """Tangential stiffness in N/m by paper 001 Eq. 4 (0 for smooth particles, e_t = -1)."""
    return k_n * q / (1.0 + q) * (math.acos(-e_t) / math.pi) ** 2


def e_t_effective(e_n: float, e_t: float) -> float:
    """Tangential restitution that the Eq.-4 spring actually produces for sticking contacts.

    Eq. 4 assumes the contact lasts pi/omega_0; with damping it lasts pi/omega with
    omega = omega_0 / sqrt(1 + (ln e_n/pi)^2), so the tangential oscillator turns through a larger
    angle: e_t,eff = -cos(arccos(-e_t) sqrt(1 + (ln e_n/pi)^2))  (PHYSICS-NOTES §1.2).
    """
    if e_t <= -1.0:
        return -1.0
    stretch = math.sqrt(1.0 + (math.log(e_n) / math.pi) ** 2)
    return -math.cos(math.acos(-e_t) * stretch)


def carnahan_starling_g(phi: float) -> float:
    """Pair correlation at contact g(2a) = (1 - phi/2)/(1 - phi)^3 (Carnahan-Starling)."""
    return (1.0 - 0.5 * phi) / (1.0 - phi) ** 3


@dataclass(frozen=True)
class Derived:
    """Derived parameters in SI units (lengths m, masses kg, times s)."""

    radius: float          # sphere radius, or volume-equivalent radius of an ellipsoid
    semi_axes: tuple       # (a, b, c); a along the body axis, b = c for prolate spheroids
    radius_max: float      # bounding-sphere radius (largest semi-axis)
    radius_min: float      # smallest semi-axis
    mass: float
    inertia: tuple         # principal moments (I_1, I_2, I_3) about the body axes
    m12: float             # reduced mass of an equal pair
    omega0: float          # undamped contact frequency sqrt(k_n/m12), 1/s
    contact_time: float    # t_c = pi/omega0, s
    gamma_n: float         # kg/s
    gamma_n_coef: float    # gamma_n / sqrt(m12): gamma of any pair = coef * sqrt(m12_pair)
    k_n: float
    k_t: float
    e_t_effective: float
    dt: float
    n_steps: int           # cooling-run steps
    output_every: int      # steps between observable records
    number_density: float  # N/V, 1/m^3
    temperature0: float    # m v_rms^2 / 3 (J), translational temperature at the start
    collision_rate0: float # Enskog collision frequency per particle at the start, 1/s
    t_thermalization: float
    n_thermalization_steps: int
    skin: float            # Verlet skin L_v in m
    cutoff: float          # neighbour-list cutoff 2 a_max + L_v in m

    def as_dict(self) -> dict:
        return asdict(self)


def derive(spec) -> Derived:
    """Compute every derived parameter of a spec (a SimulationSpec or anything with its fields)."""
    n, L, phi = spec.n_particles, spec.box_length, spec.volume_fraction
    r_eq = radius_from_volume_fraction(n, phi, L)
    volume = 4.0 / 3.0 * math.pi * r_eq**3
    mass = spec.density * volume
    xi = spec.elongation
    if spec.shape == "sphere":
        semi = (r_eq, r_eq, r_eq)
        inertia = (Q_SPHERE * mass * r_eq**2,) * 3
    else:
        # prolate spheroid with a*b^2 = r_eq^3 (paper 003 Table 1 keeps the volume fixed)
        b = r_eq / xi ** (1.0 / 3.0)
        a = xi * b
        semi = (a, b, b)
        i_perp = mass * (a * a + b * b) / 5.0
        inertia = (2.0 * mass * b * b / 5.0, i_perp, i_perp)
    m12 = 0.5 * mass
    k_n = spec.stiffness
    omega0 = math.sqrt(k_n / m12)
    t_c = math.pi / omega0
    gamma_n = gamma_n_from_restitution(spec.e_n, k_n, m12)
    smooth = spec.e_t == -1.0 or spec.friction == 0.0
    k_t = 0.0 if smooth else k_t_paper(spec.e_t, k_n)
    dt = spec.dt if spec.dt is not None else t_c / 50.0
    n_steps = max(1, int(round(spec.t_end / dt)))
    out_dt = spec.output_interval if spec.output_interval is not None else spec.t_end / 200.0
    output_every = max(1, min(n_steps, int(round(out_dt / dt))))
    nd = n / L**3
    t0 = mass * spec.velocity_rms**2 / 3.0
    g = carnahan_starling_g(phi)
    # Enskog collision frequency per particle, omega_E = 4 (2a)^2 n g sqrt(pi T/m) (PHYSICS-NOTES §2.1);
    # for spheroids the orientation-averaged excluded surface replaces (2a)^2 at leading order.
    sigma2 = (2.0 * r_eq) ** 2
    rate0 = 4.0 * sigma2 * nd * g * math.sqrt(math.pi * t0 / mass)
    t_th = spec.thermalization / rate0 if spec.thermalization > 0 else 0.0
    n_th = int(math.ceil(t_th / dt)) if t_th > 0 else 0
    from engine.spec import default_verlet_skin  # null skin: the default of spec.backend (resolved by the driver)
    skin = (spec.verlet_skin if spec.verlet_skin is not None else default_verlet_skin(spec.backend, spec.shape)) \
        * semi[1 if spec.shape == "ellipsoid" else 0]
    return Derived(
        radius=r_eq, semi_axes=semi, radius_max=max(semi), radius_min=min(semi), mass=mass,
        inertia=inertia, m12=m12, omega0=omega0, contact_time=t_c, gamma_n=gamma_n,
        gamma_n_coef=gamma_n / math.sqrt(m12), k_n=k_n, k_t=k_t,
        e_t_effective=-1.0 if smooth else e_t_effective(spec.e_n, spec.e_t), dt=dt,
        n_steps=n_steps, output_every=output_every, number_density=nd, temperature0=t0,
        collision_rate0=rate0, t_thermalization=t_th, n_thermalization_steps=n_th, skin=skin,
        cutoff=2.0 * max(semi) + skin)


#: Rough upper bound of device/host memory per particle in bytes (state, lists, history), used to
#: refuse oversize specs before they are queued. float64: ~25 doubles of state + 32 list entries.
def estimate_bytes_per_particle(precision: str) -> int:
    word = 8 if precision == "float64" else 4
    state = 25 * word                     # x, v, omega, q, F, tau, x_ref, mass, inertia, radius
    lists = 32 * (4 + 3 * word)           # neighbour index + tangential history per list slot
    return state + lists + 16             # cell index, order


def estimate_cost(spec) -> dict:
    """Memory (bytes) and work (particle-steps) a spec will need; used to refuse oversize jobs."""
    p = derive(spec)
    steps = p.n_steps + p.n_thermalization_steps
    return {
        "memory_bytes": spec.n_particles * estimate_bytes_per_particle(spec.precision),
        "particle_steps": spec.n_particles * steps,
        "steps": steps,
    }
