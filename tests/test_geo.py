"""Route geometry (interfaces.md §5): chainage along a WGS84 polyline, positions matched to it, the
registry's geometry keys, and the export's coordinates."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.integrate import quad

from cloud.coordinates import bridges_with_coordinates, roughness_geojson, roughness_with_coordinates
from shared.drivelog import read_drive_log, list_drive_logs
from shared.geo import WGS84, GeometryError, RouteGeometry, read_geojson_line
from shared.registry import RegistryError, dump_site, load_site, parse_site
from simfleet.harness import run_in_process
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

# A route with two bends near Dublin: north 0.005°, east 0.01°, then north-east.
BENT = [[53.30, -6.22], [53.305, -6.22], [53.305, -6.21], [53.309, -6.205]]

BRIDGE = dict(id="B1", route="R1", span_m=20.0, n_elements=20, E_pa=35e9, I_m4=1.25, mass_per_m=37500.0,
              depth_m=1.0, damping_ratio=0.03, supports="simply_supported")


def meridian_arc_m(lat0: float, lat1: float) -> float:
    """The WGS84 meridian arc between two latitudes by quadrature of the meridian radius of curvature
    M(φ) = a(1 − e²) / (1 − e² sin²φ)^{3/2}: an independent check of the geodesic lengths."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    m = lambda phi: a * (1 - e2) / (1 - e2 * math.sin(phi) ** 2) ** 1.5  # noqa: E731
    return quad(m, math.radians(lat0), math.radians(lat1), epsabs=1e-9)[0]


def test_chainage_along_a_meridian_is_the_meridian_arc():
    g = RouteGeometry.from_latlon([[53.30, -6.22], [53.31, -6.22], [53.32, -6.22]])
    # GeographicLib's geodesics are accurate to nanometres; quadrature to 1e-9: a micrometre holds.
    assert g.length_m == pytest.approx(meridian_arc_m(53.30, 53.32), abs=1e-6)
    assert g.vertex_chainage_m[1] == pytest.approx(meridian_arc_m(53.30, 53.31), abs=1e-6)


def test_position_and_locate_are_inverse_along_a_bent_line():
    g = RouteGeometry.from_latlon(BENT)
    c = np.linspace(0.0, g.length_m, 257)
    lat, lon = g.position(c)
    back, offset = g.locate(lat, lon)
    # The matched point lies on the projected chord, the position on the geodesic: over segments of
    # ≤ 1 km they differ by well under a millimetre.
    np.testing.assert_allclose(back, c, atol=1e-3)
    assert offset.max() < 1e-3


def test_offset_is_the_distance_to_the_line_and_chainage_is_kept():
    g = RouteGeometry.from_latlon(BENT)
    c = np.array([100.0, 300.0, 700.0, 1000.0])
    lat, lon = g.position(c)
    i = np.searchsorted(g.vertex_chainage_m, c) - 1
    az, _, _ = WGS84.inv(lon, lat, g.lon[i + 1], g.lat[i + 1])  # the geodesic's azimuth at each point
    for side in (+90.0, -90.0):
        lon2, lat2, _ = WGS84.fwd(lon, lat, az + side, np.full(len(c), 12.0))
        back, offset = g.locate(lat2, lon2)
        # The local azimuthal equidistant frame keeps scale to parts per million within a km of its
        # centre: 12 m comes back to within a millimetre, chainage likewise.
        np.testing.assert_allclose(offset, 12.0, atol=1e-3)
        np.testing.assert_allclose(back, c, atol=1e-3)


def test_repeated_vertices_are_dropped_and_bad_lines_refused():
    g = RouteGeometry.from_latlon([[53.3, -6.22], [53.3, -6.22], [53.305, -6.22]])
    assert len(g.lat) == 2
    for bad, words in (([[53.3, -6.22]], "two distinct"), ([[1, 2, 3]], "pairs"), ([[91, 0], [0, 0]], "latitude"),
                       ([[0, 0], [0, 181]], "longitude"), ([[0, 0], [math.nan, 0]], "finite"), ("x", "pairs")):
        with pytest.raises(GeometryError, match=words):
            RouteGeometry.from_latlon(bad)


