"""Results export (interfaces.md §3): a directory of Parquet tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from shared.track_quality import d1_longitudinal_level, segment_quality

from cloud.road.long_wave import drift_of, pass_error_draws
from cloud.road.mean_profile import ProfileSnapshot

ROUGHNESS_SEGMENTS_M = (10.0, 100.0)
"""Segment lengths of ``roughness.parquet`` (m)."""

REGISTRY_FRAME = "registry"
"""``chainage_frame``: chainage as the vehicles reported it against the registry's route (GNSS and
odometry; no pass re-gridded). Absolute up to the vehicles' own positioning error."""
FLEET_FRAME = "fleet-consensus"
"""``chainage_frame``: passes re-gridded into the route's fleet-consensus frame, the mean of the
passes' reported frames (their shifts and stretches about it average to zero): absolute up to the
fleet's mean GNSS bias and odometry stretch, which shrink as 1/√passes."""
CHAINAGE_FRAMES = (REGISTRY_FRAME, FLEET_FRAME)


def _frame(frames: dict[str, str] | None, route_id: str) -> str:
    frame = (frames or {}).get(route_id, REGISTRY_FRAME)
    if frame not in CHAINAGE_FRAMES:
        raise ValueError(f"chainage_frame of {route_id!r}: expected one of {CHAINAGE_FRAMES}, got {frame!r}")
    return frame


def profile_table(snapshots: dict[str, ProfileSnapshot], frames: dict[str, str] | None = None) -> pa.Table:
    """``profile.parquet``: route_id, chainage_m, elevation_m, lo95_m, hi95_m, n_passes, chainage_frame.

    Points no pass has covered are left out rather than written as NaN. ``frames``: route → the frame
    its chainage is in (:data:`CHAINAGE_FRAMES`; default :data:`REGISTRY_FRAME`).
    """
    cols = {k: [] for k in ("route_id", "chainage_m", "elevation_m", "lo95_m", "hi95_m", "n_passes",
                            "chainage_frame")}
    for rid, s in snapshots.items():
        has = np.isfinite(s.elevation_m)
        cols["route_id"].append(np.full(int(has.sum()), rid, dtype=object))
        cols["chainage_m"].append(s.chainage_m[has])
        cols["elevation_m"].append(s.elevation_m[has])
        cols["lo95_m"].append(s.lo95_m[has])
        cols["hi95_m"].append(s.hi95_m[has])
        cols["n_passes"].append(s.n_passes[has].astype(np.int64))
        cols["chainage_frame"].append(np.full(int(has.sum()), _frame(frames, rid), dtype=object))
    schema = pa.schema([("route_id", pa.string()), ("chainage_m", pa.float64()), ("elevation_m", pa.float64()),
                        ("lo95_m", pa.float64()), ("hi95_m", pa.float64()), ("n_passes", pa.int64()),
                        ("chainage_frame", pa.string())])
    arrays = [pa.array(np.concatenate(v) if v else [], type=f.type) for v, f in zip(cols.values(), schema)]
    return pa.Table.from_arrays(arrays, schema=schema)


def profile_draws(profile, route_id: str, snap: ProfileSnapshot, segments: list, n: int = 100,
                  rng: np.random.Generator | int | None = 0) -> np.ndarray:
    """``n`` draws (n, P) of a route's profile carrying every error term of its exported band: the
    posterior's own (``profile.sample``: the white/AR(1) or edge error model, and the per-pass drift
    nuisance when it is on) plus the passes' excess error beyond those
    (:func:`cloud.road.long_wave.pass_error_draws`, told of the drift nuisance), so that what is
    computed from them (the IRI) has the band's uncertainty. ``snap`` is the posterior's snapshot of
    the route, ``segments`` the held segments."""
    rng = np.random.default_rng(rng)
    draws = profile.sample(route_id, n, rng)  # (first: the posterior, hence its drift level, is computed)
    return draws + pass_error_draws(snap, segments, n, rng, drift=drift_of(profile, route_id))


