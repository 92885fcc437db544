"""The HTTP contract with FastAPI's TestClient; no worker runs (the engine is not involved)."""

from __future__ import annotations

import csv
import io

import h5py
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from tests.extras import assert_figure
from tests.jobs.conftest import make_settings
from tests.service.conftest import TINY, finish_with_fake_result


def test_submit_returns_201_with_id_and_state(client):
    r = client.post("/jobs", json=TINY, params={"priority": 3})
    assert r.status_code == 201
    body = r.json()
    assert body["state"] == "queued" and body["priority"] == 3 and len(body["id"]) == 32
    assert body["spec"]["n_particles"] == 64 and body["spec"]["e_n"] == 0.8  # defaults filled in
    got = client.get(f"/jobs/{body['id']}").json()
    assert got["progress"] == 0.0 and got["eta_s"] is None and got["error"] is None


@pytest.mark.parametrize("body, field, words", [
    ({"e_n": 1.5}, "e_n", "(0, 1]"),
    ({"volume_fraction": 0.7}, "volume_fraction", "(0, 0.64)"),
    ({"n_particles": 1}, "n_particles", "2 ... 2147483647"),
    ({"shape": "cube"}, "shape", "'sphere' or 'ellipsoid'"),
    ({"colour": "red"}, "colour", "Extra inputs are not permitted"),
    ({"e_n": "high"}, "e_n", "valid number"),
])
def test_invalid_spec_is_422_naming_field_and_limit(client, body, field, words):
    r = client.post("/jobs", json=body)
    assert r.status_code == 422
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", field] and words in err["msg"]
    assert client.get("/jobs").json()["total"] == 0


def test_cross_field_error_and_overflow_are_422(client):
    r = client.post("/jobs", json={**TINY, "dt": 1.0})
    assert r.status_code == 422 and "cannot resolve a contact" in r.json()["detail"][0]["msg"]
    r = client.post("/jobs", json={"box_length": 1e300})
    assert r.status_code == 422 and "cannot be evaluated" in r.json()["detail"][0]["msg"]
    r = client.post("/jobs", content=b'{"e_n": NaN}', headers={"content-type": "application/json"})
    assert r.status_code == 422 and "e_n = nan" in r.json()["detail"][0]["msg"]
    r = client.post("/jobs", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422


def test_json_types_are_taken_as_the_schema_states_them(client):
    """A number sent as a string or a boolean is refused (the schema says number); a whole number written
    5.0 is an integer, as in JSON Schema."""
    for body, field in (({**TINY, "e_n": "0.5"}, "e_n"), ({**TINY, "snapshots": True}, "snapshots"),
                        ({**TINY, "species": [{"radius_ratio": "1", "number_fraction": 1}]}, "species")):
        r = client.post("/jobs", json=body)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", field], body
    r = client.post("/jobs", json={**TINY, "snapshots": 2.0})
    assert r.status_code == 201 and r.json()["spec"]["snapshots"] == 2


def test_species_are_relative_and_stored_in_their_normal_form(client):
    """A species list the schema allows is accepted whatever its largest radius_ratio, its fraction sum or its
    repeated sizes, and the job holds (and its worker runs) the normal form of engine.setup.spec.normal_species."""
    species = [{"radius_ratio": 0.5, "number_fraction": 0.3}, {"radius_ratio": 0.25, "number_fraction": 0.6},
               {"radius_ratio": 0.5, "number_fraction": 0.3}]
    r = client.post("/jobs", json={**TINY, "species": species})
    assert r.status_code == 201, r.text
    normal = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 0.5, "number_fraction": 0.5}]
    assert r.json()["spec"]["species"] == normal
    r = client.post("/batches", json={"base": TINY, "sweep": {"species": [species, normal]}})
    assert r.status_code == 201, r.text
    listed = client.get("/jobs", params={"batch_id": r.json()["batch_id"]}).json()["items"]
    assert [j["spec"]["species"] for j in listed] == [normal, normal]


def test_step_count_that_cannot_be_computed_is_a_limit_error_not_a_crash(client):
    """dt = 5e-324 makes t_end/dt overflow; a huge stiffness makes dt underflow to 0."""
    for body in ({**TINY, "dt": 5e-324},
                 {"backend": "cpu", "box_length": 1.0, "density": 1.0, "stiffness": 1.755559702013982e+302}):
        r = client.post("/jobs", json=body)
        assert r.status_code == 422, body
        (err,) = r.json()["detail"]
        assert err["type"] == "limit_particle_steps" and "too large to count" in err["msg"]


def test_405_allow_names_every_method_of_the_path(client):
    r = client.request("OPTIONS", "/jobs")
    assert r.status_code == 405 and r.headers["allow"] == "GET, POST"


