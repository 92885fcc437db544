"""The FastAPI application: routes, error bodies, body-size limit, auth, optional embedded worker."""

from __future__ import annotations

import logging
import threading
from contextlib import asynccontextmanager
from typing import Optional

from fastapi import Depends, FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi

from engine.setup.spec import FIELD_RANGES, SPECIES_RANGES, field_schema_keywords, write_field_keywords

from jobs.settings import Settings
from jobs.store import JobStore
from jobs.stores import open_store
from jobs.worker import Worker
from service import dashboard
from service.deps import query_as_declared, require_token
from service.errors import InvalidRequest, on_invalid_request, on_validation_error
from service.limits import BodySizeLimit
from service.render import offered_renderers
from service.routes import batches, health, jobs, results

log = logging.getLogger("demq.service")

DESCRIPTION = """Queue granular-gas DEM simulations, follow their progress, download the HDF5 results.

A job's body is a simulation spec (see the SimulationSpec schema; missing keys take the defaults,
the default scene of Hidalgo et al. 2013). The schema states each field's type and allowed range; a spec outside
them gets 422 naming the field and the range. A schema-valid spec may still get 422 for a rule across fields (the
box must hold the neighbour cutoff, dt must resolve a contact, ...) or when its estimated memory or
particle-steps exceed the server's limits, always before it is queued.

Routes declare bearer auth only when the server has a token (DEMQ_TOKEN).

A web dashboard (jobs, progress, plots, downloads, a submit form) is served at `/`.
"""


def create_app(settings: Settings, store: Optional[JobStore] = None, embedded_worker: bool = False) -> FastAPI:
    """Build the app on ``settings``; ``embedded_worker`` runs one worker thread in the process."""
    store = store or open_store(settings.database_url, settings.table_prefix)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        worker, thread = None, None
        if embedded_worker:
            worker = Worker(store, settings)
            worker.register()   # before the first answer: the admission check knows this host's backends
            app.state.wake_worker = worker.wake     # submits wake it (service/deps.py wake_worker)
            thread = threading.Thread(target=worker.run_forever, name="demq-embedded-worker", daemon=True)
            thread.start()
        try:
            yield
        finally:
            if worker is not None:
                worker.stop()
                thread.join()

    app = FastAPI(title="demq", version="0.1.0", description=DESCRIPTION, lifespan=lifespan)
    app.state.settings, app.state.store = settings, store
    app.state.renderers = offered_renderers()     # the snapshot's renderer values, in the document's enum too
    app.add_exception_handler(RequestValidationError, on_validation_error)
    app.add_exception_handler(InvalidRequest, on_invalid_request)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    # Auth only where a token is configured: the routes (and the OpenAPI document) then declare bearer auth;
    # without a token they are open and the document says so.
    auth = [Depends(require_token)] if settings.token is not None else []
    auth_responses = {401: {"description": "missing or wrong bearer token"}} if auth else {}
    known_query = [Depends(query_as_declared)]     # after auth: a request without the token gets its 401 first
    app.include_router(health.router, dependencies=known_query)
    for module in (jobs, batches, results):
        app.include_router(module.router, dependencies=auth + known_query, responses=auth_responses)
    dashboard.install(app)
    app.openapi = lambda: _openapi(app)
    return app


def _openapi(app: FastAPI) -> dict:
    """FastAPI's document, with the spec fields' range keywords written again from engine/setup/spec.py:
    FastAPI's OpenAPI models hold minimum/maximum as floats, which rounds 2**63-1 (the largest seed) up
    to 2**63, a value the validator refuses; and with the snapshot's renderer enum of this server."""
    if app.openapi_schema is None:
        document = get_openapi(title=app.title, version=app.version, description=app.description,
                               routes=app.routes)
        components = document["components"]["schemas"]
        for name, sweep in (("SimulationSpecIn", False), ("SpecKeys", False), ("SweepValues", True)):
            write_field_keywords(components[name]["properties"], field_schema_keywords(FIELD_RANGES), items=sweep)
        write_field_keywords(components["SpeciesIn"]["properties"], field_schema_keywords(SPECIES_RANGES))
        results.offer_renderers(document, app.state.renderers)
        app.openapi_schema = document
    return app.openapi_schema
