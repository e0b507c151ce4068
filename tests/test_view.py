"""The cloud's Rerun view, read back from real .rrd files (no viewer, no display)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rerun as rr  # noqa: E402 - a dependency of the project, never optional
from rerun.chunk import RrdReader  # noqa: E402

from cloud.road.mean_profile import ProfileSnapshot  # noqa: E402
from cloud.view import (  # noqa: E402
    IRI_CLASSES,
    MAX_STRIP_POINTS,
    View,
    blueprint,
    decimate_profile,
    finite_runs,
)

T0 = 1_700_000_000.0
F32 = 1e-5  # Rerun stores 2D positions as float32: data read back through a chart agree to this share of its axis


class FakeClock:
    """Wall time that tests move by hand."""

    def __init__(self, t: float = T0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def snapshot(route_id="R1", length_m=100.0, spacing_m=0.5, gap=None, offset_m=0.0, n_passes=1):
    x = np.arange(int(round(length_m / spacing_m)) + 1) * spacing_m
    y = 0.01 * np.sin(2 * np.pi * x / 20.0) + offset_m
    if gap is not None:
        y = np.where((x >= gap[0]) & (x < gap[1]), np.nan, y)
    n = np.where(np.isfinite(y), n_passes, 0).astype(np.int64)
    return ProfileSnapshot(route_id, x, y, y - 0.002, y + 0.002, n)


def temporal_rows(path: Path, entity: str) -> list[dict]:
    """Every temporal row of ``entity`` as {timeline or component: value}, sorted by ``pass``."""
    rows = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        cols = {n: (rb.column(n).cast("int64") if n in chunk.timeline_names else rb.column(n)).to_pylist()
                for n in rb.schema.names if not n.startswith("rerun.controls")}
        rows += [{n: v[i] for n, v in cols.items()} for i in range(chunk.num_rows)]
    return sorted(rows, key=lambda r: r["pass"])


def data_axes(path: Path, root: str, row: int = -1):
    """Screen → data maps of a chart at its ``row``-th update, read from its labelled ticks alone:
    a straight line through (screen position, label value) of the x ticks and of the y ticks."""
    maps = []
    for name, col in (("x_ticks", 0), ("y_ticks", 1)):
        r = temporal_rows(path, f"{root}/axes/{name}")[row]
        pos = np.asarray(r["Points2D:positions"], dtype=float)[:, col]
        val = np.asarray([float(t) for t in r["Points2D:labels"]])
        slope, icpt = np.polyfit(pos, val, 1)
        # evenly placed (positions are stored as float32: a few parts in 10⁷ of the axis)
        np.testing.assert_allclose(slope * pos + icpt, val, atol=F32 * (val.max() - val.min()))
        maps.append(lambda s, a=slope, b=icpt: a * np.asarray(s, dtype=float) + b)
    return maps


def entities(path: Path) -> set[str]:
    return {c.entity_path for c in RrdReader(path).stream()}


@pytest.fixture
def rrd(tmp_path):
    return tmp_path / "view.rrd"


def test_profile_updates_are_rows_on_the_pass_timeline(rrd):
    clock = FakeClock()
    n = 5
    with View(rrd, routes={"R1": 100.0}, bridges=["B1"], clock=clock, recording_id="rec-1") as view:
        for k in range(1, n + 1):
            view.set_pass(k)
            clock.t = T0 + 60.0 * k
            view.log_profile(snapshot(offset_m=0.001 * k))
    reader = RrdReader(rrd)
    assert [r.recording_id for r in reader.recordings()] == ["rec-1"]
    assert len(reader.blueprints()) >= 1
    mean = temporal_rows(rrd, "/profile/R1/mean")
    assert [r["pass"] for r in mean] == list(range(1, n + 1))
    assert [r["wall_time"] for r in mean] == [int((T0 + 60.0 * k) * 1e9) for k in range(1, n + 1)]
    assert set(mean[0]) == {"pass", "wall_time", "LineStrips2D:strips", "LineStrips2D:radii", "LineStrips2D:colors"}
    band = temporal_rows(rrd, "/profile/R1/band")
    assert [r["pass"] for r in band] == list(range(1, n + 1))
    # the last update holds the last snapshot: mean in mm against chainage in m, read through the
    # chart's own tick labels; up on the screen (smaller y) is up on the road
    fx, fy = data_axes(rrd, "/profile/R1")
    s = snapshot(offset_m=0.005)
    (strip,) = mean[-1]["LineStrips2D:strips"]
    pts = np.array(strip)
    np.testing.assert_allclose(fx(pts[:, 0]), s.chainage_m, atol=1e-4)
    np.testing.assert_allclose(fy(pts[:, 1]), s.elevation_m * 1e3, atol=1e-4)
    lo, hi = (np.array(b) for b in band[-1]["LineStrips2D:strips"])
    np.testing.assert_allclose(fy(lo[:, 1]), s.lo95_m * 1e3, atol=1e-4)
    np.testing.assert_allclose(fy(hi[:, 1]), s.hi95_m * 1e3, atol=1e-4)
    assert (hi[:, 1] < lo[:, 1]).all()
    # the elevation axis holds the band: every point of it inside the chart's y ticks' range
    ticks = [float(t) for t in temporal_rows(rrd, "/profile/R1/axes/y_ticks")[-1]["Points2D:labels"]]
    assert min(ticks) <= 1e3 * s.lo95_m.min() and max(ticks) >= 1e3 * s.hi95_m.max()
    # the band is shaded: one vertical stroke per binned point, from its lower to its upper bound
    (fill,) = temporal_rows(rrd, "/profile/R1/band_fill")[-1:]
    strokes = np.array(fill["LineStrips2D:strips"])
    assert strokes.shape[1:] == (2, 2) and len(strokes) > 50
    np.testing.assert_allclose(strokes[:, 0, 0], strokes[:, 1, 0])
    assert (fy(strokes[:, 1, 1]) >= fy(strokes[:, 0, 1])).all()


def test_nan_gaps_split_strips_without_nan_coordinates(rrd):
    with View(rrd, routes={"R1": 100.0}, clock=FakeClock()) as view:
        view.set_pass(1)
        view.log_profile(snapshot(gap=(30.0, 45.0)))
        view.set_pass(2)
        view.log_profile(snapshot(gap=(0.0, 200.0)))  # no data at all yet: empty, not NaN
    mean = temporal_rows(rrd, "/profile/R1/mean")
    band = temporal_rows(rrd, "/profile/R1/band")
    strips = [np.array(s) for s in mean[0]["LineStrips2D:strips"]]
    assert len(strips) == 2
    assert all(np.isfinite(s).all() for s in strips)
    fx, _ = data_axes(rrd, "/profile/R1", 0)
    assert fx(strips[0][-1, 0]) < 30.0 and fx(strips[1][0, 0]) >= 45.0
    assert len(band[0]["LineStrips2D:strips"]) == 4
    assert all(np.isfinite(np.array(s)).all() for s in band[0]["LineStrips2D:strips"])
    assert mean[1]["LineStrips2D:strips"] == [] and band[1]["LineStrips2D:strips"] == []


def test_long_profiles_are_binned_for_the_viewer(rrd):
    s = snapshot(length_m=1000.0, spacing_m=0.05, gap=(400.0, 410.0))  # 20001 points
    with View(rrd, routes={"R1": 1000.0}, clock=FakeClock()) as view:
        view.log_profile(s)
    (row,) = temporal_rows(rrd, "/profile/R1/mean")
    strips = [np.array(p) for p in row["LineStrips2D:strips"]]
    assert len(strips) == 2
    assert sum(len(p) for p in strips) <= MAX_STRIP_POINTS
    assert all(np.isfinite(p).all() for p in strips)
    fx, _ = data_axes(rrd, "/profile/R1")
    assert fx(strips[0][0, 0]) < 1.0 and fx(strips[-1][-1, 0]) > 999.0


def test_decimate_profile_against_a_loop():
    rng = np.random.default_rng(1)
    n, max_points = 103, 10
    x = np.arange(n) * 0.1
    y = rng.normal(size=n)
    y[20:37] = np.nan  # spans whole bins and parts of bins
    lo, hi = y - rng.uniform(size=n), y + rng.uniform(size=n)
    xd, yd, lod, hid = decimate_profile(x, y, lo, hi, max_points)
    k = -(-n // max_points)
    assert xd.size <= max_points
    for b in range(xd.size):
        sl = slice(b * k, min((b + 1) * k, n))
        fin = np.isfinite(y[sl])
        assert xd[b] == pytest.approx(x[sl].mean())
        if fin.any():
            assert yd[b] == pytest.approx(y[sl][fin].mean())
            assert lod[b] == pytest.approx(lo[sl][fin].min())
            assert hid[b] == pytest.approx(hi[sl][fin].max())
        else:
            assert np.isnan(yd[b]) and np.isnan(lod[b]) and np.isnan(hid[b])
    same = decimate_profile(x, y, lo, hi, n)
    assert all(a is b for a, b in zip(same, (x, y, lo, hi)))


def test_finite_runs_drops_nan_and_single_points():
    x = np.arange(10.0)
    y = np.array([0, 1, np.nan, 3, np.nan, 5, 6, 7, np.nan, np.nan])
    runs = finite_runs(x, y)
    assert [r[:, 0].tolist() for r in runs] == [[0, 1], [5, 6, 7]]
    assert finite_runs(x, np.full(10, np.nan)) == []


def test_tile_counts_are_a_bar_chart_per_pass(rrd):
    with View(rrd, routes={"R1": 200.0}, clock=FakeClock()) as view:
        view.set_pass(1)
        view.log_tile_counts("R1", 50.0, np.array([1, 0, 0, 0]))
        view.set_pass(2)
        view.log_tile_counts("R1", 50.0, np.array([2, 1, 1, 0]))
    rows = temporal_rows(rrd, "/profile/R1/passes_per_tile")
    assert [r["pass"] for r in rows] == [1, 2]
    (values,), (abscissa,) = rows[1]["BarChart:values"], rows[1]["BarChart:abscissa"]
    assert values["shape"] == [4] and values["buffer"] == [2, 1, 1, 0]
    # Rerun draws a bar from its abscissa over its width: each bar across 90 % of its tile
    assert abscissa["buffer"] == pytest.approx([2.5, 52.5, 102.5, 152.5])
    assert rows[1]["BarChart:widths"] == pytest.approx([45.0] * 4)
    with pytest.raises(ValueError):
        View(rrd.with_name("x.rrd")).log_tile_counts("R1", 50.0, np.array([-1]))


def test_stats_are_columns_with_reasons_and_totals(rrd):
    clock = FakeClock()
    history = [
        {"accepted": 3, "rejected": {}, "passes_complete": 0, "segments_held": 3},
        {"accepted": 7, "rejected": {"duplicate": 2}, "passes_complete": 1, "segments_held": 7},
        {"accepted": 9, "rejected": {"duplicate": 2, "impossible_speed": 1}, "passes_complete": 2,
         "segments_held": 9},
    ]
    with View(rrd, clock=clock) as view:
        for k, stats in enumerate(history, start=1):
            view.set_pass(k)
            clock.t = T0 + k
            view.log_stats(stats)
        # a replay of the same history in one columnar call per series, at later passes
        view.log_stats_history([11, 12, 13], [T0 + 11, T0 + 12, T0 + 13], history)

    def series(entity):
        return [(r["pass"], r["Scalars:scalars"][0]) for r in temporal_rows(rrd, entity)]

    assert series("/stats/accepted") == [(1, 3), (2, 7), (3, 9), (11, 3), (12, 7), (13, 9)]
    assert series("/stats/passes_complete") == [(1, 0), (2, 1), (3, 2), (11, 0), (12, 1), (13, 2)]
    # a reason's series starts when it first appears, whether logged entry by entry or in one call
    assert series("/stats/rejected/duplicate") == [(2, 2), (3, 2), (12, 2), (13, 2)]
    assert series("/stats/rejected/impossible_speed") == [(3, 1), (13, 1)]
    assert series("/stats/rejected/total") == [(1, 0), (2, 2), (3, 3), (11, 0), (12, 2), (13, 3)]
    ts = [r["wall_time"] for r in temporal_rows(rrd, "/stats/accepted")]
    assert ts == [int((T0 + k) * 1e9) for k in (1, 2, 3, 11, 12, 13)]
    assert "/stats/accepted" in {c.entity_path for c in RrdReader(rrd).stream() if c.is_static}  # series style


def test_vehicle_status_is_a_markdown_table(rrd):
    status = {"V2": {"passes": 1, "last_pass": "p1", "calib_version": 0, "segments": 4},
              "V1": {"passes": 3, "last_pass": "p7", "calib_version": 2, "segments": 12, "rejected": 1}}
    with View(rrd, clock=FakeClock()) as view:
        view.set_pass(4)
        view.log_vehicle_status(status)
    (row,) = temporal_rows(rrd, "/fleet/status")
    text = row["TextDocument:text"][0]
    assert row["TextDocument:media_type"] == ["text/markdown"]
    lines = text.splitlines()
    body = [ln for ln in lines if ln.startswith("| V")]
    assert body == ["| V1 | 3 | p7 | 2 | 12 | 1 |", "| V2 | 1 | p1 | 0 | 4 | – |"]
    assert "2 vehicles" in lines[0]


def test_bridge_stiffness_along_the_span_and_alarms(rrd):
    x = np.array([1.0, 3.0, 5.0])
    with View(rrd, routes={"R1": 100.0}, bridges=["B1"], clock=FakeClock()) as view:
        view.set_pass(10)
        view.log_bridge_stiffness("B1", x, [1.0, 0.8, 1.0], [0.9, 0.7, 0.9], [1.1, 0.9, 1.1], alarm_loss=0.05)
        view.log_alarm("B1", "element at 3.0 m below 85 % of design", severity="warning")
        with pytest.raises(ValueError):
            view.log_alarm("B1", "?", severity="loud")
        with pytest.raises(ValueError):
            view.log_bridge_stiffness("B1", x, [1.0], [1.0], [1.0])
    fx, fy = data_axes(rrd, "/bridge/B1/span")
    (row,) = temporal_rows(rrd, "/bridge/B1/span/mean")
    assert row["pass"] == 10
    bars = [np.array(b) for b in row["LineStrips2D:strips"]]  # one bar across each element at its mean
    np.testing.assert_allclose([fx(b[:, 0]) for b in bars], [[0.0, 2.0], [2.0, 4.0], [4.0, 6.0]], atol=F32 * 6)
    np.testing.assert_allclose([fy(b[:, 1]) for b in bars], [[1.0, 1.0], [0.8, 0.8], [1.0, 1.0]], atol=F32)
    (wrow,) = temporal_rows(rrd, "/bridge/B1/span/whiskers")
    whiskers = [np.array(w) for w in wrow["LineStrips2D:strips"]][::3]  # the vertical stroke of each (then caps)
    np.testing.assert_allclose([fx(w[:, 0]) for w in whiskers], [[1.0, 1.0], [3.0, 3.0], [5.0, 5.0]], atol=F32 * 6)
    np.testing.assert_allclose([fy(w[:, 1]) for w in whiskers], [[0.9, 1.1], [0.7, 0.9], [0.9, 1.1]], atol=F32)
    (thr,) = temporal_rows(rrd, "/bridge/B1/span/threshold")
    np.testing.assert_allclose(fy(np.array(thr["LineStrips2D:strips"][0])[:, 1]), [0.95, 0.95], atol=F32)
    (alarm,) = temporal_rows(rrd, "/bridge/B1/alarms")
    assert alarm["TextLog:level"] == ["WARN"] and alarm["TextLog:text"][0].startswith("element at 3.0 m")


def test_calibration_converges_per_round_with_its_band(rrd):
    rounds = [{"V1": (400.0, 300.0, 500.0), "V2": (420.0, 320.0, 520.0)},
              {"V1": (410.0, 380.0, 440.0), "V2": (415.0, 390.0, 440.0)},
              {"V1": (412.0, 405.0, 419.0), "V2": (414.0, 407.0, 421.0)}]
    with View(rrd, routes={"R1": 100.0}, clock=FakeClock()) as view:
        view.set_pass(5)  # every round at one pass count, as when rounds run once the bus is quiet
        for r in rounds:
            view.log_calibration([{"vehicle_id": v, "param": "K/M", "mean": m, "lo95": lo, "hi95": hi}
                                  for v, (m, lo, hi) in r.items()])
    root = "/fleet/calibration/K_over_M"
    fx, fy = data_axes(rrd, root)
    last = temporal_rows(rrd, f"{root}/mean")[-1]
    assert last["pass"] == 5
    for strip, vid in zip(last["LineStrips2D:strips"], ("V1", "V2")):
        pts = np.array(strip)
        np.testing.assert_allclose(fx(pts[:, 0]), [1, 2, 3], atol=F32 * 2)
        np.testing.assert_allclose(fy(pts[:, 1]), [r[vid][0] for r in rounds], atol=F32 * 250)
    bands = [np.array(b) for b in temporal_rows(rrd, f"{root}/band")[-1]["LineStrips2D:strips"]]
    np.testing.assert_allclose(fy(bands[0][:, 1]), [r["V1"][1] for r in rounds], atol=F32 * 250)  # V1's lower bounds
    np.testing.assert_allclose(fy(bands[3][:, 1]), [r["V2"][2] for r in rounds], atol=F32 * 250)  # V2's upper bounds


def test_iri_bars_are_split_by_condition_class(rrd):
    start = np.array([0.0, 100.0, 200.0, 300.0])
    iri = np.array([1.2, 2.0, 3.5, np.nan])
    with View(rrd, routes={"R1": 400.0}, clock=FakeClock()) as view:
        view.set_pass(3)
        view.log_roughness("R1", 100.0, start, iri)
    got = {}
    for name, lo, hi, _ in IRI_CLASSES:
        (row,) = temporal_rows(rrd, f"/profile/R1/iri_100m/{name}")
        ((values,), (abscissa,)) = row["BarChart:values"], row["BarChart:abscissa"]
        got[name] = np.asarray(values["buffer"], dtype=float)[:4]
        # the segments' centres, then a zero bar at each end of the route (the chart's x range)
        np.testing.assert_allclose(abscissa["buffer"], [*(start + 5.0), 0.0, 400.0])
        assert values["buffer"][4:] == [0.0, 0.0]
    # each segment's bar in exactly its class; the NaN segment has no bar
    np.testing.assert_allclose(got["good"], [1.2, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(got["acceptable"], [0.0, 2.0, 0.0, 0.0])
    np.testing.assert_allclose(got["poor"], [0.0, 0.0, 3.5, 0.0])
    assert [c[1] for c in IRI_CLASSES] == [0.0, 1.5, 2.7]  # FHWA's thresholds (m/km)


def test_close_is_idempotent_and_later_calls_are_ignored(rrd):
    view = View(rrd, routes={"R1": 100.0}, clock=FakeClock())
    view.set_pass(1)
    view.log_profile(snapshot())
    assert view.flush()
    view.close()
    view.close()
    assert view.flush()
    view.log_profile(snapshot())
    view.log_stats({"accepted": 1})
    assert len(temporal_rows(rrd, "/profile/R1/mean")) == 1
    assert "/stats/accepted" not in entities(rrd)


def test_a_view_needs_an_output(rrd):
    with pytest.raises(ValueError, match="no output"):
        View()
    with View(rrd) as view, pytest.raises(ValueError):
        view.set_pass(-1)


def test_blueprint_is_one_value_for_routes_and_bridges():
    assert isinstance(blueprint({"R1": 100.0, "R2": 50.0}, ["B1"]), rr.blueprint.Blueprint)
    assert isinstance(blueprint({}, []), rr.blueprint.Blueprint)


def test_rrd_verify_accepts_the_file(rrd, tmp_path):
    clock = FakeClock()
    with View(rrd, routes={"R1": 100.0}, bridges=["B1"], clock=clock) as view:
        for k in range(1, 4):
            view.set_pass(k)
            view.log_profile(snapshot(gap=(40.0, 50.0)))
            view.log_tile_counts("R1", 50.0, np.array([k, k, 0]))
            view.log_stats({"accepted": k, "rejected": {"duplicate": 1}, "passes_complete": k})
            view.log_vehicle_status({"V1": {"passes": k}})
            view.log_bridge_stiffness("B1", [2.5, 7.5], [1.0, 1.0], [0.9, 0.9], [1.1, 1.1])
            view.log_roughness("R1", 10.0, np.arange(0.0, 100.0, 10.0), np.linspace(0.5, 4.0, 10))
            view.log_calibration([{"vehicle_id": "V1", "param": "K/M", "mean": 400.0, "lo95": 380.0, "hi95": 420.0}])
        view.log_alarm("B1", "test", "INFO")
    cli = Path(sys.executable).with_name("rerun")
    assert cli.exists(), "the rerun CLI ships with rerun-sdk and must be installed beside the interpreter"
    # The CLI's first run writes an analytics config and prints a notice on stderr: keep the
    # config inside tmp_path and ignore the notice.
    env = dict(os.environ, HOME=str(tmp_path), XDG_CONFIG_HOME=str(tmp_path / "config"))
    done = subprocess.run([str(cli), "rrd", "verify", str(rrd)], capture_output=True, text=True, env=env,
                          timeout=60)
    assert done.returncode == 0, done.stderr


def test_bridge_mril_indicators_and_summary(rrd):
    from cloud.view import MRIL_MM_PER_MN

    x = np.linspace(0.0, 20.0, 5)
    J = np.array([0.0, 2.7e-9, 3.8e-9, 2.7e-9, 0.0])
    with View(rrd, bridges=["B1"], clock=FakeClock()) as view:
        view.set_pass(4)
        view.log_bridge_mril("B1", x, J, 0.9 * J)
        view.log_bridge_indicators("B1", 10.0, 9.5, 0.97, alarm=True, alarm_probability=0.95)
        view.log_bridge_summary("B1", "**B1** after 4 passes")
        with pytest.raises(ValueError):
            view.log_bridge_mril("B1", x, J[:3])
    (cur,) = temporal_rows(rrd, "/bridge/B1/mril/current")
    (base,) = temporal_rows(rrd, "/bridge/B1/mril/baseline")
    assert cur["pass"] == 4
    fx, fy = data_axes(rrd, "/bridge/B1/mril")
    pts = np.asarray(cur["LineStrips2D:strips"][0])
    np.testing.assert_allclose(fx(pts[:, 0]), x, atol=F32 * 20)
    np.testing.assert_allclose(fy(pts[:, 1]), J * MRIL_MM_PER_MN, atol=F32 * 4)
    np.testing.assert_allclose(fy(np.asarray(base["LineStrips2D:strips"][0])[:, 1]), 0.9 * J * MRIL_MM_PER_MN,
                               atol=F32 * 4)
    (ind,) = temporal_rows(rrd, "/bridge/B1/indicators")
    np.testing.assert_allclose(ind["Scalars:scalars"], [10.0, 9.5])
    (dmg,) = temporal_rows(rrd, "/bridge/B1/damage")
    np.testing.assert_allclose(dmg["Scalars:scalars"], [97.0, 95.0, 100.0])
    (doc,) = temporal_rows(rrd, "/bridge/B1/summary")
    assert doc["TextDocument:text"][0].startswith("**B1**")


def test_blueprint_takes_registry_bridges():
    from shared.registry import Bridge

    b = Bridge(id="B1", route="R1", start_chainage_m=100.0, span_m=20.0, n_elements=20, E_pa=35e9, I_m4=1.25,
               mass_per_m=37500.0, depth_m=1.0, damping_ratio=0.03, supports="simply_supported")
    assert isinstance(blueprint({"R1": 140.0}, [b]), rr.blueprint.Blueprint)