def test_oversize_spec_refused_before_queueing(client):
    r = client.post("/jobs", json={"n_particles": 2**30})
    assert r.status_code == 422
    msgs = " ".join(e["msg"] for e in r.json()["detail"])
    assert "DEMQ_MAX_PARTICLE_STEPS" in msgs and "DEMQ_MAX_MEMORY_BYTES" in msgs
    assert client.get("/jobs").json()["total"] == 0


def test_limits_are_configurable(tmp_path):
    app = create_app(make_settings(tmp_path, max_particle_steps=1000, max_body_bytes=200))
    with TestClient(app) as c:
        r = c.post("/jobs", json=TINY)
        assert r.status_code == 422 and "limit DEMQ_MAX_PARTICLE_STEPS = 1e+03" in r.json()["detail"][0]["msg"]
        r = c.post("/jobs", json={**TINY, "seed": 1, "precision": "float64", "backend": "auto", "e_t": 0.5,
                                  "velocity_rms": 1.0, "density": 2000.0, "stiffness": 1e8, "overlap_limit": 0.05})
        assert r.status_code == 413 and "DEMQ_MAX_BODY_BYTES" in r.json()["detail"]


def test_body_over_limit_is_413_also_when_streamed(client):
    big = b"[" + b"1," * 600_000 + b"1]"
    assert client.post("/jobs", content=big, headers={"content-type": "application/json"}).status_code == 413

    def chunks():  # no Content-Length: chunked transfer
        for _ in range(20):
            yield b" " * 100_000

    r = client.post("/batches", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413


def test_unknown_id_is_404_everywhere(client):
    for method, path in [("get", "/jobs/abc"), ("post", "/jobs/abc/cancel"), ("get", "/jobs/abc/result"),
                         ("get", "/jobs/abc/energy"), ("get", "/jobs/abc/plot.png")]:
        r = client.request(method.upper(), path)
        assert r.status_code == 404 and "abc" in r.json()["detail"], path


def test_list_filters_and_pages(client):
    ids = [client.post("/jobs", json={**TINY, "seed": i}).json()["id"] for i in range(5)]
    client.post(f"/jobs/{ids[1]}/cancel")
    page = client.get("/jobs", params={"limit": 2, "offset": 1}).json()
    assert page["total"] == 5 and [j["id"] for j in page["items"]] == ids[1:3]
    queued = client.get("/jobs", params={"state": "queued"}).json()
    assert queued["total"] == 4 and ids[1] not in [j["id"] for j in queued["items"]]
    assert client.get("/jobs", params={"state": "sleeping"}).status_code == 422
    assert client.get("/jobs", params={"limit": 0}).status_code == 422


def test_batch_of_specs_and_sweep(client):
    r = client.post("/batches", json={"specs": [TINY, {**TINY, "seed": 2}]})
    assert r.status_code == 201 and r.json()["count"] == 2
    r = client.post("/batches", json={"base": TINY, "sweep": {"e_n": [0.5, 0.9], "e_t": [-1.0, 0.0, 1.0]},
                                      "priority": 2})
    assert r.status_code == 201
    body = r.json()
    assert body["count"] == 6
    listed = client.get("/jobs", params={"batch_id": body["batch_id"]}).json()
    assert listed["total"] == 6 and {j["priority"] for j in listed["items"]} == {2}
    combos = [(j["spec"]["e_n"], j["spec"]["e_t"]) for j in listed["items"]]
    assert combos == [(0.5, -1.0), (0.5, 0.0), (0.5, 1.0), (0.9, -1.0), (0.9, 0.0), (0.9, 1.0)]


def test_batch_errors_name_the_combination_and_queue_nothing(client):
    r = client.post("/batches", json={"base": TINY, "sweep": {"e_t": [0.0, 2.0]}})
    assert r.status_code == 422
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "sweep", "combination", 1, "e_t"] and "[-1, 1]" in err["msg"]
    r = client.post("/batches", json={"specs": [TINY, {"e_n": 7}]})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "specs", 1, "e_n"]
    r = client.post("/batches", json={"base": TINY, "sweep": {"seed": list(range(1001))}})
    assert r.status_code == 422 and "DEMQ_MAX_BATCH_JOBS" in r.json()["detail"][0]["msg"]
    for bad in ({}, {"specs": []}, {"specs": [TINY], "sweep": {"e_n": [0.5]}}, {"sweep": {"e_n": []}},
                {"sweep": {}}, {"specs": [TINY], "base": TINY}, {"base": TINY, "sweep": {"colour": ["red"]}}):
        assert client.post("/batches", json=bad).status_code == 422, bad
    assert client.get("/jobs").json()["total"] == 0


