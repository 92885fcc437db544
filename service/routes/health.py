"""GET /healthz — no auth; 200 when the job table answers, 503 otherwise."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from sqlalchemy.exc import SQLAlchemyError

from service.deps import StoreDep
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, responses={503: {"description": "database unreachable"}})
def healthz(store: StoreDep) -> Health:
    """Liveness and readiness: the database answers; job counts per state."""
    try:
        return Health(status="ok", jobs=store.counts())
    except SQLAlchemyError as exc:
        raise HTTPException(503, f"job table unreachable: {type(exc).__name__}") from None
