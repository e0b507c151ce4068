"""Every panel of the recording's blueprint has data at the end of a run (edge + cloud in process, real .rrd).

The blueprint is read back from the recording itself (the last blueprint store, the one in effect
at the end): every view reachable from the viewport, its origin and its content queries, resolved
against the recording's entities as the viewer resolves them. A view none of whose entities has
data, or an entity a view names explicitly without data, fails the test.
"""

from __future__ import annotations

import dataclasses
import uuid
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from rerun.chunk import RrdReader

from cloud.view import BRIDGE_STATES, View
from shared.drivelog import list_drive_logs, read_drive_log
from shared.geo import RouteGeometry
from shared.registry import Site, load_site
from simfleet.harness import Harness
from simfleet.network import local_to_latlon
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

PASSES = 4  # the bridge estimates from its third pass (BridgeSettings.min_passes), calibration from the first round


@dataclasses.dataclass
class Blueprint:
    views: dict[str, tuple[str, str, list[str]]]  # view id → (name, origin, queries)
    timeline: str | None


def read_blueprint(path: Path) -> Blueprint:
    """The last blueprint store of ``path``: the views reachable from its viewport and its time panel."""
    reader = RrdReader(path)
    # Every blueprint sent makes a store with a random id, and the reader lists stores in no order of
    # sending; the file does hold them in that order, each store's id first written where it starts.
    data = Path(path).read_bytes()
    store = max(reader.blueprints(), key=lambda st: data.find(st.recording_id.encode()))
    latest: dict[tuple[str, str], object] = {}
    for chunk in reader.stream(store=store):
        rb = chunk.to_record_batch()
        for name in rb.schema.names:
            if ":" not in name or name.startswith("rerun.controls"):
                continue
            values = [v for v in rb.column(name).to_pylist() if v is not None]
            if values:
                latest[(chunk.entity_path.strip("/"), name)] = values[-1]
    (root,) = latest[("viewport", "ViewportBlueprint:root_container")]  # a UUID as 16 bytes
    root = uuid.UUID(bytes=bytes(root))
    views, todo = {}, [f"container/{root}"]
    while todo:
        node = todo.pop()
        if node.startswith("view/"):
            vid = node
            origin = latest[(vid, "ViewBlueprint:space_origin")][0]
            name = latest.get((vid, "ViewBlueprint:display_name"), [vid])[0]
            queries = latest.get((f"{vid}/ViewContents", "ViewContents:query"), ["$origin/**"])
            views[vid] = (name, origin, list(queries))
        else:
            todo += [c.strip("/") for c in latest.get((node, "ContainerBlueprint:contents"), [])]
    timeline = latest.get(("time_panel", "TimePanelBlueprint:timeline"))
    return Blueprint(views, timeline[0] if isinstance(timeline, list) else timeline)


def entities_with_data(path: Path) -> set[str]:
    """Entities of the recording with at least one row of a logged component (static or temporal)."""
    has = defaultdict(int)
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        if any(":" in n and not n.startswith("rerun.controls") for n in rb.schema.names):
            has[chunk.entity_path.strip("/")] += chunk.num_rows
    return {e for e, n in has.items() if n}


def resolve(origin: str, queries: list[str], entities: set[str]) -> tuple[set[str], list[str]]:
    """The entities a view shows (Rerun's query rules: ``$origin``, ``/**`` subtrees, ``- `` exclusions)
    and the queries naming one entity exactly."""
    def matches(expr: str, e: str) -> bool:
        if expr.endswith("/**"):
            base = expr[:-3]
            return e == base or e.startswith(base + "/")
        return e == expr

    shown, exact = set(), []
    rules = [(q[:2] != "- ", q[2:] if q[:2] in ("- ", "+ ") else q) for q in queries]
    rules = [(inc, expr.replace("$origin", origin).strip("/")) for inc, expr in rules]
    for inc, expr in rules:
        if inc and not expr.endswith("/**"):
            exact.append(expr)
    for e in entities:
        included = [inc for inc, expr in rules if matches(expr, e)]
        if included and included[-1] and not any(not inc and matches(expr, e) for inc, expr in rules):
            shown.add(e)
    return shown, exact


def with_geometry(site: Site) -> Site:
    """The site with each route given a line: eastwards from a point in the Netherlands, its
    geodesic length the route's (a registry with geometry, as interfaces.md §5 grows it)."""
    routes = []
    for k, r in enumerate(site.routes):
        east = np.linspace(0.0, r.length_m, 11)
        lat, lon = local_to_latlon(east, np.full(east.size, 200.0 * k))
        routes.append(dataclasses.replace(r, geometry=RouteGeometry.from_latlon(np.column_stack([lat, lon]))))
    return dataclasses.replace(site, routes=tuple(routes))


def _record(sim: Path, tmp: Path, geometry: bool) -> Path:
    """A bridge run (smooth deck: the damage hypotheses and the alarm decision are on) through the
    harness with fleet calibration, the view logging to a real .rrd; ``geometry``: the registry
    has route lines (the map panel)."""
    site = load_site(sim / "site.toml")
    if geometry:
        site = with_geometry(site)
    h = Harness(site)
    rrd = tmp / "run.rrd"
    h.cloud.view = View(rrd, routes={r.id: r.length_m for r in site.routes}, bridges=list(site.bridges),
                        geometry={r.id: r.geometry for r in site.routes})
    for path in list_drive_logs(sim / "logs"):
        h.replay([read_drive_log(path)])
    h.settle()
    h.cloud.export(tmp / "export")  # every pass in the bridge's estimate, as at the end of a run
    h.cloud.view.close()
    return rrd


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """The drive logs both recordings are made from (read only)."""
    out = tmp_path_factory.mktemp("sim")
    generate(SCENARIOS["bridge-crack10-10m"], out, seed=3, passes=PASSES, vehicles=PASSES, workers=1, progress=False)
    return out


