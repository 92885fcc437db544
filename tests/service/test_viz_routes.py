"""Visualisation routes: GET /jobs/{id}/result.xmf, /export.gsd and /snapshot.png, on real engine results
(tiny CPU runs) and a 4096-particle frame written by the engine's own H5MD writer."""

from __future__ import annotations

import io
import shutil

import numpy as np
import pytest
from fastapi.testclient import TestClient

from engine.driver.simulate import run
from engine.output.h5md import H5MDWriter
from jobs.schema import DONE, FAILED
from service.app import create_app
from service.render import ovito_available
from tests.extras import NO_PLOTS, hide_matplotlib, needs_plots
from tests.jobs.conftest import make_settings
from tests.service.conftest import TINY, finish_with_fake_result

SPHERES = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.1, thermalization=0.5, snapshots=3,
               backend="cpu", velocity_rms=1.0, e_t=0.5)
ELLIPSOIDS = dict(shape="ellipsoid", elongation=2.0, n_particles=64, volume_fraction=0.05, e_n=0.9, e_t=-1.0,
                  t_end=0.01, thermalization=0.1, snapshots=3, backend="cpu", seed=3)


@pytest.fixture(scope="module")
def engine_results(tmp_path_factory):
    root = tmp_path_factory.mktemp("engine")
    return {"sphere": run(SPHERES, root / "s.h5").output, "ellipsoid": run(ELLIPSOIDS, root / "e.h5").output}


def _done_job(client, settings, spec: dict, result_file) -> str:
    """Submit ``spec``, play the worker: claim it and finish it with a copy of ``result_file``."""
    job_id = client.post("/jobs", json=spec).json()["id"]
    client.store.claim("test-worker", 30, job_id=job_id)
    settings.results_dir.mkdir(parents=True, exist_ok=True)
    path = settings.result_path(job_id)
    shutil.copyfile(result_file, path)
    client.store.finish(job_id, "test-worker", DONE, result_path=str(path), loop_s=0.1, job_wall_s=0.2, cundall=1e6,
                        error=None, progress=1.0)
    return job_id


def _png(r):
    from matplotlib.image import imread

    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    img = imread(io.BytesIO(r.content))
    assert img[..., :3].std() > 0.02                     # a picture, not a blank canvas
    return img


@pytest.mark.heavy   # draws with matplotlib: the `plots` extra
@needs_plots
@pytest.mark.parametrize("shape", ["sphere", "ellipsoid"])
def test_snapshot_png_of_a_real_result(client, settings, engine_results, shape):
    spec = SPHERES if shape == "sphere" else ELLIPSOIDS
    job_id = _done_job(client, settings, spec, engine_results[shape])
    last = _png(client.get(f"/jobs/{job_id}/snapshot.png", params={"renderer": "matplotlib"}))
    first = _png(client.get(f"/jobs/{job_id}/snapshot.png", params={"frame": 0, "color": "omega",
                                                                     "renderer": "matplotlib"}))
    assert not np.array_equal(first, last)
    _png(client.get(f"/jobs/{job_id}/snapshot.png"))         # auto: OVITO when it can render, else matplotlib


def test_snapshot_png_errors(client, settings, engine_results):
    assert client.get("/jobs/nope/snapshot.png").status_code == 404
    job_id = _done_job(client, settings, SPHERES, engine_results["sphere"])
    for frame in (3, -4):
        r = client.get(f"/jobs/{job_id}/snapshot.png", params={"frame": frame})
        assert r.status_code == 422
        (err,) = r.json()["detail"]
        assert err["loc"] == ["query", "frame"] and "3 snapshot frames" in err["msg"]
    r = client.get(f"/jobs/{job_id}/snapshot.png", params={"color": "temperature"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "color"]
    r = client.get(f"/jobs/{job_id}/snapshot.png", params={"frame": "last"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "frame"]
    if not ovito_available():
        r = client.get(f"/jobs/{job_id}/snapshot.png", params={"renderer": "ovito"})
        assert r.status_code == 422 and "OVITO is not installed" in r.json()["detail"][0]["msg"]


def test_snapshot_without_matplotlib_or_ovito_answers_501(client, settings, engine_results, monkeypatch):
    from service import render

    hide_matplotlib(monkeypatch)
    monkeypatch.setattr(render, "ovito_available", lambda: False)
    job_id = _done_job(client, settings, SPHERES, engine_results["sphere"])
    for renderer in ("matplotlib", "auto"):
        r = client.get(f"/jobs/{job_id}/snapshot.png", params={"renderer": renderer})
        assert r.status_code == 501 and r.json()["detail"].startswith("the snapshot picture"), r.text
        assert NO_PLOTS in r.json()["detail"]
    # the frame is checked before drawing: a bad index stays a 422
    assert client.get(f"/jobs/{job_id}/snapshot.png", params={"frame": 5}).status_code == 422


def test_not_done_failed_and_snapshotless_jobs_are_409(client, settings):
    queued = client.post("/jobs", json=TINY).json()["id"]
    failed = client.post("/jobs", json=TINY).json()["id"]
    client.store.claim("test-worker", 30, job_id=failed)
    client.store.finish(failed, "test-worker", FAILED, error="overlap of particle 7 exceeds the limit", progress=0.5)
    no_frames = client.post("/jobs", json=TINY).json()["id"]
    finish_with_fake_result(client.store, settings, no_frames)      # observables only, no particles
    for route in ("snapshot.png", "result.xmf", "export.gsd"):
        for job_id, words in ((queued, "is queued"), (failed, "is failed"), (no_frames, "no snapshot frame")):
            r = client.get(f"/jobs/{job_id}/{route}")
            assert r.status_code == 409 and words in r.json()["detail"], (route, job_id, r.text)
        assert client.get(f"/jobs/missing/{route}").status_code == 404


def test_a_renderer_the_server_does_not_offer_is_422_like_any_value_outside_the_enum(tmp_path, monkeypatch):
    """Without OVITO, 'ovito' is outside the document's enum: refused naming the parameter, whatever the job's
    state (as 'color=temperature' is), and with the renderers the server does offer."""
    from service import render

    monkeypatch.setattr(render, "ovito_available", lambda: False)
    with TestClient(create_app(make_settings(tmp_path))) as c:
        queued = c.post("/jobs", json=TINY).json()["id"]
        r = c.get(f"/jobs/{queued}/snapshot.png", params={"renderer": "ovito"})
        assert r.status_code == 422, r.text
        (err,) = r.json()["detail"]
        assert err["loc"] == ["query", "renderer"]
        assert "OVITO is not installed" in err["msg"] and "'auto' or 'matplotlib'" in err["msg"]
        assert c.get(f"/jobs/{queued}/snapshot.png", params={"renderer": "matplotlib"}).status_code == 409


def test_visualisation_routes_need_the_token(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, token="s3cret"))) as c:
        for route in ("snapshot.png", "result.xmf", "export.gsd"):
            assert c.get(f"/jobs/x/{route}").status_code == 401
            assert c.get(f"/jobs/x/{route}", headers={"Authorization": "Bearer s3cret"}).status_code == 404


