"""Security is Zenoh's: TLS with mutual authentication and access control, configured by
``shared.security``, tested against a real router in its own process on a free port.

Certificates are made here, at test time (openssl). Every wait is on an event with a timeout.
A refusal is shown to be Zenoh's by ordering: the forged message is published *before* an
allowed one on the same session and link, so had the router forwarded it, it would have
arrived first; the allowed one arriving while the forged one never did is the proof.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from shared import keys
from shared.drivelog import list_drive_logs, read_drive_log
from shared.schema import ApSegment, Calibration, decode_ap_segment, decode_calibration, decode_sensor_chunk
from shared.security import (
    ROLES,
    DenialCounter,
    SecurityDir,
    SecurityError,
    TlsFiles,
    access_control,
    denials_key,
    init_ca,
    issue,
)
from shared.transport import add_zenoh_arguments, config_from_args, run_router, zenoh_config
from simfleet.replay import replay
from simfleet.scenarios import SCENARIOS
from simfleet.sim import generate

NET = "sec"
TIMEOUT_S = 60.0  # a delivery, a router start or a query answered on a loaded 2-core machine
DAEMON_TIMEOUT_S = 120.0  # the first cloud start may compile numba kernels into the cache
IDENTITIES = {"router-1": "router", "cloud-1": "aggregator", "V1": "vehicle", "V2": "vehicle",
              "veh-0001": "vehicle", "viewer-1": "viewer"}


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> SecurityDir:
    sec = init_ca(tmp_path_factory.mktemp("pki"))
    for name, role in IDENTITIES.items():
        issue(sec, name, role)
    return sec


@pytest.fixture(scope="module")
def router(pki):
    with run_router(security=pki.path, net=NET, router_id="router-1", timeout_s=TIMEOUT_S) as endpoint:
        yield endpoint


def _session(endpoint: str, tls: TlsFiles) -> zenoh.Session:
    return zenoh.open(zenoh_config("client", connect=[endpoint], tls=tls))


def _segment(vehicle: str, seq: int = 0, tile: int = 0) -> ApSegment:
    return ApSegment.make(np.linspace(0.0, 0.01, 20), np.full(20, 1e-4), vehicle_id=vehicle, pass_id="p1",
                          route_id="R1", tile=tile, axle=1, start_index=tile * 1000 + 40, spacing_m=0.05,
                          calib_version=0, speed_mps=20.0, t_first=0.0, t_last=1.0, seq=seq)


def _denials(session: zenoh.Session, who: str, at_least: int = 0) -> dict:
    """The router's refusal counts, asked until ``who`` has ``at_least`` (each answer is an event)."""
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        replies = list(session.get(denials_key(NET, "router-1"), timeout=TIMEOUT_S))
        assert replies and replies[0].ok is not None, "the router did not answer its denial counts"
        body = json.loads(replies[0].ok.payload.to_bytes())
        body["n"] = sum(e["n"] for e in body["by"] if e["who"] == who)
        if body["n"] >= at_least:
            return body
        assert time.monotonic() < deadline, f"refusals not counted: {body}"


def _put_until_received(pub: zenoh.Session, key: str, payload: bytes, got: threading.Event) -> None:
    """Publish until a subscriber confirms (the subscription may still be on its way to the router)."""
    deadline = time.monotonic() + TIMEOUT_S
    while not got.is_set():
        assert time.monotonic() < deadline, f"{key} was never delivered"
        pub.put(key, payload)
        got.wait(0.5)


