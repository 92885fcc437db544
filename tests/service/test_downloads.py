"""service.downloads.Download: large files in 4 MiB reads, whole and by byte range (the speed itself:
bench/download_speed.py)."""

from __future__ import annotations

import os

from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.downloads import Download


def test_download_sends_the_whole_file_and_byte_ranges_across_its_pieces(tmp_path):
    data = os.urandom(10 * (1 << 20) + 12345)          # three pieces of 4 MiB, the last one short
    path = tmp_path / "result.h5"
    path.write_bytes(data)
    app = FastAPI()

    @app.get("/file")
    def file():
        return Download(path, media_type="application/x-hdf5", filename="result.h5")

    with TestClient(app) as c:
        r = c.get("/file")
        assert r.status_code == 200 and r.content == data
        assert r.headers["content-length"] == str(len(data))
        lo, hi = Download.chunk_size - 100, 2 * Download.chunk_size + 100      # spans two piece boundaries
        r = c.get("/file", headers={"Range": f"bytes={lo}-{hi}"})
        assert r.status_code == 206 and r.content == data[lo:hi + 1]
        r = c.get("/file", headers={"Range": f"bytes=-{5000}"})                 # the last 5000 bytes
        assert r.status_code == 206 and r.content == data[-5000:]


def test_download_reads_and_sends_the_file_in_pieces_of_4_mib(tmp_path):
    """The point of Download: 3 body messages for a 10 MB file, where starlette's FileResponse sends 161."""
    import asyncio

    path = tmp_path / "result.h5"
    path.write_bytes(os.urandom(10 * (1 << 20) + 12345))
    messages, requested = [], []

    async def receive():              # the request, then no disconnect while the response is sent
        if not requested:
            requested.append(1)
            return {"type": "http.request", "body": b"", "more_body": False}
        await asyncio.Event().wait()

    async def send(message):
        messages.append(message)

    scope = {"type": "http", "method": "GET", "path": "/", "headers": [], "http_version": "1.1",
             "query_string": b""}
    asyncio.run(Download(path, media_type="application/x-hdf5")(scope, receive, send))
    bodies = [m["body"] for m in messages if m["type"] == "http.response.body" and m.get("body")]
    assert len(bodies) == 3 and b"".join(bodies) == path.read_bytes()
