"""The ``driveby`` console script: one entry dispatching to the simulated fleet, edge and cloud.

Subcommands import their package lazily so that ``driveby --help`` stays fast and so that this
module (in ``shared``) depends on none of the process packages at import time.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

#: Thread counts of the BLAS/OpenMP libraries numpy and scipy may load. A daemon's linear algebra is
#: small (e.g. a 270×270 eigh) and shares the machine with the others: a thread per core then mostly
#: waits on the other daemons and is many times slower than one thread, so the daemons run it
#: single-threaded.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas(environ=os.environ) -> None:
    """Make BLAS single-threaded unless the user chose otherwise (a variable already set wins).

    Call before numpy is first imported: the libraries read these variables once, when loaded."""
    for name in BLAS_THREAD_VARIABLES:
        environ.setdefault(name, "1")


def _run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--logs", required=True, help="directory of drive logs (*.parquet)")
    p.add_argument("--site", required=True, help="site registry TOML")
    p.add_argument("--export", required=True, help="output directory for the Parquet export")
    p.add_argument("--rrd", help="save the Rerun recording to this file")
    p.add_argument("--calibration", choices=("fleet", "nominal"), default="fleet",
                   help="fleet: self-calibrate (default); nominal: trust each log's nominal_params")
    p.add_argument("--connect", help="use this Zenoh router instead of starting one")
    p.add_argument("--net", default="net", help="network name in the key space")
    p.add_argument("--viewer", action="store_true", help="spawn a Rerun viewer")
    p.add_argument("--rate", type=float, help="replay at X× real time (default: as fast as possible)")
    p.add_argument("--align", action="store_true",
                   help="align passes in chainage against the consensus (GNSS bias, odometry stretch)")
    p.add_argument("--shards", type=int, default=1, metavar="N",
                   help="split the routes among N cloud daemons behind two routers (scale-out, exercised locally)")
    p.add_argument("--secure", nargs="?", const=True, default=False, metavar="DIR",
                   help="TLS with mutual authentication and access control: certificates made into the export's "
                        ".run/security, or those of security directory DIR (needed with --connect)")


def _cmd_run(args) -> int:
    from pathlib import Path

    from simfleet.run import RunError, run

    try:
        res = run(Path(args.logs), Path(args.site), Path(args.export), Path(args.rrd) if args.rrd else None,
                  args.calibration, args.connect, args.net, args.viewer, rate=args.rate, align=args.align,
                  shards=args.shards, secure=args.secure)
    except RunError as e:
        print(f"driveby run: {e}", file=sys.stderr)
        return 1
    rejected = sum(res.stats.get("rejected", {}).values())
    print(f"{res.acked}/{res.passes} passes processed in {res.seconds:.1f} s; "
          f"{res.stats.get('accepted', 0)} segments accepted, {rejected} rejected; export: {args.export}")
    return 0


def _cmd_demo(args) -> int:
    from simfleet.demo import demo

    return demo(args.out, seed=args.seed, passes=args.passes)


DAEMONS = {"edge": "edge.node", "cloud": "cloud.daemon.node", "fleet": "simfleet.node"}  # subcommand → module with main
BLAS_DAEMONS = ("edge", "cloud")  # long-running, sharing the machine: single-threaded BLAS by default


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] and argv[0] in DAEMONS:
        # Daemons own their whole command line (Zenoh options, ...): hand it over untouched.
        if argv[0] in BLAS_DAEMONS:
            single_threaded_blas()
        node = importlib.import_module(DAEMONS[argv[0]])
        try:
            return node.main(argv[1:])
        except KeyboardInterrupt:
            return 130
    from simfleet.cli import add_sim_arguments, run_sim
    from simfleet.reproduce import add_reproduce_arguments, run_reproduce

    p = argparse.ArgumentParser(prog="driveby", description="fleet drive-by monitoring of roads, rail and bridges")
    sub = p.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate a small fleet over a road and a cracked bridge, run it, summarise")
    demo.add_argument("--out", default="driveby-demo", help="working directory (default ./driveby-demo)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--passes", type=int, default=20)
    add_sim_arguments(sub.add_parser("sim", help="simulate a scenario into drive logs, site.toml and truth.json"))
    _run_args(sub.add_parser("run", help="replay drive logs through edge and cloud over Zenoh, export"))
    add_reproduce_arguments(sub)
    for name, what in (("edge", "the edge daemon (see driveby edge --help)"),
                       ("cloud", "the cloud aggregator daemon (see driveby cloud --help)"),
                       ("fleet", "live simulated fleet publishers (see driveby fleet --help)")):
        sub.add_parser(name, help=what, add_help=False)
    args = p.parse_args(argv)
    handlers = {"sim": run_sim, "run": _cmd_run, "demo": _cmd_demo, "reproduce": run_reproduce}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("driveby: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
