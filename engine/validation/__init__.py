"""Physics validation runs that write reports (``demq validate ...``)."""


def run_tasks(fn, tasks, jobs: int = 1) -> None:
    """Run ``fn(task)`` for every task, ``jobs`` at a time in spawned processes, printing each result line."""
    if jobs > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            for line in pool.map(fn, tasks):
                print(line, flush=True)
    else:
        for task in tasks:
            print(fn(task), flush=True)
