"""The backend- and density-dependent default Verlet skin: a null ``verlet_skin`` is
L_max = 0.4 a on the CPU and 0.8 a on CUDA while the mean free path is at least 1.6 a (phi <= 0.1099), then
L_max lambda/1.6 a, at least 0.2 a (spheres; species: the total phi; ellipsoids 0.4 a), resolved where the
backend is known (engine.driver.simulate.SceneRun), recorded in the result file's /parameters, the same in
ensembles; an explicit value always wins; the CPU default of dilute scenes is unchanged bit for bit; the
rule sits on the measured cost fronts of both backends' skin sweeps (docs/performance.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import pytest
from pydantic import ValidationError

from engine.backends.ensemble import resolve_backend
from engine.driver.ensemble import run_ensemble
from engine.setup.params import derive
from engine.driver.simulate import SceneRun, run
from engine.setup.spec import SimulationSpec, Species
from engine.setup.params import DEFAULT_VERLET_SKIN, default_verlet_skin, largest_default_verlet_skin, mean_free_path

ROOT = Path(__file__).resolve().parents[2]

# tests/engine/test_ensemble.py's tiny scene
TINY = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.01, thermalization=0.2,
            snapshots=0, backend="cpu", velocity_rms=1.0)


def test_default_table():
    assert DEFAULT_VERLET_SKIN == {"cpu": 0.4, "cuda": 0.8}
    assert SimulationSpec().verlet_skin is None
    assert default_verlet_skin("cpu") == 0.4 and default_verlet_skin("cuda") == 0.8
    # ellipsoid skins are not measured on a GPU: they keep the CPU value; an unresolved 'auto' too
    assert default_verlet_skin("cuda", "ellipsoid") == 0.4 and default_verlet_skin("auto") == 0.4


@pytest.mark.parametrize("backend, want", [("cpu", 0.4), ("cuda", 0.8)])
def test_scene_resolves_the_backend_default(tmp_path, backend, want):
    spec = SimulationSpec(**TINY)
    scene = SceneRun(spec, tmp_path / "r.h5", backend=backend)     # builds no backend: no GPU needed
    assert scene.backend == backend and scene.verlet_skin == want
    assert scene.p.skin == want * scene.p.radius
    assert scene.cool.skin == scene.therm.skin == scene.p.skin
    assert scene.spec.verlet_skin is None and json.loads(scene.spec_json)["verlet_skin"] is None


def test_cpu_default_is_unchanged(tmp_path):
    """Bit for bit the former default 0.4 a: the same derived skin as an explicit 0.4."""
    explicit = derive(SimulationSpec(**TINY, verlet_skin=0.4))
    assert SceneRun(SimulationSpec(**TINY), tmp_path / "r.h5").p == explicit
    assert derive(SimulationSpec(**TINY)) == explicit


def test_auto_resolves_like_the_backend():
    spec = SimulationSpec(**{**TINY, "backend": "auto"})
    scene = SceneRun(spec, "unused.h5")
    assert scene.verlet_skin == default_verlet_skin(resolve_backend("auto"))


@pytest.mark.parametrize("backend", ["cpu", "cuda"])
def test_explicit_skin_wins(tmp_path, backend):
    scene = SceneRun(SimulationSpec(**TINY, verlet_skin=0.3), tmp_path / "r.h5", backend=backend)
    assert scene.verlet_skin == 0.3 and scene.p.skin == 0.3 * scene.p.radius


def test_cuda_spec_derives_the_cuda_default():
    """derive() alone (benches, validation scripts) reads the spec's own backend."""
    p = derive(SimulationSpec(**{**TINY, "backend": "cuda"}))
    assert p.skin == 0.8 * p.radius


def test_skin_in_result_parameters(tmp_path):
    out = tmp_path / "r.h5"
    run(SimulationSpec(**TINY), out)
    with h5py.File(out) as f:
        par = f["parameters"].attrs
        assert float(par["verlet_skin"]) == 0.4
        assert float(par["skin"]) == pytest.approx(0.4 * float(par["radius"]), rel=1e-15)
        assert json.loads(par["spec"])["verlet_skin"] is None


