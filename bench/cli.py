"""`demq bench`: the benchmark and stress-test command (registered by service/cli.py, the console script).

Lives in bench/ because it imports the bench scripts; the engine never imports bench/.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("bench", help="benchmarks and stress tests that write a report")
    b.add_argument("action", choices=["stability", "accuracy", "specialisation", "e2e"],
                   help="stability: the CPU stress matrix; accuracy: error against cost for dt, precision, "
                        "skin and the ellipsoid PW tolerance; specialisation: speed-up of each compile-time "
                        "specialisation (issue 6); e2e: time to result of whole jobs through engine.run, "
                        "run_ensemble and the worker, with the breakdown (issue 14; bench/e2e.py --help)")
    b.add_argument("-o", "--out-dir", default=None, help="report folder (default bench/reports/<action>)")
    b.add_argument("--only", default=None, help="stability: run only the cells whose name contains this")
    b.add_argument("--timeout", type=float, default=None,
                   help="stability: seconds per cell before it counts as a hang")
    b.add_argument("--quick", action="store_true", help="accuracy/specialisation: reduced scenes (~1 min)")
    b.add_argument("--tiny", action="store_true", help="accuracy/specialisation: smallest scenes (smoke test)")
    b.add_argument("--backend", choices=["cpu", "cuda"], default="cpu",
                   help="accuracy/specialisation: backend of the sphere rows (ellipsoids always run on the CPU)")
    b.add_argument("--threads", type=int, default=1, help="accuracy/specialisation: Numba threads (default 1)")
    b.add_argument("--n", type=int, default=None, help="accuracy/specialisation: spheres per gas scene")
    b.add_argument("--reps", type=int, default=None, help="accuracy/specialisation: timed runs per row (median)")
    b.add_argument("--no-ellipsoids", action="store_true", help="accuracy/specialisation: skip ellipsoid rows")
    b.add_argument("--cases", nargs="*", default=None, help="e2e: cases to time (bench/e2e.py lists them)")
    b.set_defaults(func=cmd_bench)


def cmd_bench(args) -> int:
    if args.action == "e2e":
        from bench import e2e

        argv = ["--reps", str(args.reps or 1)] + (["--quick"] if args.quick or args.tiny else []) + \
            (["--out", args.out_dir] if args.out_dir else []) + (["--cases", *args.cases] if args.cases else [])
        return e2e.main(argv)
    if args.action in ("accuracy", "specialisation"):
        import importlib

        mod = importlib.import_module(f"bench.{args.action}")
        variant = "tiny" if args.tiny else "quick" if args.quick else "full"
        flags = {"quick": " --quick", "tiny": " --tiny"}.get(variant, "")
        extra = "".join(f" --{k} {v}" for k, v in (("threads", args.threads), ("n", args.n), ("reps", args.reps))
                        if v is not None and not (k == "threads" and v == 1))
        cmd = f"demq bench {args.action}{flags} --backend {args.backend}{extra}" + \
            (" --no-ellipsoids" if args.no_ellipsoids else "")
        return mod.main(out_dir=args.out_dir, variant=variant, backend=args.backend, threads=args.threads,
                        n=args.n, reps=args.reps, ellipsoids=not args.no_ellipsoids, cmd=cmd)
    from bench import stability

    kw = {} if args.timeout is None else {"timeout": args.timeout}
    return stability.main(out_dir=args.out_dir, only=args.only, **kw)
