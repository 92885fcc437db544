"""The dashboard's pages: jobs list (``/``), job page, batch page, submit form, token form.

Server-rendered HTML (Jinja2); the live parts are fragments that the page polls with htmx every
2 s. A fragment whose job (or batch) has ended answers with ``HX-Refresh`` so the page reloads once
and shows the results. The JSON API is left as it is; these routes are kept out of the OpenAPI schema.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from starlette.concurrency import run_in_threadpool

from jobs.batch_results import batch_jobs
from jobs.schema import FINAL_STATES, STATES
from jobs.specs import SpecRejected, check_limits, parse_spec
from jobs.store import Job, NewJob
from service.backends import check_backends
from service.dashboard import views
from service.deps import TOKEN_COOKIE, StoreDep, SettingsDep, require_token, token_matches

HERE = Path(__file__).resolve().parent
STATIC_URL = "/ui/static"
POLL = "every 2s"
PAGE_SIZE = 50
COOKIE_MAX_AGE_S = 7 * 24 * 3600

templates = Jinja2Templates(directory=HERE / "templates")
templates.env.globals.update(
    when=views.when, duration=views.duration, sci=views.sci, eta=views.eta, scene=views.scene, live=views.live,
    percent=views.percent, show=views.show, poll=POLL, static=STATIC_URL)

#: Pages behind the token (when one is set).
router = APIRouter(include_in_schema=False, dependencies=[Depends(require_token)])
#: The token form itself.
public = APIRouter(include_in_schema=False)


def render(request: Request, name: str, status: int = 200, headers: Optional[dict] = None, **context) -> HTMLResponse:
    """Render template ``name``; every page knows whether auth is on (``token_on``: the token form, the
    log-out button)."""
    context.setdefault("token_on", request.app.state.settings.token is not None)
    context.setdefault("show_logout", context["token_on"])
    return templates.TemplateResponse(request, name, context, status_code=status, headers=headers)


def _job(store, job_id: str) -> Job:
    job = store.get(job_id) if len(job_id) <= 64 else None
    if job is None:
        raise HTTPException(404, f"no job with id {job_id!r}")
    return job


# ---- jobs list ---------------------------------------------------------------------------------------------
def _filters(request: Request) -> dict:
    """The list's filters from the query: state, batch and page (0 = the newest jobs)."""
    q = request.query_params
    state, batch = q.get("state") or None, (q.get("batch") or "").strip() or None
    if state is not None and state not in STATES:
        raise HTTPException(422, f"state = {state!r} is not a job state; choose one of {', '.join(STATES)}")
    if batch is not None and len(batch) > 64:
        raise HTTPException(422, "batch: a batch id has at most 64 characters")
    try:
        page = int(q.get("page") or 0)
        if not 0 <= page <= 10**9:
            raise ValueError
    except ValueError:
        raise HTTPException(422, f"page = {q.get('page')!r} must be a whole number >= 0") from None
    return {"state": state, "batch": batch, "page": page}


def _jobs_context(store, state, batch, page) -> dict:
    """The newest jobs first, PAGE_SIZE per page, and the counts per state."""
    _, total = store.list(state=state, batch_id=batch, limit=1, offset=0)
    end = max(0, total - page * PAGE_SIZE)
    start = max(0, end - PAGE_SIZE)
    items = list(reversed(store.list(state=state, batch_id=batch, limit=end - start, offset=start)[0])) if end else []
    query = urlencode({k: v for k, v in (("state", state), ("batch", batch), ("page", page)) if v})
    return {"jobs": items, "total": total, "counts": store.counts(), "state": state, "batch": batch, "page": page,
            "query": query, "has_older": start > 0, "states": STATES,
            "older": urlencode({k: v for k, v in (("state", state), ("batch", batch)) if v} | {"page": page + 1}),
            "newer": urlencode({k: v for k, v in (("state", state), ("batch", batch), ("page", page - 1)) if v})}


@router.get("/", response_class=HTMLResponse)
def jobs_page(request: Request, store: StoreDep) -> HTMLResponse:
    """The jobs list with filters; its table refreshes itself."""
    return render(request, "jobs.html", **_jobs_context(store, **_filters(request)))


@router.get("/ui/jobs/table", response_class=HTMLResponse)
def jobs_table(request: Request, store: StoreDep) -> HTMLResponse:
    """The live part of the jobs list (htmx fragment)."""
    return render(request, "_jobs_table.html", **_jobs_context(store, **_filters(request)))


# ---- one job -----------------------------------------------------------------------------------------------
@router.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, job_id: str, store: StoreDep) -> HTMLResponse:
    """The spec, the state, the results (plot, downloads, snapshot picture), cancel, the error."""
    job = _job(store, job_id)
    fields = views.form_fields()
    spec_rows = [(f.name, views.show(job.spec.get(f.name)) or "null", views.show(job.spec.get(f.name)) != f.default)
                 for f in fields if f.name in job.spec]
    return render(request, "job.html", job=job, spec_rows=spec_rows)


@router.get("/ui/jobs/{job_id}/live", response_class=HTMLResponse)
def job_live(request: Request, job_id: str, store: StoreDep) -> Response:
    """The live status of a job (htmx fragment); once the job has ended, ask the page to reload."""
    job = _job(store, job_id)
    headers = {"HX-Refresh": "true"} if job.state in FINAL_STATES else None
    return render(request, "_job_live.html", headers=headers, job=job)


