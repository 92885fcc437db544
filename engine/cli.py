"""Engine commands of the `demq` CLI: `demq run`, `demq export`, `demq validate`.

The console script itself lives in service/cli.py (it also offers the queue commands); it calls
:func:`register` so the engine stays importable and runnable without jobs/ or service/.

Bad input ends in one line per problem on stderr and exit status 2, before anything is written: a spec
file that is missing or not a JSON object, a ``--set`` that is not KEY=VALUE, an invalid value (the line
names the field and the value), a misspelt key (the line suggests the spec key it is closest to), a run beyond
the cost limits (engine/setup/limits.py, the service's defaults; ``--allow-large`` runs it anyway), a backend this
machine cannot run (``cuda`` without a GPU: asked of the engine's GPU probe, nothing compiled), a missing
extra (``demq validate``'s figures need matplotlib, except sonine's, which prints them as a table). The
helpers here are shared with ``demq submit`` and ``demq warm`` (service/cli.py).
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import sys
import typing
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
            raise SpecInputError(f"{where} is not valid JSON: {exc.msg} "
                                 f"(line {exc.lineno}, column {exc.colno})") from None
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


def _model_of(annotation):
    """The pydantic model class inside a field's type (``Optional[List[Species]]`` -> Species), or None."""
    from pydantic import BaseModel

    if typing.get_origin(annotation) is None and isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        model = _model_of(arg)
        if model is not None:
            return model
    return None


