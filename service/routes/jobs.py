"""Jobs: submit one spec, list and filter, status with progress, cancel."""

from __future__ import annotations

from typing import Annotated, Optional

from fastapi import APIRouter, HTTPException, Query, Request, status

from jobs.schema import CANCELLED, FINAL_STATES
from jobs.specs import check_limits
from jobs.store import NewJob
from service.backends import check_backends
from service.deps import JobDep, SettingsDep, StoreDep, wake_worker
from service.errors import rejected
from service.schemas import JobOut, JobPage, JobState, SimulationSpecIn

router = APIRouter(prefix="/jobs", tags=["jobs"])
NOT_FOUND = {404: {"description": "no job with this id"}}


@router.post("", status_code=status.HTTP_201_CREATED, response_model=JobOut,
             responses={400: {"description": "the body cannot be decoded (not UTF-8 JSON)"},
                        413: {"description": "request body too large"},
                        422: {"description": "invalid spec, its estimated cost exceeds a limit, or no live "
                                              "worker runs its backend ('cuda')"}})
def submit_job(spec: SimulationSpecIn, store: StoreDep, settings: SettingsDep, request: Request,
               priority: Annotated[int, Query(ge=-1000, le=1000, description="Higher runs first.")] = 0) -> JobOut:
    """Queue one simulation. The body is a spec (the engine's JSON keys; missing keys take defaults)."""
    with rejected():
        check_limits(spec, settings.max_particle_steps, settings.max_memory_bytes, ["body"])
        check_backends(store, settings, [spec], [["body"]])
    (job,) = store.submit([NewJob(spec.to_json(), priority)], max_attempts=settings.max_attempts)
    wake_worker(request)
    return JobOut.of(job)


@router.get("", response_model=JobPage)
def list_jobs(store: StoreDep,
              state: Annotated[Optional[JobState], Query(description="Only jobs in this state.")] = None,
              batch_id: Annotated[Optional[str], Query(max_length=64, description="Only jobs of this batch.")] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 50,
              offset: Annotated[int, Query(ge=0, le=2**62)] = 0) -> JobPage:
    """Jobs in submission order, filtered by state and batch, one page at a time."""
    items, total = store.list(state=state, batch_id=batch_id, limit=limit, offset=offset)
    return JobPage(items=[JobOut.of(j) for j in items], total=total, limit=limit, offset=offset)


@router.get("/{job_id}", response_model=JobOut, responses=NOT_FOUND)
def get_job(job: JobDep) -> JobOut:
    """State, progress (0-1), ETA, timings, Cundall number and error of a job."""
    return JobOut.of(job)


@router.post("/{job_id}/cancel", response_model=JobOut,
             responses={**NOT_FOUND, 409: {"description": "the job has already ended"}})
def cancel_job(job: JobDep, store: StoreDep) -> JobOut:
    """Cancel a queued job at once; ask the worker of a running job to stop it (state stays
    'running' with cancel_requested = true until the worker confirms 'cancelled')."""
    if job.state in FINAL_STATES:
        raise HTTPException(409, f"job {job.id} has already ended ({job.state}); nothing to cancel")
    updated = store.request_cancel(job.id)
    if updated.state in FINAL_STATES and updated.state != CANCELLED:
        raise HTTPException(409, f"job {job.id} ended ({updated.state}) before the cancel arrived")
    return JobOut.of(updated)
