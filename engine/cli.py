"""Engine commands of the `demq` CLI: `demq run`, `demq export`, `demq validate`.

The console script itself lives in service/cli.py (it also offers the queue commands and `demq bench`,
bench/cli.py); it calls :func:`register` so the engine stays importable and runnable without jobs/,
service/ or bench/.
"""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run one spec locally and write an HDF5 result")
    p.add_argument("spec", nargs="?", default=None,
                   help="spec JSON file ('-' = stdin); omitted = the default spec (paper 001 setup)")
    p.add_argument("-o", "--output", default="demq-run.h5", help="output HDF5 path")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a spec key (JSON value), e.g. --set n_particles=512")
    p.add_argument("--backend", choices=["auto", "cpu", "cuda"], default=None)
    p.add_argument("--quiet", action="store_true", help="no progress bar (it is off anyway when stderr is not a terminal)")
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


def _spec_from_args(args):
    from engine.spec import SimulationSpec

    data = {}
    if args.spec == "-":
        data = json.load(sys.stdin)
    elif args.spec:
        with open(args.spec) as fh:
            data = json.load(fh)
    for item in args.set:
        key, _, raw = item.partition("=")
        try:
            data[key] = json.loads(raw)
        except json.JSONDecodeError:
            data[key] = raw
    if getattr(args, "backend", None):
        data["backend"] = args.backend
    return SimulationSpec.model_validate(data)


def cmd_run(args) -> int:
    from pydantic import ValidationError

    from engine.errors import EngineError
    from engine.simulate import run

    try:
        spec = _spec_from_args(args)
    except ValidationError as exc:
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"]) or "spec"
            print(f"invalid spec: {loc}: {err['msg']}", file=sys.stderr)
        return 2
    from engine.progress import ProgressBar

    bar = None if args.quiet else ProgressBar(spec.n_particles, desc="demq run ")
    try:
        s = run(spec, args.output, progress=bar)
    except EngineError as exc:
        if bar:
            bar.close()
        print(f"run failed: {exc}", file=sys.stderr)
        return 1
    if bar:
        bar.close()
    print(f"wrote {s.output}: N={s.n_particles} steps={s.steps} backend={s.backend} ({s.device}) "
          f"wall={s.wall_s:.2f}s Cundall={s.cundall:.3g} particle-steps/s")
    return 0


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
