"""``driveby import FORMAT PATH --out DIR``: a logger export into a drive log (interfaces.md §5).

The importer modules load numpy: they are imported only when the subcommand runs, so
``driveby --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

FORMATS = {"phone-csv": "the Sensor Logger app's export (zip or folder): TotalAcceleration or Accelerometer + "
                        "Gravity, Gyroscope, Location, Metadata"}


def add_import_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("format", choices=sorted(FORMATS), help="; ".join(f"{k}: {v}" for k, v in FORMATS.items()))
    p.add_argument("path", type=Path, help="the export (a .zip or its unpacked folder)")
    p.add_argument("--out", type=Path, required=True, help="directory for the drive log (*.parquet)")
    p.add_argument("--model", default="quarter_car", help="vehicle_model of the log (default quarter_car)")
    p.add_argument("--vehicle", help="vehicle_id (default: the export's device name, else its file name)")
    p.add_argument("--rate", type=float, help="nominal sample_rate_hz (default: the accelerometer's median rate)")


def run_import(args: argparse.Namespace) -> int:
    from .sensor_logger import ExportFormatError, import_sensor_logger  # numpy: only when importing

    if args.rate is not None and not args.rate > 0:
        print(f"driveby import: --rate must be positive, got {args.rate}", file=sys.stderr)
        return 2
    try:
        written = import_sensor_logger(args.path, args.out, vehicle_model=args.model, vehicle_id=args.vehicle,
                                       sample_rate_hz=args.rate)
    except ExportFormatError as e:
        print(f"driveby import: {e}", file=sys.stderr)
        return 1
    except ValueError as e:  # e.g. an unknown --model
        print(f"driveby import: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"driveby import: cannot write to {args.out}: {e.strerror or e}", file=sys.stderr)
        return 1
    for p in written:
        print(f"wrote {p}")
    return 0
