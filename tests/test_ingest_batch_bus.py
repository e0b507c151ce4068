"""A cloud that falls behind loses nothing: back-pressure over real Zenoh, separate processes.

A router, a cloud daemon and a synthetic edge (``python -m benchmarks.bus publisher``: pre-encoded
``ap_batch`` passes and their pass-dones, published as fast as ``put`` returns, with
``CongestionControl.BLOCK`` as the edge publishes) on loopback. While the passes stream, the cloud
is stopped (SIGSTOP) again and again, shorter each time than zenoh's limit for a blocked link
(``wait_before_close``, 5 s): its queue at the router fills, the router stops reading the
publisher's link, and the publisher's ``put`` waits. Nothing is dropped anywhere on the way: every
pass is acknowledged, and the daemon's export (Parquet, written by it and read back) equals, bit for
bit, that of a cloud fed the same messages in process, in the same order.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import zenoh

from benchmarks.bus import ROUTE, synthetic_messages, synthetic_passes
from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.ingest.aggregator import DEFAULT_MAX_RESIDENT_PASSES
from cloud.ingest.segment_store import DEFAULT_MAX_RESIDENT
from shared import keys
from shared.blas import single_threaded_blas
from shared.registry import Route, Site, dump_site, load_site
from shared.schema import decode_ack
from shared.transport import run_router, zenoh_config

NET = "bp"
WORKER, PASSES, TILES = 0, 120, 4  # 480 segments of 1000 points: ~2.5 MB on the wire
PAUSE_S, RUN_S = 1.5, 0.5  # the cloud stopped 1.5 s of every 2 s: well under zenoh's 5 s
TIMEOUT_S = 240.0  # a loaded 2-core machine: start-up (numba cache), the stream, the export


def test_a_paused_cloud_loses_nothing(tmp_path):
    site = Site(routes=(Route(id=ROUTE, length_m=TILES * 50.0),))
    dump_site(site, tmp_path / "site.toml")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with run_router() as endpoint, zenoh.open(zenoh_config("client", connect=[endpoint])) as session:
        acks: dict[tuple[str, str], int] = {}
        lock = threading.Lock()
        all_acked = threading.Event()
        wanted = synthetic_passes(WORKER, PASSES)

        def on_ack(sample):
            ack = decode_ack(sample.payload.to_bytes())
            with lock:
                acks[(ack.vehicle_id, ack.pass_id)] = ack.n_segments_accepted
                if wanted <= acks.keys():
                    all_acked.set()

        sub = session.declare_subscriber(keys.ack_keyexpr(NET), on_ack)
        alive = threading.Event()
        token = session.liveliness().declare_subscriber(
            keys.alive_key(NET, "cloud", "c1"), lambda s: s.kind == zenoh.SampleKind.PUT and alive.set(), history=True)
        cloud = subprocess.Popen([sys.executable, "-m", "cloud", "--connect", endpoint, "--net", NET, "--id", "c1",
                                  "--site", str(tmp_path / "site.toml"), "--calibration", "nominal", "--no-align"],
                                 env=env, stdout=open(tmp_path / "cloud.log", "wb"), stderr=subprocess.STDOUT)
        publisher = subprocess.Popen([sys.executable, "-m", "benchmarks.bus", "publisher", "--connect", endpoint,
                                      "--net", NET, "--worker", str(WORKER), "--passes", str(PASSES), "--tiles",
                                      str(TILES), "--batch"], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        try:
            assert alive.wait(TIMEOUT_S), "the cloud did not come up"
            assert publisher.stdout.readline().strip() == "ready"
            publisher.stdin.write("go\n")
            publisher.stdin.flush()
            sent, pauses, deadline = [], 0, time.monotonic() + TIMEOUT_S
            reader = threading.Thread(target=lambda: sent.append(publisher.stdout.readline().split()), daemon=True)
            reader.start()
            while reader.is_alive() and time.monotonic() < deadline:  # stop the cloud while the passes stream
                os.kill(cloud.pid, signal.SIGSTOP)
                time.sleep(PAUSE_S)
                os.kill(cloud.pid, signal.SIGCONT)
                pauses += 1
                reader.join(RUN_S)
            assert sent and sent[0][0] == "sent", f"the publisher did not finish: {sent}"
            assert all_acked.wait(TIMEOUT_S), f"{len(wanted - acks.keys())} of {PASSES} passes never acknowledged"
            assert pauses >= 1  # (the stream outlasted at least one pause: the cloud did fall behind)
            assert set(acks.values()) == {TILES}
            export = tmp_path / "daemon"
            reply = next(iter(session.get(keys.control_key(NET, "c1", "export") + f"?dir={export}",
                                          timeout=TIMEOUT_S)))
            assert reply.ok is not None, reply.err.payload.to_bytes()
            stats = json.loads(reply.ok.payload.to_bytes())["stats"]
            assert stats["accepted"] == PASSES * TILES and not stats["rejected"]
        finally:
            os.kill(cloud.pid, signal.SIGCONT) if cloud.poll() is None else None
            for p in (publisher, cloud):
                if p.poll() is None:
                    p.terminate()
                    p.wait(30)
            sub.undeclare()
            token.undeclare()
    # The same messages, in the same order, into a cloud with the daemon's settings, in a process with
    # the daemon's single-threaded BLAS (a threaded one sums the drift's dense products in another order).
    blas = dict(env)
    single_threaded_blas(blas)
    subprocess.run([sys.executable, "-c", f"from tests.test_ingest_batch_bus import write_reference; "
                                          f"write_reference({str(tmp_path)!r})"], env=blas, check=True, timeout=TIMEOUT_S)
    names = sorted(p.name for p in (tmp_path / "reference").iterdir() if p.suffix == ".parquet")
    assert names == sorted(p.name for p in export.iterdir() if p.suffix == ".parquet") and "profile.parquet" in names
    for name in names:
        assert pq.read_table(export / name).equals(pq.read_table(tmp_path / "reference" / name)), name


def write_reference(tmp: str) -> None:
    """The export of a cloud fed the publisher's messages in process (the daemon's settings)."""
    site = load_site(Path(tmp) / "site.toml")
    reference = Cloud(NET, site, lambda k, p: None,
                      CloudSettings(calibration="nominal", align=False, max_resident=DEFAULT_MAX_RESIDENT,
                                    max_resident_passes=DEFAULT_MAX_RESIDENT_PASSES))
    for key, payload in synthetic_messages(WORKER, PASSES, TILES, batch=True, net=NET):
        (reference.on_segment if "/ap/" in key else reference.on_done)(key, payload)
    reference.export(Path(tmp) / "reference")
