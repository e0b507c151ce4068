"""Results export (interfaces.md §3): a directory of Parquet tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .estimators.mean_profile import ProfileSnapshot

ROUGHNESS_SEGMENTS_M = (10.0, 100.0)
"""Segment lengths of ``roughness.parquet`` (m)."""


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


def roughness_table(route_id: str, chainage_m: np.ndarray, samples: np.ndarray, spacing_m: float,
                    lengths_m: tuple[float, ...] = ROUGHNESS_SEGMENTS_M) -> pa.Table:
    """``roughness.parquet``: route_id, start_m, end_m, length_m, iri_m_per_km, iri_lo95, iri_hi95.

    ``samples`` (n_samples, P) are posterior draws of the route's profile (m) on ``chainage_m``
    (e.g. ``GmrfProfile.sample``), NaN where the profile is unknown; a single profile (P,) is one
    draw. Each draw's IRI is computed per consecutive 10 m and 100 m segment
    (:func:`shared.roughness.iri_segments`); ``iri_m_per_km`` is the posterior mean of the IRI (the
    mean over draws, not the IRI of the mean profile, which is biased low because averaging
    smooths), and the band is the 2.5 % / 97.5 % quantiles over draws. ``length_m`` is the nominal
    segment length; segments without enough profile (NaN IRI) are left out.
    """
    from shared.roughness import iri_segments  # numba: only loaded when roughness is exported

    x = np.asarray(chainage_m, dtype=np.float64)
    draws = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    if draws.shape[1] != x.size:
        raise ValueError(f"samples have {draws.shape[1]} points, chainage {x.size}")
    if x.size > 1 and not np.isclose(x[1] - x[0], spacing_m, rtol=1e-9):
        raise ValueError(f"chainage spacing {x[1] - x[0]} is not spacing_m {spacing_m}")
    names = ("start_m", "end_m", "length_m", "iri_m_per_km", "iri_lo95", "iri_hi95")
    cols: dict[str, list] = {k: [] for k in names}
    for length in lengths_m:
        start, end, v = iri_segments(x, draws, length)
        keep = np.all(np.isfinite(v), axis=0)
        v = v[:, keep]
        cols["start_m"].append(start[keep])
        cols["end_m"].append(end[keep])
        cols["length_m"].append(np.full(int(keep.sum()), float(length)))
        cols["iri_m_per_km"].append(v.mean(axis=0))
        cols["iri_lo95"].append(np.quantile(v, 0.025, axis=0))
        cols["iri_hi95"].append(np.quantile(v, 0.975, axis=0))
    n = int(sum(c.size for c in cols["start_m"]))
    schema = pa.schema([("route_id", pa.string())] + [(k, pa.float64()) for k in names])
    arrays = [pa.array(np.full(n, route_id, dtype=object), type=pa.string())]
    arrays += [pa.array(np.concatenate(cols[k]), type=pa.float64()) for k in names]
    return pa.Table.from_arrays(arrays, schema=schema)


def vehicles_table(rows: list[dict]) -> pa.Table:
    """``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95 (one row per identified quantity)."""
    schema = pa.schema([("vehicle_id", pa.string()), ("param", pa.string()), ("mean", pa.float64()),
                        ("lo95", pa.float64()), ("hi95", pa.float64())])
    return pa.Table.from_pylist(rows, schema=schema)


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
