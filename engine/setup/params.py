"""Derived parameters of a spec: particle size, mass, inertia, contact constants, time step, cost estimate.

Owns :func:`derive` (every derived number of a validated spec) and the cost estimate. The sizes, masses
and the contact time that the spec's own checks also need come from engine/setup/scales.py (which imports
neither this module nor engine/setup/spec.py). The default Verlet skin of each backend is here too
(:func:`default_verlet_skin`): :func:`derive` gives the skin of the spec's backend, :func:`with_backend` the
skin of the backend a run resolved ('auto' is resolved by the driver, after the start is placed).

Hidalgo et al. (2013) and docs/physics.md §1:
- normal spring-dashpot m12 d''+ gamma_n d' + k_n d = 0, contact ending when the overlap returns to
  zero (rule (a)); t_c = pi sqrt(m12/k_n) (elastic contact time, docs/physics.md §3.4);
- gamma_n = sqrt(4 k_n m12 / ((pi/ln(1/e_n))^2 + 1))            (Hidalgo et al. 2013, text after Eq. 3);
- k_t = k_n q/(1+q) (arccos(-e_t)/pi)^2, q = 2/5                  (Hidalgo et al. 2013, Eq. 4).
Eq. 4 is exact only for gamma_n = 0: with damping the contact lasts pi/omega instead of pi/omega_0 and
the spring model yields e_t,eff = -cos(arccos(-e_t) sqrt(1 + (ln e_n / pi)^2)) (docs/physics.md §1.3),
which is what the theory is compared with.

Polydisperse spheres (spec ``species``, in its normal form: the largest radius_ratio is 1 and the fractions
sum to 1, engine.setup.spec.normal_species): species k has radius R_k = radius_ratio_k R_max and
count N_k = round(N f_k) (the remainder goes to the species with the largest fraction, the first of
equal ones); R_max follows from the total solid volume sum_k N_k (4/3) pi R_k^3 = phi L^3. Mass
m_k = density (4/3) pi R_k^3, inertia 0.4 m_k R_k^2. Per pair, m12 = m_i m_j/(m_i + m_j) and
gamma_n = gamma_n_coef sqrt(m12) (the backends do this per pair); the shortest contact is the
small-small one, t_c = pi sqrt(m12/k_n) with m12 = m_min/2, and dt = t_c/50 of that pair. In
:class:`Derived`, ``radius``/``mass``/``inertia`` are those of the LARGEST species, ``m12``,
``omega0``, ``contact_time`` and ``gamma_n`` those of the smallest pair, ``mass_mean`` the number mean
<m>; ``species_*`` list every species (one entry for a monodisperse spec). All species start at the
same temperature T0 = <m> v_rms^2 / 3 (equipartition: ``velocity_rms`` is then the mass-weighted rms
speed sqrt(sum m|v|^2 / sum m)). The Verlet skin ``verlet_skin`` is in units of the SMALLEST radius
(for one size: of the radius), so the small particles' lists stay short (Skorych & Dosta 2022: L_v ~ 2 R_min).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Optional

import numpy as np

from engine.setup.precision import float32_reference_skin, position_dtype, state_dtype
from engine.setup.scales import (Q_SPHERE, SpeciesTable, radius_from_volume_fraction, scales,  # noqa: F401
                                 species_counts, species_table)
from engine.setup.start_kind import start_protocol, thermalization_collisions
from engine.shapes import traits


def gamma_n_from_restitution(e_n: float, k_n: float, m12: float) -> float:
    """Normal damping gamma_n in kg/s giving restitution e_n (Hidalgo et al. 2013; exact for rule (a))."""
    if e_n >= 1.0:
        return 0.0
    return math.sqrt(4.0 * k_n * m12 / ((math.pi / math.log(1.0 / e_n)) ** 2 + 1.0))


def k_t_paper(e_t: float, k_n: float, q: float = Q_SPHERE) -> float:
    """Tangential stiffness in N/m by Hidalgo et al. (2013) Eq. 4 (0 for smooth particles, e_t = -1)."""
    return k_n * q / (1.0 + q) * (math.acos(-e_t) / math.pi) ** 2


def e_t_effective(e_n: float, e_t: float) -> float:
    """Tangential restitution that the Eq.-4 spring actually produces for sticking contacts.

    Eq. 4 assumes the contact lasts pi/omega_0; with damping it lasts pi/omega with
    omega = omega_0 / sqrt(1 + (ln e_n/pi)^2), so the tangential oscillator turns through a larger
    angle: e_t,eff = -cos(arccos(-e_t) sqrt(1 + (ln e_n/pi)^2))  (docs/physics.md §1.3).
    """
    if e_t <= -1.0:
        return -1.0
    stretch = math.sqrt(1.0 + (math.log(e_n) / math.pi) ** 2)
    return -math.cos(math.acos(-e_t) * stretch)


def carnahan_starling_g(phi: float) -> float:
    """Pair correlation at contact g(2a) = (1 - phi/2)/(1 - phi)^3 (Carnahan-Starling)."""
    return (1.0 - 0.5 * phi) / (1.0 - phi) ** 3


def bmcsl_g(diameters, number_densities) -> list:
    """Contact values g_ab of the pair correlation of a hard-sphere mixture (Boublik-Mansoori-Carnahan-
    Starling-Leland): g_ab = 1/(1-x3) + 3 x2 D/(1-x3)^2 + 2 x2^2 D^2/(1-x3)^3, D = d_a d_b/(d_a + d_b),
    x_k = (pi/6) sum n_i d_i^k. One species: the Carnahan-Starling (1 - phi/2)/(1 - phi)^3."""
    x2 = math.pi / 6.0 * sum(n * d * d for n, d in zip(number_densities, diameters))
    x3 = math.pi / 6.0 * sum(n * d**3 for n, d in zip(number_densities, diameters))
    out = []
    for da in diameters:
        row = []
        for db in diameters:
            dd = da * db / (da + db)
            row.append(1.0 / (1.0 - x3) + 3.0 * x2 * dd / (1.0 - x3) ** 2 + 2.0 * (x2 * dd) ** 2 / (1.0 - x3) ** 3)
        out.append(row)
    return out


def enskog_rate_mixture(radius, count, mass, volume: float, temperature: float) -> float:
    """Mean Enskog collision frequency per particle (1/s) of a sphere mixture at temperature T (J).

    nu_a = sum_b n_b g_ab pi sigma_ab^2 sqrt(8 T / (pi m_ab)), sigma_ab = R_a + R_b, m_ab the reduced
    mass, g_ab the BMCSL contact value (:func:`bmcsl_g`) at the total volume fraction; the mean over
    particles is sum_a x_a nu_a. One species: 4 (2a)^2 n g sqrt(pi T/m) (docs/physics.md §6.1).
    """
    nd = [c / volume for c in count]
    ntot = sum(count)
    g = bmcsl_g([2.0 * r for r in radius], nd)
    rate = 0.0
    for a in range(len(radius)):
        nu = 0.0
        for b in range(len(radius)):
            sigma = radius[a] + radius[b]
            m_ab = mass[a] * mass[b] / (mass[a] + mass[b])
            nu += nd[b] * g[a][b] * math.pi * sigma**2 * math.sqrt(8.0 * temperature / (math.pi * m_ab))
        rate += count[a] / ntot * nu
    return rate


def list_slots(spec, p=None) -> int:
    """Neighbour-list stride (slots per particle) a spec is expected to need (for the cost estimate).

    Monodisperse: 32 (as before). Species: the largest species has the most neighbours,
    ~ sum_b n_b g_ab (4 pi/3)((sigma_ab + L_v)^3 - sigma_ab^3), i.e. ~ (R_L/R_s)^2 small ones per large
    one; the CPU list has one stride for all particles (= the largest count), so this count with a
    fluctuation margin (1.5 x mean + 4 sqrt(mean) + 8) sets the memory of every particle (the GPU list
    packs its rows: an upper bound there, engine/loops/cuda_memory.py predicts the device's).
    """
    p = p or derive(spec)
    sp = species_table(spec)
    if sp is None:
        return 32
    volume = spec.box_length**3
    nd = [c / volume for c in sp.count]
    g = bmcsl_g([2.0 * r for r in sp.radius], nd)
    a = max(range(len(sp.radius)), key=lambda k: sp.radius[k])
    mean = 0.0
    for b in range(len(sp.radius)):
        sigma = sp.radius[a] + sp.radius[b]
        mean += nd[b] * g[a][b] * 4.0 / 3.0 * math.pi * ((sigma + p.skin) ** 3 - sigma**3)
    return max(32, int(math.ceil(1.5 * mean + 4.0 * math.sqrt(mean) + 8.0)))


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
    thermalization: float  # collisions per particle of elastic dynamics before t = 0 (null resolved)
    t_thermalization: float
    n_thermalization_steps: int
    skin: float            # Verlet skin L_v in m
    cutoff: float          # neighbour-list cutoff 2 a_max + L_v in m
    mass_mean: float = 0.0        # number mean <m> of the particle mass, kg (= mass for one size)
    species_radius: tuple = ()    # per species radius (m); one entry for a monodisperse spec
    species_count: tuple = ()     # per species number of particles
    species_mass: tuple = ()      # per species mass (kg)
    species_inertia: tuple = ()   # per species moment of inertia (kg m^2; spheres: 0.4 m R^2)
    start: str = ""               # placement protocol, "random" or "lattice" (engine/setup/start_kind.py)

    def as_dict(self) -> dict:
        return asdict(self)


def derive(spec) -> Derived:
    """Compute every derived parameter of a spec (a SimulationSpec or anything with its fields)."""
    n, L, phi = spec.n_particles, spec.box_length, spec.volume_fraction
    sc = scales(spec)                 # sizes, masses, contact time, dt (engine/setup/scales.py)
    sp = sc.species                   # None: one size
    r_eq, semi, mass, inertia, m12, mass_mean = sc.radius, sc.semi_axes, sc.mass, sc.inertia, sc.m12, sc.mass_mean
    k_n, omega0, t_c, dt = sc.k_n, sc.omega0, sc.contact_time, sc.dt
    gamma_n = gamma_n_from_restitution(spec.e_n, k_n, m12)
    smooth = spec.e_t == -1.0 or spec.friction == 0.0
    k_t = 0.0 if smooth else k_t_paper(spec.e_t, k_n)
    n_steps = max(1, int(round(spec.t_end / dt)))
    out_dt = spec.output_interval if spec.output_interval is not None else spec.t_end / 200.0
    output_every = max(1, min(n_steps, int(round(out_dt / dt))))
    nd = n / L**3
    t0 = sc.temperature0              # species: equipartition, T0 = <m> v_rms^2 / 3
    g = carnahan_starling_g(phi)
    # Enskog collision frequency per particle, omega_E = 4 (2a)^2 n g sqrt(pi T/m) (docs/physics.md §6.1);
    # for spheroids the orientation-averaged excluded surface replaces (2a)^2 at leading order.
    sigma2 = (2.0 * r_eq) ** 2
    rate0 = 4.0 * sigma2 * nd * g * math.sqrt(math.pi * t0 / mass)
    if sp is not None:   # mixture: sum over species pairs with sigma_ab = R_a + R_b, BMCSL g_ab
        rate0 = enskog_rate_mixture(sp.radius, sp.count, sp.mass, L**3, t0)
    collisions = thermalization_collisions(spec)
    t_th = collisions / rate0 if collisions > 0 else 0.0
    n_th = int(math.ceil(t_th / dt)) if t_th > 0 else 0
    skin = _skin_length(spec, spec.backend, min(semi), None if sp is None else min(sp.radius) / r_eq)
    one = sp is None
    return Derived(
        radius=r_eq, semi_axes=semi, radius_max=max(semi), radius_min=min(semi) if one else min(sp.radius),
        mass=mass,
        inertia=inertia, m12=m12, omega0=omega0, contact_time=t_c, gamma_n=gamma_n,
        gamma_n_coef=gamma_n / math.sqrt(m12), k_n=k_n, k_t=k_t,
        e_t_effective=-1.0 if smooth else e_t_effective(spec.e_n, spec.e_t), dt=dt,
        n_steps=n_steps, output_every=output_every, number_density=nd, temperature0=t0,
        collision_rate0=rate0, thermalization=collisions, t_thermalization=t_th, n_thermalization_steps=n_th, skin=skin,
        cutoff=2.0 * max(semi) + skin, mass_mean=mass_mean,
        species_radius=(r_eq,) if one else sp.radius, species_count=(n,) if one else sp.count,
        species_mass=(mass,) if one else sp.mass, species_inertia=(inertia[0],) if one else sp.inertia,
        start=start_protocol(spec))


#: Largest Verlet skin L_v (radii) a null ``verlet_skin`` resolves to, per resolved backend: the fastest
#: skin of dilute gases in `python -m bench accuracy` (docs/performance.md, the skin tables). Ellipsoids keep the
#: CPU value on both backends (their skin is not measured on a GPU).
DEFAULT_VERLET_SKIN = {"cpu": 0.4, "cuda": 0.8}
#: Mean free path (radii) below which the default skin falls in proportion to it (phi above 0.1099) ...
DEFAULT_SKIN_MEAN_FREE_PATH = 1.6
#: ... down to this skin (radii): the fastest skin of dense gases on both backends.
DEFAULT_SKIN_FLOOR = 0.2
#: Sphere scenes of at least this many particles take the large-scene rule (:func:`large_scene_skin`), per resolved
#: backend. CUDA: a rebuild's fixed cost (launches, the many-steps loop's return to the host) is spread over enough
#: particles that a thin skin pays. CPU: the thin skin pays at 4096 spheres too, but the scenes below 2^15 (the
#: papers' scenes, the quick start) keep the general rule and their bit-identical trajectories.
LARGE_SCENE_PARTICLES = {"cuda": 1 << 17, "cpu": 1 << 15}
#: The large-scene rule's skin (radii) at its reference gas, per resolved backend: mean free path
#: LARGE_SCENE_MEAN_FREE_PATH radii, the rms speed moving LARGE_SCENE_STEP_RADII radii a step (phi = 0.058,
#: k_n = 1e8 N/m, v_rms = 2 m/s, a = 3.75 mm), a scene (or pack of scenes) of many more than
#: LARGE_SCENE_REBUILD_PARTICLES particles
LARGE_SCENE_SKIN = {"cuda": 0.045, "cpu": 0.12}
LARGE_SCENE_MEAN_FREE_PATH = 3.5
LARGE_SCENE_STEP_RADII = 5.0e-5
#: N_0 of the large-scene rule: the particles whose rebuild work equals a rebuild's fixed cost (CUDA: its ~30
#: launches and two reads of the status words, about 1 ms of host time); 0: no fixed cost counted (the CPU)
LARGE_SCENE_REBUILD_PARTICLES = {"cuda": 1 << 19, "cpu": 0}
#: The large-scene rule's smallest skin (radii)
LARGE_SCENE_SKIN_FLOOR = {"cuda": 0.03, "cpu": 0.1}


def mean_free_path(volume_fraction: float) -> float:
    """Enskog mean free path of equal spheres in radii: 1 / (3 sqrt(2) phi g(phi)), with the
    Carnahan-Starling contact value g(phi) = (1 - phi/2)/(1 - phi)^3 (docs/physics.md §6.1)."""
    phi = volume_fraction
    return 1.0 / (3.0 * math.sqrt(2.0) * phi * (1.0 - 0.5 * phi) / (1.0 - phi) ** 3)


def default_verlet_skin(backend: str, shape: str = "sphere", volume_fraction: Optional[float] = None,
                        n_particles: Optional[int] = None, step_radii: Optional[float] = None,
                        large_scene_floor: float = 0.0) -> float:
    """The skin (radii) a null ``verlet_skin`` means on ``backend`` ('cpu' or 'cuda', already resolved)
    at volume fraction ``volume_fraction`` (a species spec: the total phi; the skin then counts in radii
    of the smallest species, engine.setup.params), for a scene of ``n_particles`` whose rms speed moves
    ``step_radii`` radii a step (:func:`step_radii`; either None: the general rule alone); ``large_scene_floor``
    (radii): the thinnest skin the large-scene rule may give (:func:`verlet_skin_radii`: a CUDA scene of float64
    positions keeps its float32 list reference).

    Large scenes (spheres, n_particles >= LARGE_SCENE_PARTICLES[backend]; a CUDA pack: its particles): the smaller
    of the general rule below and :func:`large_scene_skin`, so the large-scene rule only ever thins the skin (the
    spec's box check, which knows the general rule, stays an upper bound).

    Rule (spheres): L_v = clamp(L_max lambda / lambda_0, 0.2, L_max), with lambda = mean_free_path(phi),
    lambda_0 = DEFAULT_SKIN_MEAN_FREE_PATH = 1.6 radii and L_max = DEFAULT_VERLET_SKIN[backend] (0.4 CPU,
    0.8 CUDA). That is L_max up to phi = 0.1099 (lambda >= 1.6 a: every paper scene, so the CPU default is
    exactly 0.4 there, bit for bit as before), then L_v/lambda fixed at L_max/1.6 (0.25 CPU, 0.5 CUDA), down
    to 0.2 from phi = 0.179 (CPU) / 0.267 (CUDA). Values: phi = 0.008, 0.1 -> L_max; 0.15 -> 0.26 / 0.52;
    0.2 -> 0.2 / 0.34; 0.3 -> 0.2.

    Why: the skin changes the cost only. The neighbours a skin adds to each particle's list, about
    2 sqrt(2) L_v / lambda, make the list cost grow as the skin counted in mean free paths,
    while the rebuilds it saves (one per L_v/2 of flight) do not depend on the density; so the fastest skin
    falls with lambda. Data (skin sweep of `python -m bench accuracy`, rough gas, skins 0.2, 0.4, 0.8, 1.2 a;
    within 15 % of the fastest = on the cost front): CPU, N = 4096 — phi = 0.008: 0.4 a x0.92 of the fastest
    (1.2 a), phi = 0.1: 0.4 a fastest (also in the N = 2048 cooling gas, where 0.2 a and 0.8 a are x0.80 and
    x0.75), phi = 0.3: 0.2 a fastest (0.4 a x0.78); NVIDIA H200, N = 262144 — phi = 0.008: 0.8 a fastest
    (0.4 a x0.83), phi = 0.1: 0.8 a x0.91 (0.4 a fastest; in the N = 16384 cooling gas 0.8 a is x0.96 of the
    fastest and 0.4 a x0.72), phi = 0.3: 0.2 a fastest (0.8 a x0.71). So a GPU rule giving the sweep's
    fastest 0.4 a at phi = 0.1 would be off the smaller gas's front, while 0.8 a is on both. The data bound
    lambda_0 to about 1.4-1.8 a (a CPU spot check at phi = 0.13-0.25 put the fastest at 0.2-0.3 a, as the
    rule does); the rule's value at each swept phi is a swept skin on both backends.

    Ellipsoids keep DEFAULT_VERLET_SKIN['cpu'] (not measured over phi or on a GPU). An unresolved 'auto'
    gives the CPU value: the driver (engine.driver.simulate.SceneRun) resolves the backend and gives it to
    :func:`with_backend`, so this fallback serves only callers of :func:`derive` that run no backend.
    ``volume_fraction=None`` (a caller that does not know phi) gives L_max, the dilute value.
    """
    if not traits(shape).SKIN_BY_VOLUME_FRACTION:
        return DEFAULT_VERLET_SKIN["cpu"]
    top = DEFAULT_VERLET_SKIN.get(backend, DEFAULT_VERLET_SKIN["cpu"])
    if volume_fraction is None:
        return top
    lam = mean_free_path(volume_fraction)
    if lam >= DEFAULT_SKIN_MEAN_FREE_PATH:
        skin = top                      # exactly L_max (bit-identical dilute runs)
    else:
        skin = max(DEFAULT_SKIN_FLOOR, top * lam / DEFAULT_SKIN_MEAN_FREE_PATH)
    if _large_scene(backend, n_particles) and step_radii is not None:
        return min(skin, max(large_scene_floor, large_scene_skin(lam, step_radii, backend, n_particles)))
    return skin


def _large_scene(backend: str, n_particles: Optional[int]) -> bool:
    """Whether a sphere scene of ``n_particles`` on the resolved ``backend`` takes the large-scene rule."""
    return n_particles is not None and n_particles >= LARGE_SCENE_PARTICLES.get(backend, math.inf)


def large_scene_skin(mean_free_path_radii: float, step_radii: float, backend: str = "cuda",
                     n_particles: Optional[int] = None) -> float:
    """The skin (radii) of a sphere scene of at least LARGE_SCENE_PARTICLES[backend] particles (a pack of scenes on
    CUDA: their sum), before the cap of the general rule:

        L_v = max(L_min, L_0 sqrt((lambda / 3.5) (s / 5e-5) (1 + N_0 / N))),

    with lambda the mean free path and s = v_rms dt / a the rms speed's flight per step, both in radii, N the
    particles that rebuild their lists together, and per backend L_0 (LARGE_SCENE_SKIN), N_0
    (LARGE_SCENE_REBUILD_PARTICLES) and L_min (LARGE_SCENE_SKIN_FLOOR): CUDA 0.045 a, 2^19, 0.03 a; the CPU
    0.12 a, 0 (no N term), 0.1 a.

    Why: per particle-step, a skin L_v adds about 2 sqrt(2) L_v / lambda list neighbours to the force pass
    (a cost c_p each), and a rebuild (c_r per particle and a fixed F) comes every L_v / (2 k s) steps (k s: the
    fastest particle's flight a step). The sum c_p 2 sqrt(2) L_v / lambda + (c_r + F / N) 2 k s / L_v is least at
    L_v* = sqrt(k ((c_r + F / N) / c_p) s lambda / sqrt(2)): it grows as the square root of the mean free path, of
    the flight per step and of 1 + N_0 / N with N_0 = F / c_r. The constants are measured (NVIDIA H200, `python -m
    bench loop_ab --variants skin=L`, rough and elastic spheres, the random start, the list build in row runs;
    docs/performance.md "The Verlet skin of large scenes"): at 2M and 8M spheres, phi = 0.058, the fastest skins
    were 0.035-0.05 a (0.12 a x0.94-0.96 of them, 0.8 a about x0.8); at phi = 0.2 0.03-0.05 a; at 131 072 spheres,
    where a rebuild's launches weigh more, 0.075-0.12 a (0.05 a x0.92). Below LARGE_SCENE_PARTICLES['cuda'] small
    GPU scenes keep the general rule (at 32 768 spheres, phi = 0.058, the skins 0.1-0.8 a ran within 8 % of one
    another). The CPU, one thread, 32 768 spheres: 0.1 a ran x1.7-1.9 of the general rule's 0.4 a at phi = 0.058
    and 0.05-0.1 a x1.6-1.95 of its 0.2 a at phi = 0.2.
    """
    scale = (mean_free_path_radii / LARGE_SCENE_MEAN_FREE_PATH) * (step_radii / LARGE_SCENE_STEP_RADII)
    n0 = LARGE_SCENE_REBUILD_PARTICLES[backend]
    if n0 and n_particles:
        scale *= 1.0 + n0 / n_particles
    return max(LARGE_SCENE_SKIN_FLOOR[backend], LARGE_SCENE_SKIN[backend] * math.sqrt(scale))


def largest_default_verlet_skin(backend: str, shape: str = "sphere",
                                volume_fraction: Optional[float] = None) -> float:
    """The largest skin a null ``verlet_skin`` can resolve to for a spec's ``backend`` ('auto': any backend)
    at ``volume_fraction``."""
    if backend in DEFAULT_VERLET_SKIN:
        return default_verlet_skin(backend, shape, volume_fraction)
    return max(default_verlet_skin(b, shape, volume_fraction) for b in DEFAULT_VERLET_SKIN)


def step_radii(spec) -> float:
    """s = v_rms dt / a: how far the rms speed moves a particle in one step, in radii of the smallest semi-axis
    (species: of the smallest radius)."""
    sc = scales(spec)
    return spec.velocity_rms * sc.dt / sc.radius_min


def verlet_skin_radii(spec, backend: str, pack_particles: Optional[int] = None) -> float:
    """The Verlet skin L_v (radii) a run of ``spec`` on ``backend`` uses: the spec's, or the backend's default.

    ``pack_particles``: the particles of every scene packed with this one into one CUDA ensemble, whose lists are
    rebuilt together (engine.driver.ensemble.run_ensemble); the large-scene rule then counts them, not the scene's
    own: the rebuild's cost is the pack's. The skin changes the cost only, never the equations a scene integrates."""
    if spec.verlet_skin is not None:
        return spec.verlet_skin
    n = spec.n_particles if pack_particles is None else max(spec.n_particles, pack_particles)
    return default_verlet_skin(backend, spec.shape, spec.volume_fraction, n, step_radii(spec),
                               _float32_reference_floor(spec, backend))


def _float32_reference_floor(spec, backend: str) -> float:
    """The thinnest skin (radii of the smallest sphere) at which a CUDA scene of float64 positions (float64 and mixed
    precision) keeps its list reference x_ref in float32 (engine/loops/cuda_memory.py ``xref_dtype``: 12 B a
    particle less; a float64 x_ref would make the largest scenes that fit smaller). 0 elsewhere. It is 1.32e-5 of the
    box: above the CUDA rule's floor of 0.03 a only in boxes of more than 2270 radii (1.6e8 spheres at phi = 0.058)."""
    if backend != "cuda" or spec.precision == "float32":
        return 0.0
    return float32_reference_skin(spec.box_length) / scales(spec).radius_min


def _skin_length(spec, backend: str, semi_min: float, smallest_over_radius: Optional[float],
                 pack_particles: Optional[int] = None) -> float:
    """The skin in m: L_v radii (:func:`verlet_skin_radii`) of the smallest semi-axis ``semi_min`` (the radius of a
    sphere); species (``smallest_over_radius`` = R_min / R_max): of the smallest radius (module doc)."""
    skin = verlet_skin_radii(spec, backend, pack_particles) * semi_min
    if smallest_over_radius is not None:
        skin *= smallest_over_radius
    return skin


def with_backend(p: Derived, spec, backend: str, pack_particles: Optional[int] = None) -> Derived:
    """``p = derive(spec)`` with the skin and the cutoff of the resolved ``backend`` ('cpu' or 'cuda'): the only
    derived numbers that depend on it (a null ``verlet_skin`` is that backend's default; ``pack_particles``: as
    :func:`verlet_skin_radii`)."""
    species = species_table(spec) is not None
    skin = _skin_length(spec, backend, min(p.semi_axes), min(p.species_radius) / p.radius if species else None,
                        pack_particles)
    return replace(p, skin=skin, cutoff=2.0 * max(p.semi_axes) + skin)


#: Rough upper bound of device/host memory per particle in bytes (state, lists, history), used to
#: refuse oversize specs before they are queued. float64: ~25 doubles of state + 32 list entries
#: (``slots``: the list stride, larger for wide size distributions, see :func:`list_slots`).
def estimate_bytes_per_particle(precision: str, slots: int = 32) -> int:
    word = np.dtype(state_dtype(precision)).itemsize
    pos_word = np.dtype(position_dtype(precision)).itemsize
    state = 19 * word + 6 * pos_word      # v, omega, q, F, tau, mass, inertia, radius; x and x_ref
    lists = slots * (4 + 3 * word)        # neighbour index + tangential history per list slot
    return state + lists + 16             # cell index, order


def estimate_cost(spec) -> dict:
    """Memory (bytes) and work (particle-steps) a spec will need; used to refuse oversize jobs.

    Species specs: every particle's list has the stride of the largest count (:func:`list_slots`,
    ~ (R_L/R_s)^2 small neighbours per large one), plus the multigrid cell arrays (Skorych & Dosta 2022,
    Algorithm 1: per level 2 nc^3 + 1 int64 cell starts, and one int32 entry per particle per level
    at or above its own).
    """
    p = derive(spec)
    steps = p.n_steps + p.n_thermalization_steps
    slots = list_slots(spec, p)
    memory = spec.n_particles * estimate_bytes_per_particle(spec.precision, slots)
    if species_table(spec) is not None:
        from engine.neighbours.multigrid import grid_levels

        lv = grid_levels(spec.box_length, spec.n_particles, p.radius_min, p.radius_max, p.skin)
        if lv.n_levels > 1:
            memory += int(sum(8 * (2 * int(c) ** 3 + 1) for c in lv.nc)) + 4 * spec.n_particles * lv.n_levels
    return {
        "memory_bytes": memory,
        "particle_steps": spec.n_particles * steps,
        "steps": steps,
        "list_slots": slots,
    }
