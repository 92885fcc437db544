"""Request and response bodies of the HTTP API (separate from the job table's Job record)."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, List, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, create_model, model_validator

from engine.setup.spec import FIELD_RANGES, SimulationSpec, Species, field_schema_keywords, write_field_keywords

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
    phase: Optional[str] = Field(None, description="'waiting' (behind other jobs of its worker's claim), "
                                                        "'starting', 'thermalization', 'cooling' or 'done'.")
    step: Optional[int] = None
    sim_time: Optional[float] = Field(None, description="Simulated time reached, s.")
    eta_s: Optional[float] = Field(None, description="Estimated wall seconds left (while running).")
    created_at: datetime
    started_at: Optional[datetime] = None
    finished_at: Optional[datetime] = None
    queued_s: Optional[float] = Field(None, description="Seconds from submission to the first start.")
    run_s: Optional[float] = Field(None, description="Seconds from the first start to the end.")
    loop_s: Optional[float] = Field(None, description="Wall seconds of the engine's time loop (the run's steps).")
    job_wall_s: Optional[float] = Field(None, description="Wall seconds of the whole run, from the spec to the closed "
                                                          "result file (set-up, compilation or its cache load, loop, "
                                                          "output).")
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
            loop_s=job.loop_s, job_wall_s=job.job_wall_s, cundall=job.cundall, backend=job.backend, device=job.device,
            resumed_from_step=job.resumed_from_step, attempts=job.attempts, max_attempts=job.max_attempts,
            cancel_requested=job.cancel_requested, error=job.error,
            result_available=job.state == "done" and job.result_path is not None, spec=job.spec)


class JobPage(BaseModel):
    """One page of a job listing."""

    items: list[JobOut]
    total: int = Field(description="Number of jobs matching the filters.")
    limit: int
    offset: int


class WholeNumbers(BaseModel):
    """Strict JSON types as JSON Schema means them: an integer field also takes a number with a zero
    fraction (``5.0``), which pydantic's strict mode refuses; a boolean or a string stays refused."""

    @model_validator(mode="before")
    @classmethod
    def _whole_numbers(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, info in cls.model_fields.items():
            value = out.get(name)
            if info.annotation is int and _whole(value):
                out[name] = int(value)
            elif info.annotation == list[int] and isinstance(value, list):
                out[name] = [int(v) if _whole(v) else v for v in value]
        return out


def _whole(value: Any) -> bool:
    return isinstance(value, float) and value.is_integer()


class SpeciesIn(Species):
    """One sphere size of a polydisperse spec, as the API takes it (JSON types strictly)."""

    model_config = ConfigDict(strict=True, title="Species")


class SimulationSpecIn(WholeNumbers, QueueSpec):
    """The spec as the API takes it: the queue's spec with JSON types taken strictly (a number is not a
    string, a whole number is not a boolean), as the OpenAPI document states them."""

    model_config = ConfigDict(strict=True, title="SimulationSpec")

    species: Optional[List[SpeciesIn]] = Field(None, description=SimulationSpec.model_fields["species"].description)


def _api_annotation(annotation: Any) -> Any:
    """A spec field's type with the strict species entry in place of the engine's."""
    return Optional[List[SpeciesIn]] if annotation == Optional[List[Species]] else annotation


class KeyOrder(WholeNumbers):
    """Remembers the order of the keys as given: a sweep's combinations follow it (the first key varies
    slowest), not the order of the spec's fields."""

    _order: list[str] = PrivateAttr(default_factory=list)

    @model_validator(mode="wrap")
    @classmethod
    def _remember_order(cls, data: Any, handler):
        obj = handler(data)
        if isinstance(data, dict):
            obj._order = [k for k in data if k in cls.model_fields]
        return obj

    def given(self) -> dict[str, Any]:
        """The keys given, in their order, as JSON values."""
        values = self.model_dump(mode="json", exclude_unset=True)
        return {k: values[k] for k in self._order if k in values}


def _spec_keys_model(name: str, sweep: bool) -> type[BaseModel]:
    """A model with every spec key, all optional, typed as in the spec (``sweep``: a non-empty list of such
    values), whose JSON schema carries the spec's one-field ranges: the schema of a sweep's ``base`` and
    ``sweep``. Values are range-checked when each combination is validated as a spec (loc names it)."""
    fields: dict[str, Any] = {}
    for key, info in SimulationSpec.model_fields.items():
        annotation = _api_annotation(info.annotation)
        if sweep:
            fields[key] = (list[annotation], Field(None, min_length=1, description=f"Values of {key}."))
        else:
            fields[key] = (annotation, Field(None, description=info.description,
                                                  json_schema_extra=info.json_schema_extra))

    def schema_extra(schema: dict, _model) -> None:
        for prop in schema["properties"].values():
            prop.pop("default", None)          # a key left out takes the spec's default, not null
        write_field_keywords(schema["properties"], field_schema_keywords(FIELD_RANGES), items=sweep)
        if sweep:
            schema["minProperties"] = 1

    return create_model(name, __base__=KeyOrder,
                        __config__=ConfigDict(extra="forbid", strict=True, json_schema_extra=schema_extra), **fields)


SpecKeys = _spec_keys_model("SpecKeys", sweep=False)
SweepValues = _spec_keys_model("SweepValues", sweep=True)

#: The one-of rule of a batch in JSON schema: 'specs', or 'sweep' with an optional 'base'.
_BATCH_FORMS = {"oneOf": [{"required": ["specs"]}, {"required": ["sweep"]}],
                "not": {"required": ["specs", "base"]}}


def _no_default(schema: dict) -> None:
    schema.pop("default", None)


class BatchIn(WholeNumbers):
    """A batch: either ``specs`` (a list of specs), or ``sweep`` (spec key -> values; the cartesian product)
    with an optional ``base`` (keys shared by every job of the sweep)."""

    specs: list[SimulationSpecIn] = Field(None, min_length=1, description="Specs to queue, one job each.",
                                   json_schema_extra=_no_default)
    base: SpecKeys = Field(None, description="Spec keys shared by every job of the sweep (missing keys take "
                                             "their defaults); only with 'sweep'.", json_schema_extra=_no_default)
    sweep: SweepValues = Field(
        None, description="Spec key -> non-empty list of values; one job per combination, e.g. "
                          "{\"e_n\": [0.7, 0.9], \"e_t\": [-1, 0, 1]} makes 6 jobs.", json_schema_extra=_no_default)
    priority: int = Field(0, ge=-1000, le=1000, description="Higher runs first.")

    model_config = {"extra": "forbid", "strict": True, "json_schema_extra": {**_BATCH_FORMS, "examples": [
        {"base": {"n_particles": 512, "t_end": 0.01}, "sweep": {"e_n": [0.7, 0.9], "e_t": [-1.0, 0.8]}}]}}

    @model_validator(mode="after")
    def _one_form(self) -> "BatchIn":
        if (self.specs is None) == (self.sweep is None):
            raise ValueError("give either 'specs' (a list of specs) or 'sweep' (with an optional 'base'), not both")
        if self.sweep is not None and not self.sweep.model_fields_set:
            raise ValueError("'sweep' is empty: give at least one key with a list of values")
        if self.specs is not None and self.base is not None:
            raise ValueError("'base' goes with 'sweep': with 'specs' give each spec in full")
        return self

    def sweep_items(self) -> tuple[dict[str, Any], dict[str, list[Any]]]:
        """The sweep's (base, sweep) as plain dicts of the keys given."""
        return (self.base.given() if self.base is not None else {}), self.sweep.given()


class BatchOut(BaseModel):
    """The jobs a batch created."""

    batch_id: str
    count: int
    job_ids: list[str]


class Health(BaseModel):
    status: Literal["ok"]
    jobs: dict[str, int] = Field(description="Number of jobs per state.")