def test_ensemble_scenes_resolve_per_scene(tmp_path):
    outs = [tmp_path / "a.h5", tmp_path / "b.h5"]
    res = run_ensemble([SimulationSpec(**TINY), SimulationSpec(**TINY, verlet_skin=0.6, seed=1)], outs)
    assert all(not isinstance(r, BaseException) for r in res), res
    got = []
    for o in outs:
        with h5py.File(o) as f:
            got.append(float(f["parameters"].attrs["verlet_skin"]))
    assert got == [0.4, 0.6]


def test_cuda_pack_takes_the_skin_of_its_particles(tmp_path):
    """A CUDA pack rebuilds its scenes' lists together: the large-scene rule counts the pack's particles (256 scenes
    of 4096 spheres: the skin of one scene of 2^20); a lone scene and the CPU (each scene its own lists) do not."""
    from engine.setup.params import large_scene_skin, step_radii

    small = _large(4096)
    packed = SceneRun(small, tmp_path / "p.h5", backend="cuda", pack_particles=1 << 20)
    want = large_scene_skin(mean_free_path(0.058), step_radii(small), "cuda", 1 << 20)
    assert packed.verlet_skin == want < 0.1
    assert packed.p.skin == pytest.approx(want * packed.p.radius, rel=1e-14) and packed.cool.skin == packed.p.skin
    assert SceneRun(small, tmp_path / "a.h5", backend="cuda").verlet_skin == 0.8
    assert SceneRun(small, tmp_path / "c.h5", backend="cpu", pack_particles=1 << 20).verlet_skin == 0.4
    explicit = small.model_copy(update={"verlet_skin": 0.6})
    assert SceneRun(explicit, tmp_path / "e.h5", backend="cuda", pack_particles=1 << 20).verlet_skin == 0.6


def test_huge_float64_scenes_keep_a_float32_list_reference():
    """The large-scene rule does not thin the skin of a CUDA scene of float64 positions below the skin at which its
    list reference x_ref stays float32 (12 B a particle less): at 6.5e8 spheres, phi = 0.058, the rule alone would
    make x_ref float64. float32 positions, the CPU and scenes of a few million spheres take the rule as it is."""
    import numpy as np

    from engine.loops.cuda_memory import xref_dtype
    from engine.setup.params import large_scene_skin, step_radii, verlet_skin_radii, with_backend

    def spec(n, precision):
        return SimulationSpec(n_particles=n, volume_fraction=0.058, precision=precision, backend="cuda",
                              box_length=2.0, stiffness=1e8, density=2000.0, velocity_rms=2.0, start="random")

    huge = spec(650_000_000, "float64")
    rule = large_scene_skin(mean_free_path(0.058), step_radii(huge), "cuda", huge.n_particles)
    p = derive(huge)
    assert xref_dtype(np.float64, [huge.box_length], [rule * p.radius]) == np.float64      # the rule alone
    got = verlet_skin_radii(huge, "cuda")
    assert rule < got < 0.8
    assert xref_dtype(np.float64, [huge.box_length], [with_backend(p, huge, "cuda").skin]) == np.float32
    assert verlet_skin_radii(spec(650_000_000, "mixed"), "cuda") == got
    assert verlet_skin_radii(spec(650_000_000, "float32"), "cuda") == rule
    assert verlet_skin_radii(huge, "cpu") == large_scene_skin(mean_free_path(0.058), step_radii(huge), "cpu")
    small = spec(1 << 21, "float64")
    assert verlet_skin_radii(small, "cuda") == large_scene_skin(mean_free_path(0.058), step_radii(small), "cuda",
                                                                  small.n_particles)


