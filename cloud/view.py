"""The cloud's Rerun view: current estimates logged to an explicit recording stream, one default blueprint.

The blueprint opens on the ``pass`` timeline (completed passes so far, set with `View.set_pass`);
every temporal row also carries ``wall_time``. One ``log_<thing>()`` per group of entities; entity
paths are keys::

    profile/<route>/mean, band, band_fill   the profile (mm) against chainage (m) and its 95 % band
    profile/<route>/bridges                 the route's bridges, marked between their supports
    profile/<route>/axes/...                gridlines, tick labels and titles of that chart
    profile/<route>/iri_<L>m/<class>        BarChart: IRI (m/km) per L = 10, 100 m, one entity per condition class
    profile/<route>/passes_per_tile         BarChart: passes per tile against tile-centre chainage (m)
    fleet/calibration/<param>/...           each vehicle's calibrated value and 95 % interval per round
    fleet/status                            TextDocument: per-vehicle status
    stats/<key>, stats/rejected/<reason>    Scalars: aggregator counters, grouped by scale in the blueprint
    bridge/<bridge>/span/...                stiffness ratio per element along the span with 95 % whiskers
    bridge/<bridge>/damage                  Scalars: P(damage) (%), the alarm threshold (%), the alarm (0/100)
    bridge/<bridge>/indicators              Scalars: D1 and D2 (%, eq. 3.24)
    bridge/<bridge>/mril/...                the fleet's MR-IL (mm/MN, drawn downwards) and its baseline
    bridge/<bridge>/summary, alarms         TextDocument (the assessment), TextLog (decisions and alarms)
    rail/<route>/track_quality/...          EN 13848 D1 level against chainage, sd per 200 m bars, table
    rail/<vehicle>/runs                     TextDocument, a carriage's run estimates with 95 % intervals
    map/routes/<route>/line                 GeoLineStrings: the route's line (registries with geometry only)
    map/routes/<route>/iri_100m             GeoLineStrings: one stretch per 100 m segment, coloured by IRI class
    map/bridges/<bridge>                    GeoPoints: the bridge at mid-span, coloured by its state

**Charts of one quantity against another** (profile against chainage, stiffness along the span,
MR-IL, track level) are 2D views of a `cloud.chart.Frame`. Rerun's time-series plots have real
axes but plot against a *timeline*: a profile logged at every pass on a ``chainage`` timeline
would draw every pass's profile over the others, and the view would need the whole viewer off the
``pass`` timeline. A 2D view keeps the current pass's curve alone, but has no axes, one scale for
x and y and y pointing down; so each chart maps its data rectangle (e.g. chainage m × elevation
mm, sized to the data at that pass) onto a fixed screen box that the blueprint's visual bounds
frame, and draws its own gridlines and labelled ticks. A reader of the recording gets data
coordinates back with the frame logged beside it (``axes/frame``: x_lo, x_hi, y_lo, y_hi, width,
height as Scalars). Bars against chainage (IRI, passes per tile) are Rerun bar charts with an
abscissa; quantities over passes (calibration, P(damage), counters) are time series on ``pass``.

Rerun is imported at module top: only the cloud node imports this module, and it does so lazily.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from cloud.chart import Frame
from cloud.coordinates import segment_line

log = logging.getLogger(__name__)

APPLICATION_ID = "driveby"
MAX_STRIP_POINTS = 4000  # per profile curve sent to the viewer
MAX_FILL_LINES = 800  # vertical strokes that shade a band: about one per screen pixel of a wide panel
DEFAULT_VIEWER_PORT = 9876

# Screen boxes (screen units) of the 2D charts: their aspect is that of the panel they are drawn in,
# so the chart fills it; the margins hold the tick labels and titles.
PROFILE_BOX = (1000.0, 115.0)
SPAN_BOX = (600.0, 300.0)
MRIL_BOX = (600.0, 300.0)
CAL_BOX = (500.0, 250.0)
TRACK_BOX = (1000.0, 200.0)
LABEL_GAP = 0.035  # of the box's height: tick labels sit this far outside it

MEAN_COLOUR = (70, 160, 255)
BAND_COLOUR = (120, 150, 200)
FILL_COLOUR = (120, 160, 230, 70)
GRID_COLOUR = (128, 128, 128, 90)
AXIS_COLOUR = (150, 150, 150)
LABEL_COLOUR = (200, 200, 200)
BRIDGE_COLOUR = (235, 150, 60)
TILE_COLOUR = (110, 190, 130)
DESIGN_COLOUR = (90, 190, 110)
THRESHOLD_COLOUR = (235, 80, 70)
MRIL_COLOUR = (70, 160, 255)
BASELINE_COLOUR = (150, 150, 170)
MRIL_MM_PER_MN = 1e9  # J (m/N) → mm/MN
MEAN_RADIUS = rr.Radius.ui_points(1.5)
BAND_RADIUS = rr.Radius.ui_points(0.75)
GRID_RADIUS = rr.Radius.ui_points(0.5)
FILL_RADIUS = rr.Radius.ui_points(1.0)
LABEL_RADIUS = rr.Radius.ui_points(0.01)

# IRI condition classes (m/km) after FHWA's pavement ride quality ranges (FHWA, "Status of the
# Nation's Highways, Bridges, and Transit: Conditions and Performance", ride quality on the NHS):
# good below 95 in/mi (1.50 m/km), acceptable up to 170 in/mi (2.68 m/km, quoted as 2.7), poor above.
IRI_CLASSES = (("good", 0.0, 1.5, (80, 190, 110)),
               ("acceptable", 1.5, 2.7, (235, 185, 60)),
               ("poor", 2.7, float("inf"), (230, 80, 70)))
IRI_LENGTHS_M = (100.0, 10.0)
MAP_IRI_LENGTH_M = 100.0  # the map colours the routes by the IRI per this length
MAP_ROUTE_COLOUR = (150, 150, 150)  # a route's line where no IRI is known yet
MAP_LINE_RADIUS = rr.Radius.ui_points(2.0)
MAP_IRI_RADIUS = rr.Radius.ui_points(4.0)  # wider than the route's line, which shows through gaps
MAP_BRIDGE_RADIUS = rr.Radius.ui_points(7.0)
# A bridge's state on the map: no estimate yet, estimated without a damage decision (rough deck:
# hypotheses off), no alarm, alarm.
BRIDGE_STATES = {"pending": (150, 150, 150), "undecided": (235, 150, 60), "ok": (80, 190, 110),
                 "alarm": (230, 80, 70)}
CALIBRATION_UNITS = {"K/M": "1/s²", "k/M": "1/s²", "C/M": "1/s", "c/M": "1/s", "m/M": "–"}  # quarter-car ratios

DAMAGE_SERIES = (("P(damage) %", (235, 80, 70), 2.0), ("alarm threshold %", (80, 80, 80), 1.5),
                 ("alarm (100 = raised)", (250, 200, 60), 3.0))
INDICATOR_SERIES = (("D1 %", (70, 160, 255)), ("D2 %", (160, 120, 255)))
STATS_COLOURS = {
    "accepted": (80, 200, 120),
    "passes_complete": (70, 160, 255),
    "passes": (160, 120, 255),
    "segments_held": (200, 200, 200),
    "rejected/total": (235, 80, 70),
    "spill_bytes": (200, 160, 80),
}
# Counters grouped by scale: a pass count (tens) beside a segment count (thousands) or the spill
# file's bytes (hundreds of thousands) would be a flat line at zero.
PASS_STATS = ("passes", "passes_complete", "foreign_passes")
BYTE_STATS = ("spill_bytes",)
REJECT_COLOUR = (240, 160, 60)
OTHER_COLOUR = (170, 170, 170)
TEXT_LOG_LEVELS = ("TRACE", "DEBUG", "INFO", "WARN", "ERROR", "CRITICAL")


# -- paths and the blueprint --------------------------------------------------------------------------
def _part(name: str) -> str:
    return rr.escape_entity_path_part(str(name))


def profile_path(route_id: str) -> str:
    """Entity path of a route's profile group, ``profile/<route>``."""
    return f"profile/{_part(route_id)}"