def test_vehicle_publishes_its_own_keys_and_zenoh_refuses_anothers(pki, router):
    received: queue.Queue = queue.Queue()
    probe = threading.Event()

    def on_ap(sample):
        seg = decode_ap_segment(sample.payload.to_bytes())
        received.put((str(sample.key_expr), seg.vehicle_id, seg.seq))
        if seg.seq == 0:
            probe.set()

    # The vehicle's session comes from the daemons' own options (what `driveby edge` parses).
    p = argparse.ArgumentParser()
    add_zenoh_arguments(p)
    args = p.parse_args(["--connect", router, "--tls-ca", str(pki.path / "ca.pem"),
                         "--tls-cert", str(pki.path / "V1.pem"), "--tls-key", str(pki.path / "V1.key")])
    with _session(router, pki.tls("cloud-1")) as cloud, zenoh.open(config_from_args(args)) as v1, \
            _session(router, pki.tls("viewer-1")) as viewer:
        cloud.declare_subscriber(keys.ap_keyexpr(NET), on_ap)
        _put_until_received(v1, keys.ap_key(NET, "R1", 0, "V1"), _segment("V1", 0).encode(), probe)

        forged_key = keys.ap_key(NET, "R1", 1, "V2")
        v1.put(forged_key, _segment("V2", 1, tile=1).encode())  # V1 claiming to be V2
        v1.put(keys.ap_key(NET, "R1", 1, "V1"), _segment("V1", 1, tile=1).encode())  # then its own
        while True:
            key, vehicle, seq = received.get(timeout=TIMEOUT_S)
            assert key != forged_key and vehicle == "V1", "the router forwarded a forged segment"
            if seq == 1:
                break
        assert all(item[1] == "V1" for item in list(received.queue))

        body = _denials(viewer, "V1", 1)
        mine = [e for e in body["by"] if e["who"] == "V1"]
        assert mine == [{"who": "V1", "message": "put", "flow": "ingress", "n": 1}], body
        assert {"who": "V1", "message": "put", "flow": "ingress", "key": forged_key} in body["recent"]


def test_vehicle_reads_only_its_calibration(pki, router):
    got: queue.Queue = queue.Queue()
    probe = threading.Event()

    def on_calib(sample):
        cal = decode_calibration(sample.payload.to_bytes())
        got.put((cal.vehicle_id, cal.version))
        probe.set()

    def calibration(vehicle: str, version: int) -> bytes:
        return Calibration(vehicle, version, "quarter_car", {"K/M": 112.0}, "fleet").encode()

    with _session(router, pki.tls("cloud-1")) as cloud, _session(router, pki.tls("V2")) as v2, \
            _session(router, pki.tls("viewer-1")) as viewer:
        v2.declare_subscriber(keys.calib_keyexpr(NET), on_calib)  # by wildcard, as the edge daemon does
        _put_until_received(cloud, keys.calib_key(NET, "V2"), calibration("V2", 1), probe)
        cloud.put(keys.calib_key(NET, "V1"), calibration("V1", 2))  # another vehicle's: not for V2's eyes
        cloud.put(keys.calib_key(NET, "V2"), calibration("V2", 2))
        while (item := got.get(timeout=TIMEOUT_S)) != ("V2", 2):
            assert item == ("V2", 1), f"V2 received {item}"
        assert got.empty()
        body = _denials(viewer, "V2", 1)
        assert {"who": "V2", "message": "put", "flow": "egress", "key": keys.calib_key(NET, "V1")} in body["recent"]


def test_without_a_valid_certificate_the_connection_is_refused(pki, router, tmp_path):
    with pytest.raises(zenoh.ZError):  # the CA but no certificate of one's own
        zenoh.open(zenoh_config("client", connect=[router], tls=pki.tls()))
    rogue = init_ca(tmp_path / "rogue")  # a certificate named like a vehicle, from another CA
    issue(rogue, "V1", "vehicle")
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config("client", connect=[router],
                                tls=TlsFiles(pki.path / "ca.pem", rogue.path / "V1.pem", rogue.path / "V1.key")))
    with pytest.raises(zenoh.ZError):  # plain TCP to the TLS port
        zenoh.open(zenoh_config("client", connect=[router.replace("tls/", "tcp/")]))


@pytest.fixture(scope="module")
def road(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=3, passes=1, workers=1, progress=False)
    return out