@router.post("/ui/jobs/{job_id}/cancel")
def job_cancel(job_id: str, store: StoreDep) -> Response:
    """Cancel from the job page; back to the page (409 when the job has already ended)."""
    job = _job(store, job_id)
    if job.state in FINAL_STATES:
        raise HTTPException(409, f"job {job.id} has already ended ({job.state}); nothing to cancel")
    store.request_cancel(job.id)
    return RedirectResponse(f"/ui/jobs/{job.id}", status_code=303)


# ---- one batch ---------------------------------------------------------------------------------------------
def _batch_context(store, batch_id: str) -> dict:
    jobs = batch_jobs(store, batch_id) if len(batch_id) <= 64 else []
    if not jobs:
        raise HTTPException(404, f"no batch with id {batch_id!r}")
    keys = views.varying_keys([j.spec for j in jobs])
    done = sum(j.state == "done" for j in jobs)
    return {"batch_id": batch_id, "jobs": jobs, "keys": keys, "done": done,
            "live_count": sum(views.live(j) for j in jobs),
            "base": {k: v for k, v in jobs[0].spec.items() if k not in keys}}


@router.get("/ui/batches/{batch_id}", response_class=HTMLResponse)
def batch_page(request: Request, batch_id: str, store: StoreDep) -> HTMLResponse:
    """The sweep table (the keys that vary between the batch's jobs) and the mean curves with error bands."""
    return render(request, "batch.html", **_batch_context(store, batch_id))


@router.get("/ui/batches/{batch_id}/live", response_class=HTMLResponse)
def batch_live(request: Request, batch_id: str, store: StoreDep) -> Response:
    """The sweep table (htmx fragment); once every job has ended, ask the page to reload."""
    ctx = _batch_context(store, batch_id)
    return render(request, "_batch_table.html", headers=None if ctx["live_count"] else {"HX-Refresh": "true"}, **ctx)


# ---- submit --------------------------------------------------------------------------------------------------
@router.get("/ui/submit", response_class=HTMLResponse)
def submit_form(request: Request) -> HTMLResponse:
    """A form for one spec, every field filled with the spec's default."""
    return render(request, "submit.html", fields=views.form_fields(), values={}, errors={}, general=[], priority="0")


@router.post("/ui/submit")
async def submit(request: Request, store: StoreDep, settings: SettingsDep) -> Response:
    """Validate the form like POST /jobs (same messages); queue the job and open its page, or show the form
    again (422) with each error next to its field."""
    form = {k: v for k, v in (await request.form()).items() if isinstance(v, str)}
    spec, errors = views.spec_from_form(form)
    general: list[str] = []
    priority_raw = (form.get("priority") or "0").strip()
    try:
        priority = int(priority_raw)
        if not -1000 <= priority <= 1000:
            raise ValueError
    except ValueError:
        errors["priority"] = f"priority = {priority_raw!r} must be a whole number in -1000 ... 1000"
    try:
        parsed = parse_spec({k: v for k, v in spec.items() if k not in errors})
        if not errors:
            check_limits(parsed, settings.max_particle_steps, settings.max_memory_bytes)
            check_backends(store, settings, [parsed], [[]])
    except SpecRejected as exc:
        per_field, general = views.errors_by_field(exc.errors)
        errors = {**per_field, **errors}
    if errors or general:
        return render(request, "submit.html", status=422, fields=views.form_fields(), values=form, errors=errors,
                      general=general, priority=priority_raw)
    (job,) = await run_in_threadpool(store.submit, [NewJob(parsed.to_json(), priority)],
                                     max_attempts=settings.max_attempts)
    return RedirectResponse(f"/ui/jobs/{job.id}", status_code=303)


# ---- the token form --------------------------------------------------------------------------------------------
def _local(path: Optional[str]) -> str:
    """A redirect target on this site only (no scheme, no host)."""
    return path if path and path.startswith("/") and not path.startswith("//") and "\\" not in path else "/"


@public.get("/ui/login", response_class=HTMLResponse)
def login_form(request: Request) -> HTMLResponse:
    return render(request, "login.html", next=_local(request.query_params.get("next")), wrong=False,
                  show_logout=False)


@public.post("/ui/login")
async def login(request: Request, settings: SettingsDep) -> Response:
    """Check the token and keep it in an HttpOnly, SameSite=Strict cookie (401 with the form when wrong)."""
    form = await request.form()
    token, target = str(form.get("token") or ""), _local(str(form.get("next") or "/"))
    if settings.token is not None and not token_matches(settings, token):
        return render(request, "login.html", status=401, next=target, wrong=True, show_logout=False,
                      headers={"WWW-Authenticate": "Bearer"})
    response = RedirectResponse(target, status_code=303)
    if settings.token is not None:
        response.set_cookie(TOKEN_COOKIE, token, max_age=COOKIE_MAX_AGE_S, httponly=True, samesite="strict",
                            secure=request.url.scheme == "https", path="/")
    return response


@public.post("/ui/logout")
def logout() -> Response:
    response = RedirectResponse("/ui/login", status_code=303)
    response.delete_cookie(TOKEN_COOKIE, path="/", httponly=True, samesite="strict")
    return response
