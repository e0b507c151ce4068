"""The edge's bank path (a tick of raw chunks decoded together, one inverse call per model) against
the one-chunk-at-a-time path: the same messages, byte for byte, and the same rejections."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edge.bank import feed_bank
from edge.bank_decode import ChunkDecoder, same_chunk
from edge.node import Edge
from edge.pipeline import EdgeConfig, PassProcessor
from shared.drivelog import list_drive_logs, read_drive_log
from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma, update_streams
from shared.registry import load_site
from shared.schema import Calibration, DecodeError, decode_pass_done, decode_sensor_chunk
from shared.vehicles import vehicle_from_params
from simfleet.replay import chunks_of
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

NET = "bank"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Quarter-car passes at different speeds (so different lengths) and half-car passes: two models."""
    qc, hc = tmp_path_factory.mktemp("qc"), tmp_path_factory.mktemp("hc")
    generate(SCENARIOS["road-qc"], qc, seed=3, passes=4, workers=1, progress=False)
    generate(SCENARIOS["road-hc"], hc, seed=4, passes=2, workers=1, progress=False)
    logs = [read_drive_log(p) for d in (qc, hc) for p in list_drive_logs(d / "logs")]
    return load_site(qc / "site.toml"), logs


def _fleet(logs, n_vehicles: int, passes: int) -> list[list[bytes]]:
    """Each vehicle's chunk payloads in order: ``passes`` passes of different logs each, renamed."""
    out = []
    for i in range(n_vehicles):
        vehicle = f"bk-{i:02d}"
        stream = []
        for k in range(passes):
            log = logs[(i + 3 * k) % len(logs)]
            stream += [dataclasses.replace(c, vehicle_id=vehicle, pass_id=f"{vehicle}-p{k}").encode()
                       for c in chunks_of(log)]
        out.append(stream)
    return out


def _ticks(streams: list[list[bytes]], starts: list[int], per_tick: int) -> list[list[bytes]]:
    """The fleet's payloads as ticks: vehicle i starts at tick ``starts[i]`` and sends ``per_tick``
    chunks a tick (more than one: a vehicle catching up, several of its chunks in one tick)."""
    ticks: list[list[bytes]] = []
    for stream, start in zip(streams, starts):
        for j, payload in enumerate(stream):
            t = start + j // per_tick
            while len(ticks) <= t:
                ticks.append([])
            ticks[t].append(payload)
    return ticks


def _by_vehicle(published: list[tuple[str, bytes]]) -> dict[str, list[tuple[str, bytes]]]:
    out: dict[str, list[tuple[str, bytes]]] = {}
    for key, payload in published:
        out.setdefault(key.rsplit("/", 1)[-1], []).append((key, payload))
    return out


@pytest.mark.parametrize("per_tick", [1, 3])
def test_the_bank_publishes_what_one_chunk_at_a_time_publishes(world, per_tick):
    site, logs = world
    streams = _fleet(logs, 9, 2)
    ticks = _ticks(streams, [0, 0, 1, 5, 5, 17, 40, 41, 90], per_tick)
    calibrated = "bk-02"  # calibrated mid-run: its first pass is spooled (and recomputed), then more follow
    first_pass = sum(decode_sensor_chunk(p).pass_id.endswith("-p0") for p in streams[2])
    cal_tick = 1 + first_pass // per_tick + 1
    params = {k: v * 1.07 for k, v in decode_sensor_chunk(streams[2][0]).nominal_params.items()}
    cal = Calibration(calibrated, 1, decode_sensor_chunk(streams[2][0]).vehicle_model, params, "fleet").encode()

    one, bank = [], []
    ref = Edge(NET, lambda k, p: one.append((k, p)), site)
    fast = Edge(NET, lambda k, p: bank.append((k, p)), site)
    for t, tick in enumerate(ticks):
        if t == cal_tick:
            ref.on_calibration(cal)
            fast.on_calibration(cal)
        for payload in tick:
            ref.on_chunk(payload)
        fast.on_chunks([(p, None, None) for p in tick])
    assert not ref.rejected and not fast.rejected
    a, b = _by_vehicle(one), _by_vehicle(bank)
    assert a.keys() == b.keys() and len(a) == len(streams)
    for vehicle in a:
        assert a[vehicle] == b[vehicle], vehicle  # every message, in order, byte for byte
    assert ref.segments_published == fast.segments_published > 0
    # the calibration took effect: the spooled pass republished and the pass under way finished under it
    versions = [decode_pass_done(p).calib_version for k, p in b[calibrated] if "/done/" in k]
    assert versions[0] == 0 and versions[1:].count(1) >= 1
    # the bank path decoded almost everything on its fast path (the first chunk of each layout and
    # of each pass goes through the contract's decoder)
    assert fast.decoder.fast > 0.8 * sum(len(s) for s in streams)