def did_you_mean(model, loc) -> str:
    """'; did you mean 'n_particles'?' for the unknown key at ``loc`` (pydantic's error location: keys and list
    indices) of a ``model`` input, by difflib against the field names of the model that holds the key there;
    '' when none is close."""
    for part in loc[:-1]:
        if isinstance(part, int):                     # an item of a list field: the same model
            continue
        field = model.model_fields.get(part) if model is not None else None
        model = _model_of(field.annotation) if field is not None else None
    if model is None or not loc:
        return ""
    names = [field.alias or name for name, field in model.model_fields.items()]
    close = difflib.get_close_matches(str(loc[-1]), names, n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def spec_error_lines(errors: list[dict], model=None) -> list[str]:
    """Pydantic errors of a spec (of ``model``, default :class:`engine.setup.spec.SimulationSpec`) as lines that name
    the field and the value; an unknown key gets the closest field name as a suggestion."""
    from engine.setup.spec import SimulationSpec

    lines = []
    for err in errors:
        loc = ".".join(str(x) for x in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        field = str(err["loc"][-1]) if err["loc"] else ""
        if not loc:                                   # a rule across fields: its message names them
            lines.append(f"invalid spec: {msg}")
        elif err["type"] == "extra_forbidden":
            lines.append(f"invalid spec: {loc} = {_shown(err.get('input'))}: {field!r} is not a spec key"
                         f"{did_you_mean(model or SimulationSpec, err['loc'])}")
        elif msg.startswith(f"{field} "):             # the message names the field and its value already
            lines.append(f"invalid spec: {msg}" if loc == field else f"invalid spec: {loc}: {msg}")
        else:
            value = f" = {_shown(err['input'])}" if "input" in err else ""
            lines.append(f"invalid spec: {loc}{value}: {msg}")
    return lines


def validate_spec(data: dict, model=None):
    """``model`` (default :class:`engine.setup.spec.SimulationSpec`) validated from ``data``; raises
    :class:`SpecInputError` with :func:`spec_error_lines`."""
    from pydantic import ValidationError

    from engine.setup.spec import SimulationSpec

    model = model or SimulationSpec
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise SpecInputError(*spec_error_lines(exc.errors(), model)) from None
    except ArithmeticError as exc:       # a derived size or time scale overflows (box_length = 1e300)
        raise SpecInputError(f"invalid spec: its numbers cannot be evaluated ({exc}): use physically "
                             f"sized values") from None


def cost_refusals(spec, max_particle_steps: float, max_memory_bytes: float) -> list[str]:
    """Lines refusing a spec beyond the cost limits (empty when within), each naming the estimate."""
    from engine.setup.limits import cost_excesses

    return [f"refused: {e.message}; pass --allow-large to run it anyway"
            for e in cost_excesses(spec, max_particle_steps, max_memory_bytes)]


def estimate_line(spec) -> str:
    """'N = 4096, 5.12e+03 steps, 2.1e+07 particle-steps, about 12 MB of memory' (engine.setup.params)."""
    from engine.setup.limits import sci
    from engine.setup.params import estimate_cost

    cost = estimate_cost(spec)
    return (f"N = {spec.n_particles}, {sci(cost['steps'])} steps, {sci(cost['particle_steps'])} particle-steps, "
            f"about {cost['memory_bytes'] / 2**20:.3g} MiB of memory")


def missing_output_dir(output) -> Optional[str]:
    """The line to print when ``output``'s folder does not exist or ``output`` is a folder (None when neither)."""
    if Path(output).is_dir():
        return f"cannot write {str(output)!r}: it is a folder; give -o the name of a file in it"
    parent = Path(output).resolve().parent
    return None if parent.is_dir() else f"cannot write {str(output)!r}: the folder {str(parent)!r} does not exist"


def backend_refusal(backend: str, fix: str = "use --backend auto (or cpu) to run on this machine") -> Optional[str]:
    """The line refusing ``backend`` where it cannot run, ending in ``fix`` (None where it can run): 'cuda'
    without a usable CUDA GPU, by the probe the engine's backend factory asks (engine.backends.base.cuda_available:
    it compiles nothing, and without an NVIDIA driver it does not even import numba-cuda); the CUDA simulator
    counts as a GPU, as there. 'auto' and 'cpu' always run."""
    if backend != "cuda" or os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return None
    from engine.backends.base import cuda_available

    if cuda_available():
        return None
    return f"backend = 'cuda' but no CUDA GPU is available here; {fix}"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run one spec locally and write an HDF5 result")
    p.add_argument("spec", nargs="?", default=None,
                   help="spec JSON file ('-' = stdin); omitted = the default spec: the default "
                        "scene of Hidalgo et al. (2013)")
    p.add_argument("-o", "--output", default="demq-run.h5", help="output HDF5 path")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a spec key (JSON value), e.g. --set n_particles=512")
    p.add_argument("--backend", choices=["auto", "cpu", "cuda"], default=None,
                   help="override the spec's backend: cpu, cuda (refused up front without a GPU) or auto (cuda "
                        "where a GPU is, else cpu)")
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
    v.add_argument("--backend", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the runs go: cpu, cuda (refused up front without a GPU) or auto (default: cuda "
                        "where a GPU is, else cpu)")
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
    from engine.errors import EngineError, SpecError
    from engine.setup.limits import DEFAULT_MAX_MEMORY_BYTES, DEFAULT_MAX_PARTICLE_STEPS
    from engine.driver.progress import progress_for

    try:
        data = read_spec_data(args.spec, args.set)
        if args.backend:
            data["backend"] = args.backend
        spec = validate_spec(data)
        refusals = [] if args.allow_large else cost_refusals(spec, DEFAULT_MAX_PARTICLE_STEPS, DEFAULT_MAX_MEMORY_BYTES)
        refusals += [line for line in (backend_refusal(spec.backend), missing_output_dir(args.output)) if line]
        if refusals:
            raise SpecInputError(*refusals)
    except SpecInputError as exc:
        for line in exc.lines:
            print(f"demq run: {line}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"demq run: {estimate_line(spec)}", file=sys.stderr)
    progress = None if args.quiet else progress_for(spec.n_particles, desc="demq run ")
    try:
        s = run(spec, args.output, progress=progress)
    except SpecError as exc:        # e.g. more device memory than the GPU has free: refused before it started
        print(f"demq run: refused: {exc}", file=sys.stderr)
        return 2
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
    """engine.driver.simulate.run (imported here: a refused or invalid spec costs no Numba import)."""
    from engine.driver.simulate import run as simulate

    return simulate(spec, output, progress=progress)


def cmd_export(args) -> int:
    import h5py

    src = Path(args.result)
    problem = None
    if not src.is_file():
        problem = f"no result file {src}; pass the HDF5 result of demq run or demq fetch"
    elif not h5py.is_hdf5(src):
        problem = f"{src} is not an HDF5 file; pass the HDF5 result of demq run or demq fetch"
    elif args.format == "gsd":
        problem = missing_output_dir(args.output or src.with_suffix(".gsd"))
    if problem:
        print(f"demq export: {problem}", file=sys.stderr)
        return 2
    try:
        if args.format == "xdmf":
            from engine.output.xdmf import write_xdmf

            out = write_xdmf(src)
            if out is None:
                raise ValueError(f"{src}: the result holds no snapshot frame: nothing to point at")
            if args.output and Path(args.output) != out:
                print("demq export: the xdmf sidecar is always <stem>.xmf next to the result (it names the "
                      "HDF5 file relatively); -o is ignored", file=sys.stderr)
        else:
            from engine.output.export_gsd import export_gsd

            out = export_gsd(src, args.output or src.with_suffix(".gsd"))
    except (OSError, KeyError, ValueError) as exc:
        print(f"demq export: failed: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


#: the validations whose report stands without its pictures (its figures are printed as a table; it draws the
#: pictures where matplotlib is installed); the others are refused up front without matplotlib
FIGURES_OPTIONAL = ("sonine",)


def cmd_validate(args) -> int:
    from engine.optional import MissingExtra, require_matplotlib

    refusal = backend_refusal(args.backend)
    if refusal is None and args.case not in FIGURES_OPTIONAL:
        try:               # the report ends in figures: refuse before a long run rather than after it
            require_matplotlib(f"the report of {args.case} (its figures)")
        except MissingExtra as exc:
            refusal = str(exc)
    if refusal:
        print(f"demq validate: {refusal}", file=sys.stderr)
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
