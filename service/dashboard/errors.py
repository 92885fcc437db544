"""Error pages: a browser gets a page that says what went wrong (and, for 401, the token form);
API clients keep FastAPI's JSON body.

HTML goes to the dashboard's own paths (``/`` and ``/ui/...``) and to a browser's navigation to an API
route (a GET whose Accept header names text/html: a download link of a job without a result). Images,
scripts, curl, httpx and the demq client do not send text/html in Accept, so they get JSON as before.
"""

from __future__ import annotations

import re
from urllib.parse import quote

from fastapi import Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.errors import allowed_methods

TITLES = {400: "Bad request", 401: "Token needed", 403: "Forbidden", 404: "Not found",
          405: "Method not allowed", 409: "Not available", 410: "Gone", 413: "Request too large",
          422: "Invalid request", 501: "Not installed"}
_JOB_PATH = re.compile(r"^/(?:ui/)?jobs/([0-9A-Za-z_-]{1,64})(?:/|$)")
_BATCH_PATH = re.compile(r"^/(?:ui/)?batches/([0-9A-Za-z_-]{1,64})(?:/|$)")


def dashboard_path(path: str) -> bool:
    return path == "/" or path.startswith("/ui/")


def wants_html(request: Request) -> bool:
    """Whether the error should be a page: a dashboard path, or a browser navigating to an API route."""
    if dashboard_path(request.url.path):
        return True
    return request.method == "GET" and "text/html" in request.headers.get("accept", "")


async def on_http_error(request: Request, exc: StarletteHTTPException) -> Response:
    """The HTTP error as a page for a browser, as JSON for anyone else."""
    if exc.status_code == 405:
        exc = StarletteHTTPException(405, exc.detail, headers={"Allow": allowed_methods(request)})
    if not wants_html(request):
        return await http_exception_handler(request, exc)
    from service.dashboard.routes import render

    path = request.url.path
    target = path + (f"?{request.url.query}" if request.url.query else "")
    if exc.status_code == 401 and request.headers.get("HX-Request"):
        # an htmx poll whose cookie has gone: send the whole page to the token form
        return Response(status_code=401, headers={"HX-Redirect": f"/ui/login?next={quote(target, safe='/')}"})
    job, batch = _JOB_PATH.match(path), _BATCH_PATH.match(path)
    hide = {"show_logout": False} if exc.status_code == 401 else {}
    return render(request, "error.html", status=exc.status_code, headers=getattr(exc, "headers", None), **hide,
                  code=exc.status_code, title=TITLES.get(exc.status_code, "Error"), detail=str(exc.detail),
                  next=target if request.method == "GET" else "/",
                  job_id=job.group(1) if job and exc.status_code != 404 else None,
                  batch_id=batch.group(1) if batch and exc.status_code != 404 else None)
