"""Engine commands of the `demq` CLI: `demq run`, `demq export`, `demq validate`.

The console script itself lives in service/cli.py (it also offers the queue commands); it calls
:func:`register` so the engine stays importable and runnable without jobs/ or service/.

Bad input ends in one line per problem on stderr and exit status 2, before anything is written: a spec
file that is missing or not a JSON object, a ``--set`` that is not KEY=VALUE, an invalid value (the line
names the field and the value), a run beyond the cost limits (engine/limits.py, the service's defaults;
``--allow-large`` runs it anyway). The helpers here are shared with ``demq submit`` (service/cli.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence


class SpecInputError(Exception):
    """A spec that cannot be read or is invalid; ``lines`` are what stderr gets (one per problem)."""

    def __init__(self, *lines: str):
        super().__init__("; ".join(lines))
        self.lines = list(lines)


def read_spec_data(source: Optional[str], sets: Sequence[str]) -> dict:
    """The spec keys of a JSON file (``'-'``: stdin; None: none) with the ``--set KEY=VALUE`` overrides
    (VALUE as JSON, else as a string). Raises :class:`SpecInputError`."""
    data: dict = {}
    if source is not None:
        where = "the spec on stdin" if source == "-" else f"spec file {source!r}"
        try:
            text = sys.stdin.read() if source == "-" else Path(source).read_text()
        except FileNotFoundError:
            raise SpecInputError(f"{where} does not exist") from None
        except IsADirectoryError:
            raise SpecInputError(f"{where} is a directory, not a JSON file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise SpecInputError(f"cannot read {where}: {getattr(exc, 'strerror', None) or exc}") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SpecInputError(f"{where} is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
        if not isinstance(data, dict):
            raise SpecInputError(f"{where} must hold a JSON object of spec keys, not a JSON {type(data).__name__}")
    for item in sets:
        key, eq, raw = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise SpecInputError(f"--set {item!r} is not KEY=VALUE (e.g. --set n_particles=512)")
        try:
            data[key] = json.loads(raw)
        except json.JSONDecodeError:
            data[key] = raw
    return data


def _shown(value) -> str:
    """A value as the user wrote it, shortened: 'abc' for a string, JSON otherwise."""
    text = repr(value) if isinstance(value, str) else json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def spec_error_lines(errors: list[dict]) -> list[str]:
    """Pydantic errors of a spec as lines that name the field and the value."""
    lines = []
    for err in errors:
        loc = ".".join(str(x) for x in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        field = str(err["loc"][-1]) if err["loc"] else ""
        if not loc:                                   # a rule across fields: its message names them
            lines.append(f"invalid spec: {msg}")
        elif err["type"] == "extra_forbidden":
            lines.append(f"invalid spec: {loc} = {_shown(err.get('input'))}: {field!r} is not a spec key")
        elif msg.startswith(f"{field} "):             # the message names the field and its value already
            lines.append(f"invalid spec: {msg}" if loc == field else f"invalid spec: {loc}: {msg}")
        else:
            value = f" = {_shown(err['input'])}" if "input" in err else ""
            lines.append(f"invalid spec: {loc}{value}: {msg}")
    return lines


def validate_spec(data: dict, model=None):
    """``model`` (default :class:`engine.spec.SimulationSpec`) validated from ``data``; raises
    :class:`SpecInputError` with :func:`spec_error_lines`."""
    from pydantic import ValidationError

    from engine.spec import SimulationSpec

    try:
        return (model or SimulationSpec).model_validate(data)
    except ValidationError as exc:
        raise SpecInputError(*spec_error_lines(exc.errors())) from None
    except ArithmeticError as exc:       # a derived size or time scale overflows (box_length = 1e300)
        raise SpecInputError(f"invalid spec: its numbers cannot be evaluated ({exc}): use physically "
                             f"sized values") from None


def cost_refusals(spec, max_particle_steps: float, max_memory_bytes: float) -> list[str]:
    """Lines refusing a spec beyond the cost limits (empty when within), each naming the estimate."""
    from engine.limits import cost_excesses

    return [f"refused: {e.message}; pass --allow-large to run it anyway"
            for e in cost_excesses(spec, max_particle_steps, max_memory_bytes)]


def estimate_line(spec) -> str:
    """'N = 4096, 5.12e+03 steps, 2.1e+07 particle-steps, about 12 MB of memory' (engine.params)."""
    from engine.limits import sci
    from engine.params import estimate_cost

    cost = estimate_cost(spec)
    return (f"N = {spec.n_particles}, {sci(cost['steps'])} steps, {sci(cost['particle_steps'])} particle-steps, "
            f"about {cost['memory_bytes'] / 2**20:.3g} MiB of memory")


def missing_output_dir(output) -> Optional[str]:
    """The line to print when ``output``'s folder does not exist (None when it does)."""
    parent = Path(output).resolve().parent
    return None if parent.is_dir() else f"cannot write {str(output)!r}: the folder {str(parent)!r} does not exist"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run one spec locally and write an HDF5 result")
    p.add_argument("spec", nargs="?", default=None,
                   help="spec JSON file ('-' = stdin); omitted = the default spec (paper 001 setup)")
    p.add_argument("-o", "--output", default="demq-run.h5", help="output HDF5 path")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a spec key (JSON value), e.g. --set n_particles=512")
    p.add_argument("--backend", choices=["auto", "cpu", "cuda"], default=None)
    p.add_argument("--allow-large", action="store_true",
                   help="run a spec beyond the cost limits (particle-steps, memory) that the service refuses")
    p.add_argument("--quiet", action="store_true",
                   help="no progress (a bar on a terminal, else a line per 10 %% or 10 s on stderr)")
    p.set_defaults(func=cmd_run)

    v = sub.add_parser("validate", help="physics validation runs that write a report")
    v.add_argument("case", choices=["hcs-spheres", "hcs-ellipsoids", "hcs-rough-spheroids", "hcs-long", "sonine",
                                    "encounter-dsmc"],
                   help="which validation to run")
    v.add_argument("-o", "--out-dir", default=None, help="report folder (default reports/<case>)")
    v.add_argument("--seeds", type=int, default=None,
                   help="seeds per case (default 4 spheres, 1 ellipsoids, 8 rough spheroids (quick: 2), 12 "
                        "hcs-long, sonine 64 (quick: 6), encounter-dsmc 4 (quick: 2) per rule)")
    v.add_argument("--quick", action="store_true", help="reduced size for a smoke test")
    v.add_argument("--backend", choices=["auto", "cpu", "cuda"], default="auto")
    v.add_argument("--jobs", type=int, default=1, help="runs at a time (separate processes)")
    v.add_argument("--threads", type=int, default=0, help="Numba threads per run (0 = all)")
    v.add_argument("--ensemble", action="store_true",
                   help="run all seeds and cases (hcs-ellipsoids: cells) as one ensemble (on the GPU: the same "
                        "kernel launches)")
    v.set_defaults(func=cmd_validate)

    x = sub.add_parser("export", help="convert a result's snapshot frames for other tools (gsd: OVITO, HOOMD)")
    x.add_argument("result", help="HDF5 (H5MD) result file")
    x.add_argument("--format", choices=["gsd", "xdmf"], default="gsd",
                   help="gsd: a GSD trajectory (OVITO, HOOMD, freud); xdmf: the ParaView sidecar <stem>.xmf")
    x.add_argument("-o", "--output", default=None, help="output path (default: the result's stem + .gsd)")
    x.set_defaults(func=cmd_export)