@pytest.fixture(scope="module")
def recording(sim, tmp_path_factory) -> Path:
    return _record(sim, tmp_path_factory.mktemp("panels"), geometry=False)


@pytest.fixture(scope="module")
def recording_with_map(sim, tmp_path_factory) -> Path:
    return _record(sim, tmp_path_factory.mktemp("panels_map"), geometry=True)


def test_every_panel_has_data_at_the_end(recording):
    assert_every_panel_has_data(recording)
    names = " ".join(n for n, _, _ in read_blueprint(recording).views.values())
    assert "map" not in names  # a registry without geometry has no map


def test_with_geometry_the_map_has_data_too(recording_with_map):
    assert_every_panel_has_data(recording_with_map)
    bp = read_blueprint(recording_with_map)
    (origin,) = [o for n, o, _ in bp.views.values() if n.startswith("map")]
    entities = entities_with_data(recording_with_map)
    shown, _ = resolve(origin, ["$origin/**"], entities)
    assert {"map/routes/R1/line", "map/routes/R1/iri_100m"} <= shown
    bridges = [e for e in shown if e.startswith("map/bridges/")]
    assert bridges
    # Every bridge ends estimated with the alarm decided (smooth deck): green or red, not grey or orange.
    for e in bridges:
        colour = last_value(recording_with_map, e, "GeoPoints:colors")
        assert colour in (_rgba(BRIDGE_STATES["ok"]), _rgba(BRIDGE_STATES["alarm"])), (e, colour)
    # The route's stretches are coloured by IRI class: the last row has one colour per 100 m segment.
    strips = last_value(recording_with_map, "map/routes/R1/iri_100m", "GeoLineStrings:line_strings")
    assert strips is not None and len(strips) >= 1


def _rgba(rgb) -> int:
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def last_value(path: Path, entity: str, column: str):
    """The last temporal value of ``column`` logged to ``entity`` (its first instance for colours)."""
    out = None
    for chunk in RrdReader(path).stream():
        if chunk.entity_path.strip("/") != entity or chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        if column in rb.schema.names:
            values = [v for v in rb.column(column).to_pylist() if v is not None]
            if values:
                out = values[-1]
    if column.endswith(":colors") and out is not None:
        return out[0]
    return out


def assert_every_panel_has_data(recording: Path) -> None:
    bp = read_blueprint(recording)
    entities = entities_with_data(recording)
    assert bp.timeline == "pass"
    assert len(bp.views) >= 12, f"expected the road, bridge and fleet panels, got {len(bp.views)} views"
    empty = []
    for name, origin, queries in bp.views.values():
        shown, exact = resolve(origin, queries, entities)
        missing = [e for e in exact if e not in entities]
        if not shown or missing:
            empty.append(f"{name!r} (origin {origin}, queries {queries}): missing {missing or 'everything'}")
    assert not empty, "panels without data:\n" + "\n".join(empty)
    # The panels the issue named as empty before are among those checked.
    names = " ".join(n for n, _, _ in bp.views.values())
    for panel in ("IRI per 100 m", "IRI per 10 m", "calibration round", "EI / design", "alarm", "spill"):
        assert panel in names


def test_resolve_follows_rerun_query_rules():
    ents = {"stats/passes", "stats/accepted", "stats/rejected/total", "profile/R1/mean", "profile/R1/axes/grid"}
    shown, exact = resolve("stats", ["stats/**", "- stats/passes"], ents)
    assert shown == {"stats/accepted", "stats/rejected/total"} and exact == []
    shown, exact = resolve("profile/R1", ["$origin/axes/**", "$origin/mean", "$origin/band"], ents)
    assert shown == {"profile/R1/mean", "profile/R1/axes/grid"} and exact == ["profile/R1/mean", "profile/R1/band"]


def test_an_unlogged_panel_is_caught(tmp_path):
    """A view whose entities were never logged is reported: the check can fail."""
    rrd = tmp_path / "partial.rrd"
    with View(rrd, routes={"R1": 100.0}, bridges=["B1"]) as view:
        view.set_pass(1)
        x = np.arange(0.0, 100.0, 0.5)
        view.log_profile(_Snap("R1", x, 0.001 * np.sin(x), 0.001 * np.sin(x) - 0.002, 0.001 * np.sin(x) + 0.002))
    bp = read_blueprint(rrd)
    entities = entities_with_data(rrd)
    empty = {origin for _, origin, q in bp.views.values() if not resolve(origin, q, entities)[0]}
    assert "profile/R1" not in empty
    assert {"bridge/B1/span", "bridge/B1/damage", "profile/R1/iri_100m", "fleet/status"} <= empty


@dataclasses.dataclass
class _Snap:
    route_id: str
    chainage_m: np.ndarray
    elevation_m: np.ndarray
    lo95_m: np.ndarray
    hi95_m: np.ndarray