def roughness_table(route_id: str, chainage_m: np.ndarray, samples: np.ndarray, spacing_m: float,
                    lengths_m: tuple[float, ...] = ROUGHNESS_SEGMENTS_M, frame: str = REGISTRY_FRAME) -> pa.Table:
    """``roughness.parquet``: route_id, start_m, end_m, length_m, iri_m_per_km, iri_lo95, iri_hi95,
    chainage_frame (``frame``: the frame of start_m/end_m, as the profile's).

    ``samples`` (n_samples, P) are posterior draws of the route's profile (m) on ``chainage_m``
    (:func:`profile_draws`: with every error term of the profile's band), NaN where the profile is
    unknown; a single profile (P,) is one draw. Each draw's IRI is computed per consecutive 10 m and 100 m segment
    (:func:`shared.roughness.iri_segments`); ``iri_m_per_km`` is the posterior mean of the IRI (the
    mean over draws, not the IRI of the mean profile, which is biased low because averaging
    smooths), and the band is the 2.5 % / 97.5 % quantiles over draws. ``length_m`` is the nominal
    segment length; segments without enough profile (NaN IRI) are left out.
    """
    from shared.roughness import iri_segments  # numba kernels: loaded only when roughness is exported

    x = np.asarray(chainage_m, dtype=np.float64)
    draws = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    if draws.shape[1] != x.size:
        raise ValueError(f"samples have {draws.shape[1]} points, chainage {x.size}")
    if x.size > 1 and not np.isclose(x[1] - x[0], spacing_m, rtol=1e-9):
        raise ValueError(f"chainage spacing {x[1] - x[0]} is not spacing_m {spacing_m}")
    # A segment's bounds are clipped to the profile's extent, not the route's: where the passes begin
    # a few metres in, the first segment's IRI is of the stretch from there (the car's run starts
    # there), and start_m says so — [0, L) would claim the IRI of ground no pass drove.
    # (Whether a segment is reported at all still asks for half of its nominal length.)
    has = np.flatnonzero(np.isfinite(draws).any(axis=0))
    first_m, last_m = (x[has[0]], x[has[-1]]) if has.size else (np.inf, -np.inf)
    names = ("start_m", "end_m", "length_m", "iri_m_per_km", "iri_lo95", "iri_hi95")
    cols: dict[str, list] = {k: [] for k in names}
    for length in lengths_m:
        start, end, v = iri_segments(x, draws, length)
        start, end = np.maximum(start, first_m), np.minimum(end, last_m)
        keep = np.all(np.isfinite(v), axis=0)
        v = v[:, keep]
        cols["start_m"].append(start[keep])
        cols["end_m"].append(end[keep])
        cols["length_m"].append(np.full(int(keep.sum()), float(length)))
        cols["iri_m_per_km"].append(v.mean(axis=0))
        cols["iri_lo95"].append(np.quantile(v, 0.025, axis=0))
        cols["iri_hi95"].append(np.quantile(v, 0.975, axis=0))
    n = int(sum(c.size for c in cols["start_m"]))
    frame = _frame({route_id: frame}, route_id)
    schema = pa.schema([("route_id", pa.string())] + [(k, pa.float64()) for k in names]
                       + [("chainage_frame", pa.string())])
    arrays = [pa.array(np.full(n, route_id, dtype=object), type=pa.string())]
    arrays += [pa.array(np.concatenate(cols[k]), type=pa.float64()) for k in names]
    arrays += [pa.array(np.full(n, frame, dtype=object), type=pa.string())]
    return pa.Table.from_arrays(arrays, schema=schema)


def vehicles_table(rows: list[dict]) -> pa.Table:
    """``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95 (one row per identified quantity)."""
    fields = [("vehicle_id", pa.string()), ("param", pa.string()), ("mean", pa.float64()),
              ("lo95", pa.float64()), ("hi95", pa.float64())]
    if any("pass_id" in r for r in rows):  # run properties (a train run's mv, Iv, v): keyed by pass
        fields.append(("pass_id", pa.string()))
    return pa.Table.from_pylist(rows, schema=pa.schema(fields))


