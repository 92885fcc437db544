"""Reduced long-time HCS validation (`demq validate hcs-long --quick`): runs in CI (~20 s on one core).

The full run (the scene of Hidalgo et al. (2013) to tau = 100 and the shear-unstable box, on the GPU) is
`demq validate hcs-long` on a GPU."""

import json
import math

import numpy as np
import pytest

from engine.validation import hcs_long
from tests.extras import needs_plots


@pytest.mark.heavy   # a physics validation whose report ends in figures: the `plots` extra
@needs_plots
def test_quick_long_cooling_follows_the_ode_and_measures_the_modes(tmp_path):
    rc = hcs_long.main(out_dir=tmp_path, quick=True, backend="cpu", keep=True)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary) == {"quick e=0.8", "quick e=0.6"}
    for case, s in summary.items():
        assert s["L_over_Lc"] < 1.0, case                       # the CI box is linearly stable
        assert s["tau_shear_predicted"] is None                 # (inf -> null) the theory predicts no growth
        assert s["max_abs_dev"] < hcs_long.QUICK_DEV_MAX, (case, s)
        assert 0.0 < s["S_final"] < 2.5 and math.isfinite(s["x_shear_final"])
    assert rc == 0
    series = np.load(tmp_path / "series.npz")
    for case in summary:
        x = series[f"{case}/x_shear"]
        assert x.shape == (9,) and np.all(np.isfinite(x))
        assert abs(x[0] - 1.0) < 0.75                            # thermal noise at tau = 0
    for case in summary:
        # collision rate (the collision counter's) over Enskog's: 1 in this dilute stable box within the few
        # hundred collisions' count noise of 4 short seeds (a factor-2 slip would show)
        coll = series[f"{case}/coll"]
        assert np.all(np.isfinite(coll)) and 0.85 < float(np.mean(coll[1:])) < 1.15, (case, np.mean(coll))
        assert np.all(np.isfinite(series[f"{case}/dev_rate"]))
        # energy change per collision over the Maxwellian closure's: ~1 here (soft contact and distribution move
        # it by ~1 %); per tau window the 4-seed SE is 5-50 %, so only the SE-weighted mean over tau >= 1 is
        # checked, to 20 % (a factor 2 in the collision count or the closure would fail)
        tau, lam, se = series[f"{case}/tau"], series[f"{case}/loss_T"], series[f"{case}/loss_T_err"]
        sel = (tau >= 1.0) & np.isfinite(lam) & (se > 0)
        assert sel.sum() > 20 and abs(np.average(lam[sel], weights=se[sel] ** -2.0) - 1.0) < 0.2, (case, lam[sel])
    # the reduced runs (runs.npz) give the same analysis; merged reports refuse a seed twice
    cases, meta = hcs_long.load_runs(tmp_path / "runs.npz")
    assert {k: sorted(v) for k, v in cases.items()} == {c: [0, 1, 2, 3] for c in summary} and meta["runs"] == 8
    merged = hcs_long.merge([tmp_path], tmp_path / "merged", "test")
    for case in summary:
        for name in ("T", "R", "coll", "loss_T", "loss_R_err", "x_shear", "S"):
            assert np.allclose(merged[case][name], series[f"{case}/{name}"], equal_nan=True), (case, name)
    assert (tmp_path / "merged" / "runs.npz").exists() and (tmp_path / "merged" / "README.md").exists()
    with pytest.raises(ValueError, match="seed 0 is already"):
        hcs_long.merge([tmp_path, tmp_path / "merged"], tmp_path / "twice", "test")
    readme = (tmp_path / "README.md").read_text()
    assert "Collision rate against Enskog" in readme and "Counted: every contact begun" in readme
    assert "Garzó" in readme and "Luding" in readme and "| quick e=0.8 |" in readme
    assert (tmp_path / "deviation.png").stat().st_size > 1000 and (tmp_path / "modes.png").stat().st_size > 1000
    # the analysis CLI on one case's result files: seed-mean series at the frame times
    files = sorted(str(p) for p in (tmp_path / "runs").glob("quick_e0.8_seed*.h5"))
    assert len(files) == 4
    # the counter's rate and the open contacts' rate measure the same thing: their means over the 4 seeds agree
    # within the open contacts' count noise (~1 contact per record: ~5 %)
    runs = [hcs_long._read_run(f) for f in files]
    assert all(r["collisions"] is not None and np.all(np.diff(r["collisions"][1]) >= 0) for r in runs)
    by_counter = np.mean([hcs_long.collision_rate_ratio(r)[1:].mean() for r in runs])
    by_contacts = np.mean([hcs_long.collision_rate_ratio({**r, "collisions": None})[1:].mean() for r in runs])
    assert abs(by_counter / by_contacts - 1) < 0.15, (by_counter, by_contacts)
    assert hcs_long._cli(["analyse", *files, "-o", str(tmp_path / "e08.csv")]) == 0
    rows = (tmp_path / "e08.csv").read_text().splitlines()
    assert rows[0].startswith("tau,T,T_err,T_ode,dev") and len(rows) == 1 + 9
    table = np.array([[float(v) for v in r.split(",")] for r in rows[1:]])
    assert np.all(np.isfinite(table))
    assert np.allclose(table[:, 6], series["quick e=0.8/x_shear"], rtol=1e-4)


