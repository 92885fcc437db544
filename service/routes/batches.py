"""Batches: many specs, or a base spec and a sweep (cartesian product), queued in one transaction;
the batch result (mean cooling curves over seeds with standard errors) and its plot."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from jobs.batch_results import BatchNotFound, BatchNotReady, batch_result
from jobs.specs import admit, expand_sweep, sweep_size
from jobs.store import NewJob
from service.backends import check_backends
from service.deps import SettingsDep, StoreDep, wake_worker
from service.downloads import Download
from service.errors import NEEDS_PLOTS, InvalidRequest, needs_extra, rejected
from service.results import batch_plot_png
from service.schemas import BatchIn, BatchOut

router = APIRouter(prefix="/batches", tags=["batches"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=BatchOut,
             responses={400: {"description": "the body cannot be decoded (not UTF-8 JSON)"},
                        413: {"description": "request body too large"},
                        422: {"description": "an invalid spec (all errors listed), too many jobs, or no live "
                                              "worker runs a spec's backend ('cuda')"}})
def submit_batch(batch: BatchIn, store: StoreDep, settings: SettingsDep, request: Request) -> BatchOut:
    """Queue a list of specs or a parameter sweep. All jobs are queued, or none (any error -> 422)."""
    if batch.specs is not None:
        items, loc = [s.model_dump() for s in batch.specs], ["body", "specs"]
    else:
        base, sweep = batch.sweep_items()
        n = sweep_size(sweep)
        if n > settings.max_batch_jobs:
            raise InvalidRequest([{"loc": ["body", "sweep"], "type": "limit_batch_jobs", "msg": (
                f"the sweep makes {n} jobs, above the limit DEMQ_MAX_BATCH_JOBS = {settings.max_batch_jobs}")}])
        items, loc = expand_sweep(base, sweep), ["body", "sweep", "combination"]
    if len(items) > settings.max_batch_jobs:
        raise InvalidRequest([{"loc": loc, "type": "limit_batch_jobs", "msg": (
            f"{len(items)} jobs, above the limit DEMQ_MAX_BATCH_JOBS = {settings.max_batch_jobs}")}])
    with rejected():
        specs = admit(items, settings.max_particle_steps, settings.max_memory_bytes, loc)
        check_backends(store, settings, specs, [[*loc, i] for i in range(len(specs))])
    batch_id = uuid.uuid4().hex
    jobs = store.submit([NewJob(s.to_json(), batch.priority) for s in specs], batch_id=batch_id,
                        max_attempts=settings.max_attempts)
    wake_worker(request)
    return BatchOut(batch_id=batch_id, count=len(jobs), job_ids=[j.id for j in jobs])


BatchId = Annotated[str, PathParam(max_length=64, description="The batch_id returned by POST /batches.")]
Partial = Annotated[bool, Query(description="Aggregate the jobs done so far while others are still queued or "
                                            "running (default: 409 until every job of the batch has ended).")]
RESULT_RESPONSES = {404: {"description": "no batch with this id"},
                    409: {"description": "jobs still queued or running (see partial), or no job has a result"}}


def _batch_file(store, settings, batch_id: str, partial: bool) -> Path:
    try:
        return batch_result(store, settings, batch_id, partial)
    except BatchNotFound as exc:
        raise HTTPException(404, str(exc)) from None
    except (BatchNotReady, ValueError) as exc:
        raise HTTPException(409, str(exc)) from None


@router.get("/{batch_id}/result", response_class=FileResponse, responses={
    **RESULT_RESPONSES, 200: {"content": {"application/x-hdf5": {}}, "description": "the batch HDF5"}})
def get_batch_result(batch_id: BatchId, store: StoreDep, settings: SettingsDep, partial: Partial = False):
    """Seed statistics of the batch as HDF5: its done jobs grouped by spec apart from the seed; per group
    the mean of T_tr, T_rot and E_tr/E_tr(0) over the seeds with its standard error, the number of seeds,
    the seeds and the job ids (layout: engine/analysis/ensemble_stats.py). Failed or cancelled jobs are left out
    and listed in the file's ``excluded`` attribute."""
    path = _batch_file(store, settings, batch_id, partial)
    return Download(path, media_type="application/x-hdf5", filename=f"demq-batch-{batch_id}.h5")


@router.get("/{batch_id}/plot.png", response_class=Response, responses={
    **RESULT_RESPONSES, **NEEDS_PLOTS, 200: {"content": {"image/png": {}}, "description": "PNG"}})
def get_batch_plot(batch_id: BatchId, store: StoreDep, settings: SettingsDep, partial: Partial = False) -> Response:
    """Mean T/T0 and R/T0 of each group of the batch with +-1 standard-error bands, against Luding's ODE
    (spheres) or Haff's law (ellipsoids)."""
    path = _batch_file(store, settings, batch_id, partial)
    with needs_extra():
        png = batch_plot_png(path, f"batch {batch_id[:8]}: mean over seeds")
    return Response(png, media_type="image/png")


router.add_api_route("/{batch_id}/plot", get_batch_plot, methods=["GET"], response_class=Response,
                     include_in_schema=False)  # the same plot without the suffix
