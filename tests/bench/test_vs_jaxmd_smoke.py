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
    spec = vs_jaxmd.case_spec(vs_jaxmd.CASES["elastic-2M-f64-phi0.058"], backend="cuda")
    p = derive(spec)
    assert (spec.volume_fraction, spec.box_length, spec.stiffness, spec.density, spec.velocity_rms) == \
        (0.058, 2.0, 1.0e8, 2000.0, 2.0)
    assert (spec.e_n, spec.e_t, spec.friction, spec.thermalization, spec.snapshots, spec.backend, spec.start) == \
        (1.0, -1.0, None, 0.0, 0, "cuda", "random")
    assert p.n_steps == vs_jaxmd.CASES["elastic-2M-f64-phi0.058"].steps and p.n_thermalization_steps == 0
    # t_c = pi sqrt(m12/k_n), m12 = m/2, written out here; dt = t_c/50 rounded to float32 (JAX-MD's step)
    a = (0.058 * 8.0 / (2_097_152 * 4.0 / 3.0 * math.pi)) ** (1.0 / 3.0)
    mass = 2000.0 * 4.0 / 3.0 * math.pi * a**3
    dt = math.pi * math.sqrt(mass / 2.0 / 1.0e8) / 50.0
    assert p.dt == float(np.float32(p.dt))
    assert p.dt == pytest.approx(dt, rel=6e-8)           # half a float32 ulp
    rough = vs_jaxmd.case_spec(vs_jaxmd.CASES["rough-coulomb-8M-f32-phi0.2"], backend="cuda")
    assert (rough.e_n, rough.e_t, rough.friction, rough.precision, rough.volume_fraction) == \
        (0.8, 0.8, vs_jaxmd.FRICTION_CAP, "float32", 0.2)
    assert vs_jaxmd.case_spec(vs_jaxmd.CASES["rough-2M-f64-phi0.2"], backend="cuda").friction is None
    assert all(c.steps % vs_jaxmd.CHUNK == 0 for c in vs_jaxmd.CASES.values())


def test_soft_sphere_force_is_demq_spring():
    spec = vs_jaxmd.case_spec(vs_jaxmd.CASES["elastic-2M-f64-phi0.2"]._replace(n=4096, steps=10), backend="cpu")
    p = derive(spec)
    c = vs_jaxmd.jaxmd_constants(spec)
    assert c["sigma"] == 2.0 * p.radius and c["mass"] == p.mass and c["dt"] == p.dt and c["alpha"] == 2.0
    for overlap in (1e-6, 1e-3, 5e-2):                  # delta / a
        r = c["sigma"] - overlap * p.radius
        # -dU/dr of U = eps/alpha (1 - r/sigma)^alpha at alpha = 2
        force = c["epsilon"] / c["sigma"] * (1.0 - r / c["sigma"])
        assert force == pytest.approx(p.k_n * (2.0 * p.radius - r), rel=1e-9)   # rounding of 1 - r/sigma


