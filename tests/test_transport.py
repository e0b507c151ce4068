"""Key space helpers, and real Zenoh between OS processes through a router started from Python.

Waiting is always on an event with a timeout (``threading.Event.wait(t)`` or
``queue.Queue.get(timeout=t)``), never a sleep; ports come from the OS.
"""

from __future__ import annotations

import json
import queue
import socket
import subprocess
import sys
import tempfile
import threading
import textwrap

import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from shared import keys
from shared.schema import ApSegment, Calibration, decode_ap_segment, decode_calibration
from shared.transport import free_port, run_router, zenoh_config

TIMEOUT_S = 60.0  # a child's start-up (Python, zenoh) or a delivery on a loaded 2-core machine
NET = "test"

ids = st.from_regex(r"[A-Za-z0-9_.-]{1,32}", fullmatch=True)
BAD_IDS = ["", "a/b", "*", "a*", "**", "$x", "a$", "a b", "a?b", "a#b", "é", "x" * 129, None, 3, b"veh"]


# -- key space --------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(net=ids, route=ids, tile=st.integers(0, 10**9), vehicle=ids)
def test_ap_key_round_trip(net, route, tile, vehicle):
    key = keys.ap_key(net, route, tile, vehicle)
    assert keys.parse_ap_key(key) == (net, route, tile, vehicle)
    # zenoh agrees it is a key, and that the subscriptions cover it
    assert zenoh.KeyExpr(keys.ap_keyexpr(net)).includes(key)
    assert zenoh.KeyExpr(keys.ap_keyexpr(net, route)).includes(key)
    assert zenoh.KeyExpr(keys.ap_keyexpr(net, "*", vehicle)).includes(key)
    assert not zenoh.KeyExpr(keys.ap_keyexpr(net, route + "x")).includes(key)


def test_key_layout():
    assert keys.imu_key("n", "veh-1") == "driveby/n/veh/veh-1/imu"
    assert keys.ap_key("n", "R1", 12, "veh-1") == "driveby/n/ap/R1/12/veh-1"
    assert keys.ap_keyexpr("n") == "driveby/n/ap/*/**"
    assert keys.ap_keyexpr("n", "R2") == "driveby/n/ap/R2/**"
    assert keys.calib_key("n", "veh-1") == "driveby/n/calib/veh-1"
    assert keys.state_profile_key("n", "R1", 3) == "driveby/n/state/profile/R1/3"
    assert keys.state_bridge_key("n", "B1") == "driveby/n/state/bridge/B1"
    assert keys.alarm_key("n", "B1") == "driveby/n/alarm/B1"
    assert keys.alive_key("n", "edge", "veh-1") == "driveby/n/alive/edge/veh-1"
    assert keys.done_key("n", "veh-1") == "driveby/n/done/veh-1"
    assert keys.ack_key("n", "veh-1") == "driveby/n/ack/veh-1"


@pytest.mark.parametrize(
    "concrete, expr",
    [
        (keys.imu_key("n", "v"), keys.imu_keyexpr("n")),
        (keys.done_key("n", "v"), keys.done_keyexpr("n")),
        (keys.ack_key("n", "v"), keys.ack_keyexpr("n")),
        (keys.calib_key("n", "v"), keys.calib_keyexpr("n")),
        (keys.state_profile_key("n", "R1", 0), keys.state_profile_keyexpr("n", "R1")),
        (keys.state_profile_key("n", "R1", 0), keys.state_profile_keyexpr("n")),
        (keys.state_bridge_key("n", "B1"), keys.state_bridge_keyexpr("n")),
        (keys.alarm_key("n", "B1"), keys.alarm_keyexpr("n")),
        (keys.alive_key("n", "edge", "v"), keys.alive_keyexpr("n")),
        (keys.alive_key("n", "edge", "v"), keys.alive_keyexpr("n", "edge")),
    ],
)
def test_keyexprs_cover_their_keys(concrete, expr):
    assert zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(concrete))


def test_other_parsers_round_trip():
    assert keys.parse_alive_key(keys.alive_key("n", "cloud", "agg-1")) == ("n", "cloud", "agg-1")
    for topic, make in [("imu", keys.imu_key), ("calib", keys.calib_key), ("done", keys.done_key), ("ack", keys.ack_key)]:
        assert keys.parse_vehicle_key(make("n", "veh-9"), topic) == ("n", "veh-9")
    with pytest.raises(ValueError):
        keys.parse_vehicle_key(keys.done_key("n", "v"), "ack")
    with pytest.raises(ValueError):
        keys.parse_vehicle_key(keys.done_key("n", "v"), "nonsense")