def test_contact_duration_is_how_long_the_engine_keeps_two_spheres_in_contact():
    """The collision-rate measure divides the open contacts by pi/omega: check it against two real spheres."""
    from types import SimpleNamespace

    from engine.backends.base import ContactParams, SphereSystem
    from engine.setup.params import gamma_n_from_restitution
    from engine.shapes.sphere.cpu_backend import CpuBackend

    k_n, m, a, e_n = 1.0e5, 1.0e-2, 0.01, 0.6
    m12 = m / 2
    gamma = gamma_n_from_restitution(e_n, k_n, m12)
    t_c = hcs_long.contact_duration(SimpleNamespace(gamma_n=gamma, m12=m12, omega0=math.sqrt(k_n / m12)))
    assert t_c > math.pi * math.sqrt(m12 / k_n)                  # damping lengthens it
    dt = t_c / 400
    system = SphereSystem(box_length=1.0, position=np.array([[0.5 - a - 1e-6, 0.5, 0.5], [0.5 + a + 1e-6, 0.5, 0.5]]),
                          velocity=np.array([[0.5, 0.1, 0.0], [-0.5, 0.0, 0.0]]), angular_velocity=np.zeros((2, 3)),
                          orientation=np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)), radius=np.full(2, a), mass=np.full(2, m),
                          inertia=np.full(2, 0.4 * m * a * a))
    be = CpuBackend(system, ContactParams(k_n=k_n, gamma_n_coef=gamma / math.sqrt(m12), k_t=None, friction=None,
                                          dt=dt, skin=0.2 * a, precision="float64", orientation=False,
                                          overlap_limit=0.5))
    steps_in_contact = 0
    for _ in range(800):
        be.advance(1)
        steps_in_contact += be.observe()["contacts"]
    # the overlap opens within the first step (gap 1e-6 m at 1 m/s) and closes within a step of pi/omega
    assert abs(steps_in_contact * dt - t_c) <= 2 * dt, (steps_in_contact, t_c / dt)


def test_quick_checks_fail_on_a_deviating_or_clustered_case():
    tau = np.linspace(0, 4, 81)
    good = {"tau": tau, "dev": np.zeros_like(tau), "dev_err": np.full_like(tau, 0.005),
            "x_shear": np.ones(9), "x_long": np.ones(9), "S": np.full(9, 0.6), "shear_fraction": np.full(9, 0.004),
            "S_cs": 0.67}
    assert hcs_long.quick_checks({"ok": good}) == []
    bad = dict(good, dev=np.where(tau > 2, 0.04, 0.0))          # 4 % > 1 % + 3 x 0.5 %
    assert any("exceeds" in p for p in hcs_long.quick_checks({"b": bad}))
    assert hcs_long.quick_checks({"b": dict(good, x_shear=np.full(9, 2.0))})   # x(0) = 2: not noise
    assert hcs_long.quick_checks({"b": dict(good, S=np.full(9, 3.0))})          # clustered
    assert hcs_long.quick_checks({"b": dict(good, x_shear=np.linspace(1, 5, 9))})  # shear grew
    lam = {"loss_T": np.ones_like(tau), "loss_T_err": np.full_like(tau, 0.05)}
    assert hcs_long.quick_checks({"ok": dict(good, **lam)}) == []
    halved = dict(good, **{**lam, "loss_T": np.full_like(tau, 0.5)})   # a factor 2 in the collision count
    assert any("per collision" in p for p in hcs_long.quick_checks({"b": halved}))


def test_cli_dispatches_hcs_long(monkeypatch):
    import argparse

    from engine import cli, optional

    seen = {}
    monkeypatch.setattr(hcs_long, "main", lambda **kw: seen.update(kw) or 0)
    monkeypatch.setattr(optional, "require_matplotlib", lambda what: None)   # the dispatch, with or without plots
    ap = argparse.ArgumentParser()
    cli.register(ap.add_subparsers())
    args = ap.parse_args(["validate", "hcs-long", "--quick", "--backend", "cpu", "-o", "x"])
    assert args.func(args) == 0
    assert seen["quick"] and seen["backend"] == "cpu" and seen["out_dir"] == "x"
    assert seen["command"].startswith("demq validate hcs-long -o x")
