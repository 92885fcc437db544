"""Batch statistics: the aggregation on synthetic data with known answers, the HTTP routes, and a sweep
submitted over HTTP that runs as one ensemble with the real engine."""

from __future__ import annotations

import io
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

from engine.analysis.ensemble_stats import (Run, aggregate, mean_and_standard_error, read_batch_result,
                                            write_batch_result)
from engine.analysis.theory import DOF_SMOOTH_SPHERE, haff_rate, haff_rate_smooth_spheres
from engine.setup.params import derive
from engine.setup.spec import SimulationSpec
from service.app import create_app
from tests.extras import assert_figure
from tests.jobs.conftest import TINY, make_settings
from tests.service.conftest import finish_with_fake_result
from tests.waiting import wait_for

REAL = "engine.driver.simulate:run"


# ---- the estimator ---------------------------------------------------------------------------------------

def test_mean_and_standard_error_known_answer():
    values = np.array([[1.0, 2.0, 10.0], [3.0, 2.0, 14.0], [5.0, 2.0, 12.0], [7.0, 2.0, 8.0]])
    mean, se = mean_and_standard_error(values)
    assert np.allclose(mean, [4.0, 2.0, 11.0])
    # s^2 = sum (x - mean)^2 / (K - 1): column 0: (9+1+1+9)/3 = 20/3; column 2: (1+9+1+9)/3 = 20/3
    assert np.allclose(se, [np.sqrt(20 / 3) / 2, 0.0, np.sqrt(20 / 3) / 2])
    mean1, se1 = mean_and_standard_error(values[:1])
    assert np.array_equal(mean1, values[0]) and np.isnan(se1).all()  # one seed: no spread estimate
    with pytest.raises(ValueError, match="at least one run"):
        mean_and_standard_error(np.zeros((0, 3)))


def test_standard_error_falls_like_one_over_sqrt_k():
    """SE^2 = s^2/K is unbiased for sigma^2/K, so over M independent batches mean(SE^2(K=2)) /
    mean(SE^2(K=8)) estimates 4. Var(s^2) = 2 sigma^4/(K-1): the relative standard deviation of the mean
    of SE^2 over M = 4000 batches is sqrt(2/(K-1)/M) = 2.2 % (K = 2) and 0.8 % (K = 8), 2.4 % for the
    ratio; 10 % is four of those. (The mean of SE itself is biased by c4(K) and would not give 2.)"""
    rng = np.random.default_rng(20240608)
    sigma, m, t = 0.3, 4000, 5
    ratios = {}
    for k in (2, 8):
        se2 = np.array([mean_and_standard_error(1.0 + sigma * rng.normal(size=(k, t)))[1] ** 2 for _ in range(m)])
        ratios[k] = se2.mean(axis=0)
        assert np.allclose(ratios[k], sigma**2 / k, rtol=4 * np.sqrt(2 / (k - 1) / m))
    assert np.allclose(ratios[2] / ratios[8], 4.0, rtol=0.10)
    assert np.allclose(np.sqrt(ratios[2] / ratios[8]), 2.0, rtol=0.05)  # SE ~ 1/sqrt(K)


def test_haff_rate_is_the_smooth_sphere_rate_with_three_degrees_of_freedom():
    spec = SimulationSpec(**TINY)
    p = derive(spec)
    direct = haff_rate_smooth_spheres(0.7, p.radius, p.number_density, p.mass, spec.volume_fraction,
                                      p.temperature0)
    assert haff_rate(0.7, p.collision_rate0, DOF_SMOOTH_SPHERE) == pytest.approx(direct, rel=1e-12)


# ---- aggregation of result files -------------------------------------------------------------------------

def _result(path: Path, spec: dict, temps, rot_factor=0.8, steps=None):
    """A result file with the observables the aggregation reads (and the spec)."""
    temps = np.asarray(temps, float)
    steps = np.arange(len(temps)) * 10 if steps is None else np.asarray(steps)
    with h5py.File(path, "w") as f:
        f.create_group("parameters").attrs["spec"] = json.dumps(spec)
        for name, v in (("temperature_translational", temps), ("temperature_rotational", rot_factor * temps),
                        ("kinetic_energy_translational", 1.5 * 64 * temps)):
            g = f.create_group(f"observables/{name}")
            g["step"], g["time"], g["value"] = steps, steps * 1e-4, v
    return Run(path.stem, path)


