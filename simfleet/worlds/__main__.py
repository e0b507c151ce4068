"""``python -m simfleet.worlds SCENARIO --out DIR``: simulate a scenario in the second (ivp) world."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..scenarios import SCENARIOS
from .ivp import WorldSettings, generate


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m simfleet.worlds", description=__doc__)
    p.add_argument("scenario", choices=sorted(SCENARIOS), metavar="SCENARIO", help="scenario name (driveby sim --list)")
    p.add_argument("--out", type=Path, required=True, help="output directory (logs/, site.toml, truth.json)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--passes", type=int, help="number of passes")
    p.add_argument("--vehicles", type=int, help="fleet size")
    p.add_argument("--noise", type=float, help="sensor noise, %% of each channel's std")
    p.add_argument("--nominal", choices=("class", "true"), default="class")
    p.add_argument("--speed-error", type=float, default=WorldSettings.speed_error_sd,
                   help="odometer scale error sd per run where the scenario sets none (default %(default)s)")
    p.add_argument("--wobble", type=float, default=WorldSettings.wobble,
                   help="relative amplitude of the slow speed variation (default %(default)s)")
    args = p.parse_args(argv)
    try:
        settings = WorldSettings(speed_error_sd=args.speed_error, wobble=args.wobble)
        truth = generate(SCENARIOS[args.scenario], args.out, seed=args.seed, passes=args.passes,
                         vehicles=args.vehicles, noise_pct=args.noise, nominal=args.nominal, settings=settings)
    except ValueError as e:
        print(f"simfleet.worlds: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(truth['passes'])} drive logs (ivp world), site.toml and truth.json to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
