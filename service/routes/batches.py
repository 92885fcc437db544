"""Batches: many specs, or a base spec and a sweep (cartesian product), queued in one transaction."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, status

from jobs.specs import admit, expand_sweep, sweep_size
from jobs.store import NewJob
from service.deps import SettingsDep, StoreDep
from service.errors import InvalidRequest, rejected
from service.schemas import BatchIn, BatchOut

router = APIRouter(prefix="/batches", tags=["batches"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=BatchOut,
             responses={413: {"description": "request body too large"},
                        422: {"description": "an invalid spec (all errors listed), or too many jobs"}})
def submit_batch(batch: BatchIn, store: StoreDep, settings: SettingsDep) -> BatchOut:
    """Queue a list of specs or a parameter sweep. All jobs are queued, or none (any error -> 422)."""
    if batch.specs is not None:
        items, loc = [s.model_dump() for s in batch.specs], ["body", "specs"]
    else:
        n = sweep_size(batch.sweep)
        if n > settings.max_batch_jobs:
            raise InvalidRequest([{"loc": ["body", "sweep"], "type": "limit_batch_jobs", "msg": (
                f"the sweep makes {n} jobs, above the limit DEMQ_MAX_BATCH_JOBS = {settings.max_batch_jobs}")}])
        items, loc = expand_sweep(batch.base, batch.sweep), ["body", "sweep", "combination"]
    if len(items) > settings.max_batch_jobs:
        raise InvalidRequest([{"loc": loc, "type": "limit_batch_jobs", "msg": (
            f"{len(items)} jobs, above the limit DEMQ_MAX_BATCH_JOBS = {settings.max_batch_jobs}")}])
    with rejected():
        specs = admit(items, settings.max_particle_steps, settings.max_memory_bytes, loc)
    batch_id = uuid.uuid4().hex
    jobs = store.submit([NewJob(s.to_json(), batch.priority) for s in specs], batch_id=batch_id,
                        max_attempts=settings.max_attempts)
    return BatchOut(batch_id=batch_id, count=len(jobs), job_ids=[j.id for j in jobs])
