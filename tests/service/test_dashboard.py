"""The dashboard's routes without a browser: pages, live fragments, the submit form, 4xx pages, auth."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from jobs.schema import FAILED
from service.app import create_app
from service.deps import TOKEN_COOKIE
from tests.extras import assert_figure
from tests.service.conftest import TINY, finish_with_fake_result, make_settings

HTML = {"accept": "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"}  # a browser's navigation
FORM = {k: str(v) for k, v in TINY.items()}


def _submit(client, **keys) -> str:
    r = client.post("/jobs", json={**TINY, **keys})
    assert r.status_code == 201
    return r.json()["id"]


def _fail(client, job_id: str, error: str) -> None:
    client.store.claim("test-worker", 30, job_id=job_id)
    client.store.finish(job_id, "test-worker", FAILED, error=error)


def _field_error(html: str, name: str) -> str:
    """The error shown in the form field ``name`` ('' if none)."""
    m = re.search(rf'<p class="field-error" id="e-{name}">([^<]*)</p>', html)
    return m.group(1) if m else ""


# ---- pages ------------------------------------------------------------------------------------------------
def test_jobs_list_shows_state_progress_and_filters(client, settings):
    done, queued = _submit(client), _submit(client, seed=1)
    finish_with_fake_result(client.store, settings, done)
    batch = client.post("/batches", json={"base": TINY, "sweep": {"e_n": [0.5, 0.9]}}).json()

    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    page = r.text
    for job_id in (done, queued, *batch["job_ids"]):
        assert f'id="job-{job_id}"' in page
    assert page.index(batch["job_ids"][-1]) < page.index(done), "newest first"
    assert re.search(rf'id="job-{done}" data-state="done".*?aria-valuenow="100"', page, re.S)
    assert re.search(rf'id="job-{queued}" data-state="queued".*?aria-valuenow="0"', page, re.S)
    assert "1e+06" in page  # the fake result's Cundall number
    assert 'hx-trigger="every 2s"' in page and 'hx-get="/ui/jobs/table"' in page

    only_done = client.get("/", params={"state": "done"}).text
    assert done in only_done and queued not in only_done
    in_batch = client.get("/ui/jobs/table", params={"batch": batch["batch_id"]}).text
    assert all(j in in_batch for j in batch["job_ids"]) and done not in in_batch
    assert f'hx-get="/ui/jobs/table?batch={batch["batch_id"]}"' in in_batch  # the poll keeps the filter
    assert "<html" not in in_batch  # a fragment

    r = client.get("/", params={"state": "sleeping"})
    assert r.status_code == 422 and "not a job state" in r.text and "<html" in r.text


def test_jobs_list_pages_newest_first(client, monkeypatch):
    from service.dashboard import routes

    monkeypatch.setattr(routes, "PAGE_SIZE", 2)
    ids = [_submit(client, seed=i) for i in range(5)]

    def shown(page: int) -> list[str]:
        return re.findall(r'<tr id="job-([0-9a-f]+)"', client.get("/", params={"page": page}).text)

    assert [shown(p) for p in range(4)] == [[ids[4], ids[3]], [ids[2], ids[1]], [ids[0]], []]
    assert 'href="/?page=1">older' in client.get("/").text
    last = client.get("/", params={"page": 2}).text
    assert "older &rarr;" not in last and 'href="/?page=1">&larr; newer' in last


def test_no_asset_from_elsewhere(client):
    page = client.get("/").text + client.get("/ui/submit").text
    for url in re.findall(r'(?:src|href)="([^"]+)"', page):
        assert url.startswith("/"), url
    js = client.get("/ui/static/htmx.min.js")
    assert js.status_code == 200 and "htmx" in js.text[:200]
    assert client.get("/ui/static/dashboard.css").status_code == 200


def test_done_job_page_has_plot_downloads_and_spec(client, settings):
    job_id = _submit(client, e_t=-1.0)
    finish_with_fake_result(client.store, settings, job_id)
    page = client.get(f"/ui/jobs/{job_id}").text
    for href in (f"/jobs/{job_id}/result", f"/jobs/{job_id}/energy?format=csv", f"/jobs/{job_id}/export.gsd",
                 f"/jobs/{job_id}/result.xmf", f"/jobs/{job_id}/plot.png"):
        assert f'="{href}"' in page, href
    assert f'src="/jobs/{job_id}/snapshot.png?frame=-1&amp;color=speed"' in page
    assert re.search(r'class="changed"><th>e_t</th><td class="mono">-1.0</td>', page)  # a changed key stands out
    assert "hx-get" not in page and 'id="cancel"' not in page  # ended: no polling, nothing to cancel
    assert_figure(client.get(f"/jobs/{job_id}/plot.png"))
    assert '<th>stiffness</th><td class="mono">1e8</td>' in page  # not 100000000.0


def test_spec_values_read_back_as_the_same_numbers():
    from service.dashboard.views import show

    for x in (1e8, 2.5e9, 123456.0, 1.0000000000001e8, 0.05, 2000.0, -3e7):
        assert float(show(x)) == x, x
    assert show(1e8) == "1e8" and show(2000.0) == "2000.0" and show(None) == "" and show([1, 2]) == "[1, 2]"


def test_live_job_page_polls_and_reloads_once_ended(client, settings):
    job_id = _submit(client)
    page = client.get(f"/ui/jobs/{job_id}").text
    assert f'hx-get="/ui/jobs/{job_id}/live"' in page and 'id="cancel"' in page
    assert "cooling-plot" not in page  # no result yet
    live = client.get(f"/ui/jobs/{job_id}/live")
    assert live.status_code == 200 and "HX-Refresh" not in live.headers and "<html" not in live.text
    finish_with_fake_result(client.store, settings, job_id)
    assert client.get(f"/ui/jobs/{job_id}/live").headers["HX-Refresh"] == "true"


def test_cancel_from_the_page(client):
    job_id = _submit(client)
    r = client.post(f"/ui/jobs/{job_id}/cancel", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/ui/jobs/{job_id}"
    assert client.get(f"/jobs/{job_id}").json()["state"] == "cancelled"
    assert "This job was cancelled" in client.get(f"/ui/jobs/{job_id}").text
    r = client.post(f"/ui/jobs/{job_id}/cancel")
    assert r.status_code == 409 and "already ended (cancelled)" in r.text and "<html" in r.text


def test_failed_job_shows_its_error_and_its_results_are_a_409_page(client):
    job_id = _submit(client)
    _fail(client, job_id, "unstable at step 12: overlap 0.3 R between particles 3 and 9 (dt too large?)")
    page = client.get(f"/ui/jobs/{job_id}").text
    assert "This job failed" in page and "overlap 0.3 R between particles 3 and 9 (dt too large?)" in page
    assert "cooling-plot" not in page and "/result.xmf" not in page
    # a browser following a stale download link gets a page; API clients keep the JSON body
    r = client.get(f"/jobs/{job_id}/result", headers=HTML)
    assert r.status_code == 409 and "<html" in r.text and "a result exists only when it is done" in r.text
    assert f'href="/ui/jobs/{job_id}"' in r.text
    r = client.get(f"/jobs/{job_id}/result")
    assert r.status_code == 409 and r.json()["detail"].startswith(f"job {job_id} is failed")


def test_unknown_ids_are_404_pages(client):
    for path in ("/ui/jobs/0123abc", "/ui/jobs/0123abc/live", "/ui/batches/0123abc", "/ui/nothing-here"):
        r = client.get(path)
        assert r.status_code == 404 and "<html" in r.text and "Not found" in r.text, path
    assert "no job with id &#39;0123abc&#39;" in client.get("/ui/jobs/0123abc").text
    assert client.post("/ui/jobs/0123abc/cancel").status_code == 404
    r = client.get("/jobs/0123abc/plot.png", headers=HTML)
    assert r.status_code == 404 and "<html" in r.text
    r = client.get("/jobs/0123abc")
    assert r.status_code == 404 and r.json() == {"detail": "no job with id '0123abc'"}


def test_batch_page_shows_the_sweep_and_the_mean_curves(client, settings):
    batch = client.post("/batches", json={"base": TINY, "sweep": {"e_n": [0.5, 0.9], "seed": [1, 2]}}).json()
    page = client.get(f"/ui/batches/{batch['batch_id']}").text
    assert re.search(r"<th>e_n</th><th>seed</th><th>State</th>", page)  # swept keys as columns
    assert 'hx-get="/ui/batches/' in page and "batch-plot" not in page  # live, nothing done yet
    for job_id in batch["job_ids"][:2]:
        finish_with_fake_result(client.store, settings, job_id)
    page = client.get(f"/ui/batches/{batch['batch_id']}").text
    assert f'src="/batches/{batch["batch_id"]}/plot.png?partial=true"' in page
    assert_figure(client.get(f"/batches/{batch['batch_id']}/plot.png", params={"partial": True}))
    for job_id in batch["job_ids"][2:]:
        finish_with_fake_result(client.store, settings, job_id)
    assert client.get(f"/ui/batches/{batch['batch_id']}/live").headers["HX-Refresh"] == "true"
    page = client.get(f"/ui/batches/{batch['batch_id']}").text
    assert f'src="/batches/{batch["batch_id"]}/plot.png"' in page and "hx-get" not in page


# ---- the submit form --------------------------------------------------------------------------------------------
def test_submit_form_has_the_defaults(client):
    from engine.setup.spec import SimulationSpec

    page = client.get("/ui/submit").text
    defaults = SimulationSpec()
    assert f'name="n_particles" value="{defaults.n_particles}"' in page
    assert f'name="e_n" value="{defaults.e_n}"' in page
    assert re.search(r'name="backend">\s*<option selected>auto</option>', page)
    assert 'name="dt" value="" placeholder="null"' in page
    assert re.search(r'name="orientations">\s*<option selected>true</option>\s*<option>false</option>', page)


def test_submit_form_queues_the_spec(client):
    r = client.post("/ui/submit", data={**FORM, "backend": "cpu", "seed": "11", "dt": "", "priority": "5",
                                        "orientations": "false"}, follow_redirects=False)
    assert r.status_code == 303
    job = client.get("/jobs/" + r.headers["location"].rsplit("/", 1)[1]).json()
    assert job["spec"]["backend"] == "cpu" and job["spec"]["seed"] == 11 and job["spec"]["dt"] is None
    assert job["spec"]["orientations"] is False
    assert job["spec"]["n_particles"] == TINY["n_particles"] and job["priority"] == 5


def test_submit_form_shows_errors_next_to_the_fields(client):
    r = client.post("/ui/submit", data={**FORM, "n_particles": "1", "e_n": "1.5", "species": "[{", "priority": "x"})
    assert r.status_code == 422
    assert _field_error(r.text, "species").startswith("not valid JSON")
    assert "priority" in _field_error(r.text, "priority")
    assert _field_error(r.text, "n_particles").startswith("n_particles = 1 is outside")  # all errors at once
    r = client.post("/ui/submit", data={**FORM, "n_particles": "1", "e_n": "1.5"})
    assert r.status_code == 422
    assert _field_error(r.text, "n_particles") == "n_particles = 1 is outside the allowed range 2 ... 2147483647"
    assert _field_error(r.text, "e_n") == "e_n = 1.5 is outside the allowed range (0, 1]"
    assert _field_error(r.text, "e_t") == ""
    assert 'name="e_n" value="1.5"' in r.text  # what was typed stays
    # a cross-field error and a cost limit are spec-wide
    r = client.post("/ui/submit", data={**FORM, "elongation": "2"})
    assert r.status_code == 422 and re.search(r'id="form-errors">.*elongation = 2.0 but shape is', r.text, re.S)
    assert client.get("/jobs").json()["total"] == 0


def test_submit_form_refuses_cuda_without_a_live_cuda_worker(client):
    r = client.post("/ui/submit", data={**FORM, "backend": "cuda"})
    assert r.status_code == 422 and "no live worker can run CUDA" in _field_error(r.text, "backend")
    assert client.get("/jobs").json()["total"] == 0


def test_submit_form_applies_the_cost_limits(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_particle_steps=1000))) as c:
        r = c.post("/ui/submit", data=FORM)
        assert r.status_code == 422 and "DEMQ_MAX_PARTICLE_STEPS" in r.text
        assert c.get("/jobs").json()["total"] == 0


# ---- auth ----------------------------------------------------------------------------------------------------------
@pytest.fixture
def guarded(tmp_path):
    settings = make_settings(tmp_path, token="s3cret-token")
    app = create_app(settings)
    with TestClient(app) as c:
        c.store, c.settings = app.state.store, settings
        yield c


def test_without_the_token_nothing_leaks(guarded):
    job_id = guarded.post("/jobs", json=TINY, headers={"Authorization": "Bearer s3cret-token"}).json()["id"]
    for path in ("/", f"/ui/jobs/{job_id}", f"/ui/jobs/{job_id}/live", "/ui/jobs/table", "/ui/submit",
                 "/ui/batches/abc", "/ui/jobs/unknown"):
        r = guarded.get(path)
        assert r.status_code == 401 and 'name="token"' in r.text, path
        shown = r.text.replace(f'name="next" value="{path}"', "")  # the form only echoes the path asked for
        assert job_id not in shown and "sphere" not in shown, path
    r = guarded.post("/ui/submit", data=FORM)
    assert r.status_code == 401
    assert guarded.post(f"/ui/jobs/{job_id}/cancel").status_code == 401
    assert guarded.get(f"/jobs/{job_id}").status_code == 401
    r = guarded.get("/ui/jobs/table", headers={"HX-Request": "true"})  # an htmx poll: go to the token form
    assert r.status_code == 401 and r.headers["HX-Redirect"] == "/ui/login?next=/ui/jobs/table"
    assert "Log out" not in guarded.get("/").text
    guarded.cookies.set(TOKEN_COOKIE, "wrong")
    assert guarded.get("/").status_code == 401
    assert guarded.get("/ui/static/htmx.min.js").status_code == 200  # public, holds no data


def test_token_form_sets_an_httponly_cookie(guarded):
    r = guarded.post("/ui/login", data={"token": "nope", "next": "/"})
    assert r.status_code == 401 and "not the server" in r.text and TOKEN_COOKIE not in r.headers.get("set-cookie", "")
    r = guarded.post("/ui/login", data={"token": "s3cret-token", "next": "/ui/submit"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/submit"
    cookie = r.headers["set-cookie"].lower()
    assert f"{TOKEN_COOKIE}=s3cret-token" in cookie and "httponly" in cookie and "samesite=strict" in cookie
    guarded.cookies.set(TOKEN_COOKIE, "s3cret-token")
    r = guarded.get("/")
    assert r.status_code == 200 and "Log out" in r.text
    r = guarded.post("/ui/submit", data=FORM, follow_redirects=False)
    assert r.status_code == 303
    assert guarded.get("/jobs").json()["total"] == 1  # the cookie opens the API too
    guarded.cookies.clear()
    assert guarded.get("/jobs", headers={"Authorization": "Bearer s3cret-token"}).status_code == 200
    r = guarded.post("/ui/logout", follow_redirects=False)
    assert r.status_code == 303 and f'{TOKEN_COOKIE}=""' in r.headers["set-cookie"]


def test_token_form_redirects_only_within_the_site(guarded):
    for target in ("//evil.example/x", "https://evil.example/", "/\\evil.example"):
        r = guarded.post("/ui/login", data={"token": "s3cret-token", "next": target}, follow_redirects=False)
        assert r.headers["location"] == "/", target


def test_token_form_without_auth_says_so(client):
    r = client.get("/ui/login")
    assert r.status_code == 200 and "No token needed" in r.text and 'name="token"' not in r.text
    r = client.post("/ui/login", data={"token": "anything"}, follow_redirects=False)
    assert r.status_code == 303 and "set-cookie" not in r.headers
    assert "Log out" not in client.get("/").text
