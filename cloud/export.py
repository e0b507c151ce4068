"""Results export (interfaces.md §3): a directory of Parquet tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .estimators.mean_profile import ProfileSnapshot


def profile_table(snapshots: dict[str, ProfileSnapshot]) -> pa.Table:
    """``profile.parquet``: route_id, chainage_m, elevation_m, lo95_m, hi95_m, n_passes.

    Points no pass has covered are left out rather than written as NaN.
    """
    cols = {k: [] for k in ("route_id", "chainage_m", "elevation_m", "lo95_m", "hi95_m", "n_passes")}
    for rid, s in snapshots.items():
        has = np.isfinite(s.elevation_m)
        cols["route_id"].append(np.full(int(has.sum()), rid, dtype=object))
        cols["chainage_m"].append(s.chainage_m[has])
        cols["elevation_m"].append(s.elevation_m[has])
        cols["lo95_m"].append(s.lo95_m[has])
        cols["hi95_m"].append(s.hi95_m[has])
        cols["n_passes"].append(s.n_passes[has].astype(np.int64))
    schema = pa.schema([("route_id", pa.string()), ("chainage_m", pa.float64()), ("elevation_m", pa.float64()),
                        ("lo95_m", pa.float64()), ("hi95_m", pa.float64()), ("n_passes", pa.int64())])
    arrays = [pa.array(np.concatenate(v) if v else [], type=f.type) for v, f in zip(cols.values(), schema)]
    return pa.Table.from_arrays(arrays, schema=schema)


def write_export(out_dir: Path, tables: dict[str, pa.Table]) -> list[Path]:
    """Write each table as ``<name>.parquet`` atomically (temp file + rename)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, table in tables.items():
        path = out_dir / f"{name}.parquet"
        tmp = path.with_suffix(".parquet.tmp")
        pq.write_table(table, tmp)
        tmp.replace(path)
        written.append(path)
    return written