def _daemon(module: str, router: str, pki: SecurityDir, name: str, workdir: Path, *extra: str) -> subprocess.Popen:
    tls = ["--tls-ca", str(pki.path / "ca.pem"), "--tls-cert", str(pki.path / f"{name}.pem"),
           "--tls-key", str(pki.path / f"{name}.key")]
    return subprocess.Popen([sys.executable, "-m", module, "--connect", router, *tls, "--net", NET, "--id", name,
                             *extra], env=dict(os.environ, PYTHONUNBUFFERED="1"), stdin=subprocess.DEVNULL,
                            stdout=open(workdir / f"{module}.log", "wb"), stderr=subprocess.STDOUT)


def test_real_daemons_under_access_control(pki, router, road, tmp_path):
    """The roles suffice for the real daemons: a vehicle's own edge (its raw stream in, its calibration,
    the cloud's liveliness) and the cloud (segments in, acks out, queries); a vehicle's pass goes end to end
    over TLS. A forged segment never reaches the cloud: its own counters show no trace of it."""
    vehicle = "veh-0001"  # the log's vehicle, and its identity
    site = str(road / "site.toml")
    procs = [_daemon("cloud", router, pki, "cloud-1", tmp_path, "--site", site, "--calibration", "nominal"),
             _daemon("edge", router, pki, vehicle, tmp_path, "--site", site, "--calibration", "nominal",
                     "--vehicle", vehicle)]
    try:
        with _session(router, pki.tls("viewer-1")) as viewer, _session(router, pki.tls(vehicle)) as sensor, \
                _session(router, pki.tls("V1")) as v1:
            up, acked = threading.Event(), threading.Event()
            alive: set[str] = set()

            def on_alive(sample):
                if sample.kind == zenoh.SampleKind.PUT:
                    alive.add(str(sample.key_expr))
                if {keys.alive_key(NET, "cloud", "cloud-1"), keys.alive_key(NET, "edge", vehicle)} <= alive:
                    up.set()

            viewer.liveliness().declare_subscriber(keys.alive_keyexpr(NET), on_alive, history=True)
            viewer.declare_subscriber(keys.ack_key(NET, vehicle), lambda s: acked.set())
            assert up.wait(DAEMON_TIMEOUT_S), \
                f"daemons did not come up: {alive} {[(tmp_path / f'{m}.log').read_text() for m in ('cloud', 'edge')]}"

            log = read_drive_log(list_drive_logs(road / "logs")[0])
            assert log.meta.vehicle_id == vehicle
            replay([log], lambda k, p: sensor.put(k, p, congestion_control=zenoh.CongestionControl.BLOCK), NET)
            assert acked.wait(DAEMON_TIMEOUT_S), "the vehicle's pass was not acknowledged through the secured router"

            def stats() -> dict:
                replies = list(viewer.get(keys.control_key(NET, "cloud-1", "stats"), timeout=TIMEOUT_S))
                assert replies and replies[0].ok is not None, "the viewer may ask the cloud's statistics"
                return json.loads(replies[0].ok.payload.to_bytes())["stats"]

            before, denied = stats(), _denials(viewer, "V1")["n"]
            assert before["accepted"] > 0
            v1.put(keys.ap_key(NET, "R1", 0, vehicle), _segment(vehicle, 0).encode())  # forged first
            v1.put(keys.ap_key(NET, "R1", 0, "V1"), _segment("V1", 0).encode())
            deadline = time.monotonic() + TIMEOUT_S
            while (after := stats())["accepted"] == before["accepted"]:
                assert time.monotonic() < deadline, f"V1's own segment not accepted: {after}"
            assert after["accepted"] == before["accepted"] + 1, after
            assert after["rejected"] == before["rejected"], after  # the cloud never saw the forgery
            assert _denials(viewer, "V1", denied + 1)["n"] == denied + 1
            assert all(p.poll() is None for p in procs)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()


