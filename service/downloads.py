"""The service's file downloads (a job's HDF5 result: 436 MB for 2M spheres with two frames)."""

from __future__ import annotations

from fastapi.responses import FileResponse


class Download(FileResponse):
    """starlette's FileResponse, read and sent in pieces of 4 MiB instead of 64 KiB: the per-piece work (a worker
    thread's read, an ASGI message) made a 436 MB result take 0.57-0.76 s to send to curl on the H200 host and
    1.2-1.4 s on a 2-core VM; in these pieces 0.17-0.19 s on both (bench/download_speed.py). Range requests are
    served as before (the piece size only bounds each read)."""

    chunk_size = 4 << 20
