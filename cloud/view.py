"""The cloud's Rerun view: current estimates logged to an explicit recording stream, one default blueprint.

One ``log_<thing>()`` per group of entities; every temporal row carries the ``pass`` (completed
passes so far, set with `View.set_pass`) and ``wall_time`` timelines. Entity paths are keys::

    profile/<route>/mean              LineStrips2D, (chainage m, -elevation mm), NaN gaps split strips
    profile/<route>/band              LineStrips2D, the 95 % band as thinner lower and upper strips
    profile/<route>/passes_per_tile   BarChart, passes per tile against tile-centre chainage (m)
    stats/<key>, stats/<key>/<sub>    Scalars, aggregator counters (``rejected/<reason>``, ``rejected/total``)
    fleet/status                      TextDocument, a markdown table of per-vehicle status
    bridge/<bridge>/stiffness         Scalars, element stiffness ratio: mean, lo95, hi95 per element
    bridge/<bridge>/mril/current      LineStrips2D, the fleet's MR-IL (x m, J mm/MN, drawn downwards)
    bridge/<bridge>/mril/baseline     LineStrips2D, the healthy baseline MR-IL it is compared with
    bridge/<bridge>/indicators        Scalars, D1 and D2 (%, eq. 3.24) and P(damage) (%)
    bridge/<bridge>/summary           TextDocument, the hypotheses' probabilities and the decision
    bridge/<bridge>/alarms            TextLog, alarms with a severity level
    rail/<route>/track_quality/...    LineStrips2D ``d1``, ``sd_per_200m``, ``alert_limits`` (mm, up); ``table``
    rail/<vehicle>/runs               TextDocument, a carriage's run estimates with 95 % intervals
    rail/<vehicle>/runs/<quantity>    Points2D (run index, estimate) and ``ci95`` LineStrips2D

Rerun's 2D view draws +y downwards and ignores view coordinates in 2D (rerun-io/rerun#1387), so the
profile strips store ``-elevation`` in mm: up on the screen is up on the road. Readers of the
recording flip the sign back (`SCREEN_Y`).

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

log = logging.getLogger(__name__)

APPLICATION_ID = "driveby"
MAX_STRIP_POINTS = 4000  # per profile curve sent to the viewer
SCREEN_Y = -1.0  # stored y = SCREEN_Y * elevation_mm (the 2D view's y axis points down)
DEFAULT_PROFILE_RANGE_MM = 50.0
DEFAULT_VIEWER_PORT = 9876

MEAN_COLOUR = (70, 160, 255)
BAND_COLOUR = (150, 150, 170)
TILE_COLOUR = (110, 190, 130)
IRI_COLOUR = (230, 140, 90)
MRIL_COLOUR = (70, 160, 255)
BASELINE_COLOUR = (150, 150, 170)
INDICATOR_SERIES = (("D1 %", (70, 160, 255)), ("D2 %", (160, 120, 255)), ("P(damage) %", (235, 80, 70)))
MRIL_MM_PER_MN = 1e9  # J (m/N) → mm/MN
MEAN_RADIUS = rr.Radius.ui_points(1.5)
BAND_RADIUS = rr.Radius.ui_points(0.75)
STATS_COLOURS = {
    "accepted": (80, 200, 120),
    "passes_complete": (70, 160, 255),
    "passes": (160, 120, 255),
    "segments_held": (200, 200, 200),
    "rejected/total": (235, 80, 70),
}
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


def rail_path(name: str) -> str:
    """Entity path of a rail route's or carriage's group, ``rail/<name>``."""
    return f"rail/{_part(name)}"


def blueprint(routes: Mapping[str, float], bridges: Iterable[Any] = (),
              profile_range_mm: float = DEFAULT_PROFILE_RANGE_MM,
              calibration_params: Sequence[str] = (), rail_routes: Sequence[str] = (),
              rail_vehicles: Sequence[str] = (), run_names: Sequence[str] = ()) -> rrb.Blueprint:
    """The one default layout: profiles per route, aggregator counters and fleet, bridges, rail.

    Parameters
    ----------
    routes : mapping route id → route length (m); each gets a profile panel bounded to
        [0, length] m by ±``profile_range_mm`` and a passes-per-tile bar chart.
    bridges : bridge ids or registry `Bridge` objects; each gets a stiffness time series, its
        MR-IL (bounded to the span when a `Bridge` is given), D1/D2 and P(damage) on the pass
        timeline, the hypotheses' summary and an alarm log. No bridge, no bridge row.
    rail_routes, rail_vehicles, run_names : a ``rail`` row below the rest: per rail route its
        EN 13848 D1 level, sd per 200 m and alert limits against chainage and the table; per
        carriage its runs' estimates of each of ``run_names``. No rail route or carriage, no row.
    """
    route_tabs = []
    for rid, length in routes.items():
        root = profile_path(rid)
        bounds = rrb.VisualBounds2D(x_range=[0.0, float(length)], y_range=[-profile_range_mm, profile_range_mm])
        route_tabs.append(rrb.Vertical(
            rrb.Spatial2DView(origin=root, contents=["$origin/mean", "$origin/band"],
                              name=f"{rid}: profile (mm, up) vs chainage (m)", visual_bounds=bounds),
            rrb.Horizontal(
                rrb.BarChartView(origin=f"{root}/passes_per_tile", name=f"{rid}: passes per tile"),
                rrb.BarChartView(origin=f"{root}/iri_100m", name=f"{rid}: IRI per 100 m (m/km)"),
                rrb.BarChartView(origin=f"{root}/iri_10m", name=f"{rid}: IRI per 10 m (m/km)")),
            row_shares=[3, 1], name=str(rid)))
    rows: list = []
    if route_tabs:
        rows.append(rrb.Tabs(*route_tabs, name="profiles"))
    fleet_tabs = [rrb.Horizontal(
        rrb.TimeSeriesView(origin="stats", name="aggregator counters"),
        rrb.TextDocumentView(origin="fleet/status", name="fleet"),
        column_shares=[3, 2], name="fleet")]
    if calibration_params:
        fleet_tabs.append(rrb.Grid(*[rrb.TimeSeriesView(origin=calibration_path(p), name=f"{p} per vehicle (95 %)")
                                     for p in calibration_params], name="calibration"))
    rows.append(rrb.Tabs(*fleet_tabs, name="fleet"))
    bridge_tabs = []
    for b in bridges:
        bid = _bridge_id(b)
        root = bridge_path(bid)
        bridge_tabs.append(rrb.Vertical(
            rrb.Horizontal(
                rrb.TimeSeriesView(origin=f"{root}/stiffness", name=f"{bid}: element stiffness / design (95 %)"),
                rrb.Spatial2DView(origin=f"{root}/mril", contents=["$origin/**"], visual_bounds=_mril_bounds(b),
                                  name=f"{bid}: MR-IL (mm/MN, down) vs x (m)"),
                column_shares=[1, 1]),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin=f"{root}/indicators", name=f"{bid}: D1, D2, P(damage) (%)"),
                rrb.TextDocumentView(origin=f"{root}/summary", name=f"{bid}: assessment"),
                rrb.TextLogView(origin=f"{root}/alarms", name=f"{bid}: alarms"),
                column_shares=[2, 2, 2]),
            row_shares=[3, 2], name=bid))
    if bridge_tabs:
        rows.append(rrb.Tabs(*bridge_tabs, name="bridges"))
    shares = [3] * bool(route_tabs) + [2] + [2] * bool(bridge_tabs)
    layout = rrb.Vertical(*rows, row_shares=shares)
    rail_tabs = _rail_tabs(rail_routes, rail_vehicles, run_names)
    if rail_tabs:
        layout = rrb.Vertical(layout, rrb.Tabs(*rail_tabs, name="rail"), row_shares=[3, 1])
    return rrb.Blueprint(layout, auto_views=False)


def _rail_tabs(routes: Sequence[str], vehicles: Sequence[str], run_names: Sequence[str]) -> list:
    tabs = []
    for route in routes:
        root = f"{rail_path(route)}/track_quality"
        tabs.append(rrb.Horizontal(
            rrb.Spatial2DView(origin=root, contents=["$origin/d1", "$origin/sd_per_200m", "$origin/alert_limits"],
                              name=f"{route}: EN 13848 D1 (mm, up) vs chainage (m)"),
            rrb.TextDocumentView(origin=f"{root}/table", name=f"{route}: D1 per 200 m"),
            column_shares=[3, 2], name=f"{route} track"))
    for vid in vehicles:
        root = f"{rail_path(vid)}/runs"
        tabs.append(rrb.Horizontal(
            rrb.TextDocumentView(origin=root, name=f"{vid}: runs (95 %)"),
            *[rrb.Spatial2DView(origin=f"{root}/{_part(k)}", contents=["$origin/**"], name=f"{vid}: {k} per run")
              for k in run_names], name=f"{vid} runs"))
    return tabs


def _mril_bounds(bridge: Any) -> rrb.VisualBounds2D | None:
    """The span and 1.6× the design mid-span ordinate L³/48EI, for a registry `Bridge`."""
    try:
        span, ei = float(bridge.span_m), float(bridge.E_pa) * float(bridge.I_m4)
    except (AttributeError, TypeError, ValueError):
        return None
    j_mid = span**3 / (48.0 * ei) * MRIL_MM_PER_MN
    return rrb.VisualBounds2D(x_range=[-0.05 * span, 1.05 * span], y_range=[-0.3 * j_mid, 1.6 * j_mid])


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
    routes : route id → length (m), for the blueprint's profile panels.
    bridges : bridge ids or registry `Bridge` objects, for the blueprint's bridge panels.
    recording_id : defaults to a fresh UUID.
    clock : seconds since the epoch for the ``wall_time`` timeline (tests pass a fixed clock).

    At least one output is required. Methods are thread-safe; calls after `close` are ignored.
    """

    def __init__(self, rrd_path: Path | str | None = None, spawn_viewer: bool = False,
                 connect_url: str | None = None, routes: Mapping[str, float] | None = None,
                 bridges: Sequence[Any] = (), *, recording_id: str | None = None,
                 clock: Callable[[], float] = time.time, viewer_port: int = DEFAULT_VIEWER_PORT,
                 profile_range_mm: float = DEFAULT_PROFILE_RANGE_MM, calibration_params: Sequence[str] = ()):
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
        self._layout = (dict(routes or {}), list(bridges), profile_range_mm, tuple(calibration_params))
        self._rail_layout: tuple = ((), (), ())  # (rail routes, carriages, run quantities) in the blueprint
        self.recording_id = recording_id or str(uuid.uuid4())
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=self.recording_id)
        # Exactly two timelines: `pass` and `wall_time` (log_time would duplicate wall_time).
        self._rec.set_log_time_enabled(False)
        self._rec.set_log_tick_enabled(False)
        self._rec.set_sinks(*sinks, default_blueprint=blueprint(*self._layout))

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

    # -- profile ---------------------------------------------------------------------------------------
    def log_profile(self, snapshot: Any) -> None:
        """Log one update of a route's profile: the mean and its 95 % band, mm against chainage m.

        ``snapshot`` is a `cloud.road.mean_profile.ProfileSnapshot` (or anything with
        ``route_id``, ``chainage_m``, ``elevation_m``, ``lo95_m``, ``hi95_m`` in metres). Curves are
        binned to at most `MAX_STRIP_POINTS` points and split at NaN gaps.
        """
        x = np.asarray(snapshot.chainage_m, dtype=float)
        cols = [np.asarray(a, dtype=float) * 1e3 for a in (snapshot.elevation_m, snapshot.lo95_m, snapshot.hi95_m)]
        if x.ndim != 1 or any(c.shape != x.shape for c in cols):
            raise ValueError("log_profile: chainage_m, elevation_m, lo95_m and hi95_m must be 1-D of one length")
        x, mean, lo, hi = decimate_profile(x, *cols)
        mean_strips = finite_runs(x, SCREEN_Y * mean)
        band_strips = finite_runs(x, SCREEN_Y * lo) + finite_runs(x, SCREEN_Y * hi)
        root = profile_path(snapshot.route_id)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{root}/mean", rr.LineStrips2D(mean_strips, radii=MEAN_RADIUS, colors=MEAN_COLOUR))
            self._rec.log(f"{root}/band", rr.LineStrips2D(band_strips, radii=BAND_RADIUS, colors=BAND_COLOUR))

    def log_tile_counts(self, route_id: str, tile_m: float, counts: np.ndarray) -> None:
        """Log passes per tile of ``tile_m`` (m) as a bar chart against tile-centre chainage (m).

        The whole array is one row (a BarChart tensor) at the current pass: a ``tile`` timeline
        would hide the other panels whenever it is the selected one.
        """
        counts = np.asarray(counts)
        if counts.ndim != 1 or not (tile_m > 0):
            raise ValueError("log_tile_counts: counts must be 1-D and tile_m positive")
        if counts.size and counts.min() < 0:
            raise ValueError("log_tile_counts: counts must be non-negative")
        centres = (np.arange(counts.size) + 0.5) * float(tile_m)
        chart = rr.BarChart(counts.astype(np.int64), abscissa=centres,
                            widths=np.full(counts.size, 0.9 * float(tile_m), dtype=np.float32), color=TILE_COLOUR)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{profile_path(route_id)}/passes_per_tile", chart)

    def log_roughness(self, route_id: str, length_m: float, start_m: np.ndarray, iri: np.ndarray) -> None:
        """Log IRI (m/km) per ``length_m`` segment (10 or 100 m) as bars along the route."""
        start = np.asarray(start_m, dtype=float)
        iri = np.asarray(iri, dtype=float)
        if start.shape != iri.shape or start.ndim != 1:
            raise ValueError("log_roughness: start_m and iri must be 1-D of one length")
        chart = rr.BarChart(np.nan_to_num(iri), abscissa=start + 0.5 * length_m,
                            widths=np.full(start.size, 0.9 * length_m, dtype=np.float32), color=IRI_COLOUR)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{profile_path(route_id)}/iri_{int(round(length_m))}m", chart)

    def log_calibration(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Log every vehicle's calibrated quantities with 95 % intervals at the current pass.

        ``rows`` as in ``vehicles.parquet``: vehicle_id, param, mean, lo95, hi95. One entity per
        quantity, three series (mean, lo95, hi95) per vehicle.
        """
        by_param: dict[str, list[Mapping[str, Any]]] = {}
        for r in rows:
            by_param.setdefault(str(r["param"]), []).append(r)
        with self._lock:
            if self._closed:
                return
            for param, rs in by_param.items():
                rs = sorted(rs, key=lambda r: str(r["vehicle_id"]))
                path = calibration_path(param)
                ids = tuple(str(r["vehicle_id"]) for r in rs)

                def style(ids=ids):
                    names, colours, widths = [], [], []
                    for k, vid in enumerate(ids):
                        hue = _element_colour(k, len(ids))
                        for label, w in (("", 1.5), (" lo95", 0.5), (" hi95", 0.5)):
                            names.append(f"{vid}{label}")
                            colours.append(hue)
                            widths.append(w)
                    return rr.SeriesLines(names=names, colors=colours, widths=widths)

                self._style_once(path, ids, style)
                self._stamp()
                values = np.array([[float(r["mean"]), float(r["lo95"]), float(r["hi95"])] for r in rs]).ravel()
                self._rec.log(path, rr.Scalars(values))

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
                             lo: np.ndarray, hi: np.ndarray) -> None:
        """Log each element's stiffness ratio (EI / design EI) with its 95 % band at the current pass.

        One entity ``bridge/<id>/stiffness`` with three series per element (mean, lo95, hi95),
        named by the element's centre ``element_x_m`` (m from the first support).
        """
        arrays = [np.asarray(a, dtype=float) for a in (element_x_m, ratio_mean, lo, hi)]
        x = arrays[0]
        if x.ndim != 1 or any(a.shape != x.shape for a in arrays):
            raise ValueError("log_bridge_stiffness: element_x_m, ratio_mean, lo and hi must be 1-D of one length")
        values = np.column_stack(arrays[1:]).ravel()  # mean, lo, hi of element 0, then element 1, ...
        path = f"{bridge_path(bridge_id)}/stiffness"

        def style():
            names, colours, widths = [], [], []
            for k, xk in enumerate(x):
                hue = _element_colour(k, x.size)
                for label, w in (("", 2.0), (" lo95", 0.75), (" hi95", 0.75)):
                    names.append(f"x={xk:.1f} m{label}")
                    colours.append(hue)
                    widths.append(w)
            return rr.SeriesLines(names=names, colors=colours, widths=widths)

        with self._lock:
            if self._closed:
                return
            self._style_once(path, tuple(np.round(x, 6)), style)
            self._stamp()
            self._rec.log(path, rr.Scalars(values))

    def log_bridge_mril(self, bridge_id: str, x_m: np.ndarray, J_m_per_n: np.ndarray,
                        baseline_J_m_per_n: np.ndarray | None = None) -> None:
        """Log the fleet's MR-IL (deflection per unit load, m/N, on ``x_m`` from the first support)
        and, when given, the baseline it is compared with; drawn in mm/MN, deflection downwards."""
        x = np.asarray(x_m, dtype=float)
        curves = {"current": (J_m_per_n, MRIL_COLOUR, MEAN_RADIUS), "baseline": (baseline_J_m_per_n, BASELINE_COLOUR,
                                                                               BAND_RADIUS)}
        strips = {}
        for name, (J, colour, radius) in curves.items():
            if J is None:
                continue
            J = np.asarray(J, dtype=float)
            if J.shape != x.shape or x.ndim != 1:
                raise ValueError("log_bridge_mril: x_m and the MR-ILs must be 1-D of one length")
            # Up on the screen is up: deflection (J > 0, downwards) is stored as SCREEN_Y · (−J) = +J.
            strips[name] = rr.LineStrips2D(finite_runs(x, -SCREEN_Y * J * MRIL_MM_PER_MN), radii=radius,
                                           colors=colour)
        root = bridge_path(bridge_id)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            for name, strip in strips.items():
                self._rec.log(f"{root}/mril/{name}", strip)

    def log_bridge_indicators(self, bridge_id: str, d1_pct: float, d2_pct: float, damage_probability: float) -> None:
        """Log D1 and D2 (% stiffness loss against the baseline, eq. 3.24) and the probability that
        some element lost more than the alarm fraction (as %) at the current pass. NaN: not known yet."""
        path = f"{bridge_path(bridge_id)}/indicators"
        values = np.array([d1_pct, d2_pct, 100.0 * damage_probability], dtype=float)
        with self._lock:
            if self._closed:
                return
            self._style_once(path, "indicators", lambda: rr.SeriesLines(
                names=[n for n, _ in INDICATOR_SERIES], colors=[c for _, c in INDICATOR_SERIES], widths=[2.0] * 3))
            self._stamp()
            self._rec.log(path, rr.Scalars(values))

    def log_bridge_summary(self, bridge_id: str, markdown: str) -> None:
        """Log the bridge's current assessment as a markdown document."""
        doc = rr.TextDocument(str(markdown), media_type=rr.MediaType.MARKDOWN)
        with self._lock:
            if self._closed:
                return
            self._stamp()
            self._rec.log(f"{bridge_path(bridge_id)}/summary", doc)

    def log_bridge_estimate(self, estimate: Any, baseline: Any = None) -> None:
        """Log one bridge estimate (a `cloud.bridge.estimator.BridgeEstimate`, duck-typed): element
        stiffness with 95 % bands, the MR-IL (and ``baseline``, an MR-IL on the same grid), D1/D2 and
        P(damage), and the hypotheses' summary."""
        bid = _bridge_id(estimate.bridge)
        post = estimate.posterior
        bounds = np.asarray(post.element_bounds, dtype=float)
        d = float(post.ei_design)
        self.log_bridge_stiffness(bid, bounds.mean(axis=1), post.stiffness_ratio, post.ei_lo95 / d, post.ei_hi95 / d)
        m = estimate.mril
        base = None
        if baseline is not None and np.shape(baseline.J) == np.shape(m.J):
            base = baseline.J
        self.log_bridge_mril(bid, m.x_m, m.J, base)
        ind, a = estimate.indicators, estimate.assessment
        nan = float("nan")
        self.log_bridge_indicators(bid, nan if ind is None else ind.D1_pct, nan if ind is None else ind.D2_pct,
                                   nan if a is None else a.loss_probability)
        self.log_bridge_summary(bid, bridge_summary_markdown(estimate))

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
                self._rec.send_blueprint(blueprint(*self._layout, *layout))
                self._rail_layout = layout
            self._stamp()
            for vid, route, runs in rows.runs:
                self._log_runs(vid, route, runs, rows.run_names)
            for b in rows.bridges:
                self.log_bridge_mril(b.bridge_id, b.x_m, b.J, b.reference_J)
                self.log_bridge_indicators(b.bridge_id, b.d1_pct, b.d2_pct, float(b.damaged))
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
        """A rail route's D1 level (mm, up) against chainage, its sd per 200 m as steps, the
        isolated-defect alert limits and a table per 200 m (``sd``/``isolated`` alerts)."""
        x, d1 = np.asarray(t.chainage_m, float), np.asarray(t.d1_m, float)
        root = f"{rail_path(t.route_id)}/track_quality"
        self._rec.log(f"{root}/d1", rr.LineStrips2D(finite_runs(x, SCREEN_Y * 1e3 * d1)))
        steps = [np.array([[s.start_m, SCREEN_Y * s.sd_d1_mm], [s.end_m, SCREEN_Y * s.sd_d1_mm]])
                 for s in t.segments if np.isfinite(s.sd_d1_mm)]
        self._rec.log(f"{root}/sd_per_200m", rr.LineStrips2D(steps))
        self._rec.log(f"{root}/alert_limits", rr.LineStrips2D(
            [np.array([[0.0, SCREEN_Y * lim], [x[-1], SCREEN_Y * lim]]) for lim in
             (t.alert_isolated_mm, -t.alert_isolated_mm)]))
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
    """A short markdown account of a bridge estimate: passes, global stiffness, the hypotheses."""
    post, a, ind = estimate.posterior, estimate.assessment, estimate.indicators
    ratio = np.asarray(post.stiffness_ratio, dtype=float)
    lines = [f"**{_bridge_id(estimate.bridge)}** after {estimate.n_passes} passes", "",
             f"* effective stiffness ratio {post.effective_ratio:.3f} ± {post.effective_ratio_sd:.3f}",
             f"* weakest element {int(np.argmin(ratio)) + 1}: ratio {ratio.min():.3f}"]
    if ind is not None:
        lines.append(f"* D1 {ind.D1_pct:.1f} %, D2 {ind.D2_pct:.1f} %")
    if a is None:
        lines.append("* damage hypotheses: off for this bridge's settings")
    else:
        state = "**ALARM**" if a.alarm else "no alarm"
        lines += [f"* {state}: P(element loss > threshold) = {a.loss_probability:.3f}; most probable: {a.best}", "",
                  "| hypothesis | probability |", "|---|---:|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in a.probabilities.items()]
    return "\n".join(lines)


def _element_colour(k: int, n: int) -> tuple[int, int, int]:
    """Blue (first support) to orange (second) along the span."""
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
