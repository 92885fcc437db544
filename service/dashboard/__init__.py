"""The web dashboard of ``demq serve``: jobs list at ``/``, job and batch pages, a submit form.

Server-rendered HTML (Jinja2 templates in ``templates/``) with a vendored htmx (``static/``, no CDN:
clusters have no internet) for the live parts. :func:`install` adds it to the FastAPI app.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.dashboard.errors import on_http_error
from service.dashboard.routes import HERE, STATIC_URL, public, router


def install(app: FastAPI) -> None:
    """Mount the dashboard's pages, its static files and its error pages on ``app``."""
    app.mount(STATIC_URL, StaticFiles(directory=HERE / "static"), name="dashboard-static")
    app.include_router(public)
    app.include_router(router)
    app.add_exception_handler(StarletteHTTPException, on_http_error)
