"""The ``driveby`` console script (also ``python -m simfleet``): one entry dispatching to the
simulator, the run orchestration, the reports and the edge and cloud daemons.

Subcommands import their modules lazily, so ``driveby --help`` stays fast and a daemon loads only
its own package.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from pathlib import Path

from shared.blas import single_threaded_blas


def add_sim_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    p.add_argument("--out", type=Path, help="output directory (logs/, site.toml, truth.json)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    p.add_argument("--passes", type=int, help="number of passes (vehicles cycle when passes exceed vehicles)")
    p.add_argument("--vehicles", type=int, help="fleet size")
    p.add_argument("--noise", type=float, help="sensor noise, %% of each channel's std")
    p.add_argument("--nominal", choices=("class", "true"), default="class",
                   help="nominal_params written to the logs: the class mean (default) or each vehicle's truth")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.add_argument("--world", choices=("simfleet", "ivp"), default="simfleet",
                   help="simfleet's own simulator (default) or the independent ivp world (simfleet.worlds)")


def run_sim(args: argparse.Namespace) -> int:
    # Imported here: the scenarios load numpy, which must not happen before a daemon sets its BLAS threads.
    from .scenarios import SCENARIOS

    if args.list:
        width = max(len(n) for n in SCENARIOS)
        for name, sc in SCENARIOS.items():
            print(f"{name:<{width}}  {sc.description}")
        return 0
    if not args.scenario:
        print("driveby sim: a SCENARIO is required (see driveby sim --list)", file=sys.stderr)
        return 2
    if args.scenario not in SCENARIOS:
        print(f"driveby sim: unknown scenario {args.scenario!r} (see driveby sim --list)", file=sys.stderr)
        return 2
    if args.out is None:
        print("driveby sim: --out DIR is required", file=sys.stderr)
        return 2
    for name in ("passes", "vehicles"):
        value = getattr(args, name)
        if value is not None and value < 1:
            print(f"driveby sim: --{name} must be >= 1, got {value}", file=sys.stderr)
            return 2
    if args.noise is not None and not (0 <= args.noise < 100):
        print(f"driveby sim: --noise must be a percentage in [0, 100), got {args.noise}", file=sys.stderr)
        return 2
    if args.seed < 0:  # numpy's seeding rejects negative integers with a traceback
        print(f"driveby sim: --seed must be >= 0, got {args.seed}", file=sys.stderr)
        return 2
    from .sim import generate  # the simulator: loaded only once the arguments are checked
    from .worlds.ivp import generate as generate_ivp

    if getattr(args, "world", "simfleet") == "ivp":
        generate = generate_ivp
    try:
        truth = generate(SCENARIOS[args.scenario], args.out, seed=args.seed, passes=args.passes,
                         vehicles=args.vehicles, noise_pct=args.noise, nominal=args.nominal)
    except OSError as e:  # e.g. --out names an existing file, or a read-only place
        print(f"driveby sim: cannot write to {args.out}: {e.strerror or e}", file=sys.stderr)
        return 1
    except ValueError as e:  # e.g. a rail scenario in the ivp world
        print(f"driveby sim: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(truth['passes'])} drive logs, site.toml and truth.json to {args.out}")
    return 0


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
    p.add_argument("--align", action=argparse.BooleanOptionalAction, default=True,
                   help="align passes in chainage against the consensus (GNSS bias, odometry stretch; default on, "
                        "--no-align trusts the reported chainage)")
    p.add_argument("--shards", type=int, default=1, metavar="N",
                   help="split the routes among N cloud daemons behind two routers (scale-out, exercised locally)")
    p.add_argument("--secure", nargs="?", const=True, default=False, metavar="DIR",
                   help="TLS with mutual authentication and access control: certificates made into the export's "
                        ".run/security, or those of security directory DIR (needed with --connect)")


def _cmd_run(args) -> int:
    from .run import RunError, run  # zenoh: loaded only for this subcommand

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
    from .demo import demo  # zenoh and the simulator: loaded only for this subcommand

    return demo(args.out, seed=args.seed, passes=args.passes)


def _reproduce_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=("road", "bridge", "rail", "robustness"),
                   help="which results: road (Tables 2.3, 2.6, Fig. 2.12, §4.3 MCMC), bridge (Table 3.3, "
                        "Table 4.2, Fig. 4.12, Cramér–Rao bound) or rail (Table 3.6 blind test, batch "
                        "calibration, Fig. 3.10) or robustness (headline numbers on simfleet's and the ivp "
                        "world, with coverage)")
    p.add_argument("--out", default="driveby-reproduce", help="output directory (default ./driveby-reproduce)")
    p.add_argument("--quick", action="store_true", help="smaller fleets, fewer noise levels and iterations")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    p.add_argument("--large", action="store_true", help="bridge: also the 300-pass cracks, fleet-large and the "
                   "rough decks at 30/100/300 passes (hours on a loaded machine)")


def _cmd_reproduce(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    # Each report loads its estimators, the simulator and the harness only when it runs.
    if args.what == "bridge":
        from .reproduce_bridge import reproduce_bridge

        report = reproduce_bridge(args.out, quick=args.quick, seed=args.seed, large=args.large)
    elif args.what == "robustness":
        from .reproduce_robustness import reproduce_robustness

        report = reproduce_robustness(args.out, quick=args.quick, seed=args.seed)
    elif args.what == "rail":
        from .reproduce_rail import reproduce_rail

        report = reproduce_rail(args.out, quick=args.quick, seed=args.seed)
    else:
        from .reproduce import reproduce_road

        report = reproduce_road(args.out, quick=args.quick, seed=args.seed)
    print(f"driveby reproduce: report written to {report}")
    return 0


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
    p = argparse.ArgumentParser(prog="driveby", description="fleet drive-by monitoring of roads, rail and bridges")
    sub = p.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate a small fleet over a road and a cracked bridge, run it, summarise")
    demo.add_argument("--out", default="driveby-demo", help="working directory (default ./driveby-demo)")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    demo.add_argument("--passes", type=int, default=20, help="passes to simulate (default 20)")
    add_sim_arguments(sub.add_parser("sim", help="simulate a scenario into drive logs, site.toml and truth.json"))
    _run_args(sub.add_parser("run", help="replay drive logs through edge and cloud over Zenoh, export"))
    _reproduce_args(sub.add_parser("reproduce", help="reproduce the thesis's results beside ours (report in Markdown)"))
    for name, what in (("edge", "the edge daemon (see driveby edge --help)"),
                       ("cloud", "the cloud aggregator daemon (see driveby cloud --help)"),
                       ("fleet", "live simulated fleet publishers (see driveby fleet --help)")):
        sub.add_parser(name, help=what, add_help=False)
    args = p.parse_args(argv)
    handlers = {"sim": run_sim, "run": _cmd_run, "demo": _cmd_demo, "reproduce": _cmd_reproduce}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("driveby: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
