"""The batch-level result: seed statistics over a batch's finished jobs (engine/analysis/ensemble_stats.py).

:func:`batch_result` collects the jobs of a batch from the table, groups the done ones by spec apart
from the seed, and writes ``<data_dir>/batches/<batch_id>.h5`` (mean cooling curves with standard
errors, seeds, job ids per group). Jobs that failed or were cancelled are left out and listed in the
file's ``excluded`` attribute. It is rebuilt on every request, so it follows the table.
"""

from __future__ import annotations

from pathlib import Path

from engine.analysis.ensemble_stats import Run, aggregate, write_batch_result
from jobs.schema import DONE, FINAL_STATES
from jobs.settings import Settings
from jobs.store import Job, JobStore

_PAGE = 1000


class BatchNotFound(LookupError):
    """No job carries this batch id."""


class BatchNotReady(Exception):
    """The batch has no result to aggregate yet (jobs still running, or none done)."""


def batch_jobs(store: JobStore, batch_id: str) -> list[Job]:
    """Every job of the batch, in submission order."""
    jobs: list[Job] = []
    while True:
        page, total = store.list(batch_id=batch_id, limit=_PAGE, offset=len(jobs))
        jobs.extend(page)
        if not page or len(jobs) >= total:
            return jobs


def batch_result(store: JobStore, settings: Settings, batch_id: str, partial: bool = False) -> Path:
    """Write the batch file of ``batch_id`` and return its path.

    Raises BatchNotFound for an unknown batch; BatchNotReady while jobs are queued or running (unless
    ``partial``: then the jobs done so far are aggregated) or when no job has a result; ValueError when
    runs of one spec cannot be averaged.
    """
    jobs = batch_jobs(store, batch_id)
    if not jobs:
        raise BatchNotFound(f"no batch with id {batch_id!r}")
    live = [j for j in jobs if j.state not in FINAL_STATES]
    if live and not partial:
        raise BatchNotReady(f"batch {batch_id}: {len(live)} of {len(jobs)} jobs are still queued or running; "
                            f"the batch result is made once every job has ended (or ask with partial=true "
                            f"for the jobs done so far)")
    done = [j for j in jobs if j.state == DONE and j.result_path and Path(j.result_path).is_file()]
    if not done:
        raise BatchNotReady(f"batch {batch_id}: none of its {len(jobs)} jobs has a result "
                            f"(states: {_states(jobs)})")
    ids = {j.id for j in done}
    excluded = {j.id: (j.state if j.state != DONE else "done, result file gone") for j in jobs if j.id not in ids}
    groups = aggregate([Run(j.id, Path(j.result_path)) for j in done])
    return write_batch_result(settings.batch_result_path(batch_id), groups, batch_id=batch_id, excluded=excluded)


def _states(jobs: list[Job]) -> str:
    counts: dict = {}
    for j in jobs:
        counts[j.state] = counts.get(j.state, 0) + 1
    return ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
