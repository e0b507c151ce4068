"""Coordinates in the export, for GIS tools (interfaces.md §5): where a route has geometry, the
roughness segments gain their end points' WGS84 positions, the bridges their mid-span position, and
``roughness.geojson`` draws each segment as a LineString along the route's line.

Exports of sites without geometry are left exactly as they were: no column is added.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow as pa

from shared.geo import line_feature
from shared.registry import Site

GEOJSON_NAME = "roughness.geojson"


def has_geometry(site: Site) -> bool:
    """Whether any route of ``site`` has a geometry."""
    return any(r.geometry is not None for r in site.routes)


def _positions(site: Site, route_ids, chainage_m) -> tuple[np.ndarray, np.ndarray]:
    lat = np.full(len(chainage_m), np.nan)
    lon = np.full(len(chainage_m), np.nan)
    geometry = {r.id: r.geometry for r in site.routes}
    route_ids = np.asarray(route_ids, dtype=object)
    for rid in set(route_ids.tolist()):
        g = geometry.get(rid)
        if g is None:
            continue
        at = route_ids == rid
        lat[at], lon[at] = g.position(np.asarray(chainage_m, dtype=float)[at])
    return lat, lon


def segment_line(geometry, start_m: float, end_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(lat, lon)`` of the stretch ``start_m``–``end_m`` of a route's line (a `shared.geo.RouteGeometry`):
    its ends and the line's vertices between them, so the stretch follows the route's bends."""
    v = geometry.vertex_chainage_m
    inside = v[(v > start_m) & (v < end_m)]
    return geometry.position(np.concatenate(([start_m], inside, [end_m])))


def _nullable(values: np.ndarray) -> pa.Array:
    return pa.array(values, type=pa.float64(), mask=~np.isfinite(values))


def roughness_with_coordinates(table: pa.Table, site: Site) -> pa.Table:
    """``roughness`` with ``start_lat, start_lon, end_lat, end_lon`` (null where the route has no
    geometry); unchanged when no route of ``site`` has one."""
    if not has_geometry(site) or table.num_rows == 0:
        return table
    rids = table.column("route_id").to_pylist()
    for end in ("start", "end"):
        lat, lon = _positions(site, rids, table.column(f"{end}_m").to_numpy())
        table = table.append_column(f"{end}_lat", _nullable(lat)).append_column(f"{end}_lon", _nullable(lon))
    return table


def bridges_with_coordinates(table: pa.Table, site: Site) -> pa.Table:
    """``bridge_summary`` with ``lat, lon`` of each bridge's mid-span (null without geometry)."""
    if not has_geometry(site) or table.num_rows == 0:
        return table
    rids, mids = [], []
    for bid in table.column("bridge_id").to_pylist():
        try:
            b = site.bridge(bid)
        except KeyError:
            rids.append(None)
            mids.append(math.nan)
            continue
        rids.append(b.route)
        mids.append(b.start_chainage_m + 0.5 * b.span_m)
    lat, lon = _positions(site, rids, np.asarray(mids, dtype=float))
    return table.append_column("lat", _nullable(lat)).append_column("lon", _nullable(lon))


def roughness_geojson(table: pa.Table, site: Site) -> dict | None:
    """A FeatureCollection of the roughness segments on routes with geometry, each a LineString
    along the route's line (its vertices inside the segment kept), or None if there are none."""
    if not has_geometry(site) or table.num_rows == 0:
        return None
    geometry = {r.id: r.geometry for r in site.routes}
    features = []
    for row in table.select(["route_id", "start_m", "end_m", "length_m", "iri_m_per_km", "iri_lo95",
                             "iri_hi95"]).to_pylist():
        g = geometry.get(row["route_id"])
        if g is None:
            continue
        lat, lon = segment_line(g, row["start_m"], row["end_m"])
        props = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
        features.append(line_feature(lat, lon, props))
    return {"type": "FeatureCollection", "features": features} if features else None


def write_geojson(out_dir: Path, doc: dict) -> Path:
    """Write ``roughness.geojson`` atomically beside the Parquet tables."""
    path = Path(out_dir) / GEOJSON_NAME
    tmp = path.with_suffix(".geojson.tmp")
    tmp.write_text(json.dumps(doc, allow_nan=False), encoding="utf-8")
    tmp.replace(path)
    return path