def test_update_streams_matches_each_stream_alone(world):
    _, logs = world
    qc = [log for log in logs if log.meta.vehicle_model == "quarter_car"]
    models = [build_inverse(vehicle_from_params("quarter_car", {k: v * (1 + 0.05 * i) for k, v in
                                                                 qc[0].meta.nominal_params.items()}).system(),
                            1.0 / qc[0].meta.sample_rate_hz, gamma=edge_gamma("quarter_car")) for i in range(5)]
    rng = np.random.default_rng(0)
    z = rng.standard_normal((3, 57, 1, 5))
    alone = [InverseStream(m) for m in models]
    together = [InverseStream(m) for m in models]
    for k in range(3):
        members = [0, 1, 2, 3, 4] if k != 1 else [4, 1, 3]  # members change between calls
        if k == 2:
            together[0] = InverseStream(models[0])  # and one starts afresh
            alone[0] = InverseStream(models[0])
        y = update_streams([together[q] for q in members], z[k][:, :, members])
        for j, q in enumerate(members):
            assert y[:, :, j].tobytes() == alone[q].update(z[k][:, :, q]).tobytes()


def test_feed_bank_isolates_a_failing_pass(world):
    _, logs = world
    log = logs[0]
    m = log.meta
    model = build_inverse(vehicle_from_params(m.vehicle_model, m.nominal_params).system(), 1.0 / m.sample_rate_hz,
                          gamma=edge_gamma(m.vehicle_model))
    good = PassProcessor(model, "a", "a-p", m.route_id, 0, EdgeConfig(), m.vehicle_model)
    bad = PassProcessor(model, "b", "b-p", m.route_id, 0, EdgeConfig(), m.vehicle_model)
    chunk = next(chunks_of(log))
    broken = dataclasses.replace(chunk, channels={"other": chunk.channels[next(iter(chunk.channels))]})
    out = feed_bank([(good, chunk), (bad, broken)])
    assert isinstance(out[0], list) and isinstance(out[1], ValueError)


def _corrupt(payload: bytes, at: int, value: bytes) -> bytes:
    return payload[:at] + value + payload[at + len(value):]


def test_the_decoder_accepts_and_refuses_as_the_contract(world):
    _, logs = world
    log = logs[0]
    good = [c.encode() for c in chunks_of(log)]
    seen = ChunkDecoder()
    seen.decode(good[:2])  # the layout is planned and the pass's strings are known
    chainage_at = good[5].rindex(np.asarray(decode_sensor_chunk(good[5]).chainage[:1]).tobytes())
    cases = [
        good[5],
        _corrupt(good[5], chainage_at, np.array([np.nan]).tobytes()),  # a value: non_finite
        _corrupt(good[5], chainage_at, np.array([1e12]).tobytes()),  # out of range: bad_value
        good[5].replace(log.meta.vehicle_id.encode(), b"v\xff" + log.meta.vehicle_id.encode()[2:]),  # not UTF-8
        good[5].replace(log.meta.pass_id.encode(), b"\x01" + log.meta.pass_id.encode()[1:]),  # control character
        good[5][:-3],  # truncated
        b"not arrow at all",
        _corrupt(good[5], 2200, b"\x7f"),  # somewhere in the structure
        _corrupt(good[5], 300, b"\x7f"),  # in the schema (the plan's key: another layout)
        _corrupt(good[5], len(good[5]) - 1200, b"\x7f"),  # in the body's buffers
    ]
    got = seen.decode(cases)
    for payload, result in zip(cases, got):
        try:
            want = decode_sensor_chunk(payload)
        except DecodeError as e:
            assert isinstance(result, DecodeError) and result.reason == e.reason
            continue
        assert not isinstance(result, DecodeError) and same_chunk(result, want)
    assert isinstance(got[1], DecodeError) and got[1].reason == "non_finite"
    assert isinstance(got[2], DecodeError) and got[2].reason == "bad_value"
    assert same_chunk(got[0], decode_sensor_chunk(good[5]))


