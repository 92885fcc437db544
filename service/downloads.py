"""The service's file downloads (a job's HDF5 result: 436 MB for 2M spheres with two frames)."""

from __future__ import annotations

from fastapi.responses import FileResponse


class Download(FileResponse):
    """starlette's FileResponse, read and sent in pieces of 4 MiB instead of 64 KiB: the per-piece work (a worker
    thread's read, an ASGI message) made a 436 MB result take 1.2-1.4 s to send, 0.18-0.23 s in these pieces
    (bench/download_speed.py). Range requests are served as before (the piece size only bounds each read)."""

    chunk_size = 4 << 20
