"""Typed FastAPI dependencies: the settings, the store, the bearer-token check, the refusal of undeclared query
parameters, job lookup."""

from __future__ import annotations

import secrets
from types import UnionType
from typing import Annotated, Optional, Union, get_args, get_origin

from fastapi import Depends, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from jobs.settings import Settings
from jobs.store import Job, JobStore

_bearer = HTTPBearer(auto_error=False, description="The server's token (DEMQ_TOKEN); declared only when one is set.")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def wake_worker(request: Request) -> None:
    """Tell the embedded worker (`demq serve`) that jobs were queued, so it claims them now rather than at the
    end of its idle wait (DEMQ_POLL_SECONDS); external workers keep polling."""
    wake = getattr(request.app.state, "wake_worker", None)
    if wake is not None:
        wake()


#: The HttpOnly cookie in which the dashboard keeps the token (set by its token form, /ui/login).
TOKEN_COOKIE = "demq_token"


def token_matches(settings: Settings, supplied: Optional[str]) -> bool:
    """Whether ``supplied`` is the configured token (constant-time); True when auth is off."""
    if settings.token is None:
        return True
    return supplied is not None and secrets.compare_digest(supplied.encode(), settings.token.encode())


def require_token(request: Request, settings: Annotated[Settings, Depends(get_settings)],
                  credentials: Annotated[Optional[HTTPAuthorizationCredentials], Depends(_bearer)]) -> None:
    """Token auth, on when a token is configured: the ``Authorization: Bearer`` header, or the
    dashboard's cookie (:data:`TOKEN_COOKIE`)."""
    if settings.token is None:
        return
    if credentials is not None and token_matches(settings, credentials.credentials):
        return
    if token_matches(settings, request.cookies.get(TOKEN_COOKIE)):
        return
    raise HTTPException(401, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


def _declared_query(dependant) -> dict:
    """The query parameters an operation declares, its own and its dependencies' (FastAPI's Dependant): name ->
    whether it takes several values (a list, tuple or set annotation, optional or not)."""
    names = {}
    for p in dependant.query_params:
        annotation = p.field_info.annotation
        kinds = [annotation] + list(get_args(annotation) if get_origin(annotation) in (Union, UnionType) else [])
        names[p.alias] = any(get_origin(k) in (list, tuple, set, frozenset) for k in kinds)
    for sub in dependant.dependencies:
        names.update(_declared_query(sub))
    return names


def query_as_declared(request: Request) -> None:
    """Refuse query parameters the operation does not declare, and a single-valued one given more than once, with a
    422 naming each (as unknown body fields are refused): a misspelt filter such as ``GET /jobs?stat=done`` must
    not be silently ignored, nor ``?batch_id=a&batch_id=b`` read as its last value."""
    route = request.scope.get("route")
    if route is None or not request.query_params:
        return
    declared = _declared_query(route.dependant)
    errors = []
    for k in dict.fromkeys(request.query_params.keys()):
        if k not in declared:
            errors.append({"loc": ("query", k), "type": "extra_forbidden",
                           "msg": f"unknown query parameter {k!r}; this operation takes "
                                  f"{', '.join(sorted(declared)) or 'none'}"})
        elif not declared[k] and len(request.query_params.getlist(k)) > 1:
            errors.append({"loc": ("query", k), "type": "too_many_values",
                           "msg": f"query parameter {k!r} takes one value, got "
                                  f"{len(request.query_params.getlist(k))}"})
    if errors:
        raise RequestValidationError(errors)


def get_job(job_id: str, store: Annotated[JobStore, Depends(get_store)]) -> Job:
    job = store.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job with id {job_id!r}")
    return job


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
JobDep = Annotated[Job, Depends(get_job)]
