"""Results of a done job: the HDF5 file, the energy series (JSON or CSV), the cooling-curve PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import FileResponse, PlainTextResponse, Response

from jobs.schema import DONE
from jobs.store import Job
from service.deps import JobDep
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
    return FileResponse(_result_file(job), media_type="application/x-hdf5", filename=f"demq-{job.id}.h5")


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
            responses={**RESPONSES, 200: {"content": {"image/png": {}}, "description": "PNG"}})
def get_plot(job: JobDep) -> Response:
    """T/T0 and R/T0 against the scaled time tau, with Luding's mean-field theory (spheres)."""
    s = job.spec
    title = f"job {job.id[:8]}: N={s['n_particles']}, e_n={s['e_n']}, e_t={s['e_t']}, phi={s['volume_fraction']}"
    return Response(cooling_plot_png(_result_file(job), title), media_type="image/png")
