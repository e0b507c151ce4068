"""Route geometry: a WGS84 polyline with chainage along it (interfaces.md §5).

Chainage is the geodesic length along the polyline from its first vertex (WGS84 ellipsoid, each
segment a geodesic: `pyproj.Geod`). Positions are matched to the line in a local azimuthal
equidistant projection centred on the route (`pyproj.Transformer`, `shapely`), where a route of a
few tens of kilometres keeps distances to within a few parts per million; the matched point's
chainage is then read from the geodesic segment lengths, so chainage never inherits the
projection's scale error.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from pyproj import CRS, Geod, Transformer

WGS84 = Geod(ellps="WGS84")


class GeometryError(ValueError):
    """A route geometry that breaks the contract; the message says what, in one line."""


@dataclass(frozen=True, eq=False)
class RouteGeometry:
    """A route's centre line: vertices ``lat``/``lon`` (degrees, WGS84) in the direction of chainage.

    Build with `RouteGeometry.from_latlon`; consecutive repeated vertices are dropped.
    ``vertex_chainage_m`` holds the geodesic chainage at each vertex (0 at the first).
    """

    lat: np.ndarray
    lon: np.ndarray
    vertex_chainage_m: np.ndarray
    _to_local: Transformer = field(repr=False)
    _line: shapely.LineString = field(repr=False)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RouteGeometry):
            return NotImplemented
        return np.array_equal(self.lat, other.lat) and np.array_equal(self.lon, other.lon)

    def __hash__(self) -> int:
        return hash((self.lat.tobytes(), self.lon.tobytes()))

    @classmethod
    def from_latlon(cls, latlon) -> RouteGeometry:
        """From a sequence of ``(lat, lon)`` pairs; raises `GeometryError` on anything unusable."""
        try:
            pts = np.asarray(latlon, dtype=float)
        except (TypeError, ValueError):
            raise GeometryError("must be an array of [lat, lon] pairs of numbers") from None
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise GeometryError(f"must be an array of [lat, lon] pairs, got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise GeometryError("coordinates must be finite")
        lat, lon = pts[:, 0], pts[:, 1]
        if np.any(np.abs(lat) > 90.0):
            raise GeometryError(f"latitude out of [-90, 90]: {float(lat[np.abs(lat) > 90.0][0]):g}")
        if np.any(np.abs(lon) > 180.0):
            raise GeometryError(f"longitude out of [-180, 180]: {float(lon[np.abs(lon) > 180.0][0]):g}")
        keep = np.ones(len(lat), dtype=bool)
        keep[1:] = (np.diff(lat) != 0.0) | (np.diff(lon) != 0.0)
        lat, lon = lat[keep].copy(), lon[keep].copy()
        if len(lat) < 2:
            raise GeometryError("needs at least two distinct vertices")
        _, _, seg = WGS84.inv(lon[:-1], lat[:-1], lon[1:], lat[1:])
        s = np.concatenate(([0.0], np.cumsum(seg)))
        # A local azimuthal equidistant frame about the line's middle vertex: metres, nearly true scale.
        mid = len(lat) // 2
        local = CRS.from_dict({"proj": "aeqd", "lat_0": float(lat[mid]), "lon_0": float(lon[mid]),
                               "datum": "WGS84", "units": "m"})
        to_local = Transformer.from_crs("EPSG:4326", local, always_xy=True)
        x, y = to_local.transform(lon, lat)
        for a in (lat, lon, s):
            a.setflags(write=False)
        return cls(lat, lon, s, to_local, shapely.LineString(np.column_stack([x, y])))

    @property
    def length_m(self) -> float:
        """The geodesic length of the line, m."""
        return float(self.vertex_chainage_m[-1])

    def position(self, chainage_m) -> tuple[np.ndarray, np.ndarray]:
        """``(lat, lon)`` (degrees) of the points at ``chainage_m`` (clipped to the line)."""
        c = np.clip(np.atleast_1d(np.asarray(chainage_m, dtype=float)), 0.0, self.length_m)
        i = np.clip(np.searchsorted(self.vertex_chainage_m, c, side="right") - 1, 0, len(self.lat) - 2)
        az, _, _ = WGS84.inv(self.lon[i], self.lat[i], self.lon[i + 1], self.lat[i + 1])
        lon, lat, _ = WGS84.fwd(self.lon[i], self.lat[i], az, c - self.vertex_chainage_m[i])
        return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)

    def locate(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """``(chainage_m, offset_m)`` of each position: the nearest point on the line and the
        distance to it (m). Positions beyond the ends map to the end's chainage."""
        x, y = self._to_local.transform(np.atleast_1d(np.asarray(lon, dtype=float)),
                                        np.atleast_1d(np.asarray(lat, dtype=float)))
        pts = shapely.points(np.asarray(x), np.asarray(y))
        along = shapely.line_locate_point(self._line, pts)
        offset = shapely.distance(self._line, pts)
        # The projected distance along the line → the segment and the share of it → geodesic chainage.
        xy = shapely.get_coordinates(self._line)
        seg = np.hypot(np.diff(xy[:, 0]), np.diff(xy[:, 1]))
        cum = np.concatenate(([0.0], np.cumsum(seg)))
        i = np.clip(np.searchsorted(cum, along, side="right") - 1, 0, len(seg) - 1)
        share = np.clip((along - cum[i]) / seg[i], 0.0, 1.0)
        geodesic = np.diff(self.vertex_chainage_m)
        return self.vertex_chainage_m[i] + share * geodesic[i], np.asarray(offset, dtype=float)

    def latlon(self) -> list[list[float]]:
        """The vertices as ``[[lat, lon], ...]`` (the registry's inline form)."""
        return [[float(a), float(b)] for a, b in zip(self.lat, self.lon)]


