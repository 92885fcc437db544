"""The most important cells of the stability stress matrix (bench/stability.py), run in-process."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from bench.stability import cells, run_cell_inprocess
from engine.backends.base import ContactParams, SphereSystem
from engine.shapes.sphere.cpu_backend import CpuBackend
from engine.errors import InstabilityError
from engine.setup.params import Q_SPHERE
from engine.setup.spec import SimulationSpec

A, M, K = 0.01, 1e-2, 1e5


def cell(name, shorter=1.0):
    """A cell of the bench matrix; shorter > 1 runs the same scene for 1/shorter of its time, no thermalisation."""
    c = next(c for c in cells() if c["name"] == name)
    if shorter != 1.0:
        c["spec"] = dict(c["spec"], t_end=c["spec"]["t_end"] / shorter, thermalization=0.0)
    return c


def pair(separation, precision="float64", limit=0.5):
    pos = np.array([[0.5, 0.5, 0.5], [0.5 + separation, 0.5, 0.5]])
    tc = math.pi * math.sqrt(0.5 * M / K)
    system = SphereSystem(1.0, pos, np.zeros((2, 3)), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)),
                          np.full(2, A), np.full(2, M), np.full(2, Q_SPHERE * M * A * A))
    params = ContactParams(k_n=K, gamma_n_coef=0.0, k_t=K / 4, friction=None, dt=tc / 50, skin=0.4 * A,
                           precision=precision, overlap_limit=limit)
    return system, params


@pytest.mark.parametrize("separation, precision, depth", [(1.9 * A, "float64", "0.1"), (0.0, "float64", "2"),
                                                          (0.0, "float32", "2")])
def test_overlapping_start_stops_naming_the_pair(separation, precision, depth):
    """Coincident centres used to divide by zero inside the parallel force loop (SystemError)."""
    with pytest.raises(InstabilityError, match=rf"particles [01] and [01] overlap by {depth} radii.* at the "
                                               rf"start \(step 0\)") as ei:
        CpuBackend(*pair(separation, precision, limit=0.05))
    assert ei.value.step == 0 and ei.value.particle in (0, 1)


def test_start_overlap_within_the_limit_runs_and_conserves_energy():
    be = CpuBackend(*pair(1.9 * A, limit=0.5))
    o = be.observe()
    e0 = o["kinetic_energy_translational"] + o["kinetic_energy_rotational"] + o["elastic_energy"]
    be.advance(300)
    o = be.observe()
    e1 = o["kinetic_energy_translational"] + o["kinetic_energy_rotational"] + o["elastic_energy"]
    assert np.all(np.isfinite(be.vel)) and o["contacts"] == 0
    assert abs(e1 / e0 - 1) < 1e-2  # elastic smooth pair: released spring energy, O((dt/t_c)^2) error
    assert np.array_equal(be.vel[0], -be.vel[1])  # exact antisymmetry of the pair force


def test_dt_five_times_too_large_is_refused_naming_dt():
    with pytest.raises(ValidationError, match=r"dt = .* cannot resolve a contact.*contact_time/10"):
        SimulationSpec.model_validate(cell("dt=5x too large")["spec"])
    assert run_cell_inprocess(cell("dt=5x too large"))["outcome"] == "refused"


@pytest.mark.parametrize("name", ["e_n=0.05", "float32 base"])
def test_stress_cell_runs_clean(name):
    res = run_cell_inprocess(cell(name, shorter=4.0))
    assert res["outcome"] == "ok", res
    assert res["info"]["max_overlap"] < cell(name)["spec"].get("overlap_limit", 0.05)