def bridge_path(bridge_id: str) -> str:
    """Entity path of a bridge's group, ``bridge/<bridge>``."""
    return f"bridge/{_part(bridge_id)}"


def calibration_path(param: str) -> str:
    """Entity of one calibrated quantity (e.g. ``K/M``) across the fleet."""
    return f"fleet/calibration/{_part(param.replace('/', '_over_'))}"


def _bridge_id(bridge: Any) -> str:
    """A bridge given as an id or as a registry `Bridge` (anything with ``.id``)."""
    return str(getattr(bridge, "id", bridge))


def map_route_path(route_id: str) -> str:
    """Entity path of a route's lines on the map, ``map/routes/<route>``."""
    return f"map/routes/{_part(route_id)}"


def map_bridge_path(bridge_id: str) -> str:
    """Entity path of a bridge's point on the map, ``map/bridges/<bridge>``."""
    return f"map/bridges/{_part(bridge_id)}"


def bridge_state(estimate: Any) -> str:
    """A bridge's state on the map (`BRIDGE_STATES`) from its latest estimate (None: no estimate)."""
    if estimate is None:
        return "pending"
    a = estimate.assessment
    return "undecided" if a is None else "alarm" if a.alarm else "ok"


def rail_path(name: str) -> str:
    """Entity path of a rail route's or carriage's group, ``rail/<name>``."""
    return f"rail/{_part(name)}"


def iri_class(iri_m_per_km: float) -> str:
    """The condition class (`IRI_CLASSES`) of an IRI in m/km; NaN has none ("")."""
    for name, lo, hi, _ in IRI_CLASSES:
        if lo <= iri_m_per_km < hi:
            return name
    return ""


def _chart_bounds(box: tuple[float, float]) -> rrb.VisualBounds2D:
    """The screen box with room for the tick labels (left, below) and the titles (above)."""
    w, h = box
    return rrb.VisualBounds2D(x_range=[-0.075 * w, 1.02 * w], y_range=[-0.16 * h, 1.17 * h])


def _stats_view(name: str, keys: Sequence[str] | None, exclude: Sequence[str] = ()) -> rrb.TimeSeriesView:
    contents = [f"stats/{k}" for k in keys] if keys is not None else ["stats/**"] + [f"- stats/{k}" for k in exclude]
    return rrb.TimeSeriesView(origin="stats", contents=contents, name=name)


