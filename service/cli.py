"""The ``demq`` command line: the engine's commands plus the queue's.

    demq run | export | validate         engine commands (engine/cli.py)
    demq serve                           HTTP API + one embedded worker (SQLite in the data directory)
    demq worker [--exit-when-idle]       a worker on the configured job table (drain mode: exit when empty)
    demq submit [SPEC.json] [--local --wait -o OUT.h5]
    demq status [ID]                     one job, or a list of jobs (submission order)
    demq fetch ID -o OUT.h5              download a result

Flags override ``DEMQ_*`` environment variables (jobs/settings.py lists them all). Benchmarks run from a
checkout (``python -m bench ...``), not from the installed command.

A spec is read and validated here before anything is queued or sent (engine/cli.py: one line per problem
naming the field and the value, exit status 2); ``-o`` results get their ParaView sidecar ``<stem>.xmf``
beside them, as the server's results do; progress is a bar on a terminal and plain lines elsewhere.

Every error is one line on stderr, ``demq <command>: <the problem>; <the fix>``, never a traceback: exit status 2
for a usage error (a bad option, key, URL or setting, a missing file or folder, a backend this machine cannot
run, a missing extra), 1 when the command was right but its work failed (no server or database answers, the
service refuses, a job fails), 130 for a local job interrupted by a signal.
"""

from __future__ import annotations

import argparse
import errno
import logging
import shutil
import signal
import sys
import time
from pathlib import Path

from jobs.settings import Settings

QUEUE_FLAGS = ("data_dir", "database_url", "table_prefix")


class CommandError(Exception):
    """What ends a command with one line on stderr, ``demq <command>: <message>``, and exit status ``code``
    (2: a usage error the user fixes on the command line; 1: the work failed)."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


def _add_queue_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", type=Path, help="data directory (DEMQ_DATA_DIR, default ./demq-data)")
    p.add_argument("--database-url", help="sqlite:///PATH or postgresql://... (DEMQ_DATABASE_URL)")
    p.add_argument("--table-prefix", help="table name prefix (DEMQ_TABLE_PREFIX)")


def _add_worker_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lease", dest="lease_s", type=float, help="lease seconds (DEMQ_LEASE_SECONDS)")
    p.add_argument("--heartbeat", dest="heartbeat_s", type=float, help="heartbeat seconds (DEMQ_HEARTBEAT_SECONDS)")
    p.add_argument("--max-attempts", type=int, help="attempts per job (DEMQ_MAX_ATTEMPTS)")
    p.add_argument("--checkpoint-interval", type=float, help="seconds between checkpoints (DEMQ_CHECKPOINT_INTERVAL)")
    p.add_argument("--worker-id", help="lease owner name (DEMQ_WORKER_ID)")


def _add_client_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", help="service URL (DEMQ_URL, default http://127.0.0.1:8000)")
    p.add_argument("--token", help="bearer token (DEMQ_TOKEN)")
    p.add_argument("--local", action="store_true",
                   help="use the embedded SQLite queue in the data directory, no server")
    _add_queue_flags(p)


def _settings(args) -> Settings:
    """The settings: defaults, then ``DEMQ_*`` variables, then the flags; a bad value is a usage error."""
    names = Settings.__dataclass_fields__
    try:
        return Settings.from_env(**{k: v for k, v in vars(args).items() if k in names})
    except ValueError as exc:
        raise CommandError(str(exc)) from None


def _open_store(s: Settings):
    """The job store of the settings (jobs/stores.py), or a :class:`CommandError`: a URL of no supported kind, a
    database driver that is not installed (its extra named), a data directory that cannot be made or written
    (usage, 2), a database server that does not answer (1)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import SQLAlchemyError

    from engine.optional import MissingExtra
    from jobs.stores import open_store

    try:
        return open_store(s.database_url, s.table_prefix)
    except ValueError as exc:
        raise CommandError(f"{exc} (--database-url/DEMQ_DATABASE_URL)") from None
    except MissingExtra as exc:
        raise CommandError(str(exc)) from None
    except OSError as exc:
        raise CommandError(f"cannot use the data directory {str(s.data_dir)!r} ({exc.strerror or exc}); set "
                           f"--data-dir/DEMQ_DATA_DIR to a folder you can write") from None
    except SQLAlchemyError as exc:
        shown = make_url(s.database_url).render_as_string(hide_password=True)
        reason = " ".join(str(getattr(exc, "orig", None) or exc).split())[:200]
        if s.database_url.startswith("sqlite"):          # a file: where it is, not a server, is the problem
            raise CommandError(f"cannot open the job database {shown} ({reason}); set --data-dir/DEMQ_DATA_DIR to "
                               f"a folder you can write (or --database-url/DEMQ_DATABASE_URL)") from None
        raise CommandError(f"cannot open the job database {shown} ({reason}); start that database or set "
                           f"--database-url/DEMQ_DATABASE_URL", 1) from None