def test_cancel_queued_running_and_finished(client, settings):
    a, b, c = (client.post("/jobs", json={**TINY, "seed": i}).json()["id"] for i in range(3))
    r = client.post(f"/jobs/{a}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    client.store.claim("w", 30, job_id=b)
    r = client.post(f"/jobs/{b}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "running" and r.json()["cancel_requested"]
    finish_with_fake_result(client.store, settings, c)
    assert client.post(f"/jobs/{c}/cancel").status_code == 409
    assert client.post(f"/jobs/{a}/cancel").status_code == 409


def test_result_energy_and_plot_of_a_done_job(client, settings):
    job_id = client.post("/jobs", json=TINY).json()["id"]
    assert client.get(f"/jobs/{job_id}/result").status_code == 409  # still queued
    finish_with_fake_result(client.store, settings, job_id)
    status = client.get(f"/jobs/{job_id}").json()
    assert status["state"] == "done" and status["result_available"] and status["cundall"] == 1e6
    assert status["run_s"] >= 0 and status["queued_s"] >= 0

    r = client.get(f"/jobs/{job_id}/result")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-hdf5"
    assert f'filename="demq-{job_id}.h5"' in r.headers["content-disposition"]
    with h5py.File(io.BytesIO(r.content)) as f:
        assert "observables/temperature_rotational/value" in f

    energy = client.get(f"/jobs/{job_id}/energy").json()
    assert len(energy["time"]) == 21 and energy["time"][0] == 0.0
    assert energy["kinetic_energy_translational"][0] > energy["kinetic_energy_translational"][-1] > 0
    r = client.get(f"/jobs/{job_id}/energy", params={"format": "csv"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.reader(io.StringIO(r.text)))
    assert rows[0] == ["step", "time", "kinetic_energy_translational", "kinetic_energy_rotational",
                       "temperature_translational", "temperature_rotational"]
    assert len(rows) == 22 and float(rows[1][1]) == 0.0
    assert client.get(f"/jobs/{job_id}/energy", params={"format": "xml"}).status_code == 422

    assert_figure(client.get(f"/jobs/{job_id}/plot.png"), min_bytes=10_000)


def test_deleted_result_file_is_410(client, settings):
    job_id = client.post("/jobs", json=TINY).json()["id"]
    finish_with_fake_result(client.store, settings, job_id)
    settings.result_path(job_id).unlink()
    assert client.get(f"/jobs/{job_id}/result").status_code == 410


def test_bearer_token_guards_every_route_but_healthz(tmp_path):
    app = create_app(make_settings(tmp_path, token="s3cret"))
    with TestClient(app) as c:
        assert c.get("/healthz").status_code == 200
        for method, path in [("GET", "/jobs"), ("POST", "/jobs"), ("GET", "/jobs/x"), ("POST", "/batches"),
                             ("GET", "/jobs/x/result"), ("GET", "/jobs/x/plot.png")]:
            r = c.request(method, path)
            assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", path
        assert c.get("/jobs", headers={"Authorization": "Bearer wrong"}).status_code == 401
        ok = {"Authorization": "Bearer s3cret"}
        assert c.post("/jobs", json=TINY, headers=ok).status_code == 201
        assert c.get("/jobs", headers=ok).json()["total"] == 1


def test_auth_off_by_default_and_healthz(client):
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok", "jobs": {}}
    client.post("/jobs", json=TINY)
    assert client.get("/healthz").json()["jobs"] == {"queued": 1}


def test_openapi_docs(client):
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/jobs", "/batches", "/jobs/{job_id}", "/jobs/{job_id}/cancel", "/jobs/{job_id}/result",
            "/jobs/{job_id}/energy", "/jobs/{job_id}/plot.png", "/healthz"} <= set(paths)


def _age_workers(store, seconds: float) -> None:
    """Move every worker's last sign of life ``seconds`` into the past (a worker that died silently)."""
    from sqlalchemy import update

    with store.engine.begin() as conn:
        conn.execute(update(store.workers).values(seen_at=store.workers.c.seen_at - seconds))


def test_cuda_refused_without_a_live_cuda_worker(client, settings):
    r = client.post("/jobs", json={**TINY, "backend": "cuda"})
    assert r.status_code == 422
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "backend"] and err["type"] == "backend_unavailable"
    assert "backend = 'cuda'" in err["msg"] and "no live worker can run CUDA" in err["msg"]
    client.store.register_worker("cpu-only", "host-a", 11, ["cpu"])      # a CPU worker does not help
    assert client.post("/jobs", json={**TINY, "backend": "cuda"}).status_code == 422
    for backend in ("auto", "cpu"):                                       # these run on any worker
        assert client.post("/jobs", json={**TINY, "backend": backend}).status_code == 201
    assert client.get("/jobs").json()["total"] == 2


def test_an_embedded_workers_backends_are_known_from_the_first_answer(settings, monkeypatch):
    """`demq serve` on a GPU host: a cuda job sent as soon as the server answers is accepted, however long the
    worker takes to find its GPU (here 1 s, stood in for: this machine has none), because the service registers its
    embedded worker before it answers (service/app.py)."""
    import time

    from jobs.worker import Worker

    def finds_a_gpu_slowly(self):
        time.sleep(1.0)
        return ("cpu", "cuda")

    monkeypatch.setattr(Worker, "_backends", finds_a_gpu_slowly)
    monkeypatch.setattr(Worker, "run_forever", lambda self, exit_when_idle=False: self.register())
    with TestClient(create_app(settings, embedded_worker=True)) as c:
        r = c.post("/jobs", json={**TINY, "backend": "cuda"})
        assert r.status_code == 201, r.json()
        assert [w.backends for w in c.app.state.store.live_workers(settings.lease_s)] == [("cpu", "cuda")]


def test_cuda_accepted_while_a_cuda_worker_is_alive(client, settings):
    client.store.register_worker("gpu-0", "host-b", 12, ["cpu", "cuda"])
    r = client.post("/jobs", json={**TINY, "backend": "cuda"})
    assert r.status_code == 201 and r.json()["spec"]["backend"] == "cuda"
    _age_workers(client.store, 2 * settings.lease_s)                     # not seen for two leases: lost
    assert client.post("/jobs", json={**TINY, "backend": "cuda"}).status_code == 422
    client.store.worker_seen("gpu-0")
    assert client.post("/jobs", json={**TINY, "backend": "cuda"}).status_code == 201
    client.store.unregister_worker("gpu-0")
    assert client.post("/jobs", json={**TINY, "backend": "cuda"}).status_code == 422


def test_batch_with_cuda_refused_whole_naming_each_combination(client):
    r = client.post("/batches", json={"base": TINY, "sweep": {"backend": ["cpu", "cuda"], "seed": [1, 2]}})
    assert r.status_code == 422
    locs = [e["loc"] for e in r.json()["detail"]]
    assert locs == [["body", "sweep", "combination", 2, "backend"], ["body", "sweep", "combination", 3, "backend"]]
    r = client.post("/batches", json={"specs": [TINY, {**TINY, "backend": "cuda"}]})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "specs", 1, "backend"]
    assert client.get("/jobs").json()["total"] == 0
    client.store.register_worker("gpu-0", "host-b", 12, ["cuda"])
    assert client.post("/batches", json={"specs": [TINY, {**TINY, "backend": "cuda"}]}).status_code == 201