def test_cell_order_numbers_particles_cell_by_cell_x_fastest():
    box, cell = 2.0, 0.5                                 # 4 cells a side
    rng = np.random.default_rng(3)
    pos = rng.random((500, 3)) * box
    pos[0] = (box + 0.1, 0.1, 0.1)                       # outside the box: wrapped into cell (0, 0, 0)
    order = vs_jaxmd.cell_order(pos, box, cell)
    assert sorted(order.tolist()) == list(range(500))
    c = (np.mod(pos[order], box) // cell).astype(int)
    key = c[:, 0] + 4 * (c[:, 1] + 4 * c[:, 2])
    assert (np.diff(key) >= 0).all() and key[0] == 0 and order[0] == 0
    # a cell edge that does not divide the box: floor(box / min_cell) cells, each at least min_cell
    c3 = vs_jaxmd.cell_order(pos, box, 0.6)
    k3 = (np.mod(pos[c3], box) // (box / 3)).astype(int)
    assert (np.diff(k3[:, 0] + 3 * (k3[:, 1] + 3 * k3[:, 2])) >= 0).all()


def test_collision_counts_and_rebuild_model():
    assert vs_jaxmd.collisions_per_particle(150, 100) == 3.0            # each contact involves two particles
    # 10 pairs in contact among 1000 particles, a window of 50 contact times: 2 x 10 / 1000 x 50 = 1 per particle
    assert vs_jaxmd.collisions_from_overlaps(10, 1000, 5.0, 0.1) == pytest.approx(1.0)
    # half a skin of 1e-3 m at 2 m/s x 1e-7 s per step: 2500 steps; never below one step
    assert vs_jaxmd.steps_between_rebuilds(1e-3, 2.0, 1e-7) == pytest.approx(2500.0)
    assert vs_jaxmd.steps_between_rebuilds(1e-9, 2.0, 1e-7) == 1.0
    assert vs_jaxmd.predicted_cundall(1000, 1e-3, 0.5, 1000) == pytest.approx(1000 / 1.5e-3)


def test_search_plan_walks_to_the_best_skin_and_capacity():
    calls = []

    def trial(fmt, skin, capacity):      # a landscape: OrderedSparse best, skin 0.2 best, capacity 1.1 best
        calls.append((fmt, skin, capacity))
        if (fmt, skin, capacity) == ("Sparse", 0.4, 1.25):
            return None                   # a failed trial is never chosen
        return {"Dense": 1.0, "Sparse": 2.0, "OrderedSparse": 3.0}[fmt] - skin + (capacity == 1.1)

    best, seen = vs_jaxmd.search_plan(("Dense", "Sparse", "OrderedSparse"), (0.8, 0.2, 0.4, 1.6, 0.1),
                                      (1.25, 1.1), trial)
    assert best == ("OrderedSparse", 0.1, 1.1)
    assert len(calls) == len(set(calls)) == len(seen)              # no configuration tried twice
    assert {c for c in calls if c[0] != "OrderedSparse"} == {("Dense", 0.4, 1.25), ("Sparse", 0.4, 1.25)}
    assert ("OrderedSparse", 1.6, 1.25) not in calls               # the walk goes towards the winning side only
    with pytest.raises(RuntimeError, match="every JAX-MD configuration failed"):
        vs_jaxmd.search_plan(("Dense",), (0.4,), (1.25,), lambda *cfg: None)


def test_start_groups_put_the_cases_of_one_gas_together_smaller_n_first():
    groups = vs_jaxmd.start_groups(["elastic-8M-f32-phi0.2", "rough-2M-f64-phi0.2", "elastic-2M-f64-phi0.2",
                                    "elastic-8M-f64-phi0.2", "elastic-2M-f64-phi0.058"])
    assert list(groups) == [(2_097_152, 0.2), (2_097_152, 0.058), (8_388_608, 0.2)]
    assert groups[(2_097_152, 0.2)] == ["rough-2M-f64-phi0.2", "elastic-2M-f64-phi0.2"]
    assert groups[(8_388_608, 0.2)] == ["elastic-8M-f32-phi0.2", "elastic-8M-f64-phi0.2"]


@pytest.mark.heavy
@pytest.mark.skipif(importlib.util.find_spec("jax_md") is None, reason="jax_md not installed")
def test_quick_side_by_side(tmp_path):
    rows = vs_jaxmd.main(["--quick", "--backend", "cpu",
                          "--cases", "elastic-2M-f64-phi0.2", "rough-coulomb-2M-f64-phi0.2",
                          "--formats", "Dense", "OrderedSparse", "--skins", "0.4", "0.8", "--capacities", "1.25",
                          "--out", str(tmp_path)])
    elastic, rough = rows
    demq, jaxmd = elastic["demq"], elastic["jaxmd"]
    assert "error" not in demq and "error" not in jaxmd, (demq, jaxmd)
    assert elastic["n"] == vs_jaxmd.QUICK_N and demq["steps"] == jaxmd["steps"] == vs_jaxmd.QUICK_STEPS
    # the search tried both formats at 0.4 a, then 0.8 a for the better one; the timed run is its best prediction
    trials = jaxmd["trials"]
    assert {(t["format"], t["skin_radii"]) for t in trials} >= {("Dense", 0.4), ("OrderedSparse", 0.4)}
    assert len(trials) == 3 and jaxmd["searched"]
    best = max(trials, key=lambda t: t["predicted_cundall"])
    assert (jaxmd["format"], jaxmd["skin_radii"]) == (best["format"], best["skin_radii"])
    # both codes integrate the same equations from the same start (JAX-MD's renumbered in cell order) with the same
    # dt: the final states differ by rounding only (measured 1e-11 radii and v_rms after 0.6 collisions per particle)
    sd = elastic["state_difference"]
    assert sd["max_position_diff_radii"] < 1e-8 and sd["max_velocity_diff_rel"] < 1e-8
    assert elastic["ke_rel_diff"] < 1e-10
    # the gas collides: demq counted 0.63 collisions per particle against Enskog's 0.71 (the RSA start's pair
    # correlation at contact is below Carnahan-Starling's at phi = 0.2); 4096 particles, so within 30 %
    assert demq["collisions"] > 0
    assert 0.7 < demq["collisions_per_particle"] / demq["enskog_collisions_per_particle"] < 1.0
    assert jaxmd["collisions_per_particle_estimate"] > 0
    assert elastic["ratio_loop"] == pytest.approx(demq["cundall_loop"] / jaxmd["cundall_loop"])
    # the rough case runs demq alone from the same start and is compared with the elastic JAX-MD run
    assert "error" not in rough["demq"] and rough["jaxmd"] == jaxmd and "state_difference" not in rough
    assert rough["demq"]["start_draw_s"] == demq["start_draw_s"]           # one draw for the group
    assert rough["ratio_loop"] == pytest.approx(rough["demq"]["cundall_loop"] / jaxmd["cundall_loop"])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert [r["case"] for r in saved["rows"]] == ["elastic-2M-f64-phi0.2", "rough-coulomb-2M-f64-phi0.2"]
    md = (tmp_path / "results.md").read_text()
    assert "| elastic-2M-f64-phi0.2 | 4096 | 0.2 | float64 | 3000 |" in md
    assert "rough-coulomb-2M-f64-phi0.2 (vs elastic JAX-MD)" in md


def test_start_memo_hands_out_copies_made_before_the_clock():
    """The second run gets the first run's start, copied by prepare() before its timing starts: equal values, its own
    arrays (a run may write into them), and a call without prepare() still copies."""
    from engine.setup.spec import SimulationSpec

    calls = []
    memo = vs_jaxmd.StartMemo()
    try:
        draw = memo.draw
        memo.draw = lambda spec, p, on_device: calls.append(1) or draw(spec, p, on_device)
        spec = SimulationSpec(n_particles=512, volume_fraction=0.058, start="random", backend="cpu")
        p = derive(spec)
        first = memo(spec, p)
        memo.prepare()
        ready = memo.ready[memo.key(spec)]
        second = memo(spec, p)
        assert second is ready and memo.ready == {} and calls == [1]
        third = memo(spec, p)
        for s in (first, second, third):
            assert np.array_equal(s.position, memo.starts[memo.key(spec)].position)
        assert len({id(s.position) for s in (first, second, third, memo.starts[memo.key(spec)])}) == 4
    finally:
        memo.close()
    # close() puts back the function the memo replaced, not the stand-in this test gave it as its draw
    import engine.setup.scene as scene

    assert scene.initial_spheres is draw