def test_the_daemon_serves_ticks_over_zenoh_as_one_chunk_at_a_time(world):
    """serve(): raw chunks from several vehicles put back to back (so the worker takes them in ticks
    of many), a calibration among them; what the edge publishes over a real router is, per vehicle,
    what the in-process edge publishes one chunk at a time, calibration in the same place.

    The calibration arrives on its own key and subscriber, so over Zenoh its place among the raw
    chunks is not given by the order of the puts: the test puts it once the edge has taken in every
    chunk before it, and puts the chunks after it once the edge has applied it (the real handlers,
    observed), so the place is the reference's."""
    import threading

    import zenoh

    from edge.node import serve
    from shared import keys
    from shared.transport import run_router, zenoh_config

    site, logs = world
    streams = _fleet(logs, 6, 2)
    cal_vehicle = "bk-01"
    first = decode_sensor_chunk(streams[1][0])
    cal = Calibration(cal_vehicle, 1, first.vehicle_model, {k: v * 0.95 for k, v in first.nominal_params.items()},
                      "fleet").encode()
    order: list[tuple[str, str, bytes]] = []  # (kind, vehicle, payload) in publication order
    for k in range(max(len(s) for s in streams)):
        if k == 5:
            order.append(("calib", cal_vehicle, cal))
        order += [("imu", decode_sensor_chunk(s[k]).vehicle_id, s[k]) for s in streams if k < len(s)]
    want: list[tuple[str, bytes]] = []
    ref = Edge(NET, lambda key, p: want.append((key, p)), site)
    for kind, vehicle, payload in order:
        (ref.on_chunk if kind == "imu" else ref.on_calibration)(payload, vehicle)
    n_expected = len(want)

    got: list[tuple[str, bytes]] = []
    all_in, stop = threading.Event(), threading.Event()
    before_cal = next(i for i, (kind, _, _) in enumerate(order) if kind == "calib")
    taken = threading.Condition()
    chunks_taken = [0]
    applied = threading.Event()

    def collect(sample):
        got.append((str(sample.key_expr), sample.payload.to_bytes()))
        if len(got) >= n_expected:
            all_in.set()

    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as edge_s, \
            zenoh.open(zenoh_config("client", connect=[endpoint])) as veh_s:
        edge = Edge(NET, lambda key, p: edge_s.put(key, p, congestion_control=zenoh.CongestionControl.BLOCK), site)
        real_chunks, real_calibration = edge.on_chunks, edge.on_calibration

        def on_chunks(messages):  # the real handler, counted (serve() looks it up on the instance)
            real_chunks(messages)
            with taken:
                chunks_taken[0] += len(messages)
                taken.notify_all()

        def on_calibration(payload, vehicle=None):
            real_calibration(payload, vehicle)
            applied.set()

        edge.on_chunks, edge.on_calibration = on_chunks, on_calibration
        subs = [veh_s.declare_subscriber(keys.ap_keyexpr(NET), collect),
                veh_s.declare_subscriber(keys.done_keyexpr(NET), collect)]
        server = threading.Thread(target=serve, args=(edge_s, edge, "edge-bank", stop), daemon=True)
        server.start()
        up = threading.Event()
        watch = veh_s.liveliness().declare_subscriber(keys.alive_key(NET, "edge", "edge-bank"),
                                                      lambda s: up.set(), history=True)
        assert up.wait(60.0), "the edge never came up"
        watch.undeclare()
        for i, (kind, vehicle, payload) in enumerate(order):
            if kind == "imu":
                veh_s.put(keys.imu_key(NET, vehicle), payload, congestion_control=zenoh.CongestionControl.BLOCK)
                continue
            with taken:
                assert taken.wait_for(lambda: chunks_taken[0] >= before_cal, 120.0), "chunks before the calibration"
            veh_s.put(keys.calib_key(NET, vehicle), payload, congestion_control=zenoh.CongestionControl.BLOCK)
            assert applied.wait(120.0), "the calibration was never applied"
        assert all_in.wait(120.0), f"{len(got)} of {n_expected} messages arrived"
        stop.set()
        server.join(30.0)
        for s in subs:
            s.undeclare()
    assert not edge.rejected
    # per vehicle and kind (two subscriptions: their deliveries interleave freely), in order
    def split(messages):
        return {(v, kind): [m for m in ms if f"/{kind}/" in m[0]] for v, ms in _by_vehicle(messages).items()
                for kind in ("ap", "done")}

    assert split(got) == split(want) and len(got) == n_expected


def test_a_busy_edge_holds_zenoh_back_instead_of_queueing_without_bound(world, monkeypatch):
    """serve(): while the worker is busy, at most INBOX_MESSAGES wait for it (zenoh's delivering
    thread waits beyond that, so the publisher's puts are held back), and nothing is lost."""
    import threading

    import zenoh

    from edge import node
    from edge.node import serve
    from shared import keys
    from shared.transport import run_router, zenoh_config

    site, logs = world
    monkeypatch.setattr(node, "INBOX_MESSAGES", 8)
    stream = _fleet(logs, 1, 1)[0]
    vehicle = decode_sensor_chunk(stream[0]).vehicle_id
    ticks: list[int] = []
    first_busy = threading.Event()

    class BusyEdge(Edge):
        def on_chunks(self, messages):
            ticks.append(len(messages))
            if len(ticks) == 1:
                first_busy.wait(0.5)  # busy: the chunks behind this tick pile up against the bound
            super().on_chunks(messages)

    done, stop = threading.Event(), threading.Event()
    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as edge_s, \
            zenoh.open(zenoh_config("client", connect=[endpoint])) as veh_s:
        edge = BusyEdge(NET, lambda key, p: edge_s.put(key, p), site)
        sub = veh_s.declare_subscriber(keys.done_keyexpr(NET), lambda s: done.set())
        server = threading.Thread(target=serve, args=(edge_s, edge, "edge-busy", stop), daemon=True)
        server.start()
        up = threading.Event()
        watch = veh_s.liveliness().declare_subscriber(keys.alive_key(NET, "edge", "edge-busy"),
                                                      lambda s: up.set(), history=True)
        assert up.wait(60.0), "the edge never came up"
        watch.undeclare()
        for payload in stream:
            veh_s.put(keys.imu_key(NET, vehicle), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        assert done.wait(120.0), "the pass never ended"
        stop.set()
        server.join(30.0)
        sub.undeclare()
    assert sum(ticks) == len(stream) and not edge.rejected  # every chunk, once
    assert max(ticks) <= 8 < len(stream)  # never more than the bound waiting
    assert len(ticks) > 1