def blueprint(routes: Mapping[str, float], bridges: Iterable[Any] = (),
              calibration_params: Sequence[str] = (), rail_routes: Sequence[str] = (),
              rail_vehicles: Sequence[str] = (), run_names: Sequence[str] = (), with_map: bool = False
              ) -> rrb.Blueprint:
    """The one default layout, opened on the ``pass`` timeline: road (with the map), bridges, fleet, rail.

    Parameters
    ----------
    routes : mapping route id → route length (m); each gets its profile chart, IRI per 100 m
        and per 10 m by condition class, and passes per tile.
    bridges : bridge ids or registry `Bridge` objects; each gets its stiffness along the span,
        P(damage) with the alarm over passes, D1/D2, the MR-IL, the assessment and the alarm log.
    calibration_params : the fleet-calibrated quantities, one convergence plot each.
    rail_routes, rail_vehicles, run_names : per rail route its track quality; per carriage its runs.
    with_map : a map of the routes coloured by IRI class and the bridges by state, beside the road
        panels (only when the registry has route geometry).
    """
    rows: list = []
    shares: list[float] = []
    bridges = list(bridges)
    bridge_routes = {getattr(b, "route", None) for b in bridges}
    road = [_road_view(rid, rid in bridge_routes) for rid in routes]
    if road:
        road_row = rrb.Tabs(*road, name="road") if len(road) > 1 else road[0]
        if with_map:
            road_row = rrb.Horizontal(road_row, _map_view(), column_shares=[3, 2])
        rows.append(road_row)
        shares.append(5.0)
    bridge_views = [_bridge_view(b) for b in bridges]
    if bridge_views:
        rows.append(rrb.Tabs(*bridge_views, name="bridges") if len(bridge_views) > 1 else bridge_views[0])
        shares.append(4.0)
    fleet = []
    if calibration_params:
        fleet.append(rrb.Grid(*[rrb.Spatial2DView(origin=calibration_path(p), contents=["$origin/**"],
                                                  visual_bounds=_chart_bounds(CAL_BOX),
                                                  name=f"{p} of each vehicle against calibration round, 95 %")
                                for p in calibration_params], grid_columns=len(calibration_params),
                              name="calibration"))
    fleet.append(rrb.Horizontal(
        _stats_view("passes", PASS_STATS),
        _stats_view("segments", None, PASS_STATS + BYTE_STATS),
        _stats_view("spill file (bytes)", BYTE_STATS),
        rrb.TextDocumentView(origin="fleet/status", name="vehicles"),
        column_shares=[1, 1, 1, 2], name="aggregator"))
    rows.append(rrb.Tabs(*fleet, name="fleet"))
    shares.append(3.0)
    rail = _rail_tabs(rail_routes, rail_vehicles, run_names)
    if rail:
        rows.append(rrb.Tabs(*rail, name="rail"))
        shares.append(3.0)
    return rrb.Blueprint(
        rrb.Vertical(*rows, row_shares=shares),
        rrb.TimePanel(timeline="pass", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        auto_views=False)


def _road_view(rid: str, has_bridges: bool) -> rrb.Container:
    root = profile_path(rid)
    (good, _, g_hi, _), (fair, _, f_hi, _), (poor, _, _, _) = IRI_CLASSES
    classes = f"green {good} < {g_hi:g}, amber {fair} {g_hi:g}–{f_hi:g}, red {poor} > {f_hi:g}"
    no_legend = rrb.PlotLegend(visible=False)
    return rrb.Vertical(
        rrb.Spatial2DView(origin=root, contents=["$origin/axes/**", "$origin/band_fill", "$origin/band", "$origin/mean"]
                          + ["$origin/bridges"] * has_bridges,
                          name=f"{rid}: profile (mm) and its 95 % band against chainage (m)",
                          visual_bounds=_chart_bounds(PROFILE_BOX)),
        rrb.Horizontal(
            rrb.BarChartView(origin=f"{root}/iri_100m", name=f"IRI per 100 m (m/km): FHWA {classes}",
                             plot_legend=no_legend),
            rrb.BarChartView(origin=f"{root}/iri_10m", name="IRI per 10 m (m/km), classes as per 100 m",
                             plot_legend=no_legend),
            rrb.BarChartView(origin=f"{root}/passes_per_tile", name="passes per 50 m tile", plot_legend=no_legend),
            column_shares=[2, 2, 1]),
        row_shares=[3, 2], name=str(rid))


def _map_view() -> rrb.MapView:
    (good, _, g_hi, _), (fair, _, f_hi, _), (poor, _, _, _) = IRI_CLASSES
    return rrb.MapView(origin="map", name=f"map: IRI per {MAP_IRI_LENGTH_M:g} m (green {good} < {g_hi:g}, amber "
                       f"{fair}, red {poor} > {f_hi:g} m/km); bridges: grey no estimate, orange undecided, "
                       "green no alarm, red alarm", background=rrb.MapProvider.OpenStreetMap)


def _bridge_view(b: Any) -> rrb.Container:
    bid = _bridge_id(b)
    root = bridge_path(bid)
    return rrb.Horizontal(
        rrb.Spatial2DView(origin=f"{root}/span", contents=["$origin/**"], visual_bounds=_chart_bounds(SPAN_BOX),
                          name=f"{bid}: EI / design per element along the span (m), 95 %; "
                               "green design, red alarm loss"),
        rrb.Vertical(
            rrb.TimeSeriesView(origin=f"{root}/damage", name=f"{bid}: P(damage) and the alarm over passes (%)",
                               axis_y=rrb.ScalarAxis(range=[0.0, 105.0])),
            rrb.TimeSeriesView(origin=f"{root}/indicators", name=f"{bid}: D1, D2 stiffness loss (%)"),
            row_shares=[3, 2]),
        rrb.Tabs(
            rrb.TextDocumentView(origin=f"{root}/summary", name="assessment"),
            rrb.Spatial2DView(origin=f"{root}/mril", contents=["$origin/**"], visual_bounds=_chart_bounds(MRIL_BOX),
                              name="MR-IL (mm/MN, down) along the span (m)"),
            name=f"{bid}"),
        rrb.TextLogView(origin=f"{root}/alarms", name=f"{bid}: decisions and alarms",
                        columns=rrb.archetypes.TextLogColumns(text_log_columns=["loglevel", "body"])),
        column_shares=[4, 3, 3, 3], name=bid)


def _rail_tabs(routes: Sequence[str], vehicles: Sequence[str], run_names: Sequence[str]) -> list:
    tabs = []
    for route in routes:
        root = f"{rail_path(route)}/track_quality"
        tabs.append(rrb.Horizontal(
            rrb.Spatial2DView(origin=root, contents=["$origin/axes/**", "$origin/d1", "$origin/alert_limits"],
                              visual_bounds=_chart_bounds(TRACK_BOX),
                              name=f"{route}: EN 13848 D1 longitudinal level (mm) against chainage (m)"),
            rrb.BarChartView(origin=f"{root}/sd_200m", name=f"{route}: D1 sd per 200 m (mm)"),
            rrb.TextDocumentView(origin=f"{root}/table", name=f"{route}: D1 per 200 m"),
            column_shares=[3, 2, 2], name=f"{route} track"))
    for vid in vehicles:
        root = f"{rail_path(vid)}/runs"
        tabs.append(rrb.Horizontal(
            rrb.TextDocumentView(origin=root, name=f"{vid}: runs (95 %)"),
            *[rrb.Spatial2DView(origin=f"{root}/{_part(k)}", contents=["$origin/**"], name=f"{vid}: {k} per run")
              for k in run_names],
            name=f"{vid} runs"))
    return tabs


# -- array helpers (pure) -----------------------------------------------------------------------------
def _bin_reduce(y: np.ndarray, k: int, how: str) -> np.ndarray:
    """Reduce consecutive bins of ``k`` samples, ignoring NaN; a bin with no finite sample is NaN."""
    pad = (-y.size) % k
    yb = np.concatenate([y, np.full(pad, np.nan)]).reshape(-1, k)
    ok = np.isfinite(yb)
    has = ok.any(axis=1)
    if how == "mean":
        out = np.where(ok, yb, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    elif how == "min":
        out = np.where(ok, yb, np.inf).min(axis=1)
    else:
        out = np.where(ok, yb, -np.inf).max(axis=1)
    return np.where(has, out, np.nan)


def decimate_profile(x: np.ndarray, mean: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     max_points: int = MAX_STRIP_POINTS):
    """Bin a profile to at most ``max_points`` points: mean of x and of the mean, band as envelope.

    Binning (not striding) keeps short waves from aliasing, and the band stays conservative
    (lowest lower bound, highest upper bound in each bin). Returns ``(x, mean, lo, hi)``.
    """
    if max_points < 2:
        raise ValueError("decimate_profile: max_points must be at least 2")
    k = -(-x.size // max_points)
    if k <= 1:
        return x, mean, lo, hi
    return (_bin_reduce(x, k, "mean"), _bin_reduce(mean, k, "mean"),
            _bin_reduce(lo, k, "min"), _bin_reduce(hi, k, "max"))


def finite_runs(x: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
    """Split ``(x, y)`` at non-finite values into strips of (n, 2) points, each with n ≥ 2."""
    ok = np.isfinite(x) & np.isfinite(y)
    edges = np.flatnonzero(np.diff(np.concatenate([[False], ok, [False]]).astype(np.int8)))
    return [np.column_stack([x[a:b], y[a:b]]) for a, b in zip(edges[::2], edges[1::2]) if b - a >= 2]


def _flatten_stats(stats: Mapping[str, Any]) -> dict[str, float]:
    """Numbers as ``key``; a mapping of counters as ``key/<sub>`` plus ``key/total``."""
    out: dict[str, float] = {}
    for key, value in stats.items():
        if isinstance(value, Mapping):
            subs = {f"{key}/{sub}": float(v) for sub, v in value.items()
                    if isinstance(v, (int, float, np.number)) and not isinstance(v, bool)}
            out.update(subs)
            out[f"{key}/total"] = float(sum(subs.values()))
        elif isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
            out[str(key)] = float(value)
    return out


def _stats_path(flat_key: str) -> str:
    return "stats/" + "/".join(_part(p) for p in flat_key.split("/"))


def _markdown_cell(value: Any) -> str:
    return "–" if value is None or value == "" else str(value).replace("|", "\\|")


# -- the view -----------------------------------------------------------------------------------------
class View:
    """The cloud's live view: an explicit `rerun.RecordingStream`, never the global one.

    Parameters
    ----------
    rrd_path : save the recording to this .rrd file.
    spawn_viewer : start the viewer that ships with the wheel (needs a display) and stream to it.
    connect_url : stream to a running viewer, e.g. ``rerun+http://127.0.0.1:9876/proxy``.
    routes : route id → length (m), for the blueprint's road panels and the profile's x axis.
    bridges : bridge ids or registry `Bridge` objects, for the blueprint's bridge panels (registry
        bridges are also marked on their route's profile).
    recording_id : defaults to a fresh UUID.
    clock : seconds since the epoch for the ``wall_time`` timeline (tests pass a fixed clock).
    calibration_params : calibrated quantities known up front; others join the blueprint when
        `log_calibration` first sees them.

    At least one output is required. Methods are thread-safe; calls after `close` are ignored.
    """

    def __init__(self, rrd_path: Path | str | None = None, spawn_viewer: bool = False,
                 connect_url: str | None = None, routes: Mapping[str, float] | None = None,
                 bridges: Sequence[Any] = (), *, recording_id: str | None = None,
                 clock: Callable[[], float] = time.time, viewer_port: int = DEFAULT_VIEWER_PORT,
                 calibration_params: Sequence[str] = (), geometry: Mapping[str, Any] | None = None):
        sinks: list = []
        if rrd_path is not None:
            Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd_path)))
        urls = []
        if spawn_viewer:
            rr.spawn(port=viewer_port, connect=False)
            urls.append(f"rerun+http://127.0.0.1:{viewer_port}/proxy")
        if connect_url and connect_url not in urls:
            urls.append(connect_url)
        sinks += [rr.GrpcSink(u) for u in urls]
        if not sinks:
            raise ValueError("View: no output; give rrd_path, spawn_viewer or connect_url")
        self._lock = threading.RLock()
        self._clock = clock
        self._pass = 0
        self._closed = False
        self._styled: dict[str, Any] = {}  # entity path → what its static style was made for
        self._routes = dict(routes or {})
        self._bridges = list(bridges)
        self._geometry = {rid: g for rid, g in (geometry or {}).items() if g is not None}
        self._calibration_params = tuple(calibration_params)
        self._calibration_rounds = 0
        self._calibration_history: dict[str, dict[str, list]] = {}  # param → vehicle → (round, mean, lo, hi)
        self._rail_layout: tuple = ((), (), ())  # (rail routes, carriages, run quantities) in the blueprint
        self._first_estimate_logged: set[str] = set()
        self.recording_id = recording_id or str(uuid.uuid4())
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=self.recording_id)
        # Exactly two timelines: `pass` and `wall_time` (log_time would duplicate wall_time).
        self._rec.set_log_time_enabled(False)
        self._rec.set_log_tick_enabled(False)
        self._rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        self._log_map_base()

    def _blueprint(self) -> rrb.Blueprint:
        return blueprint(self._routes, self._bridges, self._calibration_params, *self._rail_layout,
                         with_map=bool(self._geometry))

    # -- time ------------------------------------------------------------------------------------------
    @property
    def pass_count(self) -> int:
        """The current value of the ``pass`` timeline."""
        return self._pass

    def set_pass(self, n: int) -> None:
        """Set the ``pass`` timeline (completed passes so far) for the rows logged next."""
        n = int(n)
        if n < 0:
            raise ValueError(f"View.set_pass: n must be >= 0, got {n}")
        with self._lock:
            self._pass = n

    def _stamp(self) -> None:
        # Set on every call, under the lock: the stream's time is per thread, and callers may
        # log from zenoh's threads.
        self._rec.set_time("pass", sequence=self._pass)
        self._rec.set_time("wall_time", timestamp=float(self._clock()))

    def _style_once(self, path: str, key: Any, make: Callable[[], Any]) -> None:
        if self._styled.get(path) != key:
            self._rec.log(path, make(), static=True)
            self._styled[path] = key

    def _log_axes(self, root: str, frame: Frame, y_title: str) -> None:
        """A chart's gridlines, outline, labelled ticks and y title under ``<root>/axes``."""
        gap = LABEL_GAP * frame.height
        self._rec.log(f"{root}/axes/grid", rr.LineStrips2D(frame.gridlines(), radii=GRID_RADIUS, colors=GRID_COLOUR,
                                                           draw_order=-10.0))
        self._rec.log(f"{root}/axes/box", rr.LineStrips2D([frame.box()], radii=GRID_RADIUS, colors=AXIS_COLOUR,
                                                          draw_order=-9.0))
        for name, (pos, text) in (("x_ticks", frame.x_labels(gap)), ("y_ticks", frame.y_labels(3 * gap))):
            self._rec.log(f"{root}/axes/{name}", rr.Points2D(pos, labels=text, radii=LABEL_RADIUS, colors=LABEL_COLOUR,
                                                             show_labels=True))
        # The y axis's title above its ticks (a label is centred on its point: a long one starts
        # further in); the x axis's unit is in the view's name, where it is never clipped.
        title = np.array([[min(0.008 * frame.width * len(y_title), 0.4 * frame.width), -3.0 * gap]])
        self._rec.log(f"{root}/axes/titles", rr.Points2D(title, labels=[y_title], radii=LABEL_RADIUS,
                                                         colors=LABEL_COLOUR, show_labels=True))

    # -- map -------------------------------------------------------------------------------------------
    def _bridge_position(self, bridge: Any) -> tuple[float, float] | None:
        g = self._geometry.get(getattr(bridge, "route", None))
        if g is None or not hasattr(bridge, "start_chainage_m"):
            return None
        lat, lon = g.position(float(bridge.start_chainage_m) + 0.5 * float(bridge.span_m))
        return float(lat[0]), float(lon[0])

    def _log_map_base(self) -> None:
        """The routes' lines (static: the registry's, unchanging) and every bridge as yet unestimated."""
        with self._lock:
            for rid, g in self._geometry.items():
                lat, lon = segment_line(g, 0.0, g.length_m)
                self._rec.log(f"{map_route_path(rid)}/line", rr.GeoLineStrings(
                    lat_lon=[np.column_stack([lat, lon])], radii=MAP_LINE_RADIUS, colors=MAP_ROUTE_COLOUR),
                    static=True)
        for b in self._bridges:
            self.log_bridge_state(_bridge_id(b), None)

    def log_map_roughness(self, route_id: str, start_m: np.ndarray, end_m: np.ndarray, iri: np.ndarray) -> None:
        """Colour the route's line on the map by IRI class (`IRI_CLASSES`), one stretch per
        segment ``start_m``–``end_m`` (m); NaN IRI draws no stretch. Nothing without geometry."""
        g = self._geometry.get(route_id)
        if g is None:
            return
        start, end, iri = (np.asarray(a, dtype=float) for a in (start_m, end_m, iri))
        colour = {name: c for name, _, _, c in IRI_CLASSES}
        strips, colours = [], []
        for a, b, v in zip(start, end, iri):
            if np.isfinite(v) and b > a:
                lat, lon = segment_line(g, a, b)
                strips.append(np.column_stack([lat, lon]))
                colours.append(colour[iri_class(v)])
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{map_route_path(route_id)}/iri_{int(round(MAP_IRI_LENGTH_M))}m", rr.GeoLineStrings(
                lat_lon=strips, radii=MAP_IRI_RADIUS, colors=colours or None))

    def log_bridge_state(self, bridge_id: str, estimate: Any) -> None:
        """Place the bridge on the map coloured by its state (`bridge_state` of its latest estimate,
        None before the first); nothing when its route has no geometry."""
        b = next((b for b in self._bridges if _bridge_id(b) == bridge_id), None)
        at = None if b is None else self._bridge_position(b)
        if at is None:
            return
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(map_bridge_path(bridge_id), rr.GeoPoints(
                lat_lon=[at], radii=MAP_BRIDGE_RADIUS, colors=BRIDGE_STATES[bridge_state(estimate)]))

    # -- profile ---------------------------------------------------------------------------------------
    def log_profile(self, snapshot: Any) -> None:
        """Log one update of a route's profile: the mean and its 95 % band (mm) against chainage (m).

        ``snapshot`` is a `cloud.road.mean_profile.ProfileSnapshot` (or anything with
        ``route_id``, ``chainage_m``, ``elevation_m``, ``lo95_m``, ``hi95_m`` in metres). Curves are
        binned to at most `MAX_STRIP_POINTS` points and split at NaN gaps; the chart's elevation
        axis is sized to the band at this pass, its chainage axis to the route.
        """
        x = np.asarray(snapshot.chainage_m, dtype=float)
        cols = [np.asarray(a, dtype=float) * 1e3 for a in (snapshot.elevation_m, snapshot.lo95_m, snapshot.hi95_m)]
        if x.ndim != 1 or any(c.shape != x.shape for c in cols):
            raise ValueError("log_profile: chainage_m, elevation_m, lo95_m and hi95_m must be 1-D of one length")
        rid = snapshot.route_id
        length = float(self._routes.get(rid, x[-1] if x.size else 1.0))
        frame = Frame.fit((0.0, max(length, 1e-3)), _finite_range(cols[1], cols[2], cols[0]), *PROFILE_BOX)
        xd, mean, lo, hi = decimate_profile(x, *cols)
        mean_strips = [frame.points(s[:, 0], s[:, 1]) for s in finite_runs(xd, mean)]
        band_strips = [frame.points(s[:, 0], s[:, 1]) for s in finite_runs(xd, lo) + finite_runs(xd, hi)]
        xf, _, flo, fhi = decimate_profile(x, *cols, max_points=MAX_FILL_LINES)
        ok = np.isfinite(xf) & np.isfinite(flo) & np.isfinite(fhi)
        fill = np.stack([frame.points(xf[ok], flo[ok]), frame.points(xf[ok], fhi[ok])], axis=1)
        root = profile_path(rid)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._log_axes(root, frame, "elevation (mm)")
            self._log_route_bridges(root, rid, frame)
            self._rec.log(f"{root}/band_fill", rr.LineStrips2D(list(fill), radii=FILL_RADIUS, colors=FILL_COLOUR))
            self._rec.log(f"{root}/band", rr.LineStrips2D(band_strips, radii=BAND_RADIUS, colors=BAND_COLOUR))
            self._rec.log(f"{root}/mean", rr.LineStrips2D(mean_strips, radii=MEAN_RADIUS, colors=MEAN_COLOUR))

    def _log_route_bridges(self, root: str, route_id: str, frame: Frame) -> None:
        spans = [(_bridge_id(b), float(b.start_chainage_m), float(b.end_chainage_m)) for b in self._bridges
                 if getattr(b, "route", None) == route_id and hasattr(b, "start_chainage_m")]
        if not spans:
            return
        x0 = frame.sx([s[1] for s in spans])
        x1 = frame.sx([s[2] for s in spans])
        self._rec.log(f"{root}/bridges", rr.Boxes2D(
            mins=np.column_stack([x0, np.zeros(len(spans))]),
            sizes=np.column_stack([x1 - x0, np.full(len(spans), frame.height)]),
            labels=[f"bridge {bid}" for bid, _, _ in spans], colors=BRIDGE_COLOUR, radii=GRID_RADIUS,
            show_labels=True, draw_order=-5.0))

    def log_tile_counts(self, route_id: str, tile_m: float, counts: np.ndarray) -> None:
        """Log passes per tile of ``tile_m`` (m) as a bar chart against chainage (m), a bar across each tile.

        The whole array is one row (a BarChart tensor) at the current pass: a ``tile`` timeline
        would hide the other panels whenever it is the selected one.
        """
        counts = np.asarray(counts)
        if counts.ndim != 1 or not (tile_m > 0):
            raise ValueError("log_tile_counts: counts must be 1-D and tile_m positive")
        if counts.size and counts.min() < 0:
            raise ValueError("log_tile_counts: counts must be non-negative")
        lefts = (np.arange(counts.size) + 0.05) * float(tile_m)  # Rerun draws a bar from its abscissa
        chart = rr.BarChart(counts.astype(np.int64), abscissa=lefts,
                            widths=np.full(counts.size, 0.9 * float(tile_m), dtype=np.float32), color=TILE_COLOUR)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{profile_path(route_id)}/passes_per_tile", chart)

    def log_roughness(self, route_id: str, length_m: float, start_m: np.ndarray, iri: np.ndarray,
                      end_m: np.ndarray | None = None) -> None:
        """Log IRI (m/km) per ``length_m`` segment (10 or 100 m) as bars along the route, coloured by
        condition class (`IRI_CLASSES`): one bar chart entity per class, ``iri_<L>m/<class>``, each
        zero outside its class so that the bars of one segment never stack. ``end_m`` (default
        ``start_m + length_m``) bounds each bar; NaN IRI (not enough profile) is no bar."""
        start = np.asarray(start_m, dtype=float)
        iri = np.asarray(iri, dtype=float)
        end = start + float(length_m) if end_m is None else np.asarray(end_m, dtype=float)
        if start.shape != iri.shape or start.ndim != 1 or end.shape != start.shape:
            raise ValueError("log_roughness: start_m, end_m and iri must be 1-D of one length")
        # Rerun draws a bar from its abscissa to abscissa + width: a gap of 5 % each side.
        lefts, widths = start + 0.05 * (end - start), (0.9 * (end - start)).astype(np.float32)
        route_m = self._routes.get(route_id)
        ends = [] if route_m is None else [0.0, float(route_m)]
        # Zero-height bars at the route's ends: the chart's x range is the route.
        lefts = np.concatenate([lefts, ends])
        widths = np.concatenate([widths, np.full(len(ends), 1e-3, dtype=np.float32)])
        root = f"{profile_path(route_id)}/iri_{int(round(length_m))}m"
        charts = {}
        for name, lo, hi, colour in IRI_CLASSES:
            mine = np.isfinite(iri) & (iri >= lo) & (iri < hi)
            values = np.concatenate([np.where(mine, iri, 0.0), np.zeros(len(ends))])
            charts[name] = rr.BarChart(values, abscissa=lefts, widths=widths, color=colour)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            for name, chart in charts.items():
                self._rec.log(f"{root}/{name}", chart)
        if abs(float(length_m) - MAP_IRI_LENGTH_M) < 1e-9:
            self.log_map_roughness(route_id, start, end, iri)

    def log_calibration(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Log one calibration round: every vehicle's calibrated quantities with 95 % intervals.

        ``rows`` as in ``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95. Per quantity a
        chart of each vehicle's value (line) and interval (thin lines) against the round number,
        every round so far: rounds run when the bus is quiet, often many at one pass count, so
        the ``pass`` timeline could not show them converge. A quantity seen for the first time
        joins the blueprint.
        """
        by_param: dict[str, list[Mapping[str, Any]]] = {}
        for r in rows:
            by_param.setdefault(str(r["param"]), []).append(r)
        if not by_param:
            return
        with self._lock:
            if self._closed:
                return
            new = tuple(p for p in by_param if p not in self._calibration_params)
            if new:
                self._calibration_params += new
                self._rec.send_blueprint(self._blueprint())
            self._calibration_rounds += 1
            k = self._calibration_rounds
            self._stamp()
            for param, rs in by_param.items():
                history = self._calibration_history.setdefault(param, {})
                for r in rs:
                    history.setdefault(str(r["vehicle_id"]), []).append(
                        (k, float(r["mean"]), float(r["lo95"]), float(r["hi95"])))
                self._log_calibration_chart(param, history, k)

    def _log_calibration_chart(self, param: str, history: Mapping[str, list], rounds: int) -> None:
        ids = sorted(history)
        arr = {vid: np.asarray(history[vid], dtype=float) for vid in ids}
        frame = Frame.fit((1.0, float(max(rounds, 2))), _finite_range(*[a[:, 2:] for a in arr.values()]), *CAL_BOX,
                          x_ticks=6)
        root = calibration_path(param)
        colours = [_element_colour(i, len(ids)) for i in range(len(ids))]
        unit = CALIBRATION_UNITS.get(param)
        self._log_axes(root, frame, f"{param} ({unit})" if unit else param)
        means = [frame.points(arr[v][:, 0], arr[v][:, 1]) for v in ids]
        bands = [frame.points(arr[v][:, 0], arr[v][:, c]) for c in (2, 3) for v in ids]
        self._rec.log(f"{root}/band", rr.LineStrips2D(bands, radii=GRID_RADIUS,
                                                      colors=[(*c, 110) for c in colours] * 2))
        self._rec.log(f"{root}/mean", rr.LineStrips2D(means, radii=BAND_RADIUS, colors=colours,
                                                      labels=ids if len(ids) <= 8 else None))

    # -- fleet and aggregator --------------------------------------------------------------------------
    def log_vehicle_status(self, status: Mapping[str, Mapping[str, Any]]) -> None:
        """Log the fleet table: vehicle → passes, last_pass, calib_version, segments, rejected."""
        fields = ("passes", "last_pass", "calib_version", "segments", "rejected")
        lines = [f"**{len(status)} vehicles** at pass {self._pass}", "",
                 "| vehicle | passes | last pass | calibration | segments | rejected |",
                 "|---|---:|---|---:|---:|---:|"]
        for vid in sorted(status):
            row = status[vid]
            lines.append("| " + " | ".join([_markdown_cell(vid)] + [_markdown_cell(row.get(f)) for f in fields]) + " |")
        doc = rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log("fleet/status", doc)

    def log_stats(self, stats: Mapping[str, Any]) -> None:
        """Log the aggregator's counters at the current pass (``Aggregator.stats()`` as it is).

        Numbers go to ``stats/<key>``; a mapping such as ``rejected`` to ``stats/rejected/<reason>``
        and ``stats/rejected/total``. Other values are skipped.
        """
        with self._lock:
            self.log_stats_history([self._pass], [float(self._clock())], [stats])

    def log_stats_history(self, passes: Sequence[int], wall_time_s: Sequence[float],
                          history: Sequence[Mapping[str, Any]]) -> None:
        """Send a history of counters in one columnar call per series (e.g. replayed from a journal).

        Parameters
        ----------
        passes, wall_time_s : the ``pass`` value and wall time (s since the epoch) of each entry.
        history : one ``stats`` mapping per entry, as for `log_stats`. A key (or reason) absent
            from an entry leaves that row out of its series, exactly as entry-by-entry
            `log_stats` calls would: a series starts when its key first appears.
        """
        passes = np.asarray(passes, dtype=np.int64)
        times = np.asarray(wall_time_s, dtype=float)
        if not (passes.ndim == 1 and passes.shape == times.shape and len(history) == passes.size):
            raise ValueError("log_stats_history: passes, wall_time_s and history must have one length")
        flat = [_flatten_stats(s) for s in history]
        series: dict[str, tuple[list[int], list[float]]] = {}
        for i, f in enumerate(flat):
            for key, value in f.items():
                rows, values = series.setdefault(key, ([], []))
                rows.append(i)
                values.append(value)
        with self._lock:
            if self._closed:
                return
            for key, (rows, values) in sorted(series.items()):
                path = _stats_path(key)
                colour = STATS_COLOURS.get(key, REJECT_COLOUR if key.startswith("rejected/") else OTHER_COLOUR)
                self._style_once(path, key, lambda: rr.SeriesLines(names=[key], colors=[colour], widths=[2.0]))
                self._rec.send_columns(
                    path,
                    indexes=[rr.TimeColumn("pass", sequence=passes[rows]),
                             rr.TimeColumn("wall_time", timestamp=times[rows])],
                    columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))

    # -- bridges ---------------------------------------------------------------------------------------
    def log_bridge_stiffness(self, bridge_id: str, element_x_m: np.ndarray, ratio_mean: np.ndarray,
                             lo: np.ndarray, hi: np.ndarray, element_bounds_m: np.ndarray | None = None,
                             alarm_loss: float | None = None) -> None:
        """Log each element's stiffness ratio (EI / design EI) with its 95 % interval along the span
        at the current pass: a bar across the element at the mean, a whisker at its centre
        ``element_x_m`` (m from the first support), the design ratio 1 and, given ``alarm_loss``,
        the ratio ``1 − alarm_loss`` below which an element counts as damaged.

        ``element_bounds_m`` (n, 2) are the elements' ends; by default they meet halfway between
        the centres.
        """
        arrays = [np.asarray(a, dtype=float) for a in (element_x_m, ratio_mean, lo, hi)]
        x, mean, lo, hi = arrays
        if x.ndim != 1 or any(a.shape != x.shape for a in arrays) or x.size == 0:
            raise ValueError("log_bridge_stiffness: element_x_m, ratio_mean, lo and hi must be 1-D of one length")
        if element_bounds_m is None:
            half = 0.5 * (x[1] - x[0]) if x.size > 1 else 0.5, 0.5 * (x[-1] - x[-2]) if x.size > 1 else 0.5
            edges = np.concatenate([[x[0] - half[0]], 0.5 * (x[1:] + x[:-1]), [x[-1] + half[1]]])
            bounds = np.column_stack([edges[:-1], edges[1:]])
        else:
            bounds = np.asarray(element_bounds_m, dtype=float)
            if bounds.shape != (x.size, 2):
                raise ValueError("log_bridge_stiffness: element_bounds_m must be (n, 2)")
        refs = [1.0] + ([1.0 - float(alarm_loss)] if alarm_loss is not None else [])
        frame = Frame.fit((float(bounds.min()), float(bounds.max())), _finite_range(lo, hi, np.array(refs)),
                          *SPAN_BOX, y_pad=0.08)
        w = 0.25 * (bounds[:, 1] - bounds[:, 0])  # whisker caps: half the element's width
        bars = [frame.points(b, [m, m]) for b, m in zip(bounds, mean) if np.isfinite(m)]
        whiskers = []
        for xc, a, b, c in zip(x, lo, hi, w):
            if np.isfinite(a) and np.isfinite(b):
                whiskers += [frame.points([xc, xc], [a, b]), frame.points([xc - c, xc + c], [a, a]),
                             frame.points([xc - c, xc + c], [b, b])]
        span_x = [frame.x_lo, frame.x_hi]
        root = f"{bridge_path(bridge_id)}/span"
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._log_axes(root, frame, "EI / design EI")
            self._rec.log(f"{root}/design", rr.LineStrips2D([frame.points(span_x, [1.0, 1.0])], radii=BAND_RADIUS,
                                                            colors=DESIGN_COLOUR))
            if alarm_loss is not None:
                self._rec.log(f"{root}/threshold", rr.LineStrips2D(
                    [frame.points(span_x, [refs[1], refs[1]])], radii=BAND_RADIUS, colors=THRESHOLD_COLOUR))
            self._rec.log(f"{root}/whiskers", rr.LineStrips2D(whiskers, radii=BAND_RADIUS, colors=BAND_COLOUR))
            self._rec.log(f"{root}/mean", rr.LineStrips2D(bars, radii=rr.Radius.ui_points(2.5), colors=MEAN_COLOUR))

    def log_bridge_mril(self, bridge_id: str, x_m: np.ndarray, J_m_per_n: np.ndarray,
                        baseline_J_m_per_n: np.ndarray | None = None) -> None:
        """Log the fleet's MR-IL (deflection per unit load, m/N, on ``x_m`` from the first support)
        and, when given, the baseline it is compared with: a chart in mm/MN along the span."""
        x = np.asarray(x_m, dtype=float)
        curves = {"current": (J_m_per_n, MRIL_COLOUR, MEAN_RADIUS),
                  "baseline": (baseline_J_m_per_n, BASELINE_COLOUR, BAND_RADIUS)}
        mm = {}
        for name, (J, _, _) in curves.items():
            if J is None:
                continue
            J = np.asarray(J, dtype=float)
            if J.shape != x.shape or x.ndim != 1:
                raise ValueError("log_bridge_mril: x_m and the MR-ILs must be 1-D of one length")
            mm[name] = J * MRIL_MM_PER_MN
        if not x.size:
            return
        frame = Frame.fit((float(np.nanmin(x)), float(np.nanmax(x))), _finite_range(np.zeros(1), *mm.values()),
                          *MRIL_BOX)
        root = bridge_path(bridge_id)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._log_axes(f"{root}/mril", frame, "deflection per load (mm/MN)")
            for name, J in mm.items():
                _, colour, radius = curves[name]
                strips = [frame.points(s[:, 0], s[:, 1]) for s in finite_runs(x, J)]
                self._rec.log(f"{root}/mril/{name}", rr.LineStrips2D(strips, radii=radius, colors=colour,
                                                                     labels=[name] * len(strips)))

    def log_bridge_indicators(self, bridge_id: str, d1_pct: float, d2_pct: float, damage_probability: float,
                              alarm: bool | None = None, alarm_probability: float | None = None) -> None:
        """Log at the current pass D1 and D2 (% stiffness loss against the baseline, eq. 3.24) to
        ``indicators``, and to ``damage`` the probability that some element lost more than the
        alarm fraction, the probability above which the alarm is raised and the alarm itself
        (100: raised, 0: not), all in %. NaN or None: not known."""
        nan = float("nan")
        damage = np.array([100.0 * damage_probability,
                           nan if alarm_probability is None else 100.0 * alarm_probability,
                           nan if alarm is None else 100.0 * bool(alarm)], dtype=float)
        root = bridge_path(bridge_id)
        with self._lock:
            if self._closed:
                return
            self._style_once(f"{root}/indicators", "indicators", lambda: rr.SeriesLines(
                names=[n for n, _ in INDICATOR_SERIES], colors=[c for _, c in INDICATOR_SERIES], widths=[2.0] * 2))
            self._style_once(f"{root}/damage", "damage", lambda: rr.SeriesLines(
                names=[n for n, _, _ in DAMAGE_SERIES], colors=[c for _, c, _ in DAMAGE_SERIES],
                widths=[w for _, _, w in DAMAGE_SERIES]))
            self._stamp()
            self._rec.log(f"{root}/indicators", rr.Scalars(np.array([d1_pct, d2_pct], dtype=float)))
            self._rec.log(f"{root}/damage", rr.Scalars(damage))

    def log_bridge_summary(self, bridge_id: str, markdown: str) -> None:
        """Log the bridge's current assessment as a markdown document."""
        doc = rr.TextDocument(str(markdown), media_type=rr.MediaType.MARKDOWN)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{bridge_path(bridge_id)}/summary", doc)

    def log_bridge_estimate(self, estimate: Any, baseline: Any = None, hypotheses: Any = None) -> None:
        """Log one bridge estimate (a `cloud.bridge.estimator.BridgeEstimate`, duck-typed): stiffness
        along the span with 95 % intervals, the MR-IL (and ``baseline``, an MR-IL on the same grid),
        D1/D2, P(damage) and the alarm, and the assessment. ``hypotheses`` (a
        `cloud.bridge.hypotheses.HypothesisSettings`: ``alarm_loss``, ``alarm_probability``) draws
        the alarm's thresholds. The bridge's first estimate also goes to its decision log, so the
        log says what is being decided before any alarm is raised."""
        bid = _bridge_id(estimate.bridge)
        post = estimate.posterior
        bounds = np.asarray(post.element_bounds, dtype=float)
        d = float(post.ei_design)
        alarm_loss = getattr(hypotheses, "alarm_loss", None)
        alarm_p = getattr(hypotheses, "alarm_probability", None)
        self.log_bridge_stiffness(bid, bounds.mean(axis=1), post.stiffness_ratio, post.ei_lo95 / d, post.ei_hi95 / d,
                                  element_bounds_m=bounds, alarm_loss=alarm_loss)
        m = estimate.mril
        base = None
        if baseline is not None and np.shape(baseline.J) == np.shape(m.J):
            base = baseline.J
        self.log_bridge_mril(bid, m.x_m, m.J, base)
        ind, a = estimate.indicators, estimate.assessment
        nan = float("nan")
        self.log_bridge_indicators(bid, nan if ind is None else ind.D1_pct, nan if ind is None else ind.D2_pct,
                                   nan if a is None else a.loss_probability,
                                   alarm=None if a is None else bool(a.alarm), alarm_probability=alarm_p)
        self.log_bridge_summary(bid, bridge_summary_markdown(estimate))
        self.log_bridge_state(bid, estimate)
        with self._lock:
            first = bid not in self._first_estimate_logged
            self._first_estimate_logged.add(bid)
        if first:
            if a is None:
                text = (f"{estimate.n_passes} passes: first estimate; damage hypotheses off (rough deck): "
                        "no alarm decided")
            else:
                rule = "" if alarm_p is None else f", alarm above {alarm_p:g}"
                text = (f"{estimate.n_passes} passes: first estimate, {'ALARM' if a.alarm else 'no alarm'} "
                        f"(P(damage) {a.loss_probability:.2f}{rule})")
            self.log_alarm(bid, text, "ERROR" if a is not None and a.alarm else "INFO")

    def log_alarm(self, bridge_id: str, message: str, severity: str = "WARN") -> None:
        """Log an alarm for a bridge; ``severity`` is a text-log level (INFO, WARN, ERROR, CRITICAL...)."""
        level = str(severity).upper()
        level = {"WARNING": "WARN", "FATAL": "CRITICAL"}.get(level, level)
        if level not in TEXT_LOG_LEVELS:
            raise ValueError(f"log_alarm: severity must be one of {TEXT_LOG_LEVELS}, got {severity!r}")
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{bridge_path(bridge_id)}/alarms", rr.TextLog(str(message), level=level))

    # -- rail ------------------------------------------------------------------------------------------
    def log_rail(self, rows: Any) -> None:
        """Log the rail batches at the current pass (a `cloud.rail.batches.RailViewRows`, duck-typed):
        each carriage's run estimates, each rail bridge's bogie MR-IL against its reference and
        D1/D2, each rail route's D1 track quality. The blueprint gains the rail row (its routes and
        carriages) the first time they appear."""
        layout = (tuple(rows.routes), tuple(rows.vehicles), tuple(rows.run_names))
        with self._lock:
            if self._closed:
                return
            if layout != self._rail_layout and (layout[0] or layout[1]):
                self._rail_layout = layout
                self._rec.send_blueprint(self._blueprint())
            self._stamp()
            for vid, route, runs in rows.runs:
                self._log_runs(vid, route, runs, rows.run_names)
            for b in rows.bridges:
                self.log_bridge_mril(b.bridge_id, b.x_m, b.J, b.reference_J)
                self.log_bridge_indicators(b.bridge_id, b.d1_pct, b.d2_pct, float(b.damaged), alarm=bool(b.damaged))
            for t in rows.track:
                self._log_track_quality(t)

    def _log_runs(self, vehicle_id: str, route_id: str, runs: Sequence[Any], names: Sequence[str]) -> None:
        """A carriage's runs: a markdown table (mv, Iv in t, t·m²; v in m/s) and per quantity the
        estimate (Points2D) and its 95 % interval (``ci95``) against the run's index."""
        root = f"{rail_path(vehicle_id)}/runs"
        lines = [f"### {vehicle_id} on {route_id}: {len(runs)} runs", "",
                 "| run | mv (t) | Iv (t·m²) | v (m/s) |", "|---|---|---|---|"]
        for r in runs:
            cells = [f"{r.mean[k] / s:.4g} [{r.lo95[k] / s:.4g}, {r.hi95[k] / s:.4g}]"
                     for k, s in (("mv", 1e3), ("Iv", 1e3), ("v", 1.0))]
            lines.append(f"| {r.pass_id} | " + " | ".join(cells) + " |")
        self._rec.log(root, rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN))
        idx = np.arange(len(runs), dtype=float)
        for k in names:
            mean = np.array([r.mean[k] for r in runs])
            lo = np.array([r.lo95[k] for r in runs])
            hi = np.array([r.hi95[k] for r in runs])
            self._rec.log(f"{root}/{_part(k)}", rr.Points2D(np.stack([idx, mean], axis=1), radii=0.1))
            self._rec.log(f"{root}/{_part(k)}/ci95",
                          rr.LineStrips2D([np.array([[i, a], [i, b]]) for i, a, b in zip(idx, lo, hi)]))

    def _log_track_quality(self, t: Any) -> None:
        """A rail route's D1 level (mm) against chainage with the isolated-defect alert limits, its
        sd per 200 m as bars (within / above the sd alert limit) and a table per 200 m."""
        x, d1 = np.asarray(t.chainage_m, float), 1e3 * np.asarray(t.d1_m, float)
        root = f"{rail_path(t.route_id)}/track_quality"
        lim = float(t.alert_isolated_mm)
        frame = Frame.fit((float(np.nanmin(x)), float(np.nanmax(x))), _finite_range(d1, np.array([-lim, lim])),
                          *TRACK_BOX)
        self._log_axes(root, frame, "D1 level (mm)")
        self._rec.log(f"{root}/d1", rr.LineStrips2D([frame.points(s[:, 0], s[:, 1]) for s in finite_runs(x, d1)],
                                                    radii=MEAN_RADIUS, colors=MEAN_COLOUR))
        ends = [frame.x_lo, frame.x_hi]
        self._rec.log(f"{root}/alert_limits", rr.LineStrips2D(
            [frame.points(ends, [v, v]) for v in (lim, -lim)], radii=BAND_RADIUS, colors=THRESHOLD_COLOUR,
            labels=[f"alert ±{lim:g} mm", ""], show_labels=True))
        segs = [s for s in t.segments if np.isfinite(s.sd_d1_mm)]
        lefts = np.array([s.start_m + 0.05 * (s.end_m - s.start_m) for s in segs], dtype=float)
        widths = np.array([0.9 * (s.end_m - s.start_m) for s in segs], dtype=np.float32)
        sd = np.array([s.sd_d1_mm for s in segs], dtype=float)
        above = sd > t.alert_sd_mm
        for name, mask, colour in (("within", ~above, IRI_CLASSES[0][3]), ("above_alert", above, IRI_CLASSES[2][3])):
            self._rec.log(f"{root}/sd_200m/{name}", rr.BarChart(np.where(mask, sd, 0.0), abscissa=lefts,
                                                                widths=widths, color=colour))
        lines = [f"### {t.route_id}: EN 13848 D1 (3–25 m)", "",
                 "| start m | end m | sd mm | max abs mm | alert |", "|---|---|---|---|---|"]
        for s in t.segments:
            alert = "sd" if s.sd_d1_mm > t.alert_sd_mm else ""
            if any(s.start_m <= d[0] < s.end_m for d in t.defects):
                alert = (alert + " isolated").strip()
            lines.append(f"| {s.start_m:.0f} | {s.end_m:.0f} | {s.sd_d1_mm:.3f} | {s.max_abs_d1_mm:.3f} | {alert} |")
        self._rec.log(f"{root}/table", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN))

    # -- lifetime --------------------------------------------------------------------------------------
    def flush(self, timeout_s: float = 10.0) -> bool:
        """Push everything logged so far to the file / viewer, waiting at most about ``timeout_s``.

        Returns False (and logs a warning) if an output could not take it, e.g. an unreachable
        viewer: the view is a side subscriber and never raises into the daemon for that.
        """
        with self._lock:
            if self._closed:
                return True
            try:
                self._rec.flush(timeout_sec=timeout_s)
            except Exception as e:  # rerun raises RuntimeError when a gRPC sink cannot connect
                log.warning("rerun flush failed: %s", e)
                return False
            return True

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush and disconnect every output; the file is complete afterwards. Idempotent.

        With an unreachable viewer, rerun itself waits some seconds before giving up on it.
        """
        with self._lock:
            if self._closed:
                return
            self.flush(timeout_s)
            self._closed = True
            self._rec.disconnect()

    def __enter__(self) -> View:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bridge_summary_markdown(estimate: Any) -> str:
    """A short markdown account of a bridge estimate: passes, global stiffness, the decision, the hypotheses."""
    post, a, ind = estimate.posterior, estimate.assessment, estimate.indicators
    ratio = np.asarray(post.stiffness_ratio, dtype=float)
    lines = [f"**{_bridge_id(estimate.bridge)}** after {estimate.n_passes} passes", "",
             f"* effective stiffness ratio {post.effective_ratio:.3f} ± {post.effective_ratio_sd:.3f}",
             f"* weakest element {int(np.argmin(ratio)) + 1}: ratio {ratio.min():.3f}"]
    if ind is not None:
        lines.append(f"* D1 {ind.D1_pct:.1f} %, D2 {ind.D2_pct:.1f} %")
    if a is None:
        lines.append("* damage hypotheses: off for this bridge (rough deck): no alarm is decided")
    else:
        state = "**ALARM**" if a.alarm else "no alarm"
        lines += [f"* {state}: P(element loss > threshold) = {a.loss_probability:.3f}",
                  "* hypotheses: " + ", ".join(f"{k} {v:.2f}" for k, v in a.probabilities.items())
                  + f" (most probable: {a.best})"]
    return "\n".join(lines)


def _finite_range(*arrays: np.ndarray) -> tuple[float, float]:
    """(min, max) over the finite values of ``arrays``; (−1, 1) if there are none."""
    vals = np.concatenate([np.ravel(np.asarray(a, dtype=float)) for a in arrays]) if arrays else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    return (float(vals.min()), float(vals.max())) if vals.size else (-1.0, 1.0)


def _element_colour(k: int, n: int) -> tuple[int, int, int]:
    """Blue (first) to orange (last)."""
    t = k / max(n - 1, 1)
    return (int(60 + 195 * t), int(140 + 20 * t), int(255 - 195 * t))


def recorded_alarms(rrd_path: Path | str, bridge_id: str) -> list[tuple[str, str]]:
    """The alarms a recording shows for a bridge, in the order logged: (level, message) each."""
    path = f"{bridge_path(bridge_id)}/alarms".strip("/")
    out = []
    for chunk in RrdReader(str(rrd_path)).stream():
        if chunk.entity_path.strip("/") != path or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        texts = batch.column("TextLog:text").to_pylist() if "TextLog:text" in names else []
        levels = batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(texts)
        out += [(str((level or [""])[0]), str(text[0])) for text, level in zip(texts, levels) if text]
    return out