@pytest.mark.heavy   # a real reader: the `viz` extra
@pytest.mark.parametrize("shape", ["sphere", "ellipsoid"])
def test_result_xmf_names_the_download_and_vtk_reads_the_pair(client, settings, engine_results, shape, tmp_path):
    xdmf2 = pytest.importorskip("vtkmodules.vtkIOXdmf2", reason="the vtk wheel (pip install '.[viz]')")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    job_id = _done_job(client, settings, SPHERES if shape == "sphere" else ELLIPSOIDS, engine_results[shape])
    r = client.get(f"/jobs/{job_id}/result.xmf")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/xml")
    assert f"demq-{job_id}.h5:/particles/all/position/value" in r.text and str(settings.results_dir) not in r.text
    (tmp_path / f"demq-{job_id}.xmf").write_text(r.text)
    (tmp_path / f"demq-{job_id}.h5").write_bytes(client.get(f"/jobs/{job_id}/result").content)
    reader = xdmf2.vtkXdmfReader()
    reader.SetFileName(str(tmp_path / f"demq-{job_id}.xmf"))
    reader.Update()
    grid = reader.GetOutputDataObject(0).GetBlock(0)
    import h5py

    with h5py.File(engine_results[shape]) as f:
        first = f["particles/all/position/value"][0]
    assert np.array_equal(vtk_to_numpy(grid.GetPoints().GetData()), first)


def test_export_gsd_route(client, settings, engine_results, tmp_path):
    gsd_hoomd = pytest.importorskip("gsd.hoomd")
    job_id = _done_job(client, settings, ELLIPSOIDS, engine_results["ellipsoid"])
    r = client.get(f"/jobs/{job_id}/export.gsd")
    assert r.status_code == 200 and f'demq-{job_id}.gsd' in r.headers["content-disposition"]
    out = tmp_path / "x.gsd"
    out.write_bytes(r.content)
    with gsd_hoomd.open(out, "r") as traj:
        assert len(traj) == 3 and traj[2].particles.N == 64
        assert traj[0].particles.type_shapes[0]["type"] == "Ellipsoid"


def _big_result(path, n=4096):
    """4096 random spheroids in two frames, through the engine's H5MDWriter (only the render's speed is tested)."""
    rng = np.random.default_rng(1)
    b, box = 0.03, 2.0
    w = H5MDWriter(path, n=n, box_length=box, spec_json="{}", derived={}, semi_axes=np.tile([2 * b, b, b], (n, 1)),
                   mass=np.ones(n))
    for k in range(2):
        q = rng.normal(size=(n, 4))
        w.snapshot(k, 0.1 * k, {"position": rng.uniform(0, box, (n, 3)), "velocity": rng.normal(size=(n, 3)),
                                "orientation": q / np.linalg.norm(q, axis=1)[:, None],
                                "angular_velocity": rng.normal(size=(n, 3))})
    return w.finish({})


@pytest.mark.heavy   # draws with matplotlib: the `plots` extra
@needs_plots
@pytest.mark.parametrize("renderer", ["matplotlib", "auto"])
def test_snapshot_of_4096_particles(client, settings, tmp_path, renderer):
    """A picture of a 4096-spheroid frame by each renderer (its speed is not a test's business)."""
    big = _big_result(tmp_path / "big.h5")
    job_id = _done_job(client, settings, dict(ELLIPSOIDS, n_particles=4096), big)
    _png(client.get(f"/jobs/{job_id}/snapshot.png", params={"renderer": renderer, "frame": 0}))
    _png(client.get(f"/jobs/{job_id}/snapshot.png", params={"renderer": renderer}))
