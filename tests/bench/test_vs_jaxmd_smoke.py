"""Smoke tests of bench/vs_jaxmd.py: the JAX-MD constants are demq's contact law, and (only where jax_md imports)
the --quick CPU run integrates the same gas on both sides, particle by particle."""

import importlib.util
import json
import math

import numpy as np
import pytest

from bench import vs_jaxmd
from engine.setup.params import derive


def test_case_spec_is_the_issue_scene():
    spec = vs_jaxmd.case_spec(2_097_152, "float64", 2000, rough=False, backend="cuda")
    p = derive(spec)
    assert (spec.volume_fraction, spec.box_length, spec.stiffness, spec.density, spec.velocity_rms) == \
        (0.058, 2.0, 1.0e8, 2000.0, 2.0)
    assert (spec.e_n, spec.e_t, spec.thermalization, spec.snapshots, spec.backend) == (1.0, -1.0, 0.0, 0, "cuda")
    assert p.n_steps == 2000 and p.n_thermalization_steps == 0
    # t_c = pi sqrt(m12/k_n), m12 = m/2, written out here; dt = t_c/50 rounded to float32 (JAX-MD's step)
    a = (0.058 * 8.0 / (2_097_152 * 4.0 / 3.0 * math.pi)) ** (1.0 / 3.0)
    mass = 2000.0 * 4.0 / 3.0 * math.pi * a**3
    dt = math.pi * math.sqrt(mass / 2.0 / 1.0e8) / 50.0
    assert p.dt == float(np.float32(p.dt))
    assert p.dt == pytest.approx(dt, rel=6e-8)           # half a float32 ulp
    rough = vs_jaxmd.case_spec(8_388_608, "float32", 1000, rough=True, backend="cuda")
    assert (rough.e_n, rough.e_t, rough.precision) == (0.8, 0.8, "float32")


def test_soft_sphere_force_is_demq_spring():
    spec = vs_jaxmd.case_spec(4096, "float64", 10, rough=False, backend="cpu")
    p = derive(spec)
    c = vs_jaxmd.jaxmd_constants(spec)
    assert c["sigma"] == 2.0 * p.radius and c["mass"] == p.mass and c["dt"] == p.dt and c["alpha"] == 2.0
    for overlap in (1e-6, 1e-3, 5e-2):                  # delta / a
        r = c["sigma"] - overlap * p.radius
        # -dU/dr of U = eps/alpha (1 - r/sigma)^alpha at alpha = 2
        force = c["epsilon"] / c["sigma"] * (1.0 - r / c["sigma"])
        assert force == pytest.approx(p.k_n * (2.0 * p.radius - r), rel=1e-9)   # rounding of 1 - r/sigma


@pytest.mark.heavy
@pytest.mark.skipif(importlib.util.find_spec("jax_md") is None, reason="jax_md not installed")
def test_quick_side_by_side(tmp_path):
    rows = vs_jaxmd.main(["--quick", "--backend", "cpu", "--no-warmup", "--cases", "elastic-2M-f64", "rough-2M-f64",
                          "--formats", "Dense", "OrderedSparse", "--skins", "0.8", "--out", str(tmp_path)])
    elastic, rough = rows
    assert "error" not in elastic["demq"], elastic["demq"]
    assert all("error" not in r for r in elastic["jaxmd_runs"]), elastic["jaxmd_runs"]
    assert elastic["n"] == vs_jaxmd.QUICK_N and elastic["demq"]["steps"] == vs_jaxmd.QUICK_STEPS
    assert {r["format"] for r in elastic["jaxmd_runs"]} == {"Dense", "OrderedSparse"}
    shapes = {r["format"]: r["list_shape"] for r in elastic["jaxmd_runs"]}
    assert shapes["Dense"][0] == vs_jaxmd.QUICK_N and shapes["OrderedSparse"][0] == 2   # (N, slots) and (2, pairs)
    # the check saw contacts, and both codes integrate the same equations from the same start with the same dt:
    # the final states differ by rounding only (measured 7e-15 radii, 8e-13 v_rms; JAX-MD given float32 sigma
    # and epsilon instead, they differed by 2e-9)
    assert elastic["demq"]["collisions"] > 0
    sd = elastic["state_difference"]
    assert sd["jaxmd_runs_compared"] == 2
    assert sd["max_position_diff_radii"] < 1e-10 and sd["max_velocity_diff_rel"] < 1e-10
    assert elastic["ke_rel_diff"] < 1e-12
    loop = elastic["jaxmd_best_loop"]
    assert loop["cundall_loop"] == max(r["cundall_loop"] for r in elastic["jaxmd_runs"])
    assert elastic["ratio_loop"] == pytest.approx(elastic["demq"]["cundall_loop"] / loop["cundall_loop"])
    # the rough case runs demq alone and is compared with the elastic JAX-MD runs of its N and precision
    assert "error" not in rough["demq"] and rough["jaxmd_runs"] == elastic["jaxmd_runs"]
    assert rough["ratio_loop"] == pytest.approx(rough["demq"]["cundall_loop"] / loop["cundall_loop"])
    assert "state_difference" not in rough
    saved = json.loads((tmp_path / "results.json").read_text())
    assert [r["case"] for r in saved["rows"]] == ["elastic-2M-f64", "rough-2M-f64"]
    md = (tmp_path / "results.md").read_text()
    assert "| elastic-2M-f64 | 4096 | float64 | 3000 |" in md and "rough-2M-f64 (vs elastic JAX-MD)" in md
