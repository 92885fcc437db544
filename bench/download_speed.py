"""How fast the service sends a large file (a result is downloadable when it is done, and a 2M-sphere
job's result is 436 MB): a file of --mb MiB served by uvicorn through starlette's FileResponse and through
service.downloads.Download, each downloaded --reps times over localhost by a streaming httpx client that
discards the bytes, and by curl (-o /dev/null) when there is one; prints the seconds of each download and the
median per response class and client.

    python -m bench download_speed [--mb 436] [--reps 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SERVER = r'''
import sys
sys.path.insert(0, sys.argv[4])
import uvicorn
from fastapi import FastAPI
from fastapi.responses import FileResponse
from service.downloads import Download

cls = {"FileResponse": FileResponse, "Download": Download}[sys.argv[3]]
app = FastAPI()

@app.get("/file")
def file():
    return cls(sys.argv[2], media_type="application/x-hdf5", filename="result.h5")

@app.get("/up")
def up():
    return {}

uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning")
'''


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def time_downloads(path: str, response: str, reps: int) -> list:
    import httpx

    port = _port()
    server = subprocess.Popen([sys.executable, "-c", SERVER, str(port), path, response, ROOT])
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120.0) as c:
            for _ in range(300):
                try:
                    if c.get("/up").status_code == 200:
                        break
                except httpx.HTTPError:
                    time.sleep(0.05)
            times = {"httpx": [], "curl": []}
            for _ in range(reps):
                t = time.perf_counter()
                size = 0
                with c.stream("GET", "/file") as r:
                    for piece in r.iter_raw(4 << 20):
                        size += len(piece)
                times["httpx"].append(time.perf_counter() - t)
                if size != os.path.getsize(path):
                    raise RuntimeError(f"{response}: got {size} bytes of {os.path.getsize(path)}")
                if shutil.which("curl"):
                    t = time.perf_counter()
                    subprocess.run(["curl", "-s", "-f", "-o", os.devnull, f"http://127.0.0.1:{port}/file"], check=True)
                    times["curl"].append(time.perf_counter() - t)
            return {k: v for k, v in times.items() if v}
    finally:
        server.terminate()
        server.wait(timeout=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mb", type=int, default=436)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "result.h5")
        with open(path, "wb") as f:
            for _ in range(a.mb):
                f.write(os.urandom(1 << 20))
        for response in ("FileResponse", "Download", "FileResponse", "Download"):
            for client, t in time_downloads(path, response, a.reps).items():
                med = statistics.median(t)
                print(f"{response:13s} {client:5s} {a.mb} MiB: " + ", ".join(f"{x:.3f}" for x in t)
                      + f" s (median {med:.3f} s, {a.mb / med:.0f} MiB/s)", flush=True)


if __name__ == "__main__":
    main()