@pytest.mark.parametrize("bad", BAD_IDS)
def test_builders_reject_bad_ids(bad):
    for build in (
        lambda: keys.imu_key(bad, "v"),
        lambda: keys.imu_key("n", bad),
        lambda: keys.ap_key("n", bad, 0, "v"),
        lambda: keys.ap_key("n", "R1", 0, bad),
        lambda: keys.calib_key("n", bad),
        lambda: keys.state_bridge_key("n", bad),
        lambda: keys.alive_key("n", "edge", bad),
        lambda: keys.done_key("n", bad),
        lambda: keys.ack_key(bad, "v"),
    ):
        with pytest.raises(ValueError):  # even "*": wildcards belong to *_keyexpr only
            build()


@pytest.mark.parametrize("tile", [-1, 1.0, "3", True, None])
def test_builders_reject_bad_tiles(tile):
    with pytest.raises(ValueError):
        keys.ap_key("n", "R1", tile, "v")
    with pytest.raises(ValueError):
        keys.state_profile_key("n", "R1", tile)


@pytest.mark.parametrize(
    "key",
    [
        "driveby/n/ap/R1/3",  # too short
        "driveby/n/ap/R1/3/v/x",  # too long
        "other/n/ap/R1/3/v",
        "driveby/n/calib/R1/3/v",
        "driveby/n/ap/R1/03/v",  # non-canonical tile
        "driveby/n/ap/R1/-3/v",
        "driveby/n/ap/R1/x/v",
        "driveby/n/ap/*/3/v",
        "driveby/n/ap/R1/3/**",
        "driveby/n/ap/R1/3/$v",
        "driveby/n/ap/R 1/3/v",
        "driveby//ap/R1/3/v",
        None,
    ],
)
def test_parse_ap_key_rejects(key):
    with pytest.raises(ValueError):
        keys.parse_ap_key(key)


# -- helpers: plain values -> config, ports ----------------------------------------------


def test_free_port_is_bindable():
    port = free_port()
    assert 1024 <= port <= 65535
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))


def test_zenoh_config_from_plain_values():
    conf = zenoh_config("client", connect="tcp/127.0.0.1:1234", listen=["tcp/127.0.0.1:0"])
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1234"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zenoh_config(no_multicast=False).get_json("scouting/multicast/enabled")) is None


