"""Command-line entry of the simulated fleet: ``driveby sim`` (and ``python -m simfleet``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .scenarios import SCENARIOS


def add_sim_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    p.add_argument("--out", type=Path, help="output directory (logs/, site.toml, truth.json)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--passes", type=int, help="number of passes (vehicles cycle when passes exceed vehicles)")
    p.add_argument("--vehicles", type=int, help="fleet size")
    p.add_argument("--noise", type=float, help="sensor noise, %% of each channel's std")
    p.add_argument("--nominal", choices=("class", "true"), default="class",
                   help="nominal_params written to the logs: the class mean (default) or each vehicle's truth")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")


def run_sim(args: argparse.Namespace) -> int:
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
    from .sim import generate

    try:
        truth = generate(SCENARIOS[args.scenario], args.out, seed=args.seed, passes=args.passes,
                         vehicles=args.vehicles, noise_pct=args.noise, nominal=args.nominal)
    except OSError as e:  # e.g. --out names an existing file, or a read-only place
        print(f"driveby sim: cannot write to {args.out}: {e.strerror or e}", file=sys.stderr)
        return 1
    print(f"wrote {len(truth['passes'])} drive logs, site.toml and truth.json to {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["fleet"]:  # its own parser (and its heavier imports) only when asked for
        from .fleet import main as fleet_main

        return fleet_main(argv[1:])
    p = argparse.ArgumentParser(prog="python -m simfleet", description="simulated fleet")
    sub = p.add_subparsers(dest="command", required=True)
    add_sim_arguments(sub.add_parser("sim", help="simulate a scenario into drive logs"))
    sub.add_parser("fleet", help="live simulated fleet publishers (fleet --help for its options)")
    args = p.parse_args(argv)
    return run_sim(args)
