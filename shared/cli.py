"""The ``driveby`` console script: one entry dispatching to the simulated fleet, edge and cloud.

Subcommands import their package lazily so that ``driveby --help`` stays fast and so that this
module (in ``shared``) depends on none of the process packages at import time.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    from simfleet.cli import add_sim_arguments, run_sim

    p = argparse.ArgumentParser(prog="driveby", description="fleet drive-by monitoring of roads, rail and bridges")
    sub = p.add_subparsers(dest="command", required=True)
    add_sim_arguments(sub.add_parser("sim", help="simulate a scenario into drive logs, site.toml and truth.json"))
    args = p.parse_args(argv)
    handlers = {"sim": run_sim}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("driveby: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
