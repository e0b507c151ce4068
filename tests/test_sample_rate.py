"""Logs at sample rates other than the logger's original 500 Hz (interfaces.md §1: any rate).

The cloud undoes the edge inverse's Newmark transfer per pass (cloud.road.continuous.continuous_ap), and
that transfer depends on the step the edge inverted at. Undone at 2 ms whatever the rate, a 1 ms pass's
AP comes out worse than the edge sent it, a 5 ms pass's stays 12 % off at 0.5–1 m. So the edge says
its sample interval in the pass-done (``PassDone.sample_interval_s``, optional: a
message without it was made at 500 Hz) and the cloud's models of the pass use it.
"""

import numpy as np
import pyarrow as pa
import pytest
from scipy.signal import butter, sosfiltfilt

from cloud.ingest.aggregator import Aggregator
from cloud.road.continuous import continuous_segments
from edge.pipeline import PassProcessor
from shared.dynamics.forward import simulate_on_profile
from shared.dynamics.inverse import build_inverse, edge_gamma
from shared.profiles import iso8608_profile, tyre_filter
from shared.registry import parse_site
from shared.schema import LEGACY_SAMPLE_INTERVAL_S, InvalidMessage, PassDone, SensorChunk, decode_pass_done
from shared.vehicles import QuarterCar
from simfleet.scenarios import TABLE_4_1

FINE_S = 0.0005  # s: the simulation's step (finer physics than any edge inverse here, Newmark γ ½)


def _drop_column(payload: bytes, name: str) -> bytes:
    """``payload`` re-encoded without column ``name`` (what an older edge sent)."""
    batch = pa.ipc.open_stream(payload).read_next_batch()
    keep = [i for i, n in enumerate(batch.schema.names) if n != name]
    assert len(keep) == len(batch.schema.names) - 1
    schema = pa.schema([batch.schema.field(i) for i in keep], metadata=batch.schema.metadata)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema) as w:
        w.write_batch(pa.RecordBatch.from_arrays([batch.column(i) for i in keep], schema=schema))
    return sink.getvalue().to_pybytes()


def test_pass_done_carries_the_sample_interval_and_old_ones_mean_500_hz():
    done = PassDone("veh-1", "p1", "R1", 2, 7, "quarter_car", {"M": 1.0}, sample_interval_s=0.001)
    assert decode_pass_done(done.encode()).sample_interval_s == 0.001
    old = _drop_column(done.encode(), "sample_interval_s")
    assert decode_pass_done(old).sample_interval_s == LEGACY_SAMPLE_INTERVAL_S == 0.002
    assert decode_pass_done(old).params == {"M": 1.0}
    for bad in (0.0, -0.001, 2.0):
        with pytest.raises(InvalidMessage) as e:
            PassDone("veh-1", "p1", "R1", 2, 7, sample_interval_s=bad)
        assert e.value.reason == "bad_value"


def _band(y: np.ndarray, h: float, lo_m: float, hi_m: float) -> np.ndarray:
    sos = butter(4, [1.0 / hi_m, 1.0 / lo_m], btype="band", fs=1.0 / h, output="sos")
    return sosfiltfilt(sos, y)