def test_run_ensemble_counts_the_pack(tmp_path, monkeypatch):
    """run_ensemble hands every scene the particles of the whole pack."""
    import engine.driver.ensemble as ens
    from engine.errors import SpecError

    seen = []

    class Spy:
        def __init__(self, spec, output, **kw):
            seen.append(kw["pack_particles"])
            raise SpecError("spied")

    monkeypatch.setattr(ens, "SceneRun", Spy)
    specs = [SimulationSpec(**{**TINY, "n_particles": n}) for n in (64, 100, 36)]
    res = run_ensemble(specs, [tmp_path / f"{k}.h5" for k in range(3)])
    assert all(isinstance(r, SpecError) for r in res) and seen == [200, 200, 200]


def test_box_check_uses_the_largest_default():
    # 13 spheres at phi = 0.1 in a box of 8.17 radii: 3 neighbour cutoffs are 7.2 a at L_v = 0.4 a, 8.4 a at 0.8 a
    tight = dict(n_particles=13, volume_fraction=0.1, box_length=0.2, velocity_rms=0.5)
    SimulationSpec(**tight, backend="cpu")                       # the CPU default fits
    SimulationSpec(**tight, backend="auto", verlet_skin=0.4)     # an explicit skin is checked as given
    for backend in ("auto", "cuda"):                              # the run may land on a GPU: 0.8 a must fit
        with pytest.raises(ValidationError, match="verlet_skin = 0.8, the default of backend"):
            SimulationSpec(**tight, backend=backend)


def test_box_check_uses_the_default_at_the_spec_density():
    # 23 spheres at phi = 0.3 in a box of 6.85 radii: 3 cutoffs are 6.6 a at L_v = 0.2 a (the default there on
    # both backends), 7.2 a at 0.4 a
    dense = dict(n_particles=23, volume_fraction=0.3, box_length=0.2, velocity_rms=0.5)
    assert largest_default_verlet_skin("auto", "sphere", 0.3) == 0.2
    for backend in ("cpu", "cuda", "auto"):
        SimulationSpec(**dense, backend=backend)
    with pytest.raises(ValidationError, match="verlet_skin = 0.4\\)"):
        SimulationSpec(**dense, verlet_skin=0.4)


# ---- the density-dependent rule ----------------------------------------------------------------------

def test_mean_free_path():
    # lambda/a = 1/(3 sqrt(2) phi g), Carnahan-Starling g: 28.9 at the phi of Hidalgo et al. (2013), 1.81 at 0.1,
    # 0.317 at 0.3
    assert mean_free_path(0.008) == pytest.approx(28.877, rel=1e-4)
    assert mean_free_path(0.1) == pytest.approx(1.8087, rel=1e-4)
    assert mean_free_path(0.3) == pytest.approx(0.31704, rel=1e-4)


@pytest.mark.parametrize("phi, cpu, cuda", [
    (0.008, 0.4, 0.8), (0.058, 0.4, 0.8), (0.1, 0.4, 0.8),     # swept (0.008, 0.1) and the paper scenes: L_max
    (0.15, 0.4 * 1.04325 / 1.6, 0.8 * 1.04325 / 1.6),        # L_max lambda / 1.6 a
    (0.2, 0.2, 0.8 * 0.670442 / 1.6),                          # CPU at the floor from phi = 0.179
    (0.3, 0.2, 0.2),                                           # swept: both at the floor (CUDA from 0.267)
])
def test_rule_values(phi, cpu, cuda):
    assert default_verlet_skin("cpu", "sphere", phi) == pytest.approx(cpu, rel=1e-4)
    assert default_verlet_skin("cuda", "sphere", phi) == pytest.approx(cuda, rel=1e-4)
    assert default_verlet_skin("cuda", "ellipsoid", phi) == 0.4      # ellipsoids: 0.4 at any phi


def test_cpu_dilute_default_is_exactly_0_4():
    """Every phi up to the paper scenes' 0.058 (and on to 0.109) gives the float 0.4 itself: bit-identical runs."""
    for k in range(1, 110):
        phi = k / 1000.0
        assert default_verlet_skin("cpu", "sphere", phi) == 0.4, phi
        assert default_verlet_skin("cuda", "sphere", phi) == 0.8, phi


