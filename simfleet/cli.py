"""The ``driveby`` console script (also ``python -m simfleet``): one entry dispatching to the
simulator, the run orchestration, the reports and the edge and cloud daemons.

Subcommands import their modules lazily, so ``driveby --help`` stays fast and a daemon loads only
its own package.

Every subcommand fails the same way: one line on stderr naming what is wrong, and exit code 2 when
the command line itself is wrong (an unknown or missing option, a value out of range: argparse's
rule), 1 when what it names cannot be used or the work fails (a missing or malformed file, a
directory that cannot be written, no cloud answering, a timeout).
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import math
import subprocess
import sys
from pathlib import Path

from shared.blas import single_threaded_blas

from .importers.cli import add_import_arguments, run_import


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
    p.add_argument("--state", type=Path, metavar="DIR",
                   help="keep the cloud's durable state (journal + snapshots, as driveby cloud --state) in DIR: "
                        "a later run with the same DIR continues from it (its passes, calibration, a rail "
                        "bridge's healthy baseline); default: a fresh state per run")


def _cmd_run(args) -> int:
    from .run import RunError, run  # zenoh: loaded only for this subcommand

    try:
        res = run(Path(args.logs), Path(args.site), Path(args.export), Path(args.rrd) if args.rrd else None,
                  args.calibration, args.connect, args.net, args.viewer, rate=args.rate, align=args.align,
                  shards=args.shards, secure=args.secure, state=args.state)
    except RunError as e:
        print(f"driveby run: {e}", file=sys.stderr)
        return 1
    rejected = sum(res.stats.get("rejected", {}).values())
    print(f"{res.acked}/{res.passes} passes processed in {res.seconds:.1f} s; "
          f"{res.stats.get('accepted', 0)} segments accepted, {rejected} rejected; export: {args.export}")
    return 0


def _control_args(p: argparse.ArgumentParser, what: str) -> None:
    from .control import add_cloud_arguments, add_replay_arguments  # zenoh: loaded only for these subcommands

    if what == "replay":
        add_replay_arguments(p)
    else:
        add_cloud_arguments(p)
    if what == "status":
        p.add_argument("--json", action="store_true", help="print the clouds' status as JSON (one object per line)")
        p.add_argument("--wait", type=float, default=None, metavar="S",
                       help="ask again until every cloud has settled (calibration and estimates caught up with "
                            "the passes acknowledged); exit 1 if not within S seconds")
    if what == "export":
        p.add_argument("--out", required=True, help="directory to write the export's Parquet tables into")


def _no_router(args, command: str) -> bool:
    """The deployed network is named by --connect (or a Zenoh --config): without either, a usage error."""
    if args.connect or args.config:
        return False
    print(f"driveby {command}: --connect ENDPOINT is required (the deployed router, e.g. tcp/hub:7447)",
          file=sys.stderr)
    return True


def _cmd_status(args) -> int:
    from .control import ControlError, UsageError, format_status, status

    if _no_router(args, "status"):
        return 2
    if args.wait is not None and not (math.isfinite(args.wait) and args.wait > 0):
        print(f"driveby status: --wait {args.wait:g}: must be a positive number of seconds", file=sys.stderr)
        return 2
    try:
        bodies = status(args)
    except ControlError as e:
        print(f"driveby status: {e}", file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1
    for body in bodies:
        print(json.dumps(body) if args.json else format_status(body))
    return 0


def _cmd_export(args) -> int:
    from .control import ControlError, UsageError, export

    if _no_router(args, "export"):
        return 2
    try:
        written, stats = export(args)
    except ControlError as e:
        print(f"driveby export: {e}", file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1
    rejected = sum(stats.get("rejected", {}).values())
    print(f"wrote {', '.join(p.name for p in written)} to {args.out} ({stats.get('passes_complete', 0)} passes, "
          f"{stats.get('accepted', 0)} segments accepted, {rejected} rejected)")
    return 0


def _cmd_replay(args) -> int:
    from .control import ControlError, UsageError, replay_logs

    if _no_router(args, "replay"):
        return 2
    try:
        res = replay_logs(args)
    except ControlError as e:
        print(f"driveby replay: {e}", file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1
    print(f"{res.acked}/{res.passes} passes acknowledged in {res.seconds:.1f} s"
          + (f" ({res.resent_passes} published again)" if res.resent_passes else ""))
    return 0


def _cmd_view(args) -> int:
    path = Path(args.file)
    if not path.is_file():
        print(f"driveby view: {path}: no such file (a Rerun recording, e.g. driveby-demo/demo.rrd)", file=sys.stderr)
        return 1
    # The viewer of the Rerun SDK installed beside this Python: works without activating the venv.
    cmd = [sys.executable, "-m", "rerun", str(path), *(["--web-viewer"] if args.web else [])]
    try:
        return subprocess.call(cmd)
    except OSError as e:
        print(f"driveby view: cannot start the Rerun viewer: {e}", file=sys.stderr)
        return 1


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


def build_parser() -> argparse.ArgumentParser:
    """The ``driveby`` parser (the daemons' own parsers: each daemon module's ``build_parser``)."""
    p = argparse.ArgumentParser(prog="driveby", description="fleet drive-by monitoring of roads, rail and bridges")
    sub = p.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate a small fleet over a road and a cracked bridge, run it, summarise")
    demo.add_argument("--out", default="driveby-demo", help="working directory (default ./driveby-demo)")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    demo.add_argument("--passes", type=int, default=None, help="passes to simulate (default: the demo's, 30)")
    add_sim_arguments(sub.add_parser("sim", help="simulate a scenario into drive logs, site.toml and truth.json"))
    _run_args(sub.add_parser("run", help="replay drive logs through edge and cloud over Zenoh, export"))
    _reproduce_args(sub.add_parser("reproduce", help="reproduce the thesis's results beside ours (report in Markdown)"))
    add_import_arguments(sub.add_parser("import", help="convert a logger export into a drive log (with positions)"))
    for name, what in (("edge", "the edge daemon (see driveby edge --help)"),
                       ("cloud", "the cloud aggregator daemon (see driveby cloud --help)"),
                       ("fleet", "live simulated fleet publishers (see driveby fleet --help)"),
                       ("router", "a Zenoh router for the daemons to meet at (see driveby router --help)")):
        sub.add_parser(name, help=what, add_help=False)
    _control_args(sub.add_parser("replay", help="publish drive logs as their vehicles to a deployed router and wait "
                                                "for every pass's acknowledgement (no edge or cloud of its own)"),
                  "replay")
    _control_args(sub.add_parser("status", help="ask the running clouds for their status: passes, segments "
                                                "accepted/rejected, vehicles, bridges"), "status")
    _control_args(sub.add_parser("export", help="ask the running clouds for their export; write its Parquet "
                                                "tables here"), "export")
    view = sub.add_parser("view", help="open a Rerun recording (.rrd) in the Rerun viewer installed with driveby")
    view.add_argument("file", metavar="FILE.rrd", help="the recording, e.g. driveby-demo/demo.rrd")
    view.add_argument("--web", action="store_true", help="serve the web viewer and open it in a browser instead")
    return p


HANDLERS = {"sim": run_sim, "run": _cmd_run, "demo": _cmd_demo, "reproduce": _cmd_reproduce, "status": _cmd_status,
            "export": _cmd_export, "replay": _cmd_replay, "view": _cmd_view, "import": run_import}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["router"]:  # a Zenoh router from the zenoh wheel: no zenohd binary to install
        return importlib.import_module("shared.transport").main(argv, prog="driveby")
    if argv[:1] and argv[0] in DAEMONS:
        # Daemons own their whole command line (Zenoh options, ...): hand it over untouched.
        if argv[0] in BLAS_DAEMONS:
            single_threaded_blas()
        node = importlib.import_module(DAEMONS[argv[0]])
        try:
            return node.main(argv[1:])
        except KeyboardInterrupt:
            return 130
    args = build_parser().parse_args(argv)
    try:
        return HANDLERS[args.command](args)
    except KeyboardInterrupt:
        print("driveby: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