TRACK_QUALITY_SCHEMA = pa.schema([("route_id", pa.string()), ("start_m", pa.float64()), ("end_m", pa.float64()),
                                  ("sd_d1_mm", pa.float64()), ("max_abs_d1_mm", pa.float64())])


def track_quality_table(snapshots: dict[str, ProfileSnapshot]) -> pa.Table:
    """``track_quality.parquet`` (rail routes): route_id, start_m, end_m, sd_d1_mm, max_abs_d1_mm —
    the EN 13848 D1 longitudinal level (3–25 m) of the fused AP per 200 m (:mod:`shared.track_quality`)."""
    rows = []
    for rid, s in snapshots.items():
        if s.chainage_m.size < 2:
            continue
        spacing = float(s.chainage_m[1] - s.chainage_m[0])
        d1 = d1_longitudinal_level(s.elevation_m, spacing)
        for q in segment_quality(s.chainage_m, d1):
            rows.append({"route_id": rid, "start_m": q.start_m, "end_m": q.end_m, "sd_d1_mm": q.sd_d1_mm,
                         "max_abs_d1_mm": q.max_abs_d1_mm})
    return pa.Table.from_pylist(rows, schema=TRACK_QUALITY_SCHEMA)


BRIDGE_ELEMENTS_SCHEMA = pa.schema([
    ("bridge_id", pa.string()), ("element", pa.int64()), ("x_start_m", pa.float64()), ("x_end_m", pa.float64()),
    ("EI_mean", pa.float64()), ("EI_lo95", pa.float64()), ("EI_hi95", pa.float64()),
    ("stiffness_ratio", pa.float64())])
BRIDGE_BEARINGS_SCHEMA = pa.schema([
    ("bridge_id", pa.string()), ("support", pa.int64()), ("log10_krot_mean", pa.float64()),
    ("log10_krot_lo95", pa.float64()), ("log10_krot_hi95", pa.float64())])
BRIDGE_SUMMARY_SCHEMA = pa.schema([
    ("bridge_id", pa.string()), ("n_passes", pa.int64()), ("D1_pct", pa.float64()), ("D2_pct", pa.float64()),
    ("midspan_mril", pa.float64()), ("damaged", pa.bool_())])


def _rows_table(rows: list[dict], schema: pa.Schema, name: str) -> pa.Table:
    """A table of exactly ``schema``'s columns from dict rows (extra keys are an error: the contract)."""
    names = set(schema.names)
    for r in rows:
        if set(r) != names:
            raise ValueError(f"{name}: row keys {sorted(r)} differ from the contract's {schema.names}")
    return pa.Table.from_pylist(rows, schema=schema)


def bridge_elements_table(rows: list[dict]) -> pa.Table:
    """``bridge_elements.parquet``: one row per bridge finite element — bridge_id, element (1-based),
    x_start_m, x_end_m (from the first support), EI_mean, EI_lo95, EI_hi95 (N·m²), stiffness_ratio
    (EI_mean / registry E·I)."""
    return _rows_table(rows, BRIDGE_ELEMENTS_SCHEMA, "bridge_elements")


def bridge_bearings_table(rows: list[dict]) -> pa.Table:
    """``bridge_bearings.parquet``: bridge_id, support (1 = first), log10_krot_mean, _lo95, _hi95
    (N·m/rad); rows only for bridges with ``supports = "rotational_springs"``."""
    return _rows_table(rows, BRIDGE_BEARINGS_SCHEMA, "bridge_bearings")


def bridge_summary_table(rows: list[dict]) -> pa.Table:
    """``bridge_summary.parquet``: bridge_id, n_passes, D1_pct, D2_pct (thesis indicators against
    the healthy baseline, %), midspan_mril (m/N), damaged (the alarm state)."""
    return _rows_table(rows, BRIDGE_SUMMARY_SCHEMA, "bridge_summary")


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
