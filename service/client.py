"""HTTP client of the demq service, used by ``demq submit/status/fetch`` (without --local)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import httpx


class ServiceError(Exception):
    """The service answered with an error status; the message carries its detail."""


class Client:
    """Thin wrapper over httpx with the bearer token and readable errors."""

    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 30.0):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url, headers=headers, timeout=timeout)

    def _check(self, r: httpx.Response) -> httpx.Response:
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            if isinstance(detail, list):
                detail = "; ".join(f"{'.'.join(map(str, d.get('loc', [])))}: {d.get('msg')}" for d in detail)
            raise ServiceError(f"HTTP {r.status_code}: {detail}")
        return r

    def submit(self, spec: dict, priority: int = 0) -> dict:
        return self._check(self.http.post("/jobs", json=spec, params={"priority": priority})).json()

    def get(self, job_id: str) -> dict:
        return self._check(self.http.get(f"/jobs/{job_id}")).json()

    def list(self, state: Optional[str] = None, limit: int = 50) -> dict:
        params = {"limit": limit, **({"state": state} if state else {})}
        return self._check(self.http.get("/jobs", params=params)).json()

    def fetch(self, job_id: str, output: Path) -> Path:
        """Stream the HDF5 result to ``output`` (written to a temporary name, then renamed)."""
        output = Path(output)
        tmp = output.with_name(output.name + ".part")
        with self.http.stream("GET", f"/jobs/{job_id}/result") as r:
            if r.status_code >= 400:
                r.read()
                self._check(r)
            with open(tmp, "wb") as fh:
                for chunk in r.iter_bytes():
                    fh.write(chunk)
        os.replace(tmp, output)
        return output