def cmd_run(args) -> int:
    from engine.errors import EngineError
    from engine.limits import DEFAULT_MAX_MEMORY_BYTES, DEFAULT_MAX_PARTICLE_STEPS
    from engine.progress import progress_for

    try:
        data = read_spec_data(args.spec, args.set)
        if args.backend:
            data["backend"] = args.backend
        spec = validate_spec(data)
        refusals = [] if args.allow_large else cost_refusals(spec, DEFAULT_MAX_PARTICLE_STEPS, DEFAULT_MAX_MEMORY_BYTES)
        no_dir = missing_output_dir(args.output)
        if refusals or no_dir:
            raise SpecInputError(*refusals, *([no_dir] if no_dir else []))
    except SpecInputError as exc:
        for line in exc.lines:
            print(f"demq run: {line}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"demq run: {estimate_line(spec)}", file=sys.stderr)
    progress = None if args.quiet else progress_for(spec.n_particles, desc="demq run ")
    try:
        s = run(spec, args.output, progress=progress)
    except EngineError as exc:
        print(f"demq run: run failed: {exc}", file=sys.stderr)
        return 1
    finally:
        if progress:
            progress.close()
    print(f"wrote {s.output}: N={s.n_particles} steps={s.steps} backend={s.backend} ({s.device}) "
          f"loop={s.loop_s:.2f}s job={s.job_wall_s:.2f}s Cundall={s.cundall:.3g} particle-steps/s")
    return 0


def run(spec, output, progress=None):
    """engine.simulate.run (imported here: a refused or invalid spec costs no Numba import)."""
    from engine.simulate import run as simulate

    return simulate(spec, output, progress=progress)


def cmd_export(args) -> int:
    from pathlib import Path

    src = Path(args.result)
    if not src.is_file():
        print(f"export: no result file {src}", file=sys.stderr)
        return 2
    try:
        if args.format == "xdmf":
            from engine.xdmf import write_xdmf

            out = write_xdmf(src)
            if out is None:
                raise ValueError(f"{src}: the result holds no snapshot frame: nothing to point at")
            if args.output and Path(args.output) != out:
                print("export: the xdmf sidecar is always <stem>.xmf next to the result (it names the "
                      "HDF5 file relatively); -o is ignored", file=sys.stderr)
        else:
            from engine.export_gsd import export_gsd

            out = export_gsd(src, args.output or src.with_suffix(".gsd"))
    except (OSError, KeyError, ValueError) as exc:
        print(f"export failed: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


def cmd_validate(args) -> int:
    from engine.optional import MissingExtra, require_matplotlib

    try:                   # the reports end in figures: refuse before a long run rather than after it
        require_matplotlib("demq validate (its report's figures)")
    except MissingExtra as exc:
        print(exc, file=sys.stderr)
        return 2
    out_dir = args.out_dir or f"reports/{args.case}"
    if args.case == "encounter-dsmc":
        from engine.validation import encounter_report

        return encounter_report.main(out_dir=out_dir, seeds=args.seeds, quick=args.quick, jobs=args.jobs)
    if args.case == "sonine":
        from engine.validation import sonine

        return sonine.main(out_dir=out_dir, seeds=args.seeds or (6 if args.quick else 64), quick=args.quick,
                           backend=args.backend, jobs=args.jobs, threads=args.threads, ensemble=args.ensemble)
    if args.case == "hcs-ellipsoids":
        from engine.validation import hcs_ellipsoids

        return hcs_ellipsoids.main(out_dir=out_dir, seeds=args.seeds or 1, quick=args.quick, backend=args.backend,
                                   jobs=args.jobs, threads=args.threads, ensemble=args.ensemble)
    if args.case == "hcs-rough-spheroids":
        from engine.validation import hcs_rough_spheroids

        return hcs_rough_spheroids.main(
            out_dir=out_dir, seeds=args.seeds or (2 if args.quick else 8), quick=args.quick, backend=args.backend,
            command=f"demq validate hcs-rough-spheroids -o {out_dir}" + (f" --seeds {args.seeds}" if args.seeds else "")
            + (" --quick" if args.quick else "") + f" --backend {args.backend}")
    if args.case == "hcs-long":
        from engine.validation import hcs_long

        return hcs_long.main(out_dir=out_dir, seeds=args.seeds, quick=args.quick, backend=args.backend,
                             command=f"demq validate hcs-long -o {out_dir}"
                             + (f" --seeds {args.seeds}" if args.seeds else "")
                             + (" --quick" if args.quick else "") + f" --backend {args.backend}")
    from engine.validation import hcs_spheres

    return hcs_spheres.main(out_dir=out_dir, seeds=args.seeds or 4, quick=args.quick, backend=args.backend,
                            jobs=args.jobs, threads=args.threads, ensemble=args.ensemble)