def read_geojson_line(path: str | os.PathLike) -> RouteGeometry:
    """The LineString of a GeoJSON file: a bare geometry, a Feature, or a FeatureCollection holding
    exactly one LineString feature. GeoJSON orders coordinates ``[lon, lat]`` (RFC 7946)."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise GeometryError("does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise GeometryError(f"cannot read ({getattr(e, 'strerror', None) or e})") from None
    except json.JSONDecodeError as e:
        raise GeometryError(f"not JSON ({e.msg} at line {e.lineno})") from None
    geom = doc
    if isinstance(doc, dict) and doc.get("type") == "FeatureCollection":
        lines = [f.get("geometry") for f in doc.get("features") or []
                 if isinstance(f, dict) and isinstance(f.get("geometry"), dict)
                 and f["geometry"].get("type") == "LineString"]
        if len(lines) != 1:
            raise GeometryError(f"a FeatureCollection must hold exactly one LineString, found {len(lines)}")
        geom = lines[0]
    elif isinstance(doc, dict) and doc.get("type") == "Feature":
        geom = doc.get("geometry")
    if not isinstance(geom, dict) or geom.get("type") != "LineString":
        kind = geom.get("type") if isinstance(geom, dict) else type(geom).__name__
        raise GeometryError(f"expected a GeoJSON LineString, got {kind!r}")
    coords = geom.get("coordinates")
    if not isinstance(coords, list) or not all(isinstance(c, list) and len(c) >= 2 for c in coords):
        raise GeometryError("LineString coordinates must be [lon, lat] positions")
    return RouteGeometry.from_latlon([[c[1], c[0]] for c in coords])


def line_feature(lat, lon, properties: dict) -> dict:
    """A GeoJSON LineString feature through ``(lat, lon)`` points, coordinates ``[lon, lat]``."""
    coords = [[round(float(b), 8), round(float(a), 8)] for a, b in zip(lat, lon) if math.isfinite(a)]
    return {"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
            "properties": properties}
