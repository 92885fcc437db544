"""HTTP client of the demq service, used by ``demq submit/status/fetch`` (without --local).

Every failure is a :class:`ServiceError` whose message is one line naming the problem and the fix: the
service's error answer (``HTTP 404: no job with id 'abc'``), no answer at all (:class:`ServiceUnreachable`:
no server at the URL, a timeout, a host name that does not resolve), or a URL that is not an http(s) URL
(:class:`BadServiceURL`, a usage error).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional

import httpx

#: where the URL and the token come from, for the fixes the messages name
URL_SOURCES = "--url/DEMQ_URL"
TOKEN_SOURCES = "--token/DEMQ_TOKEN"


class ServiceError(Exception):
    """The service answered with an error status or not at all; the message is one line with its detail."""


class ServiceUnreachable(ServiceError):
    """No answer from the service: nothing listens at the URL, the host does not resolve, or it timed out."""


class BadServiceURL(ServiceError):
    """The service URL is not an http(s) URL with a host (a usage error: the command line or DEMQ_URL)."""


def _reason(exc: httpx.TransportError, timeout: float) -> str:
    """What went wrong with a request, in a few words: 'connection refused', 'no answer within 30 s', ..."""
    if isinstance(exc, httpx.TimeoutException):
        return f"no answer within {timeout:g} s"
    text = re.sub(r"^\[Errno -?\d+\]\s*", "", str(exc).strip()) or type(exc).__name__
    return text[:1].lower() + text[1:]


class Client:
    """Thin wrapper over httpx with the bearer token and one-line errors (:class:`ServiceError`)."""

    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 30.0):
        try:
            parsed = httpx.URL(url)
        except (httpx.InvalidURL, TypeError) as exc:
            raise BadServiceURL(f"the service URL {url!r} is not a URL ({exc}); set {URL_SOURCES} to one such as "
                                f"http://127.0.0.1:8000") from None
        if parsed.scheme not in ("http", "https") or not parsed.host:
            raise BadServiceURL(f"the service URL {url!r} is not an http(s) URL with a host; set {URL_SOURCES} "
                                f"to one such as http://127.0.0.1:8000")
        self.url, self.timeout = url, timeout
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url, headers=headers, timeout=timeout)

    def _unreachable(self, exc: httpx.TransportError) -> ServiceUnreachable:
        return ServiceUnreachable(f"cannot reach the server at {self.url} ({_reason(exc, self.timeout)}); start it "
                                  f"with `demq serve` or set {URL_SOURCES}")

    def _check(self, r: httpx.Response) -> httpx.Response:
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            if isinstance(detail, list):
                detail = "; ".join(f"{'.'.join(map(str, d.get('loc', [])))}: {d.get('msg')}" for d in detail)
            detail = " ".join(str(detail).split())                # one line, whatever the server sent
            if len(detail) > 300:                                 # a page, not a demq answer: its start
                detail = detail[:297] + "..."
            if r.status_code == 401:
                detail += f"; pass the server's token with {TOKEN_SOURCES}"
            raise ServiceError(f"HTTP {r.status_code}: {detail}")
        return r

    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            return self._check(self.http.request(method, path, **kwargs))
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None

    def submit(self, spec: dict, priority: int = 0) -> dict:
        return self._request("POST", "/jobs", json=spec, params={"priority": priority}).json()

    def get(self, job_id: str) -> dict:
        return self._request("GET", f"/jobs/{job_id}").json()

    def list(self, state: Optional[str] = None, limit: int = 50) -> dict:
        params = {"limit": limit, **({"state": state} if state else {})}
        return self._request("GET", "/jobs", params=params).json()

    def fetch(self, job_id: str, output: Path) -> Path:
        """Stream the HDF5 result to ``output`` (written to a temporary name, then renamed; a broken transfer
        leaves no file)."""
        output = Path(output)
        tmp = output.with_name(output.name + ".part")
        try:
            with self.http.stream("GET", f"/jobs/{job_id}/result") as r:
                if r.status_code >= 400:
                    r.read()
                    self._check(r)
                with open(tmp, "wb") as fh:
                    for chunk in r.iter_bytes():
                        fh.write(chunk)
        except httpx.TransportError as exc:
            tmp.unlink(missing_ok=True)
            raise self._unreachable(exc) from None
        os.replace(tmp, output)
        return output
