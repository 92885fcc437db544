"""Figures and the `plots` extra: without matplotlib every route that draws answers 501 naming the extra and
`demq validate` stops before running; with it the cooling and batch plots are real pictures (the snapshot
picture: test_viz_routes.py)."""

from __future__ import annotations

import argparse
import io

import pytest

from tests.extras import NO_PLOTS, hide_matplotlib, needs_plots
from tests.service.conftest import TINY, finish_with_fake_result

HTML = {"Accept": "text/html"}


def test_figure_routes_without_matplotlib_answer_501_naming_the_extra(client, settings, monkeypatch):
    hide_matplotlib(monkeypatch)
    job_id = client.post("/jobs", json=TINY).json()["id"]
    finish_with_fake_result(client.store, settings, job_id)
    batch = client.post("/batches", json={"base": TINY, "sweep": {"seed": [1, 2]}}).json()
    for jid in batch["job_ids"]:
        finish_with_fake_result(client.store, settings, jid)
    for path, what in ((f"/jobs/{job_id}/plot.png", "the cooling plot"),
                       (f"/batches/{batch['batch_id']}/plot.png", "the batch plot")):
        r = client.get(path)
        assert r.status_code == 501 and r.json()["detail"].startswith(what) and NO_PLOTS in r.json()["detail"]
        page = client.get(path, headers=HTML)                  # a browser gets the error page
        assert page.status_code == 501 and "Not installed" in page.text and "demq[plots]" in page.text
    # the routes still answer what they answered before drawing: 404, 409
    assert client.get("/jobs/nope/plot.png").status_code == 404
    queued = client.post("/jobs", json=TINY).json()["id"]
    assert client.get(f"/jobs/{queued}/plot.png").status_code == 409
    schema = client.get("/openapi.json").json()["paths"]
    for path in ("/jobs/{job_id}/plot.png", "/jobs/{job_id}/snapshot.png", "/batches/{batch_id}/plot.png"):
        assert "501" in schema[path]["get"]["responses"], path


def test_validate_stops_before_running_without_matplotlib(monkeypatch, capsys):
    from engine import cli
    from engine.validation import hcs_spheres

    hide_matplotlib(monkeypatch)
    ran = []
    monkeypatch.setattr(hcs_spheres, "main", lambda **kw: ran.append(kw) or 0)
    args = argparse.Namespace(case="hcs-spheres", out_dir=None, seeds=None, quick=True, backend="cpu", jobs=1,
                              threads=1, ensemble=False)
    assert cli.cmd_validate(args) == 2 and ran == []
    err = capsys.readouterr().err
    assert "demq validate" in err and "matplotlib" in err and NO_PLOTS in err
    # a report's figure itself (here the sphere report's) names the extra too
    from engine.optional import MissingExtra

    with pytest.raises(MissingExtra, match=r"demq\[plots\]"):
        hcs_spheres.plot({}, "unused.png")


@pytest.mark.heavy   # draws with matplotlib: the `plots` extra
@needs_plots
def test_cooling_and_batch_plots_are_pictures(client, settings):
    from matplotlib.image import imread

    job_id = client.post("/jobs", json=TINY).json()["id"]
    finish_with_fake_result(client.store, settings, job_id)
    batch = client.post("/batches", json={"base": TINY, "sweep": {"e_n": [0.7, 0.9], "seed": [1, 2]}}).json()
    for jid in batch["job_ids"]:
        finish_with_fake_result(client.store, settings, jid)
    for path in (f"/jobs/{job_id}/plot.png", f"/batches/{batch['batch_id']}/plot.png"):
        r = client.get(path)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
        img = imread(io.BytesIO(r.content))
        assert img.shape[0] > 300 and img[..., :3].std() > 0.02          # a drawn figure, not a blank canvas
