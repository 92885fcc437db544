"""Error bodies: 422 with the field and the limit, JSON-safe (a spec may hold NaN or huge numbers)."""

from __future__ import annotations

from contextlib import contextmanager

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.routing import Match

from jobs.specs import SpecRejected


class InvalidRequest(Exception):
    """A request the service refuses with 422; ``errors`` as in :class:`jobs.specs.SpecRejected`."""

    def __init__(self, errors: list[dict]):
        self.errors = errors


@contextmanager
def rejected():
    """Turn :class:`SpecRejected` raised inside into a 422 answer."""
    try:
        yield
    except SpecRejected as exc:
        raise InvalidRequest(exc.errors) from None


@contextmanager
def needs_extra():
    """Turn :class:`engine.optional.MissingExtra` raised inside (a figure without matplotlib) into a 501 answer
    whose detail names the extra to install."""
    from fastapi import HTTPException

    from engine.optional import MissingExtra

    try:
        yield
    except MissingExtra as exc:
        raise HTTPException(501, str(exc)) from None


#: The 501 of a route that draws a figure, for its OpenAPI ``responses``.
NEEDS_PLOTS = {501: {"description": "this server lacks matplotlib (the plots extra)"}}


#: The methods a 405's ``Allow`` header may list.
HTTP_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def allowed_methods(request: Request) -> str:
    """The ``Allow`` header of a 405: every method some route answers on the request's path (Starlette's
    own header names only the first route it matched, so GET /jobs hid POST /jobs and the reverse)."""
    allowed = [m for m in HTTP_METHODS
               if any(route.matches({**request.scope, "method": m})[0] == Match.FULL
                      for route in request.app.router.routes)]
    return ", ".join(allowed)


def _clean(errors) -> list[dict]:
    return [{"loc": [str(x) if not isinstance(x, int) else x for x in e.get("loc", ())],
             "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))} for e in errors]


async def on_validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's own validation errors (body, query, path), without echoing the input back."""
    return JSONResponse({"detail": _clean(exc.errors())}, status_code=422)


async def on_invalid_request(_request: Request, exc: InvalidRequest) -> JSONResponse:
    return JSONResponse({"detail": _clean(exc.errors)}, status_code=422)