def test_rule_is_monotone_and_bounded():
    for backend in ("cpu", "cuda"):
        vals = [default_verlet_skin(backend, "sphere", k / 1000.0) for k in range(1, 600)]
        assert all(0.2 <= v <= DEFAULT_VERLET_SKIN[backend] for v in vals)
        assert all(b <= a for a, b in zip(vals, vals[1:]))
        assert vals[-1] == 0.2


def skin_sweep_table(backend: str) -> list[dict]:
    r"""The measured skin sweep of docs/performance.md for ``backend``: rows {phi, skin, cundall, marked} from the
    Markdown table after the marker ``<!-- skin-sweep: BACKEND -->`` (written from `python -m bench accuracy`);
    ``marked``: the cell carries the table's default mark ``\*``."""
    lines = (ROOT / "docs" / "performance.md").read_text().splitlines()
    start = lines.index(f"<!-- skin-sweep: {backend} -->") + 1
    skins = [float(c) for c in lines[start].strip().strip("|").split("|")[1:]]
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        phi, *cells = [c.strip() for c in line.strip().strip("|").split("|")]
        for skin, cell in zip(skins, cells):
            marked = cell.endswith(r"\*")
            rows.append({"phi": float(phi), "skin": skin, "cundall": float(cell.removesuffix(r"\*")),
                         "marked": marked})
    return rows


@pytest.mark.parametrize("backend", ["cpu", "cuda"])
def test_rule_on_the_measured_cost_fronts(backend):
    """At every swept phi of the measured skin sweep (docs/performance.md), the rule's skin is a swept skin, is the
    one the table marks as the default, and runs within the timing noise (15 %) of the fastest one, as the accuracy
    report's verdict asks. A change of the rule must come with a new sweep."""
    from bench.accuracy import TIME_NOISE, sweep_default_row

    rows = skin_sweep_table(backend)
    assert {r["phi"] for r in rows} == {0.008, 0.1, 0.3} and len(rows) == 12
    for phi in sorted({r["phi"] for r in rows}):
        want, row, exact = sweep_default_row(rows, phi, backend)
        best = max(r["cundall"] for r in rows if r["phi"] == phi)
        assert exact and row["cundall"] >= (1.0 - TIME_NOISE) * best, (backend, phi, want)
        assert [r["skin"] for r in rows if r["phi"] == phi and r["marked"]] == [want], (backend, phi)


@pytest.mark.parametrize("backend, want", [("cpu", 0.2), ("cuda", 0.2)])
def test_dense_scene_resolves_the_rule(tmp_path, backend, want):
    spec = SimulationSpec(**{**TINY, "volume_fraction": 0.3})
    scene = SceneRun(spec, tmp_path / "r.h5", backend=backend)
    assert scene.verlet_skin == want and scene.p.skin == want * scene.p.radius
    explicit = SceneRun(SimulationSpec(**{**TINY, "volume_fraction": 0.3, "verlet_skin": 0.8}), tmp_path / "e.h5",
                        backend=backend)
    assert explicit.verlet_skin == 0.8                       # an explicit value wins at any density


def test_intermediate_density_cuda(tmp_path):
    scene = SceneRun(SimulationSpec(**{**TINY, "volume_fraction": 0.15}), tmp_path / "r.h5", backend="cuda")
    assert scene.verlet_skin == default_verlet_skin("cuda", "sphere", 0.15)
    assert scene.verlet_skin == pytest.approx(0.8 * mean_free_path(0.15) / 1.6)


def test_species_use_the_total_volume_fraction(tmp_path):
    species = [Species(radius_ratio=1.0, number_fraction=0.5), Species(radius_ratio=0.5, number_fraction=0.5)]
    spec = SimulationSpec(**{**TINY, "volume_fraction": 0.25, "species": species})
    scene = SceneRun(spec, tmp_path / "r.h5", backend="cpu")
    assert scene.verlet_skin == default_verlet_skin("cpu", "sphere", 0.25) == 0.2
    assert scene.p.skin == pytest.approx(0.2 * scene.p.radius_min, rel=1e-12)   # radii of the smallest species
    assert math.isclose(SceneRun(spec, tmp_path / "c.h5", backend="cuda").verlet_skin,
                        0.8 * mean_free_path(0.25) / 1.6)