def test_geojson_files(tmp_path):
    line = {"type": "LineString", "coordinates": [[-6.22, 53.30], [-6.22, 53.305]]}
    for doc in (line, {"type": "Feature", "geometry": line, "properties": {}},
                {"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": line}]}):
        (tmp_path / "r.geojson").write_text(json.dumps(doc))
        g = read_geojson_line(tmp_path / "r.geojson")
        assert g.lat.tolist() == [53.30, 53.305] and g.lon.tolist() == [-6.22, -6.22]  # [lon, lat] order read
    for text, words in (("{", "not JSON"), (json.dumps({"type": "Point", "coordinates": [0, 0]}), "LineString"),
                        (json.dumps({"type": "FeatureCollection", "features": []}), "exactly one")):
        (tmp_path / "bad.geojson").write_text(text)
        with pytest.raises(GeometryError, match=words):
            read_geojson_line(tmp_path / "bad.geojson")
    with pytest.raises(GeometryError, match="does not exist"):
        read_geojson_line(tmp_path / "none.geojson")


def test_registry_geometry_inline_and_file_round_trip(tmp_path):
    g = RouteGeometry.from_latlon(BENT)
    start_lat, start_lon = g.position(500.0)
    doc = {"route": [{"id": "R1", "geometry": BENT}],
           "bridge": [dict(BRIDGE, start_lat=float(start_lat[0]), start_lon=float(start_lon[0]))]}
    site = parse_site(doc, "<site>")
    assert site.routes[0].length_m == g.length_m  # length_m omitted: the geodesic length
    assert site.bridges[0].start_chainage_m == pytest.approx(500.0, abs=1e-3)
    dump_site(site, tmp_path / "site.toml")
    assert load_site(tmp_path / "site.toml") == site
    (tmp_path / "R1.geojson").write_text(json.dumps(
        {"type": "LineString", "coordinates": [[lon, lat] for lat, lon in BENT]}))
    (tmp_path / "file.toml").write_text('[[route]]\nid = "R1"\ngeometry_file = "R1.geojson"\n')
    assert load_site(tmp_path / "file.toml").routes[0].geometry == g  # relative to the registry


def test_old_registries_are_unchanged(tmp_path):
    (tmp_path / "s.toml").write_text('[[route]]\nid = "R1"\nlength_m = 240.0\n')
    site = load_site(tmp_path / "s.toml")
    assert site.routes[0].geometry is None and site.routes[0].length_m == 240.0


@pytest.mark.parametrize("text, key, words", [
    ('[[route]]\nid = "R1"\ngeometry = [[53.3, -6.22]]\n', "route[0].geometry", "two distinct"),
    ('[[route]]\nid = "R1"\ngeometry_file = "none.geojson"\n', "route[0].geometry_file", "does not exist"),
    ('[[route]]\nid = "R1"\ngeometry = [[53.3, -6.22], [53.305, -6.22]]\ngeometry_file = "x"\n',
     "route[0].geometry", "not both"),
    ('[[route]]\nid = "R1"\nlength_m = 600.0\ngeometry = [[53.3, -6.22], [53.305, -6.22]]\n',
     "route[0].length_m", "disagrees"),
    ('[[route]]\nid = "R1"\nlength_m = 600.0\n', "bridge[0].start_lat", "needs a route with geometry"),
    ('[[route]]\nid = "R1"\ngeometry = [[53.3, -6.22], [53.305, -6.22]]\n', "bridge[0].start_lat", "m from route"),
])
def test_bad_geometry_is_one_line_naming_the_key(tmp_path, text, key, words):
    if "bridge" in key:
        text += '\n[[bridge]]\n' + "\n".join(f"{k} = {json.dumps(v)}" for k, v in BRIDGE.items())
        text += "\nstart_lat = 53.302\nstart_lon = -6.21\n"  # ~670 m east of the line
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises(RegistryError) as err:
        load_site(tmp_path / "s.toml")
    assert err.value.key == key and words in err.value.problem and "\n" not in str(err.value)


