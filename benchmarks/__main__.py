"""Run the project's benchmarks: ``python -m benchmarks [NAME ...]`` prints one JSON object per line.

Each benchmark module has ``run() -> Iterable[dict]`` yielding results shaped like
``{"name": "inverse.quarter_car.one_stream", "value": 6.1e7, "unit": "samples/s",
"ratio_to": {"realtime_500hz": 1.2e5, "plain_loop": 300}}``; ratios are measured in the same run.
Run from the repository root (some benchmarks time the reference loops in ``tests/naive.py``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

#: Benchmark name → module. Add new benchmarks (bus, profile, bridge, …) here.
REGISTRY: dict[str, str] = {
    "inverse": "benchmarks.inverse",
    "bus": "benchmarks.bus",
    "profile": "benchmarks.profile",
    "bridge": "benchmarks.bridge",
    "crash": "benchmarks.crash",
    "soak": "benchmarks.soak",
    "rail": "benchmarks.rail",
    "edge": "benchmarks.edge",
    "align": "benchmarks.align",
    "calib": "benchmarks.calib",
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"benchmarks to run (default: all of {', '.join(REGISTRY)})")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in REGISTRY]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(REGISTRY)}")
    for name in args.names or list(REGISTRY):
        module = importlib.import_module(REGISTRY[name])
        for result in module.run():
            print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