def _client(args):
    """The service client of the command's settings (service/client.py)."""
    from service.client import Client

    s = _settings(args)
    return Client(s.url, s.token)


def _service_failed(exc) -> CommandError:
    """A :class:`service.client.ServiceError` as the command's end: a bad URL is a usage error, the rest failed."""
    from service.client import BadServiceURL

    return CommandError(str(exc), 2 if isinstance(exc, BadServiceURL) else 1)


def _logging(verbose: bool = True) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")


def _on_signals(stop) -> None:
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop())


# ---- serve and worker ---------------------------------------------------------------------------------
def _check_port_free(host: str, port: int) -> None:
    """A :class:`CommandError` when ``host:port`` cannot be listened on (another server has it: 1; the address is
    not this machine's: 2), found by binding it as uvicorn will (SO_REUSEADDR) and letting it go at once."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, proto, _, address = infos[0]
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise CommandError(f"cannot listen on {host}:{port} ({exc.strerror}); stop the server that has it or pick "
                               f"another port with --port/DEMQ_PORT", 1) from None
        raise CommandError(f"cannot listen on {host}:{port} ({exc.strerror or exc}); pick an address of this machine "
                           f"with --host/DEMQ_HOST (127.0.0.1: this machine only; 0.0.0.0: every interface)") from None


def cmd_serve(args) -> int:
    import uvicorn

    from service.app import create_app

    s = _settings(args)
    _check_port_free(s.host, s.port)
    _logging()
    app = create_app(s, store=_open_store(s), embedded_worker=not args.no_worker)
    uvicorn.run(app, host=s.host, port=s.port, log_level="info")
    return 0


def cmd_worker(args) -> int:
    from jobs.worker import Worker

    s = _settings(args)
    _logging()
    store = _open_store(s)
    worker = Worker(store, s)
    _on_signals(worker.stop)
    worker.run_forever(exit_when_idle=args.exit_when_idle)
    store.close()
    return 0


def cmd_warm(args) -> int:
    """Compile (or load from numba's disk cache) every kernel specialisation this host can run (jobs/warm.py)."""
    from engine.cli import backend_refusal
    from jobs.warm import local_backends, warm

    for backend in args.backend or ():
        refusal = backend_refusal(backend, "leave out --backend cuda (the default warms what this host can run)")
        if refusal:
            raise CommandError(refusal)
    _logging()
    report = warm(args.backend or local_backends(), args.shape or None, args.precision or None)
    print(report.line())
    return 1 if report.failed else 0


# ---- client commands ----------------------------------------------------------------------------------
def _job_progress(job_id: str, n_particles):
    """The job's progress on stderr: a tqdm bar on a terminal, plain lines elsewhere (engine/driver/progress.py)."""
    from engine.driver.progress import progress_for

    return progress_for(n_particles, desc=f"job {job_id[:8]} ")


def _with_sidecar(output) -> None:
    """Write the ParaView sidecar ``<stem>.xmf`` beside a result copied or downloaded to ``output`` (it names
    the HDF5 file by its name, so a copy needs its own); a result without snapshot frames has none."""
    from engine.output.xdmf import write_xdmf

    sidecar = write_xdmf(output)
    print(f"wrote {output}" + (f" and {sidecar}" if sidecar else ""))


def _submit_local(args, spec) -> int:
    from engine.cli import backend_refusal
    from jobs.specs import SpecRejected, check_limits
    from jobs.store import NewJob
    from jobs.worker import Worker

    s = _settings(args)
    try:
        check_limits(spec, s.max_particle_steps, s.max_memory_bytes)
    except SpecRejected as exc:
        for e in exc.errors:
            print(f"demq submit: refused: {e['msg']}", file=sys.stderr)
        return 2
    refusal = backend_refusal(spec.backend, "use --set backend=auto (or cpu), or leave out --wait for a worker on "
                                            "a GPU host") if args.wait else None    # --wait runs it here, now
    if refusal:
        raise CommandError(refusal)
    store = _open_store(s)
    (job,) = store.submit([NewJob(spec.to_json(), args.priority)], max_attempts=s.max_attempts)
    print(job.id, flush=True)
    if not args.wait:
        return 0
    bar = _job_progress(job.id, spec.n_particles)
    worker = Worker(store, s, on_progress=lambda _job, p: bar.update(p.get("fraction") or 0.0, p.get("phase") or "",
                                                                     p.get("eta_s"), p.get("cundall")))
    _on_signals(worker.stop)
    try:
        final = worker.run_job(job.id)
    finally:
        bar.close()
    if final is None or final.state != "done":
        state = final.state if final else "unknown"
        if worker.stopping and state == "queued":
            print(f"job {job.id} interrupted; it stays queued in {s.data_dir}", file=sys.stderr)
            return 130
        print(f"job {job.id} {state}: {final.error if final else ''}", file=sys.stderr)
        return 1
    cundall = f" (Cundall number {final.cundall:.3g} particle-steps/s)" if final.cundall else ""
    print(f"job {job.id} done{cundall}", file=sys.stderr)
    if args.output:
        _copy_result(final.result_path, args.output)
    return 0


def _submit_remote(args, data: dict) -> int:
    from service.client import ServiceError

    try:
        client = _client(args)
        job = client.submit(data, args.priority)
        print(job["id"], flush=True)
        if not args.wait:
            return 0
        bar = _job_progress(job["id"], (job.get("spec") or {}).get("n_particles"))
        try:
            while job["state"] in ("queued", "running"):
                bar.update(job["progress"], job.get("phase") or job["state"], job.get("eta_s"), job.get("cundall"))
                time.sleep(1.0)
                job = client.get(job["id"])
            bar.update(job["progress"], job["state"], None, job.get("cundall"))
        finally:
            bar.close()
        if job["state"] != "done":
            print(f"job {job['id']} {job['state']}: {job['error'] or ''}", file=sys.stderr)
            return 1
        if args.output:
            client.fetch(job["id"], args.output)
            _with_sidecar(args.output)
        return 0
    except ServiceError as exc:
        raise _service_failed(exc) from None


def cmd_submit(args) -> int:
    from engine.cli import SpecInputError, missing_output_dir, read_spec_data, validate_spec
    from jobs.specs import QueueSpec

    if args.output and not args.wait:
        print("demq submit: -o/--output needs --wait", file=sys.stderr)
        return 2
    try:
        data = read_spec_data(args.spec, args.set)
        spec = validate_spec(data, QueueSpec)      # the checks the service makes, before anything is queued
        no_dir = missing_output_dir(args.output) if args.output else None
        if no_dir:
            raise SpecInputError(no_dir)
    except SpecInputError as exc:
        for line in exc.lines:
            print(f"demq submit: {line}", file=sys.stderr)
        return 2
    return _submit_local(args, spec) if args.local else _submit_remote(args, data)


def _print_job(job: dict) -> None:
    keys = ("id", "state", "progress", "eta_s", "attempts", "created_at", "started_at", "finished_at",
            "loop_s", "job_wall_s", "cundall", "backend", "device", "error", "batch_id")
    for k in keys:
        if job.get(k) is not None:
            print(f"{k:>12s}: {job[k]}")


def cmd_status(args) -> int:
    if args.local:
        from service.schemas import JobOut

        s = _settings(args)
        store = _open_store(s)
        if args.id:
            job = store.get(args.id)
            if job is None:
                raise CommandError(f"no job with id {args.id!r} in {s.data_dir}; `demq status --local` lists them", 1)
            _print_job(JobOut.of(job).model_dump(mode="json"))
        else:
            items, _ = store.list(state=args.state, limit=args.limit)
            for j in items:
                print(f"{j.id}  {j.state:<9s} {100 * j.progress:5.1f}%  {j.error or ''}")
        return 0
    from service.client import ServiceError

    try:
        client = _client(args)
        if args.id:
            _print_job(client.get(args.id))
        else:
            for j in client.list(args.state, args.limit)["items"]:
                print(f"{j['id']}  {j['state']:<9s} {100 * j['progress']:5.1f}%  {j['error'] or ''}")
    except ServiceError as exc:
        raise _service_failed(exc) from None
    return 0


def _copy_result(result_path, output) -> None:
    """Copy a local job's result to ``output``, with its sidecar (:func:`_with_sidecar`)."""
    try:
        shutil.copyfile(result_path, output)
    except FileNotFoundError:
        raise CommandError(f"the job's result {str(result_path)!r} is gone from the data directory; run the "
                           f"spec again", 1) from None
    except OSError as exc:
        raise CommandError(f"cannot write {str(output)!r} ({exc.strerror or exc})", 1) from None
    _with_sidecar(output)


def cmd_fetch(args) -> int:
    from engine.cli import missing_output_dir

    no_dir = missing_output_dir(args.output)
    if no_dir:
        raise CommandError(no_dir)
    if args.local:
        s = _settings(args)
        job = _open_store(s).get(args.id)
        if job is None or job.state != "done":
            raise CommandError(f"job {args.id}: no result ({job.state if job else 'unknown id'}); `demq status "
                               f"--local` lists the jobs and their states", 1)
        _copy_result(job.result_path, args.output)
        return 0
    from service.client import ServiceError

    try:
        _client(args).fetch(args.id, args.output)
    except ServiceError as exc:
        raise _service_failed(exc) from None
    except OSError as exc:
        raise CommandError(f"cannot write {str(args.output)!r} ({exc.strerror or exc})", 1) from None
    _with_sidecar(args.output)
    return 0


# ---- the parser ---------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    from engine.cli import register

    parser = argparse.ArgumentParser(prog="demq", description="GPU DEM simulations of granular gases, "
                                                              "run from a durable job queue.")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)

    p = sub.add_parser("serve", help="HTTP API with one embedded worker")
    _add_queue_flags(p)
    _add_worker_flags(p)
    p.add_argument("--host", help="listen address (DEMQ_HOST)")
    p.add_argument("--port", type=int, help="listen port (DEMQ_PORT)")
    p.add_argument("--token", help="require this bearer token (DEMQ_TOKEN)")
    p.add_argument("--max-particle-steps", type=float, help="DEMQ_MAX_PARTICLE_STEPS")
    p.add_argument("--max-memory-bytes", type=float, help="DEMQ_MAX_MEMORY_BYTES")
    p.add_argument("--max-body-bytes", type=int, help="DEMQ_MAX_BODY_BYTES")
    p.add_argument("--no-worker", action="store_true", help="API only (run workers separately)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("worker", help="claim and run jobs until SIGTERM")
    _add_queue_flags(p)
    _add_worker_flags(p)
    p.add_argument("--exit-when-idle", action="store_true",
                   help="drain mode: exit (status 0) once no job is queued or running (Slurm job arrays)")
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("warm", help="compile every kernel specialisation into the disk cache before the first job")
    p.add_argument("--backend", action="append", choices=["cpu", "cuda"],
                   help="only this backend (repeatable; default: this host's: cpu, and cuda where a GPU is)")
    p.add_argument("--shape", action="append", help="only this shape (repeatable; default: all)")
    p.add_argument("--precision", action="append", choices=["float64", "float32", "mixed"],
                   help="only this precision (repeatable; default: all)")
    p.set_defaults(func=cmd_warm)

    p = sub.add_parser("submit", help="queue a spec (default spec if none given)")
    p.add_argument("spec", nargs="?", help="spec JSON file ('-' = stdin); omitted = the default spec")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a spec key")
    p.add_argument("--priority", type=int, default=0, help="higher runs first (default 0; ties: submission order)")
    p.add_argument("--wait", action="store_true",
                   help="wait for the job to finish, printing progress (a bar on a terminal, else lines)")
    p.add_argument("-o", "--output", help="with --wait: write the HDF5 result here (and its <stem>.xmf)")
    _add_client_flags(p)
    _add_worker_flags(p)
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("status", help="one job's status, or a list of jobs")
    p.add_argument("id", nargs="?", help="the job's id (as submit printed it); omitted = a list of jobs")
    p.add_argument("--state", choices=["queued", "running", "done", "failed", "cancelled"],
                   help="list only the jobs in this state")
    p.add_argument("--limit", type=int, default=20, help="list at most this many jobs (default 20)")
    _add_client_flags(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("fetch", help="download a job's HDF5 result")
    p.add_argument("id", help="the job's id (as submit printed it)")
    p.add_argument("-o", "--output", required=True, help="the HDF5 result (and its <stem>.xmf beside it)")
    _add_client_flags(p)
    p.set_defaults(func=cmd_fetch)
    return parser


def main(argv=None) -> None:
    """Run the command of ``argv`` (default: the process's arguments) and exit with its status; a
    :class:`CommandError` ends it with its one line on stderr."""
    args = build_parser().parse_args(argv)
    try:
        code = args.func(args)
    except CommandError as exc:
        print(f"demq {args.command}: {exc}", file=sys.stderr)
        code = exc.code
    sys.exit(code)


if __name__ == "__main__":
    main()