def test_every_vehicle_rule_names_only_its_own_keys():
    acl = access_control(NET, {"V1": "vehicle", "V2": "vehicle", "c": "aggregator"})
    assert acl["default_permission"] == "deny"
    by_id = {r["id"]: r for r in acl["rules"]}
    policy = {p["id"]: p for p in acl["policies"]}
    for me, other in (("V1", "V2"), ("V2", "V1")):
        assert {"id": me, "cert_common_names": [me]} in acl["subjects"]
        publish = [k for rid in policy[me]["rules"] for r in [by_id[rid]] if r["flows"] == ["ingress"]
                   and "put" in r["messages"] for k in r["key_exprs"]]
        receive = [k for rid in policy[me]["rules"] for r in [by_id[rid]] if r["flows"] == ["egress"]
                   and "put" in r["messages"] for k in r["key_exprs"]]
        own = [keys.imu_key(NET, me), keys.ap_key(NET, "R1", 3, me), keys.done_key(NET, me)]
        theirs = [keys.imu_key(NET, other), keys.ap_key(NET, "R1", 3, other), keys.done_key(NET, other),
                  keys.calib_key(NET, me), keys.status_key(NET, me), keys.ack_key(NET, me)]
        assert all(any(zenoh.KeyExpr(k).includes(key) for k in publish) for key in own)
        assert not any(zenoh.KeyExpr(k).intersects(zenoh.KeyExpr(key)) for k in publish for key in theirs)
        assert all(any(zenoh.KeyExpr(k).includes(key) for k in receive)
                   for key in (keys.calib_key(NET, me), keys.ack_key(NET, me)))
        assert not any(zenoh.KeyExpr(k).intersects(zenoh.KeyExpr(key)) for k in receive
                       for key in (keys.calib_key(NET, other), keys.imu_key(NET, other), keys.ack_key(NET, other)))
    assert set(ROLES) >= {"vehicle", "aggregator", "viewer", "router"}
    # Nobody but a vehicle (and the trusted fleet roles) publishes segments; a viewer publishes nothing.
    acl = access_control(NET, {"view": "viewer", "c": "aggregator"})
    puts = [k for r in acl["rules"] if r["flows"] == ["ingress"] and "put" in r["messages"] for k in r["key_exprs"]]
    assert all(k.startswith(f"driveby/{NET}/") and "/ap/" not in k and "/veh/" not in k for k in puts), puts
    assert not [r for r in acl["rules"] if r["id"].startswith("view/") and r["flows"] == ["ingress"]
                and {"put", "delete", "declare_queryable", "reply", "liveliness_token"} & set(r["messages"])]


def test_bad_security_inputs_are_one_line_errors(pki, tmp_path):
    with pytest.raises(SecurityError, match="nope.pem"):
        TlsFiles(tmp_path / "nope.pem")
    with pytest.raises(SecurityError, match="both"):
        TlsFiles(pki.path / "ca.pem", pki.path / "V1.pem")
    with pytest.raises(SecurityError, match="unknown role"):
        access_control(NET, {"V1": "superuser"})
    with pytest.raises(ValueError, match="identity"):
        access_control(NET, {"V1/ap": "vehicle"})
    p = argparse.ArgumentParser()
    add_zenoh_arguments(p)
    with pytest.raises(ValueError, match="need --tls-ca"):
        config_from_args(p.parse_args(["--tls-cert", "x.pem"]))
    res = subprocess.run([sys.executable, "-m", "shared.transport", "router", "--listen", "tls/127.0.0.1:1",
                          "--security", str(tmp_path)], capture_output=True, text=True, timeout=60,
                         stdin=subprocess.DEVNULL)
    assert res.returncode == 1 and res.stderr.count("\n") == 1 and "ca.pem" in res.stderr  # a missing file: 1


