"""Results of a done job: the HDF5 file, the energy series (JSON or CSV), the cooling-curve PNG, and the
visualisation outputs: the XDMF sidecar (ParaView), a GSD export (OVITO, HOOMD), a picture of a snapshot."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse, PlainTextResponse, Response
from starlette.background import BackgroundTask

from jobs.schema import DONE
from jobs.store import Job
from service.deps import JobDep
from service.downloads import Download
from service.errors import NEEDS_PLOTS, InvalidRequest, needs_extra
from service.results import cooling_plot_png, energy_csv, read_energy

router = APIRouter(prefix="/jobs", tags=["results"])
RESPONSES = {404: {"description": "no job with this id"},
             409: {"description": "the job has no result (not done)"}}


def _result_file(job: Job) -> Path:
    if job.state != DONE or not job.result_path:
        raise HTTPException(409, f"job {job.id} is {job.state}: a result exists only when it is done")
    path = Path(job.result_path)
    if not path.is_file():
        raise HTTPException(410, f"the result file of job {job.id} is gone from the result storage")
    return path


@router.get("/{job_id}/result", response_class=FileResponse,
            responses={**RESPONSES, 410: {"description": "the result file was deleted"},
                       200: {"content": {"application/x-hdf5": {}}, "description": "the HDF5 (H5MD) result"}})
def get_result(job: JobDep) -> FileResponse:
    """Download the HDF5 result file."""
    return Download(_result_file(job), media_type="application/x-hdf5", filename=f"demq-{job.id}.h5")


@router.get("/{job_id}/energy", responses={**RESPONSES, 200: {
    "description": "JSON object of columns, or CSV", "content": {"application/json": {}, "text/csv": {}}}})
def get_energy(job: JobDep, format: Annotated[Literal["json", "csv"], Query()] = "json"):
    """Energy time series: step, time, translational/rotational kinetic energy and temperature (SI)."""
    series = read_energy(_result_file(job))
    if format == "csv":
        return PlainTextResponse(energy_csv(series), media_type="text/csv",
                                 headers={"Content-Disposition": f'attachment; filename="demq-{job.id}-energy.csv"'})
    return {"job_id": job.id, **series}


@router.get("/{job_id}/plot.png", response_class=Response,
            responses={**RESPONSES, **NEEDS_PLOTS, 200: {"content": {"image/png": {}}, "description": "PNG"}})
def get_plot(job: JobDep) -> Response:
    """T/T0 and R/T0 against the scaled time tau, with Luding's mean-field theory (spheres)."""
    s = job.spec
    title = f"job {job.id[:8]}: N={s['n_particles']}, e_n={s['e_n']}, e_t={s['e_t']}, phi={s['volume_fraction']}"
    path = _result_file(job)
    with needs_extra():
        png = cooling_plot_png(path, title)
    return Response(png, media_type="image/png")


SNAPSHOT_RESPONSES = {**RESPONSES, 409: {"description": "the job is not done, or its result has no snapshot frame"},
                      410: {"description": "the result file was deleted"}}


def _no_snapshot(job: Job) -> HTTPException:
    return HTTPException(409, f"job {job.id} has no snapshot frame in its result (its spec asked for "
                              f"snapshots = {job.spec.get('snapshots')})")


@router.get("/{job_id}/result.xmf", responses={**SNAPSHOT_RESPONSES, 200: {
    "content": {"application/xml": {}}, "description": "XDMF 3 document pointing into demq-{id}.h5"}})
def get_xdmf(job: JobDep) -> Response:
    """The XDMF sidecar of the result for ParaView / VisIt, naming the download name ``demq-{id}.h5``:
    save it next to the file from ``GET /jobs/{id}/result`` and open the ``.xmf``."""
    from engine.output.xdmf import xdmf_text

    text = xdmf_text(_result_file(job), h5_ref=f"demq-{job.id}.h5")
    if text is None:
        raise _no_snapshot(job)
    return Response(text, media_type="application/xml",
                    headers={"Content-Disposition": f'attachment; filename="demq-{job.id}.xmf"'})


@router.get("/{job_id}/export.gsd", response_class=FileResponse, responses={**SNAPSHOT_RESPONSES, 200: {
    "content": {"application/octet-stream": {}}, "description": "GSD trajectory (HOOMD schema, SI units)"}})
def get_gsd(job: JobDep) -> FileResponse:
    """Every snapshot frame as a GSD file (OVITO, HOOMD-blue, freud); engine/output/export_gsd.py lists the fields."""
    from engine.output.export_gsd import export_gsd
    from service.render import frame_count

    path = _result_file(job)
    if frame_count(path) == 0:
        raise _no_snapshot(job)
    fd, tmp = tempfile.mkstemp(suffix=".gsd", prefix=f"demq-{job.id}-")
    os.close(fd)
    try:
        export_gsd(path, tmp)
    except BaseException:
        os.unlink(tmp)
        raise
    return Download(tmp, media_type="application/octet-stream", filename=f"demq-{job.id}.gsd",
                    background=BackgroundTask(os.unlink, tmp))


SNAPSHOT_ROUTE = "/{job_id}/snapshot.png"


def offer_renderers(document: dict, offered: list[str]) -> None:
    """Write ``offered`` (the app's renderers, service.render.offered_renderers) as the enum of the snapshot's
    ``renderer`` in the OpenAPI ``document``: the route declares every renderer the code knows, the document
    only those this server runs."""
    for param in document["paths"][router.prefix + SNAPSHOT_ROUTE]["get"]["parameters"]:
        if param["name"] == "renderer":
            param["schema"]["enum"] = list(offered)


@router.get(SNAPSHOT_ROUTE, response_class=Response, responses={
    **SNAPSHOT_RESPONSES, **NEEDS_PLOTS,
    422: {"description": "frame index out of range, an unknown colour, or a renderer this server does not run"},
    200: {"content": {"image/png": {}}, "description": "PNG"}})
def get_snapshot(job: JobDep, request: Request,
                 frame: Annotated[int, Query(description="snapshot frame, Python-style: 0 = first, -1 = last")] = -1,
                 color: Annotated[Literal["speed", "omega"], Query(
                     description="colour by the speed |v| (m/s) or the angular speed |omega| (1/s)")] = "speed",
                 renderer: Annotated[Literal["auto", "ovito", "matplotlib"], Query(
                     description="auto: OVITO's Tachyon when installed, else matplotlib; the enum lists the "
                                 "renderers this server runs")] = "auto") -> Response:
    """A picture of one snapshot frame: spheres or oriented spheroids, coloured with a colour bar, box outline."""
    from service.render import FrameOutOfRange, NoSnapshot, snapshot_png

    offered = request.app.state.renderers
    if renderer not in offered:     # 'ovito' where OVITO cannot render: outside the document's enum
        raise InvalidRequest([{"loc": ["query", "renderer"], "type": "value_error",
                               "msg": f"renderer = {renderer!r}: OVITO is not installed on this server (pip install "
                                      f"ovito, and a Vulkan loader); use " + " or ".join(map(repr, offered))}])
    path = _result_file(job)
    try:
        with needs_extra():
            png = snapshot_png(path, frame, color, renderer, label=f"job {job.id[:8]}: ")
    except NoSnapshot:
        raise _no_snapshot(job) from None
    except FrameOutOfRange as exc:
        raise InvalidRequest([{"loc": ["query", "frame"], "msg": str(exc), "type": "value_error"}]) from None
    return Response(png, media_type="image/png")