def test_dense_skin_in_result_parameters(tmp_path):
    out = tmp_path / "r.h5"
    run(SimulationSpec(**{**TINY, "volume_fraction": 0.3}), out)
    with h5py.File(out) as f:
        par = f["parameters"].attrs
        assert float(par["verlet_skin"]) == 0.2
        assert float(par["skin"]) == pytest.approx(0.2 * float(par["radius"]), rel=1e-15)
        assert json.loads(par["spec"])["verlet_skin"] is None


# ---- the large-scene rule (spheres, N >= LARGE_SCENE_PARTICLES[backend]) -------------------------------------------

def test_large_scene_skin_formula():
    """L_v = max(L_min, L_0 sqrt((lambda / 3.5) (s / 5e-5) (1 + N_0 / N))): the reference gas, the square roots, the
    rebuild's fixed cost spread over N (CUDA only), the floor; per backend."""
    from engine.setup.params import large_scene_skin

    big = 1 << 40       # N_0 / N = 5e-7: the square root within 3e-7 of the N-free value
    for backend, l0, floor in (("cuda", 0.045, 0.03), ("cpu", 0.12, 0.1)):
        assert large_scene_skin(3.5, 5e-5, backend, big) == pytest.approx(l0, rel=1e-6)
        assert large_scene_skin(4 * 3.5, 5e-5, backend, big) == pytest.approx(2 * l0, rel=1e-6)   # sqrt of lambda
        assert large_scene_skin(3.5, 4 * 5e-5, backend, big) == pytest.approx(2 * l0, rel=1e-6)   # sqrt of s
        assert large_scene_skin(mean_free_path(0.3), 5e-5, backend, big) == floor                 # the floor
    # CUDA: 1 + N_0 / N with N_0 = 2^19; the CPU counts no fixed cost
    assert large_scene_skin(3.5, 5e-5, "cuda", 1 << 19) == pytest.approx(0.045 * math.sqrt(2), rel=1e-12)
    assert large_scene_skin(3.5, 5e-5, "cuda", 1 << 17) == pytest.approx(0.045 * math.sqrt(5), rel=1e-12)
    assert large_scene_skin(3.5, 5e-5, "cpu", 1 << 15) == pytest.approx(0.12, rel=1e-12)


def test_step_radii_is_the_rms_flight_per_step():
    from engine.setup.params import step_radii

    spec = SimulationSpec(**TINY)
    p = derive(spec)
    assert step_radii(spec) == pytest.approx(spec.velocity_rms * p.dt / p.radius, rel=1e-14)


def _large(n, phi=0.058, **kw):
    from bench.loop_ab import case_specs

    return case_specs("rough-2M-f64", 6000, n=n, phi=phi, **kw)[0]


@pytest.mark.parametrize("backend, general", [("cuda", 0.8), ("cpu", 0.4)])
def test_large_scenes_take_the_large_scene_rule(backend, general):
    from engine.setup.params import LARGE_SCENE_PARTICLES, large_scene_skin, step_radii, verlet_skin_radii

    n = LARGE_SCENE_PARTICLES[backend]
    big = _large(n)
    want = large_scene_skin(mean_free_path(0.058), step_radii(big), backend, n)
    assert 0.05 < want < 0.2
    assert verlet_skin_radii(big, backend) == want
    p = derive(big.model_copy(update={"backend": backend}))
    assert p.skin == pytest.approx(want * p.radius, rel=1e-14)
    # one particle fewer: the general rule; spheroids and an explicit skin are untouched
    assert verlet_skin_radii(_large(n - 1), backend) == general
    assert verlet_skin_radii(big.model_copy(update={"verlet_skin": 0.6}), backend) == 0.6
    assert default_verlet_skin(backend, "ellipsoid", 0.058, 1 << 21, 5e-5) == 0.4
    # a faster gas moves further a step: a thicker skin
    fast = _large(n, velocity_rms=4 * big.velocity_rms)
    assert verlet_skin_radii(fast, backend) == pytest.approx(2 * want, rel=1e-12)


