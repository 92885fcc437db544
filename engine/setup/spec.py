"""The simulation spec: one pydantic model, the public JSON contract of demq.

Every key here is part of the contract shared by the engine, the job queue, the HTTP API and the
result files (the spec is stored verbatim in ``/parameters@spec``). SI units throughout.

Defaults reproduce the setup of Hidalgo et al. (2013): N = 4096 rough spheres in a
periodic cube of L = 2 m at volume fraction 0.008, k_n = 1e8 N/m, density 2000 kg/m^3,
e_n = e_t = 0.8. The default ``velocity_rms`` keeps the largest overlap near 1 % of the radius and
the default ``t_end`` keeps a default run to about a minute on a laptop CPU.

Every check that fails names the field, the value and the allowed range, so an invalid spec is
rejected before it costs anything.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from typing import List, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from engine.setup.params import largest_default_verlet_skin
from engine.setup.precision import check_shape
from engine.setup.scales import scales
from engine.shapes import SHAPES, traits

#: Random close packing of monodisperse spheres; no homogeneous gas start exists above it.
RANDOM_CLOSE_PACKING = 0.64

#: A contact must span at least this many time steps (t_c / dt); coarser steps cannot resolve it.
MIN_STEPS_PER_CONTACT = 10.0

#: Largest volume fraction of a species spec. Random sequential addition (engine/setup/scene.py) jams near
#: 0.38 for nearly equal sizes; measured with 1000 N + 1e5 candidates (2026-11-21): at 0.35 it failed for
#: 4 of 20 seeds at N = 100 (radius ratio 0.999), at 0.33 for 1 of 50 at N = 20, at 0.30 never (50 seeds
#: each, N = 10 ... 100); at 0.30, N = 1e5 nearly equal spheres are placed in 1.5 s on the CI machine.
SPECIES_MAX_VOLUME_FRACTION = 0.30

#: Most species a spec may list.
MAX_SPECIES = 16

#: Species number fractions whose sum is within this of 1 are kept as given; others are divided by their sum.
SPECIES_FRACTION_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Range:
    """The allowed values of one numeric spec field: an interval, each end closed or open.

    One table (:data:`FIELD_RANGES`) feeds both the validator (:meth:`check`) and the JSON schema
    (:meth:`json_schema`: minimum/maximum or exclusiveMinimum/exclusiveMaximum), so the published
    schema states exactly the one-field limits the validator enforces. ``high = inf`` (open) means
    any finite number; NaN is outside every range.
    """

    low: float
    high: float
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    why: str = ""            # appended to the error message, e.g. ": a start above ... does not exist"

    def contains(self, v: float) -> bool:
        above = v > self.low if self.low_open else v >= self.low
        below = v < self.high if self.high_open else v <= self.high
        return bool(above and below)

    def text(self) -> str:
        """The range as the error messages write it: '2 ... 2147483647', '(0, 1]', '[0, inf)'."""
        if self.integer:
            return f"{self.low} ... {self.high}"
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"

    def check(self, name: str, v: float, nullable: bool = False) -> None:
        """Raise ValueError naming the field, the value and the range when ``v`` is outside."""
        if self.contains(v):
            return
        null = " (or null)" if nullable else ""
        if self.low == 0.0 and self.low_open and self.high == math.inf:
            raise ValueError(f"{name} = {v} must be a finite number > 0{null}")
        raise ValueError(f"{name} = {v} is outside the allowed range {self.text()}{self.why}{null}")

    def json_schema(self) -> dict:
        """JSON-schema keywords of the range (OpenAPI 3.1: numeric exclusiveMinimum/exclusiveMaximum)."""
        out: dict = {("exclusiveMinimum" if self.low_open else "minimum"): self.low}
        if self.high != math.inf:
            out["exclusiveMaximum" if self.high_open else "maximum"] = self.high
        return out


def _positive() -> Range:
    """(0, inf): a finite number > 0."""
    return Range(0.0, math.inf, low_open=True, high_open=True)


#: The one-field ranges of the spec (validator and JSON schema). Checks between fields (box size,
#: contact resolution, overlap, shape-specific keys) are in SimulationSpec._consistent.
FIELD_RANGES: dict[str, Range] = {
    "n_particles": Range(2, 2**31 - 1, integer=True),
    "volume_fraction": Range(0.0, RANDOM_CLOSE_PACKING, low_open=True, high_open=True,
                             why=": a homogeneous start above random close packing does not exist"),
    "e_n": Range(0.0, 1.0, low_open=True),
    "e_t": Range(-1.0, 1.0),
    "elongation": Range(1.0, 10.0),
    "friction": Range(0.0, math.inf, high_open=True),
    "stiffness": _positive(),
    "density": _positive(),
    "box_length": _positive(),
    "velocity_rms": _positive(),
    "t_end": _positive(),
    "thermalization": Range(0.0, 1.0e4, why=" collisions per particle"),
    "dt": _positive(),
    "output_interval": _positive(),
    "snapshots": Range(0, 10000, integer=True),
    "seed": Range(0, 2**63 - 1, integer=True),
    "verlet_skin": Range(0.0, 4.0, low_open=True, why=" radii"),
    "overlap_limit": Range(0.0, 0.5, low_open=True, why=" radii"),
}

#: The ranges of a species entry's fields.
SPECIES_RANGES: dict[str, Range] = {
    "radius_ratio": Range(0.01, 1.0, why=" (a relative radius; the list is scaled so that the largest is 1)"),
    "number_fraction": Range(0.0, 1.0, low_open=True),
}


def field_schema_keywords(ranges: dict[str, Range]) -> dict[str, dict]:
    """The JSON-schema keywords of each field's one-field check: its range; for the spec also the species
    count and the registered shapes."""
    out = {name: r.json_schema() for name, r in ranges.items()}
    if ranges is FIELD_RANGES:
        out["species"] = {"minItems": 1, "maxItems": MAX_SPECIES}
        out["shape"] = {"enum": list(SHAPES)}
    return out


def write_field_keywords(properties: dict, keywords: dict[str, dict], items: bool = False) -> None:
    """Add ``keywords[name]`` to each property of a JSON schema (into the non-null branch of a nullable one;
    ``items``: into the schema of the property's array items, as in a sweep of values)."""
    for name, extra in keywords.items():
        if name not in properties:
            continue
        prop = properties[name]["items"] if items else properties[name]
        for branch in prop.get("anyOf", [prop]):
            if branch.get("type") != "null":
                branch.update(extra)


class Species(BaseModel):
    """One sphere size of a polydisperse spec."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=lambda schema, _model: write_field_keywords(
        schema["properties"], field_schema_keywords(SPECIES_RANGES)))

    radius_ratio: float = Field(
        ..., description="Relative radius of this species, in [0.01, 1]: the list's ratios are divided by the "
                         "largest one (which becomes exactly 1; the stored spec holds the divided values), so "
                         "the sizes differ by a factor of 100 at most. Absolute radii follow from n_particles, "
                         "volume_fraction and box_length.")
    number_fraction: float = Field(
        ..., description="Relative number of the n_particles spheres in this species, in (0, 1]: the list's "
                         "fractions are divided by their sum unless it is 1 within 1e-9 (the stored spec holds "
                         "the divided values). Counts are round(N f), the remainder going to the largest "
                         "fraction.")

    @field_validator("radius_ratio", "number_fraction")
    @classmethod
    def _in_range(cls, v: float, info) -> float:
        SPECIES_RANGES[info.field_name].check(info.field_name, v)
        return v


def normal_species(entries: List[Species]) -> List[Species]:
    """The normal form of a size distribution, the one the stored spec, the derived parameters and the result's
    /parameters hold: every radius_ratio divided by the largest (which becomes exactly 1), entries of equal
    ratio merged into the first of them (their number_fraction values added), and the number_fraction values
    divided by their sum unless it is within SPECIES_FRACTION_TOLERANCE of 1 (and no merged fraction
    exceeds 1). So no rule across entries refuses a list: [0.5, 0.25] and [1, 0.5] are one distribution.

    Each entry stays in its range, so the entries are built unchecked: a ratio r >= 0.01 of a largest t <= 1
    becomes r/t >= r (rounding is monotone), and a fraction f of a sum S >= f becomes f/S <= 1; one so small that
    f/S underflows to 0 holds no particle, which the spec's cross-field check refuses naming
    ``species[k].number_fraction`` and n_particles (engine.setup.scales.species_counts). Idempotent, bit for bit: a list
    already in normal form comes back with the same values (the worker re-validates the stored spec).
    """
    largest = max(s.radius_ratio for s in entries)
    merged: dict[float, List[float]] = {}
    for s in entries:
        merged.setdefault(s.radius_ratio / largest, []).append(s.number_fraction)
    fractions = {ratio: math.fsum(parts) for ratio, parts in merged.items()}
    total = math.fsum(fractions.values())
    kept = abs(total - 1.0) <= SPECIES_FRACTION_TOLERANCE and max(fractions.values()) <= 1.0
    scale = 1.0 if kept else total
    entry = type(entries[0])
    return [entry.model_construct(radius_ratio=ratio, number_fraction=f / scale) for ratio, f in fractions.items()]


class SimulationSpec(BaseModel):
    """A granular-gas simulation: particles, contact law, protocol, output and numerics."""

    model_config = ConfigDict(extra="forbid", validate_assignment=False,
                              json_schema_extra=lambda schema, _model: write_field_keywords(
                                  schema["properties"], field_schema_keywords(FIELD_RANGES)))

    shape: str = Field(
        "sphere",   # its schema enum is the registry at schema time (field_schema_keywords)
        description="Particle shape, a plug-in of engine/shapes/: "
                    + "; ".join(f"'{k}' ({traits(k).SUMMARY})" for k in SHAPES) + ".")
    n_particles: int = Field(
        4096, description="Number of particles N (2 ... 2**31-1).")
    volume_fraction: float = Field(
        0.008, description="Solid volume fraction phi = N v_particle / L^3, in (0, 0.64).")
    e_n: float = Field(
        0.8, description="Normal coefficient of restitution, in (0, 1]; 1 = elastic.")
    e_t: float = Field(
        0.8, description="Tangential coefficient of restitution, in [-1, 1]; -1 = smooth, 1 = perfectly rough.")
    elongation: float = Field(
        1.0, description="Aspect ratio xi = a/b of a prolate spheroid (>= 1); must be 1 for spheres.")
    friction: Optional[float] = Field(
        None, description="Coulomb friction coefficient mu >= 0; null = no sliding limit "
                          "(Luding's constant-e_t model of Hidalgo et al. 2013).")
    stiffness: float = Field(1.0e8, description="Normal spring constant k_n in N/m (> 0).")
    density: float = Field(2000.0, description="Material density in kg/m^3 (> 0).")
    box_length: float = Field(
        2.0, description="Edge L of the periodic cubic box in m; the particle size follows from N, "
                         "phi and L at equal particle volume.")
    velocity_rms: float = Field(
        2.0, description="Root-mean-square translational speed sqrt(<|v|^2>) at the start, in m/s; "
                         "the rotational temperature starts equal to the translational one.")
    start: Optional[Literal["random", "lattice"]] = Field(
        None, description="Initial placement: 'random' = uniform random non-overlapping positions (random "
                          "sequential addition, an equilibrium gas at low density; volume_fraction <= 0.30); "
                          "'lattice' = fcc lattice sites with a random displacement (the rough-sphere papers' "
                          "protocol; one-size spheres and ellipsoids); null = 'random' where it is cheap "
                          "(species; one-size spheres up to volume_fraction 0.30, placed in parallel from 2^20 "
                          "particles on; spheroids up to volume_fraction x elongation^2 = 0.30), else 'lattice'.")
    thermalization: Optional[float] = Field(
        None, description="Collisions per particle run without dissipation before t = 0 (0 ... 10000); "
                          "null = what the start needs: a random start 0 up to volume_fraction 0.02, 0.25 up to "
                          "0.1, 1 above; a lattice start 1.")
    t_end: float = Field(0.1, description="Length of the cooling run in s (> 0).")
    dt: Optional[float] = Field(
        None, description="Time step in s; null = contact_time / 50.")
    output_interval: Optional[float] = Field(
        None, description="Interval between observable records in s; null = t_end / 200.")
    snapshots: int = Field(
        5, description="Number of full particle snapshots, evenly spaced over [0, t_end] (0 ... 10000).")
    orientations: bool = Field(
        True, description="Whether the snapshots hold each sphere's orientation (a unit quaternion, integrated "
                          "from its spin). A sphere's orientation changes nothing else: false integrates none, "
                          "leaves it out of the snapshots and holds none on the GPU (24 B a particle in float32, "
                          "40 in float64). Spheroids always have theirs (it is part of their dynamics).")
    precision: Literal["float64", "float32", "mixed"] = Field(
        "float64", description="Floating-point precision of the state and the arithmetic: 'float64'; "
                               "'float32'; 'mixed' = positions in float64, every other array in float32, "
                               "separations and overlaps formed in float64 (spheres only; engine/setup/precision.py).")
    seed: int = Field(0, description="Seed of the random initial state (0 ... 2**63-1).")
    backend: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="'auto' = CUDA when a GPU is present, else CPU.")
    verlet_skin: Optional[float] = Field(
        None, description="Verlet-list skin L_v in units of the particle radius (0 < L_v <= 4; species: "
                          "of the smallest radius); the list is rebuilt when a particle has moved more than "
                          "L_v/2 (Skorych & Dosta 2022). null = the fastest skin of `python -m bench accuracy` for the "
                          "backend and density: L_max = 0.4 on the CPU, 0.8 on CUDA up to phi = 0.11, then "
                          "L_max x (mean free path / 1.6 radii), at least 0.2 (0.2 from phi = 0.18 on the "
                          "CPU, 0.27 on CUDA); ellipsoids 0.4. The value used is in the result's /parameters.")
    overlap_limit: float = Field(
        0.05, description="Largest allowed overlap as a fraction of the radius; a run that exceeds it "
                          "stops with an error (0 < limit <= 0.5).")
    species: Optional[List[Species]] = Field(
        None, description="Polydisperse spheres: a list of 1 ... 16 sizes {radius_ratio, number_fraction} "
                          "(relative radii, divided by the largest; relative numbers, divided by their sum; "
                          "entries of equal size merged; the stored spec holds this normal form). "
                          "null = one size. Spheres only, volume_fraction <= 0.30. All species start at the "
                          "same temperature <m> v_rms^2/3 (velocity_rms is the mass-weighted rms speed); "
                          "the Verlet skin is in units of the smallest radius, dt = t_c/50 of the "
                          "small-small contact, overlaps count relative to the smaller radius of a pair.")
    list_mode: Literal["auto", "gpu", "cpu-sequential", "cpu-pipelined"] = Field(
        "auto", description="Where the CUDA backend builds the Verlet list (Skorych & Dosta 2022, §3): 'gpu'; "
                            "'cpu-sequential' (the GPU waits while CPU threads build it); 'cpu-pipelined' "
                            "(CPU threads build the next list while the GPU integrates, checked a posteriori); "
                            "'auto' (measures tau_CPU, tau_GPU and the transfers while running and keeps the "
                            "fastest; jobs packed into an ensemble always use the GPU list). The CPU backend "
                            "ignores it.")

    # ---- field checks: each message names the value and the allowed range ------------------------

    @field_validator("shape")
    @classmethod
    def _known_shape(cls, v: str) -> str:
        if v not in SHAPES:   # looked up at validation time: a registered plug-in needs no edit here
            raise ValueError(f"shape = {v!r} is not a registered shape; expected "
                             + " or ".join(repr(k) for k in SHAPES))
        return v

    @field_validator(*FIELD_RANGES)
    @classmethod
    def _in_range(cls, v, info):
        """The one-field ranges of :data:`FIELD_RANGES` (also written into the JSON schema)."""
        if v is None:      # the null of a nullable field (pydantic refuses null for the others first)
            return v
        nullable = cls.model_fields[info.field_name].default is None
        FIELD_RANGES[info.field_name].check(info.field_name, v, nullable=nullable)
        return v

    @field_validator("species")
    @classmethod
    def _species(cls, v: Optional[List[Species]]) -> Optional[List[Species]]:
        """The entry count (also in the JSON schema), then the list's normal form (:func:`normal_species`)."""
        if v is None:
            return v
        if not 1 <= len(v) <= MAX_SPECIES:
            raise ValueError(f"species has {len(v)} entries, outside the allowed range 1 ... {MAX_SPECIES} "
                             f"(or null for one size)")
        return normal_species(v)

    # ---- checks that need several fields (sizes and time scales: engine/setup/scales.py) -------------------

    @model_validator(mode="after")
    def _consistent(self) -> "SimulationSpec":
        shape = traits(self.shape)
        if not shape.ELONGATED and self.elongation != 1.0:
            raise ValueError(f"elongation = {self.elongation} but shape is {self.shape!r}: elongation must be 1 "
                             f"for {self.shape}s")
        check_shape(self.precision, self.shape)
        if shape.ELONGATED and not self.orientations:
            raise ValueError(f"orientations = false but shape is {self.shape!r}: a spheroid's orientation is part "
                             f"of its dynamics; set orientations to true")
        poly = self.species is not None and len(self.species) > 1
        if self.species is not None and not shape.SPECIES:
            which = " or ".join(repr(k) for k in SHAPES if traits(k).SPECIES)
            raise ValueError(f"species is given but shape is {self.shape!r}: size distributions are for "
                             f"shape {which} only; set species to null")
        if poly and self.volume_fraction > SPECIES_MAX_VOLUME_FRACTION:
            raise ValueError(
                f"volume_fraction = {self.volume_fraction:g} is above {SPECIES_MAX_VOLUME_FRACTION:g}, the largest "
                f"for a species spec: the random sequential placement of several sizes cannot start denser "
                f"reliably (it jams near 0.38)")
        if self.start == "lattice" and poly:
            raise ValueError("start = 'lattice' but species is given: size distributions are placed by random "
                             "sequential addition only; set start to 'random' or null")
        # ellipsoids: the random start's cells hold their bounding spheres, whose volume fraction is phi xi^2
        bounding = self.volume_fraction * self.elongation**2
        if self.start == "random" and bounding > SPECIES_MAX_VOLUME_FRACTION:
            raise ValueError(
                f"start = 'random' needs volume_fraction x elongation^2 <= {SPECIES_MAX_VOLUME_FRACTION:g} (the "
                f"bounding spheres' volume fraction, which sets the random start's cost), but it is {bounding:g}; "
                f"use start = 'lattice' or null")
        p = scales(self)
        if not p.temperature0 >= sys.float_info.min:
            # T0 = <m> v_rms^2 / 3 underflows: the collision rate, hence the thermalisation time, would be 0 or nan
            raise ValueError(
                f"velocity_rms = {self.velocity_rms:g} m/s is too slow: the temperature <m> v_rms^2/3 = "
                f"{p.temperature0:g} J is not a normal float64 (>= {sys.float_info.min:g}); use a larger velocity_rms")
        if self.dt is not None and self.dt > p.contact_time / MIN_STEPS_PER_CONTACT:
            raise ValueError(
                f"dt = {self.dt:.6g} s cannot resolve a contact: the contact time is {p.contact_time:.6g} s, "
                f"so dt must be <= contact_time/{MIN_STEPS_PER_CONTACT:g} = "
                f"{p.contact_time / MIN_STEPS_PER_CONTACT:.6g} s")
        if self.output_interval is not None and self.output_interval < p.dt:
            raise ValueError(
                f"output_interval = {self.output_interval:.6g} s is shorter than the time step dt = {p.dt:.6g} s")
        # a null skin is checked at the largest default the spec's backend can resolve to ('auto': any)
        skin = self.verlet_skin if self.verlet_skin is not None else largest_default_verlet_skin(
            self.backend, self.shape, self.volume_fraction)
        cutoff = 2.0 * p.radius_max * (1.0 + 0.5 * skin)
        if self.box_length < 3.0 * cutoff:
            # The minimum-image convention and the cell list need L > 2 * cutoff; keep a margin.
            raise ValueError(
                f"box_length = {self.box_length:g} m is too small for particles of radius {p.radius_max:.4g} m: "
                f"it must be at least {3.0 * cutoff:.4g} m (3 x the neighbour cutoff at verlet_skin = {skin:g}"
                f"{'' if self.verlet_skin is not None else ', the default of backend ' + repr(self.backend)})")
        # A typical head-on collision compresses by v_rel/omega_0; reject specs whose *typical* overlap
        # already exceeds the limit (the run-time guard catches the rare tails).
        typical = math.sqrt(2.0) * self.velocity_rms / p.omega0
        if poly:
            # equal temperatures: a pair a-b meets at <|v_ab|^2> = 3 T0/m_ab and compresses by v_ab/omega_ab
            # = sqrt(3 T0/k_n) for every pair; relative to the smaller radius the small-small pair is worst
            typical = math.sqrt(3.0 * p.temperature0 / p.k_n)
        if typical > self.overlap_limit * p.radius_min:
            vmax = self.overlap_limit * p.radius_min * p.omega0 / math.sqrt(2.0)
            if poly:
                vmax = self.overlap_limit * p.radius_min * math.sqrt(p.k_n / p.mass_mean)
            raise ValueError(
                f"velocity_rms = {self.velocity_rms:g} m/s is too fast for stiffness = {self.stiffness:g} N/m: "
                f"a typical collision would overlap {typical / p.radius_min:.3g} radii, above "
                f"overlap_limit = {self.overlap_limit:g}; use velocity_rms <= {vmax:.4g} m/s or a stiffer contact")
        return self

    # ---- helpers -----------------------------------------------------------------------------------

    def to_json(self) -> str:
        """Canonical JSON of the full spec (all keys, defaults filled in)."""
        return json.dumps(self.model_dump(mode="json"), sort_keys=True)

    @property
    def smooth(self) -> bool:
        """True when contacts carry no tangential force (e_t = -1 or mu = 0)."""
        return self.e_t == -1.0 or self.friction == 0.0


def load_spec(source) -> SimulationSpec:
    """Validate a spec from a dict, a JSON string or a path to a JSON file."""
    from pathlib import Path

    if isinstance(source, SimulationSpec):
        return source
    if isinstance(source, dict):
        return SimulationSpec.model_validate(source)
    if isinstance(source, Path) or (isinstance(source, str) and not source.lstrip().startswith("{")):
        return SimulationSpec.model_validate_json(Path(source).read_text())
    return SimulationSpec.model_validate_json(source)