def test_export_coordinates_follow_the_route():
    site = parse_site({"route": [{"id": "R1", "geometry": BENT}, {"id": "R2", "length_m": 100.0}],
                       "bridge": [dict(BRIDGE, start_chainage_m=500.0)]})
    rough = pa.table({"route_id": ["R1", "R1", "R2"], "start_m": [0.0, 500.0, 0.0], "end_m": [500.0, 1000.0, 100.0],
                      "length_m": [500.0, 500.0, 100.0], "iri_m_per_km": [1.0, 2.0, 3.0],
                      "iri_lo95": [0.9, 1.8, 2.5], "iri_hi95": [1.1, 2.2, 3.5]})
    out = roughness_with_coordinates(rough, site)
    g = site.routes[0].geometry
    lat, lon = g.position([500.0, 1000.0])
    assert out.column("end_lat").to_pylist()[:2] == pytest.approx(lat.tolist(), abs=1e-12)
    assert out.column("end_lon").to_pylist()[:2] == pytest.approx(lon.tolist(), abs=1e-12)
    assert out.column("start_lat").to_pylist()[2] is None  # R2 has no geometry: null, not 0
    doc = roughness_geojson(out, site)
    assert [f["properties"]["route_id"] for f in doc["features"]] == ["R1", "R1"]
    first = doc["features"][0]["geometry"]["coordinates"]
    # [lon, lat], through the bend at the second vertex (chainage 556 m lies beyond 500 m: not in it),
    # the second segment holds the vertex at 556 m.
    assert first[0] == [-6.22, 53.3] and len(first) == 2 and len(doc["features"][1]["geometry"]["coordinates"]) == 3
    summary = pa.table({"bridge_id": ["B1"], "n_passes": [3]})
    mid_lat, mid_lon = g.position(510.0)
    with_pos = bridges_with_coordinates(summary, site)
    assert with_pos.column("lat").to_pylist() == pytest.approx(mid_lat.tolist(), abs=1e-12)
    assert with_pos.column("lon").to_pylist() == pytest.approx(mid_lon.tolist(), abs=1e-12)
    plain = parse_site({"route": [{"id": "R1", "length_m": 100.0}]})
    assert roughness_with_coordinates(rough, plain) is rough and roughness_geojson(rough, plain) is None


def test_a_run_on_a_registry_with_geometry_exports_coordinates(tmp_path):
    """A simulated road whose registry gains a geometry of the same length: the run's export carries
    the coordinates and roughness.geojson, and the estimates are those of the run without geometry."""
    sim = tmp_path / "sim"
    generate(SCENARIOS["road-qc"], sim, seed=3, passes=3, vehicles=3)
    plain = load_site(sim / "site.toml")
    length = plain.routes[0].length_m
    # A straight line due north of exactly the route's length (Geod.fwd: the geodesic end point).
    lon1, lat1, _ = WGS84.fwd(-6.22, 53.30, 0.0, length)
    geo = dataclasses.replace(plain, routes=(dataclasses.replace(
        plain.routes[0], geometry=RouteGeometry.from_latlon([[53.30, -6.22], [lat1, lon1]])),))
    logs = [read_drive_log(p) for p in list_drive_logs(sim / "logs")]
    run_in_process(logs, plain, tmp_path / "plain")
    run_in_process(logs, geo, tmp_path / "geo")
    a, b = pq.read_table(tmp_path / "plain" / "roughness.parquet"), pq.read_table(tmp_path / "geo" / "roughness.parquet")
    assert "start_lat" not in a.column_names
    assert b.select(a.column_names).equals(a)  # geometry adds columns, changes no estimate
    lat = np.array(b.column("end_lat").to_pylist())
    assert np.all(np.diff(lat[b.column("length_m").to_numpy() == 100.0]) > 0)  # northwards along chainage
    doc = json.loads((tmp_path / "geo" / "roughness.geojson").read_text())
    assert len(doc["features"]) == b.num_rows