def test_the_thresholds():
    """CUDA from 2^17 (at 32 768 spheres the skins ran within 8 %); the CPU from 2^15, so that the papers' scenes and
    the quick start (4096 spheres) keep their skin and their bits; an unresolved 'auto' takes no large-scene rule."""
    from engine.setup.params import LARGE_SCENE_PARTICLES, verlet_skin_radii

    assert LARGE_SCENE_PARTICLES == {"cuda": 1 << 17, "cpu": 1 << 15}
    assert verlet_skin_radii(_large(1 << 16), "cuda") == 0.8 and verlet_skin_radii(_large(1 << 16), "cpu") < 0.2
    assert verlet_skin_radii(_large(1 << 20), "auto") == 0.4
    assert verlet_skin_radii(SimulationSpec(**{**TINY, "n_particles": 4096}), "cpu") == 0.4


def test_large_scene_rule_never_thickens_the_skin():
    """The spec's box check knows the general rule (largest_default_verlet_skin): the large-scene rule stays under it
    at every phi, flight per step and N."""
    from engine.setup.params import LARGE_SCENE_SKIN_FLOOR

    for backend in ("cuda", "cpu"):
        for k in range(1, 600, 7):
            phi = k / 1000.0
            general = default_verlet_skin(backend, "sphere", phi)
            for s in (1e-6, 5e-5, 1e-3, 1e-1):
                for n in (1 << 17, 1 << 22, 1 << 30):
                    got = default_verlet_skin(backend, "sphere", phi, n, s)
                    assert LARGE_SCENE_SKIN_FLOOR[backend] <= got <= general <= largest_default_verlet_skin(
                        "auto", "sphere", phi)


def large_skin_table(backend: str) -> list[dict]:
    """docs/performance.md's measured table of the large-scene rule on ``backend`` (after
    ``<!-- skin-sweep: BACKEND-large -->``):
    per row the `bench loop_ab` scene (case, N, phi, v_rms, steps), the rule's skin, the loop Cundall numbers at it
    and at the other skins tried."""
    lines = (ROOT / "docs" / "performance.md").read_text().splitlines()
    start = lines.index(f"<!-- skin-sweep: {backend}-large -->") + 3
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        case, n, phi, v, steps, rule, at_rule, others = [c.strip() for c in line.strip().strip("|").split("|")]
        rows.append({"case": case.strip("`"), "n": int(n.replace(" ", "")), "phi": float(phi),
                     "velocity_rms": float(v), "steps": int(steps), "rule": float(rule),
                     "at_rule": [float(x) for x in at_rule.split(",")],
                     "others": {float(k): [float(x) for x in v.split(",")]
                                for k, v in (c.split(":") for c in others.split(";"))}})
    return rows


@pytest.mark.parametrize("backend, min_rows", [("cuda", 6), ("cpu", 4)])
def test_large_scene_rule_on_the_measured_cost_front(backend, min_rows):
    """Every measured scene: the code's rule gives the skin the table was measured at (a change of the rule needs a
    new measurement), and that skin runs within the timing noise (15 %) of the fastest skin tried."""
    from bench.accuracy import TIME_NOISE
    from bench.loop_ab import case_specs
    from engine.setup.params import verlet_skin_radii

    rows = large_skin_table(backend)
    assert len(rows) >= min_rows and {r["phi"] for r in rows} >= {0.008, 0.058, 0.2}
    for r in rows:
        spec = case_specs(r["case"], r["steps"], n=r["n"], phi=r["phi"], velocity_rms=r["velocity_rms"])[0]
        assert round(verlet_skin_radii(spec, backend), 4) == r["rule"], r
        best = max(max(v) for v in r["others"].values())
        assert max(r["at_rule"]) >= (1.0 - TIME_NOISE) * best, r
