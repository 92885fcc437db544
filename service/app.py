"""The FastAPI application: routes, error bodies, body-size limit, auth, optional embedded worker."""

from __future__ import annotations

import logging
import threading
from contextlib import asynccontextmanager
from typing import Optional

from fastapi import Depends, FastAPI
from fastapi.exceptions import RequestValidationError

from jobs.settings import Settings
from jobs.store import JobStore
from jobs.stores import open_store
from jobs.worker import Worker
from service import dashboard
from service.deps import require_token
from service.errors import InvalidRequest, on_invalid_request, on_validation_error
from service.limits import BodySizeLimit
from service.routes import batches, health, jobs, results

log = logging.getLogger("demq.service")

DESCRIPTION = """Queue granular-gas DEM simulations, follow their progress, download the HDF5 results.

A job's body is a simulation spec (see the SimulationSpec schema; missing keys take the defaults of
paper 001). Invalid specs get 422 naming the field and the allowed range; specs whose estimated
memory or particle-steps exceed the server's limits get 422 before they are queued.

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
    app.add_exception_handler(RequestValidationError, on_validation_error)
    app.add_exception_handler(InvalidRequest, on_invalid_request)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    auth = [Depends(require_token)]
    app.include_router(health.router)
    for module in (jobs, batches, results):
        app.include_router(module.router, dependencies=auth)
    dashboard.install(app)
    return app