def test_aggregate_groups_seeds_and_knows_the_answer(tmp_path):
    base = SimulationSpec(**TINY).model_dump(mode="json")
    runs, curves = [], {0.7: [], 0.9: []}
    rng = np.random.default_rng(3)
    for seed in range(4):
        for e_n in (0.7, 0.9):
            temps = (1.0 + 0.1 * rng.normal(size=6)) * np.linspace(1.0, 0.5, 6) * (2 if e_n == 0.9 else 1)
            curves[e_n].append(temps)
            runs.append(_result(tmp_path / f"j{e_n}-{seed}.h5", {**base, "e_n": e_n, "seed": seed,
                                                                  "backend": "cpu" if seed else "auto"}, temps))
    groups = aggregate(runs)
    assert [g.label for g in groups] == ["e_n=0.7", "e_n=0.9"] and [g.n_seeds for g in groups] == [4, 4]
    for g, e_n in zip(groups, (0.7, 0.9)):
        v = np.array(curves[e_n])
        assert g.runs == [f"j{e_n}-{s}" for s in range(4)] and g.seeds == [0, 1, 2, 3]
        assert "seed" not in g.spec and g.spec["e_n"] == e_n
        assert np.allclose(g.mean["temperature_translational"], v.mean(0))
        assert np.allclose(g.standard_error["temperature_translational"], v.std(0, ddof=1) / 2)
        assert np.allclose(g.mean["temperature_rotational"], 0.8 * v.mean(0))
        ratio = v / v[:, :1]
        assert np.allclose(g.mean["kinetic_energy_translational_ratio"], ratio.mean(0))
        assert g.standard_error["kinetic_energy_translational_ratio"][0] == 0.0
    out = write_batch_result(tmp_path / "b" / "batch.h5", groups, batch_id="b1", excluded={"x": "failed"})
    back = read_batch_result(out)
    assert back["batch_id"] == "b1" and back["n_groups"] == 2 and back["n_runs"] == 8
    assert back["excluded"] == {"x": "failed"}
    g0 = back["groups"][0]
    assert g0["job_ids"] == groups[0].runs and list(g0["seeds"]) == [0, 1, 2, 3] and g0["n_seeds"] == 4
    assert np.array_equal(g0["temperature_translational"]["standard_error"],
                          groups[0].standard_error["temperature_translational"])
    assert g0["temperature_translational"]["values"].shape == (4, 6)
    assert not list((tmp_path / "b").glob("*.part"))


def test_runs_of_one_spec_with_other_records_are_refused(tmp_path):
    spec = SimulationSpec(**TINY).model_dump(mode="json")
    a = _result(tmp_path / "a.h5", {**spec, "seed": 1}, [1.0, 0.9, 0.8])
    b = _result(tmp_path / "b.h5", {**spec, "seed": 2}, [1.0, 0.9, 0.8], steps=[0, 7, 14])
    with pytest.raises(ValueError, match="run b has 3 records at other steps than run a"):
        aggregate([a, b])


# ---- routes without a worker ---------------------------------------------------------------------------

def test_batch_result_routes_404_409_partial_and_plot(client, settings):
    assert client.get("/batches/nope/result").status_code == 404
    assert "nope" in client.get("/batches/nope/plot.png").json()["detail"]
    body = client.post("/batches", json={"base": TINY, "sweep": {"e_n": [0.7, 0.9], "seed": [1, 2, 3]}}).json()
    bid, ids = body["batch_id"], body["job_ids"]
    r = client.get(f"/batches/{bid}/result")
    assert r.status_code == 409 and "6 of 6 jobs are still queued or running" in r.json()["detail"]
    r = client.get(f"/batches/{bid}/result", params={"partial": True})
    assert r.status_code == 409 and "none of its 6 jobs has a result" in r.json()["detail"]
    for job_id in ids[:2] + ids[3:5]:
        finish_with_fake_result(client.store, settings, job_id)
    client.post(f"/jobs/{ids[2]}/cancel")
    assert client.get(f"/batches/{bid}/result").status_code == 409  # one job still queued
    r = client.get(f"/batches/{bid}/result", params={"partial": True})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-hdf5"
    with h5py.File(io.BytesIO(r.content)) as f:
        assert f.attrs["n_groups"] == 2 and json.loads(f.attrs["excluded"]) == {ids[2]: "cancelled",
                                                                               ids[5]: "queued"}
        assert list(f["groups/g000/job_ids"].asstr()[()]) == ids[:2]
    client.post(f"/jobs/{ids[5]}/cancel")
    assert client.get(f"/batches/{bid}/result").status_code == 200  # every job has ended
    for path in (f"/batches/{bid}/plot.png", f"/batches/{bid}/plot"):
        assert_figure(client.get(path), min_bytes=10_000)
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/batches/{batch_id}/result", "/batches/{batch_id}/plot.png"} <= set(paths)