def test_an_undeclared_query_parameter_is_422_naming_it(client):
    """A misspelt filter is refused, not ignored (unknown body fields are refused the same way); declared ones
    still work, and /healthz takes none."""
    r = client.get("/jobs", params={"stat": "done"})
    assert r.status_code == 422
    (err,) = r.json()["detail"]
    assert err["loc"] == ["query", "stat"] and err["type"] == "extra_forbidden"
    assert "state" in err["msg"] and "'stat'" in err["msg"]
    assert client.get("/jobs", params={"state": "done", "limit": 5}).status_code == 200
    r = client.get("/healthz", params={"verbose": "1"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "verbose"]


def test_a_single_valued_query_parameter_given_twice_is_422(client):
    r = client.get("/jobs?batch_id=a&batch_id=b")
    assert r.status_code == 422
    (err,) = r.json()["detail"]
    assert err["loc"] == ["query", "batch_id"] and err["type"] == "too_many_values" and "2" in err["msg"]


def test_cuda_spec_larger_than_every_live_gpu_refused_naming_the_estimate(client):
    """A CUDA sphere spec whose predicted device memory (engine/loops/cuda_memory.py) exceeds the largest live GPU
    worker's memory is refused up front (422 at n_particles) with the estimate and the largest n_particles that
    fits; it fits a larger GPU; an unknown GPU size refuses nothing."""
    import re
    import time

    client.store.register_worker("gpu-small", "host-b", 12, ["cuda"], device_memory=2 * 10**9)
    big = {**TINY, "backend": "cuda", "n_particles": 10_000_000, "t_end": 1e-6}
    t0 = time.perf_counter()
    r = client.post("/jobs", json=big)
    assert time.perf_counter() - t0 < 5.0
    assert r.status_code == 422, r.json()
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "n_particles"] and err["type"] == "device_memory"
    fits = float(re.search(r"largest n_particles that fits is about ([0-9.e+]+)", err["msg"]).group(1))
    assert "GB of device memory" in err["msg"] and 1e5 < fits < 10_000_000
    assert client.post("/jobs", json={**big, "n_particles": int(fits * 0.9)}).status_code == 201
    client.store.register_worker("gpu-large", "host-c", 13, ["cuda"], device_memory=200 * 10**9)
    assert client.post("/jobs", json=big).status_code == 201
    client.store.register_worker("gpu-unknown", "host-d", 14, ["cuda"])
    client.store.unregister_worker("gpu-large")
    assert client.post("/jobs", json=big).status_code == 201
