"""Reduced Sonine check (docs/physics.md §7.4); the full comparison is `demq validate sonine --ensemble` on a GPU.
The DSMC reference is checked against two exact limits first."""

import json

import pytest

from engine.validation import sonine as v
from tests.extras import needs_plots


def test_dsmc_elastic_limit_is_maxwellian():
    """alpha = 1: the Boltzmann equilibrium, a2 = 0; 4 repeats x N = 20000 give a standard error ~0.001 (the
    t-distribution with 3 dof puts 99 % within 5.8 s.e.; 0.004 absolute covers a bad error estimate)."""
    r = v.dsmc_hcs(1.0, n=20_000, s_skip=2.0, s_end=12.0, repeats=4)
    assert abs(r["a2"]) < max(5.8 * r["a2_err"], 0.004), r


def test_dsmc_rough_limits():
    """Elastic perfectly rough spheres (alpha = beta = 1) conserve energy and relax to equipartition with zero
    cumulants (exact); at alpha = beta = 0.8 the HCS T_rot/T_tr is within 1 % of the Maxwellian fixed point of
    Luding's (A, B, C), B r^2 + (C - A) r - B = 0 (measured 0.2 %; the cumulants are small there, a02 ~ 0.04;
    at beta = 0.6 they are not, a02 ~ 0.1, and the DSMC ratio is 1.5 % below the Maxwellian one)."""
    r = v.dsmc_hcs(1.0, 1.0, n=20_000, s_skip=2.0, s_end=10.0, repeats=4)
    assert abs(r["T_ratio"] - 1) < 0.01 and abs(r["a2"]) < 0.01 and abs(r["a11"]) < 0.01, r
    r = v.dsmc_hcs(0.8, 0.8, n=20_000, s_skip=8.0, s_end=20.0, repeats=4)
    assert abs(r["T_ratio"] / v.maxwellian_temperature_ratio(0.8, 0.8) - 1) < 0.01, r["T_ratio"]


@pytest.mark.heavy   # a physics validation whose report ends in figures: the `plots` extra
@needs_plots
def test_quick_validation_runs_and_passes(tmp_path):
    """`demq validate sonine --quick --ensemble`: e_n = 0.4, 6 seeds of N = 800 as one (CPU) ensemble, the code
    path of the full GPU report (~30 s on one core)."""
    rc = v.main(out_dir=tmp_path, seeds=6, quick=True, backend="cpu", threads=1, ensemble=True)
    rows = json.loads((tmp_path / "summary.json").read_text())
    (row,) = rows
    assert rc == 0 and row["pass"], row
    assert row["a2"] > 0.03 and abs(row["dsmc"]["a2"] - 0.076) < 0.01, row
    assert "| 0.4 |" in (tmp_path / "README.md").read_text()
    assert (tmp_path / "sonine.png").stat().st_size > 1000