@pytest.mark.parametrize("rate_hz", [1000.0, 200.0])
def test_the_cloud_undoes_the_edge_inverse_at_the_edges_own_step(rate_hz):
    """A quarter-car pass from finer physics, logged at ``rate_hz``, through the edge's pass processor
    (true parameters) and its pass-done's round trip through the schema and the aggregator; the
    continuous-time AP the cloud makes of it at the step the pass-done says, against the road at
    0.5–1 and 1–2 m. Measured: 1000 Hz 0.6/0.2 %, 200 Hz 0.8/0.2 % (undone at the legacy 2 ms instead:
    2.7/1.6 %, 11.9/5.9 %; the edge's AP as sent 2.3/1.5 %, 16.7/9.0 %)."""
    true = dict(TABLE_4_1["mean"])
    prof = tyre_filter(iso8608_profile(230.0, 0.01, "A", seed=11))
    speed, dt = 22.0, 1.0 / rate_hz
    sub = int(round(dt / FINE_S))
    system = QuarterCar(**true).system()
    r = simulate_on_profile(system, prof.at, prof.slope, 0.0, speed, 210.0 / speed, FINE_S, gamma=0.5)
    x = r.x_cg[::sub]
    chunk = SensorChunk(vehicle_id="veh-1", pass_id="p1", route_id="R1", vehicle_model="quarter_car", seq=0,
                        t0=0.0, sample_rate_hz=rate_hz, chainage=x, speed=np.full(x.size, speed),
                        channels={ch.name: r.channels[::sub, i].astype(np.float32)
                                  for i, ch in enumerate(system.channels)}, final=True)
    proc = PassProcessor(build_inverse(system, dt, gamma=edge_gamma("quarter_car")), "veh-1", "p1", "R1", 0,
                         model_name="quarter_car")
    segs = proc.feed(chunk)
    more, done = proc.finish()
    segs += more
    # The edge says its step; the cloud's pass state keeps what the pass-done said (as cloud.daemon.node
    # reads it for the correction), on the wire both ways.
    agg = Aggregator(parse_site({"route": [{"id": "R1", "length_m": 230.0}]}), [])
    for seg in segs:
        agg.on_segment(seg.encode(), "veh-1")
    (ack,) = agg.on_pass_done(done.encode())
    assert ack.n_segments_accepted == len(segs)
    ps = agg.passes[("veh-1", "p1")]
    assert ps.sample_interval_s == pytest.approx(dt, rel=1e-12)
    segs = [agg.held[sl] for sl in sorted(ps.slots)]
    fixed = continuous_segments("quarter_car", true, segs, ps.sample_interval_s)
    h = segs[0].spacing_m

    def on_grid(ss):
        lo, hi = min(s.start_index for s in ss), max(s.end_index for s in ss)
        v = np.full(hi - lo, np.nan)
        for s in ss:
            v[s.start_index - lo : s.end_index - lo] = s.values
        k = np.arange(lo, hi)
        ok = np.isfinite(v) & (k * h > 20.0) & (k * h < 190.0)  # past the warm-up, short of the end
        return k[ok] * h, v[ok]

    xg, ap = on_grid(segs)
    _, cont = on_grid(fixed)
    road = prof.at(xg)
    errors = {}
    for lo, hi in ((0.5, 1.0), (1.0, 2.0)):
        rb = _band(road, h, lo, hi)[100:-100]
        errors[(lo, hi)] = [float(np.std(_band(y, h, lo, hi)[100:-100] - rb) / np.std(rb)) for y in (ap, cont)]
    for (lo, hi), (sent, corrected) in errors.items():
        assert corrected < 0.015, (rate_hz, lo, hi, errors)
        assert corrected < 0.5 * sent, (rate_hz, lo, hi, errors)  # the test sees the edge's discretisation


def test_the_fused_profile_of_200_hz_logs_has_the_roads_gain(tmp_path):
    """Through the edge and cloud code (in process; nominal calibration = the true parameters, 0.2 %
    noise so the posterior hardly shrinks): six road-qc quarter-cars logged at 200 Hz, the fused
    profile's gain against the road at 0.5–1 and 1–2 m. The cloud must take the 5 ms step from the
    pass-done: undone at 2 ms the gain at 0.5–1 m is 1.085, at 5 ms 0.993 (1–2 m: 0.999)."""
    import dataclasses

    from shared.drivelog import list_drive_logs, read_drive_log
    from simfleet.scenarios import SCENARIOS
    from simfleet.sim import generate
    from tests.test_discretisation import fused_profile_gains

    sim = tmp_path / "sim"
    generate(dataclasses.replace(SCENARIOS["road-qc"], sample_rate_hz=200.0), sim, seed=5, passes=6, vehicles=6,
             noise_pct=0.2, nominal="true", workers=1, progress=False)
    assert {read_drive_log(p).meta.sample_rate_hz for p in list_drive_logs(sim / "logs")} == {200.0}
    for (lo, hi), gain in fused_profile_gains(sim, tmp_path / "out").items():
        assert abs(gain - 1.0) < 0.01, (lo, hi, gain)
