"""Request and response bodies of the HTTP API (separate from the job table's Job record)."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Literal, Optional

from pydantic import BaseModel, Field, model_validator

from jobs.schema import STATES
from jobs.specs import QueueSpec
from jobs.store import Job

JobState = Literal[STATES]  # type: ignore[valid-type]


def _iso(t: Optional[float]) -> Optional[datetime]:
    return datetime.fromtimestamp(t, tz=timezone.utc) if t is not None else None


class JobOut(BaseModel):
    """A job: state, progress, timings, result."""

    id: str
    state: JobState
    batch_id: Optional[str] = None
    priority: int
    progress: float = Field(description="Fraction of the run done, 0 ... 1.")
    phase: Optional[str] = Field(None, description="'thermalization', 'cooling' or 'done'.")
    step: Optional[int] = None
    sim_time: Optional[float] = Field(None, description="Simulated time reached, s.")
    eta_s: Optional[float] = Field(None, description="Estimated wall seconds left (while running).")
    created_at: datetime
    started_at: Optional[datetime] = None
    finished_at: Optional[datetime] = None
    queued_s: Optional[float] = Field(None, description="Seconds from submission to the first start.")
    run_s: Optional[float] = Field(None, description="Seconds from the first start to the end.")
    wall_s: Optional[float] = Field(None, description="Wall seconds of the engine's time loop.")
    cundall: Optional[float] = Field(None, description="Cundall number: particle-steps per wall second.")
    backend: Optional[str] = None
    device: Optional[str] = None
    resumed_from_step: Optional[int] = None
    attempts: int
    max_attempts: int
    cancel_requested: bool
    error: Optional[str] = None
    result_available: bool
    spec: dict[str, Any]

    @classmethod
    def of(cls, job: Job) -> "JobOut":
        end = job.finished_at
        return cls(
            id=job.id, state=job.state, batch_id=job.batch_id, priority=job.priority, progress=job.progress,
            phase=job.phase, step=job.step, sim_time=job.sim_time, eta_s=job.eta_s,
            created_at=_iso(job.created_at), started_at=_iso(job.started_at), finished_at=_iso(end),
            queued_s=job.started_at - job.created_at if job.started_at else None,
            run_s=end - job.started_at if end and job.started_at else None,
            wall_s=job.wall_s, cundall=job.cundall, backend=job.backend, device=job.device,
            resumed_from_step=job.resumed_from_step, attempts=job.attempts, max_attempts=job.max_attempts,
            cancel_requested=job.cancel_requested, error=job.error,
            result_available=job.state == "done" and job.result_path is not None, spec=job.spec)


class JobPage(BaseModel):
    """One page of a job listing."""

    items: list[JobOut]
    total: int = Field(description="Number of jobs matching the filters.")
    limit: int
    offset: int


class BatchIn(BaseModel):
    """A batch: either ``specs`` (a list of specs), or ``base`` plus ``sweep`` (cartesian product)."""

    specs: Optional[list[QueueSpec]] = Field(None, description="Specs to queue, one job each.")
    base: Optional[dict[str, Any]] = Field(
        None, description="Spec keys shared by every job of the sweep (missing keys take their defaults).")
    sweep: Optional[dict[str, list[Any]]] = Field(
        None, description="Spec key -> list of values; one job per combination, e.g. "
                          "{\"e_n\": [0.7, 0.9], \"e_t\": [-1, 0, 1]} makes 6 jobs.")
    priority: int = Field(0, ge=-1000, le=1000, description="Higher runs first.")

    model_config = {"extra": "forbid", "json_schema_extra": {"examples": [
        {"base": {"n_particles": 512, "t_end": 0.01}, "sweep": {"e_n": [0.7, 0.9], "e_t": [-1.0, 0.8]}}]}}

    @model_validator(mode="after")
    def _one_form(self) -> "BatchIn":
        if (self.specs is None) == (self.sweep is None):
            raise ValueError("give either 'specs' (a list of specs) or 'sweep' (with an optional 'base'), not both")
        if self.specs is not None and not self.specs:
            raise ValueError("'specs' is empty: a batch needs at least one spec")
        if self.sweep is not None:
            if not self.sweep:
                raise ValueError("'sweep' is empty: give at least one key with a list of values")
            empty = [k for k, v in self.sweep.items() if not v]
            if empty:
                raise ValueError(f"sweep key(s) {empty} have no values")
        if self.specs is None and self.base is None:
            self.base = {}
        return self


class BatchOut(BaseModel):
    """The jobs a batch created."""

    batch_id: str
    count: int
    job_ids: list[str]


class Health(BaseModel):
    status: Literal["ok"]
    jobs: dict[str, int] = Field(description="Number of jobs per state.")
