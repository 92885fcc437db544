"""Smoke tests of `python -m bench accuracy` and `python -m bench specialisation` on their tiny variants.

They run every report builder on the smallest scenes, check the report files, and check the errors that
physics says must shrink with dt (the full reports' figures are in docs/performance.md).
"""

from __future__ import annotations

import json
import math

import pytest

from bench import accuracy, specialisation


@pytest.fixture(scope="module")
def acc(tmp_path_factory):
    out = tmp_path_factory.mktemp("accuracy")
    assert accuracy.main(out_dir=out, variant="tiny", backend="cpu", threads=1, log=lambda *_: None) == 0
    return out, json.loads((out / "summary.json").read_text())


def _row(rows, frac, prec="float64", skin=0.4):
    (r,) = [r for r in rows if r["dt_fraction"] == frac and r["precision"] == prec and r.get("skin", 0.4) == skin]
    return r


@pytest.mark.heavy   # the tiny accuracy report (fixture acc): about two minutes of one core
def test_accuracy_report_files(acc):
    out, s = acc
    text = (out / "REPORT.md").read_text()
    assert "Pareto" in text and "Verdict on the defaults" in text and s["machine"]["cpu"] in text
    assert (out / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(s["scenes"]) == {"collisions", "elastic_smooth", "elastic_rough", "cooling", "skin_sweep", "ellipsoid"}
    assert s["default_skin"] == 0.4 and "L_v = 0.4 a on this backend" in text
    sweep = s["scenes"]["skin_sweep"]["rows"]
    assert sweep and all(r["cundall"] > 0 and 0 < r["vs_fastest"] <= 1 for r in sweep)
    assert s["defaults_on_front"]["skin_sweep"] in (True, False)
    for name, block in s["scenes"].items():
        if name == "skin_sweep":
            continue
        assert block["rows"], name
        for r in block["rows"]:
            assert math.isfinite(r["error"]) and r["cundall"] > 0, (name, r)
        # the front is what pareto() says: no front row is dominated by any row
        front = [r for r in block["rows"] if r["on_front"]]
        assert front and all(not accuracy.dominates(q, p, block.get("floor", 0.0))
                             for p in front for q in block["rows"] if q is not p)
        assert s["defaults_on_front"][name] in (True, False)


@pytest.mark.heavy   # the tiny accuracy report (fixture acc): about two minutes of one core
def test_restitution_error_shrinks_with_dt(acc):
    rows = acc[1]["scenes"]["collisions"]["rows"]
    coarse, default, fine = (_row(rows, f) for f in (10, 50, 200))
    # The event-corrected contact law is second order in dt (docs/physics.md §1.5): a 20x smaller dt must
    # cut the head-on error by far more than 10x (measured ~100x; dt^2 alone would give 400x).
    assert fine["err_e_n"] < coarse["err_e_n"] / 10
    assert default["err_e_n"] < coarse["err_e_n"]
    # the README's figure for the default: |de_n| within 4e-4 at dt = t_c/50
    assert default["err_e_n"] < 4e-4
    assert default["err_e_t"] < coarse["err_e_t"]


@pytest.mark.heavy   # the tiny accuracy report (fixture acc): about two minutes of one core
def test_elastic_energy_error_per_collision_shrinks_with_dt(acc):
    smooth = acc[1]["scenes"]["elastic_smooth"]["rows"]
    # velocity Verlet with event corrections: energy error O(dt^2) or better per contact (smooth: nothing else)
    assert _row(smooth, 200)["error"] < _row(smooth, 50)["error"] < _row(smooth, 10)["error"] / 10
    rough = acc[1]["scenes"]["elastic_rough"]
    # rough: the part dt adds to the model's own loss; zero at the reference itself
    assert _row(rough["rows"], 200)["error"] == 0.0
    assert _row(rough["rows"], 50)["error"] < _row(rough["rows"], 10)["error"] / 10
    # the model's own loss does not depend on dt: t_c/200 and t_c/800 agree (it is not a dt error)
    ml = rough["model_loss"]
    assert ml["eps_ref"] < 0 and abs(ml["eps_fine"] - ml["eps_ref"]) < 0.2 * abs(ml["eps_ref"])
    assert all(r["pairs_apart"] for r in smooth + rough["rows"])


@pytest.mark.heavy   # the tiny accuracy report (fixture acc): about two minutes of one core
def test_ellipsoid_geometry_precision(acc):
    rows = acc[1]["scenes"]["ellipsoid"]["rows"]
    f64 = [r for r in rows if r["precision"] == "float64"][0]
    f32 = [r for r in rows if r["precision"] == "float32"][0]
    # bounds of tests/engine/test_ellipsoid_geometry.py (rounding of 1 - W_0^2 in each precision)
    assert f64["error"] < 1e-13 and f32["error"] < 3e-5
    assert f64["nan"] == 0 and f32["nan"] == 0 and f64["missed"] == 0


def test_pareto_marks_a_dominated_default():
    rows = [{"dt_fraction": 50, "precision": "float64", "skin": 0.4, "error": 1e-3, "throughput": 1.0},
            {"dt_fraction": 35, "precision": "float64", "skin": 0.4, "error": 5e-4, "throughput": 2.0},
            {"dt_fraction": 10, "precision": "float64", "skin": 0.4, "error": 1e-2, "throughput": 5.0},
            {"dt_fraction": 20, "precision": "float64", "skin": 0.4, "error": 1e-2, "throughput": 5.2}]
    front = accuracy.pareto(rows)
    assert [r["dt_fraction"] for r in front] == [35, 10, 20]      # 5.2 vs 5.0: a tie within timing noise
    assert not rows[0]["on_front"] and rows[0]["dominated_by"] == ["t_c/35 float64"]
    # below a floor, errors are equal: the faster point wins
    accuracy.pareto(rows, floor=2e-2)
    assert [r["on_front"] for r in rows] == [False, False, True, True]


def test_front_with_error_bars():
    """Errors the seed scatter cannot rank: neither row dominates; resolved: the more accurate one is kept."""
    cheap = {"dt_fraction": 35, "precision": "float64", "skin": 0.4, "error": 6e-6, "error_se": 1e-6, "throughput": 2.0}
    dear = {"dt_fraction": 50, "precision": "float64", "skin": 0.4, "error": 4e-6, "error_se": 1e-6, "throughput": 1.0}
    assert not accuracy.dominates(cheap, dear) and not accuracy.dominates(dear, cheap)   # 2e-6 < 2 x hypot(SE)
    assert accuracy.unresolved(cheap, dear)
    cheap["error_se"] = dear["error_se"] = 0.3e-6
    assert not accuracy.dominates(cheap, dear) and not accuracy.unresolved(cheap, dear)  # resolved: a trade-off
    cheap["error"] = 3e-6
    assert accuracy.dominates(cheap, dear)          # resolved more accurate and cheaper
    # the same error to rounding (the skin rows run one trajectory): the measurably cheaper row wins
    a = {"dt_fraction": 50, "precision": "float64", "skin": 0.4, "error": 1e-3, "throughput": 1.0}
    b = dict(a, skin=0.8, error=1.01e-3, throughput=1.3)
    assert accuracy.dominates(b, a) and not accuracy.dominates(a, b)


@pytest.mark.heavy   # compiles a kernel of every specialisation the report compares: over a minute on 2 cores
def test_specialisation_report(tmp_path):
    assert specialisation.main(out_dir=tmp_path, variant="tiny", backend="cpu", threads=1,
                               log=lambda *_: None) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (tmp_path / "REPORT.md").read_text().startswith("# Compile-time specialisations")
    names = {r["variant"] for r in s["spheres"]}
    assert {"baseline", "smooth", "coulomb", "orientation", "float32", "maximal"} <= names
    assert all(r["cundall"] > 0 and math.isfinite(r["cundall"]) for r in s["spheres"] + s["output"])
    assert {r["variant"] for r in s["ellipsoids"]["rows"]} == {"float64", "float32"}