def test_zenoh_config_file_and_overrides(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:0"] } }')
    conf = zenoh_config(None, config_file=path)
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(zenoh_config("peer", config_file=path).get_json("mode")) == "peer"


@pytest.mark.parametrize("kwargs", [{"mode": "server"}, {"connect": ["127.0.0.1:7447"]}, {"listen": [7447]}])
def test_zenoh_config_rejects(kwargs):
    with pytest.raises(ValueError):
        zenoh_config(**kwargs)


# -- real Zenoh between processes --------------------------------------------------------


@pytest.fixture(scope="module")
def router() -> str:
    with run_router(timeout_s=TIMEOUT_S) as endpoint:
        yield endpoint


class Child:
    """A ``python -c`` subprocess whose stdout lines arrive on a queue (read with a timeout)."""

    def __init__(self, script: str, *args: str) -> None:
        self._stderr = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", textwrap.dedent(script), *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        with self.proc.stdout:
            for line in self.proc.stdout:
                self.lines.put(line.strip())
        self.lines.put(None)

    def expect(self, word: str, timeout: float = TIMEOUT_S) -> None:
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            line = f"<nothing within {timeout} s>"
        assert line == word, f"child said {line!r}, expected {word!r}; stderr: {self.stderr()}"

    def stderr(self) -> str:
        self._stderr.seek(0)
        return self._stderr.read()[-3000:]

    def close(self) -> None:
        """Close its stdin (the child's cue to exit), then wait, then kill."""
        if self.proc.stdin and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(TIMEOUT_S)
        self._stderr.close()


@pytest.fixture
def children():
    started: list[Child] = []

    def start(script: str, *args: str) -> Child:
        child = Child(script, *args)
        started.append(child)
        return child

    yield start
    for child in started:
        child.close()


def _conf(mode: str, endpoint: str) -> zenoh.Config:
    listen = ["tcp/127.0.0.1:0"] if mode == "peer" else []
    return zenoh_config(mode, connect=[endpoint], listen=listen)


PUBLISHER = """
    import sys, threading, zenoh
    from shared.transport import zenoh_config
    endpoint, mode, key, path, timeout = sys.argv[1:6]
    payload = open(path, "rb").read()
    listen = ["tcp/127.0.0.1:0"] if mode == "peer" else []
    with zenoh.open(zenoh_config(mode, connect=[endpoint], listen=listen)) as session:
        pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        matched = threading.Event()
        listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
        if pub.matching_status.matching:  # NB: the MatchingStatus object itself is always truthy
            matched.set()
        if not matched.wait(float(timeout)):
            print("unmatched", flush=True)
            sys.exit(1)
        pub.put(payload)
        print("sent", flush=True)
        sys.stdin.read()  # keep the session until the test closes our stdin
"""


def _segment() -> ApSegment:
    x = np.arange(1000) * 0.05
    return ApSegment.make(
        0.01 * np.sin(x),
        np.full(1000, 2e-4),
        vehicle_id="veh-0007",
        pass_id="pass-1",
        route_id="R1",
        tile=4,
        axle=1,
        start_index=4000,
        spacing_m=0.05,
        calib_version=0,
        speed_mps=18.0,
        t_first=11.0,
        t_last=13.8,
        seq=0,
        n_segments_in_pass=5,
    )


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_ap_segment_crosses_processes_through_router(router, children, tmp_path, mode):
    segment = _segment()
    path = tmp_path / "segment.arrow"
    path.write_bytes(segment.encode())
    key = keys.ap_key(NET, "R1", 4, "veh-0007")

    received: list[zenoh.Sample] = []
    arrived = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append(sample)
        arrived.set()

    with zenoh.open(_conf(mode, router)) as session:
        session.declare_subscriber(keys.ap_keyexpr(NET, "R1"), on_sample)
        child = children(PUBLISHER, router, mode, key, str(path), str(TIMEOUT_S))
        # The child's start-up, then its wait for a match: each within TIMEOUT_S.
        assert arrived.wait(2 * TIMEOUT_S), f"no sample; publisher stderr: {child.stderr()}"
        child.expect("sent")
    sample = received[0]
    assert str(sample.key_expr) == key
    assert keys.parse_ap_key(str(sample.key_expr))[3] == segment.vehicle_id
    assert decode_ap_segment(sample.payload.to_bytes()) == segment


QUERYABLE = """
    import sys, zenoh
    from shared.transport import zenoh_config
    endpoint, key, path = sys.argv[1:4]
    payload = open(path, "rb").read()

    def on_query(query):
        with query:  # leaving the block finalises the query, so the querier is not left waiting
            query.reply(key, payload)

    with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        session.declare_queryable(key, on_query)
        print("ready", flush=True)
        sys.stdin.read()
"""


def test_queryable_in_another_process_answers_get(router, children, tmp_path):
    calib = Calibration("veh-0007", 4, "quarter_car", {"K/M": 112.4, "k/M": 438.2}, "fleet")
    path = tmp_path / "calib.arrow"
    path.write_bytes(calib.encode())
    key = keys.state_profile_key(NET, "R1", 7)
    child = children(QUERYABLE, router, key, str(path))
    child.expect("ready")

    with zenoh.open(_conf("client", router)) as session:
        querier = session.declare_querier(key, timeout=TIMEOUT_S)
        # "ready" was printed once declared locally; the router may not know yet.
        matched = threading.Event()
        _listener = querier.declare_matching_listener(lambda s: s.matching and matched.set())
        if querier.matching_status.matching:
            matched.set()
        assert matched.wait(TIMEOUT_S), child.stderr()

        replies: list[zenoh.Reply] = []
        done = threading.Event()
        querier.get(zenoh.handlers.Callback(replies.append, done.set))
        assert done.wait(TIMEOUT_S + 1)  # the drop callback fires once the query is finalised
    assert len(replies) == 1 and replies[0].ok is not None, [str(r.err and r.err.payload.to_string()) for r in replies]
    assert str(replies[0].ok.key_expr) == key
    assert decode_calibration(replies[0].ok.payload.to_bytes()) == calib


TOKEN = """
    import sys, zenoh
    from shared.transport import zenoh_config
    endpoint, key = sys.argv[1:3]
    with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        token = session.liveliness().declare_token(key)
        print("declared", flush=True)
        sys.stdin.read()
"""


@pytest.mark.parametrize("ending", ["exit", "kill"])
def test_liveliness_token_seen_and_lost(router, children, ending):
    key = keys.alive_key(NET, "edge", f"veh-{ending}")
    alive, gone = threading.Event(), threading.Event()
    kinds: list[zenoh.SampleKind] = []

    def on_change(sample: zenoh.Sample) -> None:
        if str(sample.key_expr) != key:
            return
        kinds.append(sample.kind)
        (alive if sample.kind == zenoh.SampleKind.PUT else gone).set()

    with zenoh.open(_conf("client", router)) as session:
        # history=True: a token declared before this subscriber is reported too
        session.liveliness().declare_subscriber(keys.alive_keyexpr(NET, "edge"), on_change, history=True)
        child = children(TOKEN, router, key)
        child.expect("declared")
        assert alive.wait(TIMEOUT_S), child.stderr()
        assert not gone.is_set()
        if ending == "kill":
            child.proc.kill()  # a crash: no undeclare, the router sees the link drop
        else:
            child.proc.stdin.close()  # a clean exit
        child.proc.wait(TIMEOUT_S)
        assert gone.wait(TIMEOUT_S)
    assert kinds == [zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE]


def test_router_stops_and_frees_its_port():
    port = free_port()
    with run_router(port, timeout_s=TIMEOUT_S) as endpoint:
        assert endpoint == f"tcp/127.0.0.1:{port}"
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
            assert session.info.routers_zid()
    with socket.socket() as s:  # nothing listens there any more
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()


def test_run_router_reports_a_port_it_cannot_take():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(RuntimeError, match="did not start"):
            with run_router(port, timeout_s=TIMEOUT_S):
                pass


def test_the_edges_raw_spool_is_bounded_across_the_fleet(tmp_path):
    """A large fleet's raw passes (kept to recompute when a calibration arrives) are bounded in bytes
    for the whole edge, not only per vehicle: the oldest are dropped, counted, and no longer
    recomputed; those kept still are."""
    import dataclasses

    from edge.node import Edge
    from shared.drivelog import list_drive_logs, read_drive_log
    from shared.schema import decode_pass_done
    from simfleet.replay import chunks_of
    from simfleet.scenarios import SCENARIOS
    from simfleet.sim import generate

    generate(SCENARIOS["road-qc"], tmp_path, seed=5, passes=1, workers=1, progress=False)
    log = read_drive_log(list_drive_logs(tmp_path / "logs")[0])
    chunks = list(chunks_of(log))

    def payloads(vehicle, pass_id):
        return [dataclasses.replace(c, vehicle_id=vehicle, pass_id=pass_id).encode() for c in chunks]

    pass_bytes = sum(map(len, payloads("a", "p0")))
    done: list[tuple[str, int]] = []

    def publish(key, payload):
        if "/done/" in key:
            d = decode_pass_done(payload)
            done.append((d.pass_id, d.calib_version))

    edge = Edge("n", publish, calibration="nominal", spool_max_bytes=int(2.5 * pass_bytes))
    vehicles = ("a", "b")
    for k in range(4):  # passes p0..p3, alternating vehicles
        for payload in payloads(vehicles[k % 2], f"p{k}"):
            edge.on_chunk(payload)
    assert [p for p, _ in done] == ["p0", "p1", "p2", "p3"] and not edge.rejected
    kept = sum(map(len, payloads("a", "p2"))) + sum(map(len, payloads("b", "p3")))
    assert edge.stats()["raw_spool"] == {"passes": 2, "bytes": kept, "evicted": 2}
    done.clear()
    for vehicle in vehicles:  # a new calibration: what is still spooled is recomputed under it
        edge.on_calibration(Calibration(vehicle, 1, log.meta.vehicle_model, dict(log.meta.nominal_params),
                                        "fleet").encode())
    assert sorted(done) == [("p2", 1), ("p3", 1)]