def test_denial_counter_attributes_each_drop_to_its_decision():
    zid = "7ab9d677ca41b2cb809adaa4fb92601d"
    subject = f"Interface(lo)+CertCommonName(V1)+Transport(Tls)+{zid}"
    trace = "TRACE rx-0 ThreadId(8) zenoh::net::routing::interceptor"
    lines = [
        # decisions computed to fill the cache at a declaration: no message dropped, not counted
        f"{trace}::access_control: {zid} on {subject} is unauthorized to Put (ingress) on {NET}/x",
        f"{trace}::access_control: {zid} on {subject} is unauthorized to Reply (egress) on {NET}/x",
        f"{trace}::access_control: Using cached result: {zid} is unauthorized to Put (ingress) on {NET}/y",
        f"{trace}: Msg intercepted!",
        f"{trace}::access_control: {zid} on {subject} is authorized to Put (ingress) on {NET}/z",
        f"{trace}: Msg intercepted!",  # no unauthorized decision pending on this thread: not a denial
    ]
    c = DenialCounter()
    assert [c.feed(line) for line in lines] == [None, None, None, ("V1", "put", "ingress", f"{NET}/y"), None,
                                                None]
    assert c.snapshot()["total"] == 1


def test_driveby_run_through_a_secured_router_is_refused_nothing(road, tmp_path):
    """``driveby run --connect ROUTER --secure DIR``: every daemon and the run's own session connect
    with their own identity, and the roles suffice for a whole run (raw chunks through the vehicles'
    advanced publishers included): the router refuses nothing. A missing identity is a one-line error."""
    from simfleet.run import RunError, run

    pki = init_ca(tmp_path / "pki")
    for name, role in {"router-1": "router", "run": "operator", "edge-1": "edge", "cloud-1": "aggregator",
                       "viewer-1": "viewer"}.items():
        issue(pki, name, role)
    with run_router(security=pki.path, net=NET, router_id="router-1", timeout_s=TIMEOUT_S) as endpoint:
        res = run(road / "logs", road / "site.toml", tmp_path / "out", calibration="nominal", progress=False,
                  connect=endpoint, net=NET, secure=pki.path)
        assert res.acked == res.passes == 1 and res.stats["accepted"] > 0 and not res.stats["rejected"], res
        with _session(endpoint, pki.tls("viewer-1")) as viewer:
            assert _denials(viewer, "run")["total"] == 0
    (pki.path / "identities.toml").write_text('[identities]\n"run" = "operator"\n')
    with pytest.raises(RunError, match="edge-1"):
        run(road / "logs", road / "site.toml", tmp_path / "out2", connect="tls/127.0.0.1:1", net=NET,
            secure=pki.path)


def test_driveby_run_secure_makes_its_certificates_and_secures_both_routers(tmp_path, monkeypatch):
    """``driveby run --secure --shards 2``: a CA and every identity made into the export's state, both
    routers TLS-only with access control (the second joins the first over mutual TLS), every pass through."""
    import dataclasses

    import simfleet.run
    from shared.drivelog import write_drive_log
    from simfleet.run import run

    logs = tmp_path / "logs"
    logs.mkdir()
    for i, route in enumerate(("R1", "R2")):  # two routes, one pass each: one per shard
        generate(SCENARIOS["road-qc"], tmp_path / route, seed=30 + i, passes=1, workers=1, progress=False)
        for path in list_drive_logs(tmp_path / route / "logs"):
            log = read_drive_log(path)
            meta = dataclasses.replace(log.meta, route_id=route, vehicle_id=f"{route}-{log.meta.vehicle_id}")
            write_drive_log(logs / f"{route}-{path.name}", dataclasses.replace(log, meta=meta))
    site = (tmp_path / "R1" / "site.toml").read_text()
    (tmp_path / "site.toml").write_text(
        site.replace("[[route]]", '[[route]]\nid = "R2"\nlength_m = 200.0\n\n[[route]]', 1))
    routers: list[dict] = []
    real = simfleet.run.run_router

    def recorded(*args, **kw):  # the real router, its arguments noted
        routers.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(simfleet.run, "run_router", recorded)
    res = run(logs, tmp_path / "site.toml", tmp_path / "out", calibration="nominal", progress=False, shards=2,
              secure=True)
    assert res.acked == res.passes == 2 and res.stats["accepted"] > 0 and not res.stats["rejected"], res
    sec = SecurityDir(tmp_path / "out" / ".run" / "security")
    assert sec.identities() == {"run": "operator", "edge-1": "edge", "cloud-1": "aggregator",
                                "cloud-2": "aggregator", "router-1": "router", "router-2": "router"}
    assert [(r["security"], r["router_id"]) for r in routers] == [(sec.path, "router-1"), (sec.path, "router-2")]
    assert len(routers[1]["connect"]) == 1 and routers[1]["connect"][0].startswith("tls/")