# ---- a sweep over HTTP, run by the embedded worker with the real engine ---------------------------------

#: 64 spheres at phi = 0.1: ~2.5 collisions per particle in t_end = 0.1 s (~3.6e4 steps of t_c/50)
SWEEP_BASE = {**TINY, "volume_fraction": 0.1, "t_end": 0.1, "output_interval": 0.005, "backend": "cpu"}


def test_sweep_over_http_runs_as_one_ensemble_with_batch_statistics(tmp_path):
    # the CPU runs a claim as a sequence by default (jobs/packing.py): this case pins the ensemble mode
    settings = make_settings(tmp_path, engine_run=REAL, engine_run_ensemble="engine.driver.ensemble:run_ensemble",
                             cpu_packs="ensemble")
    with TestClient(create_app(settings, embedded_worker=True)) as c:
        r = c.post("/batches", json={"base": SWEEP_BASE, "sweep": {"e_n": [0.7, 0.9], "seed": [0, 1, 2, 3]}})
        assert r.status_code == 201
        bid, ids = r.json()["batch_id"], r.json()["job_ids"]
        wait_for(lambda: all(c.get(f"/jobs/{i}").json()["state"] in ("done", "failed", "cancelled") for i in ids),
                 "every job of the batch ended",
                 activity=lambda: [c.get(f"/jobs/{i}").json()["progress"] for i in ids])
        jobs = [c.get(f"/jobs/{i}").json() for i in ids]
        assert all(j["state"] == "done" for j in jobs), [(j["state"], j["error"]) for j in jobs]

        per_job = {}
        for j in jobs:  # every job ends with its own valid HDF5, made in one ensemble of all eight
            content = c.get(f"/jobs/{j['id']}/result").content
            with h5py.File(io.BytesIO(content)) as f:
                assert f["parameters"].attrs["ensemble_size"] == 8
                assert json.loads(f["parameters"].attrs["spec"])["seed"] == j["spec"]["seed"]
                per_job[j["id"]] = {name: f[f"observables/{name}/value"][()] for name in
                                    ("temperature_translational", "temperature_rotational",
                                     "kinetic_energy_translational")}
                assert f["particles/all/position/value"].shape == (1, 64, 3)
        assert len({j["device"] for j in jobs}) == 1 and {j["backend"] for j in jobs} == {"cpu"}

        r = c.get(f"/batches/{bid}/result")
        assert r.status_code == 200
        (tmp_path / "batch.h5").write_bytes(r.content)
        data = read_batch_result(tmp_path / "batch.h5")
        assert data["n_groups"] == 2 and data["n_runs"] == 8 and data["excluded"] == {}
        for g, e_n in zip(data["groups"], (0.7, 0.9)):
            assert g["spec"]["e_n"] == e_n and g["n_seeds"] == 4 and sorted(g["seeds"]) == [0, 1, 2, 3]
            assert g["job_ids"] == [j["id"] for j in jobs if j["spec"]["e_n"] == e_n]
            tt = np.array([per_job[i]["temperature_translational"] for i in g["job_ids"]])
            et = np.array([per_job[i]["kinetic_energy_translational"] for i in g["job_ids"]])
            for name, v in (("temperature_translational", tt), ("kinetic_energy_translational_ratio",
                                                                 et / et[:, :1])):
                q = g[name]
                assert np.isfinite(q["mean"]).all() and np.isfinite(q["standard_error"]).all()
                assert np.allclose(q["mean"], v.mean(0), rtol=1e-12)
                assert np.allclose(q["standard_error"], v.std(0, ddof=1) / 2, rtol=1e-9, atol=1e-300)
            ratio = g["kinetic_energy_translational_ratio"]
            assert ratio["mean"][0] == 1.0 and ratio["standard_error"][0] == 0.0
            assert (ratio["standard_error"][len(g["time"]) // 2:] > 0).all()  # the seeds differ once they collide
            assert ratio["mean"][-1] < 0.98  # the gas cooled
        # stronger dissipation cools faster
        assert data["groups"][0]["kinetic_energy_translational_ratio"]["mean"][-1] < \
            data["groups"][1]["kinetic_energy_translational_ratio"]["mean"][-1]
        assert_figure(c.get(f"/batches/{bid}/plot.png"))
