"""Typed FastAPI dependencies: the settings, the store, the bearer-token check, job lookup."""

from __future__ import annotations

import secrets
from typing import Annotated, Optional

from fastapi import Depends, HTTPException, Request
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


def get_job(job_id: str, store: Annotated[JobStore, Depends(get_store)]) -> Job:
    job = store.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job with id {job_id!r}")
    return job


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
JobDep = Annotated[Job, Depends(get_job)]