def test_raw_chunks_lost_in_a_secured_router_restart_are_recovered_under_access_control(pki, road):
    """The vehicle's advanced publisher and the edge's recovery pass the roles: chunks published while
    the secured router was down are fetched from the vehicle's cache (queries by wildcard, replies on
    its own keys), the pass completes, and the router refuses nothing."""
    from edge.node import Edge, serve
    from shared.transport import free_port, start_router as _start_router, stop_router as _stop
    from simfleet.replay import ImuPublishers, chunks_of

    issue(pki, "edge-1", "edge")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    extra = ["--security", str(pki.path), "--net", NET, "--id", "router-1"]

    def start():
        proc, error = _start_router(endpoint, None, TIMEOUT_S, extra)
        assert error is None, error
        return proc

    log = read_drive_log(list_drive_logs(road / "logs")[0])
    vehicle, chunks = log.meta.vehicle_id, list(chunks_of(log))
    before, during = len(chunks) // 3, len(chunks) // 3
    router = start()
    stop, edge_up, got_before, done = threading.Event(), threading.Event(), threading.Event(), threading.Event()
    last_handled = threading.Event()
    try:
        with _session(endpoint, pki.tls("edge-1")) as edge_s, _session(endpoint, pki.tls(vehicle)) as veh_s, \
                _session(endpoint, pki.tls("viewer-1")) as viewer:
            edge = Edge(NET, lambda k, p: edge_s.put(k, p), calibration="nominal")
            feed = edge.on_chunk

            def on_chunk(payload, key_vehicle=None):  # the real handler, observed
                feed(payload, key_vehicle)
                chunk = decode_sensor_chunk(payload)
                if chunk.seq == before - 1:
                    got_before.set()
                if chunk.final:
                    last_handled.set()  # the handler has returned: its last put on edge_s is over

            edge.on_chunk = on_chunk
            viewer.declare_subscriber(keys.done_keyexpr(NET), lambda s: done.set())
            threading.Thread(target=serve, args=(edge_s, edge, "edge-1", stop), daemon=True).start()
            veh_s.liveliness().declare_subscriber(keys.alive_key(NET, "edge", "edge-1"), lambda s: edge_up.set(),
                                                  history=True)
            assert edge_up.wait(TIMEOUT_S), "the edge never came up"
            with ImuPublishers(veh_s, heartbeat_s=0.2) as publish:
                key = keys.imu_key(NET, vehicle)
                for c in chunks[:before]:
                    publish(key, c.encode())
                assert got_before.wait(TIMEOUT_S), edge.stats()
                router.kill()
                router.wait(TIMEOUT_S)
                for c in chunks[before:before + during]:
                    publish(key, c.encode())
                router = start()
                for c in chunks[before + during:]:
                    publish(key, c.encode())
                assert done.wait(3 * TIMEOUT_S), f"the pass did not complete: {edge.stats()}"
                # A session is closed only once no callback is inside one of its calls (zenoh refuses:
                # "Already borrowed"); the pass-done arrives while the edge's put of it may still be returning.
                assert last_handled.wait(TIMEOUT_S)
            assert not edge.rejected, edge.stats()
            body = _denials(viewer, vehicle)
            assert body["total"] == 0, body
    finally:
        stop.set()
        _stop(router)
