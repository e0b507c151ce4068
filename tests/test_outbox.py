"""The edge's store of unacknowledged passes: held while no cloud is there, resent when one appears."""

import pytest

from edge.outbox import Outbox


def _fill(box, vehicle="veh-1", pass_id="p1", version=0, n=3, size=10):
    for i in range(n):
        box.add(vehicle, pass_id, version, f"driveby/t/ap/R1/{i}/{vehicle}", bytes([i]) * size)


@pytest.mark.parametrize("on_disk", [False, True])
def test_a_pass_stays_until_acknowledged_under_its_version(tmp_path, on_disk):
    box = Outbox(tmp_path / "spool" if on_disk else None)
    _fill(box, version=2)
    assert len(box.messages()) == 3 and box.nbytes == 30
    box.ack("veh-1", "p1", 1)  # an older version's ack does not cover the recomputed pass
    assert len(box.messages()) == 3
    box.ack("veh-1", "p1", 2)
    assert box.messages() == [] and box.nbytes == 0 and box.acked == 1
    if on_disk:
        assert list((tmp_path / "spool").glob("*/*.arrows")) == []


def test_a_recomputed_pass_replaces_the_old_version(tmp_path):
    box = Outbox(tmp_path)
    _fill(box, version=0, n=3)
    _fill(box, version=1, n=2)
    box.add("veh-1", "p1", 0, "late/old", b"x")  # a straggler from the old version is ignored
    assert [k for k, _ in box.messages()] == [f"driveby/t/ap/R1/{i}/veh-1" for i in range(2)]
    assert Outbox(tmp_path).messages() == box.messages()


def test_a_restarted_edge_recovers_what_was_not_acknowledged(tmp_path):
    box = Outbox(tmp_path)
    _fill(box, "veh-1", "p1", n=3)
    _fill(box, "veh-2", "p/2 odd", n=2)  # pass ids are quoted into file names
    _fill(box, "veh-1", "p3", n=1)
    box.ack("veh-1", "p3", 0)
    box.close()
    again = Outbox(tmp_path)
    assert sorted(again.pending) == [("veh-1", "p1"), ("veh-2", "p/2 odd")]
    assert again.nbytes == 50
    # more messages for a recovered pass keep the earlier ones on disk too
    again.add("veh-1", "p1", 0, "k", b"yy")
    again.close()
    assert len(Outbox(tmp_path).pending[("veh-1", "p1")].messages) == 4


def test_a_torn_spool_file_keeps_its_complete_messages(tmp_path):
    box = Outbox(tmp_path)
    _fill(box, n=5)
    box.close()
    (path,) = tmp_path.glob("*/*.arrows")
    path.write_bytes(path.read_bytes()[:-20])
    msgs = Outbox(tmp_path).messages()
    assert 0 < len(msgs) < 5


def test_the_oldest_passes_are_dropped_and_counted_beyond_the_bound(tmp_path):
    box = Outbox(tmp_path, max_bytes=100)
    for p in range(6):
        _fill(box, pass_id=f"p{p}", n=2, size=20)  # 40 bytes a pass
    assert [k[1] for k in box.pending] == ["p4", "p5"]
    assert box.evicted == 4 and box.nbytes == 80
    assert len(list(tmp_path.glob("*/*.arrows"))) == 2


def test_bad_settings_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="max_bytes"):
        Outbox(None, 0)
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(ValueError, match="not a directory"):
        Outbox(f)


# -- the edge with an outbox, wired to a real cloud core (no network: the cores are transport-free) --

import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402

from cloud.daemon.core import Cloud  # noqa: E402
from cloud.daemon.settings import CloudSettings  # noqa: E402
from edge.node import Edge  # noqa: E402
from shared.registry import load_site  # noqa: E402
from simfleet.scenarios import SCENARIOS  # noqa: E402
from simfleet.sim import generate  # noqa: E402

from tests.support import drive, drive_logs, edge_messages  # noqa: E402

NET = "t"


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    out = tmp_path_factory.mktemp("road")
    generate(SCENARIOS["road-qc"], out, seed=7, passes=3, workers=1, progress=False)
    return out


def _cloud(road, sent):
    site = load_site(road / "site.toml")
    return Cloud(NET, site, lambda k, p: sent.append((k, p)), CloudSettings(calibration="nominal"))


def _deliver(cloud, edge, msgs):
    for key, payload in msgs:
        if "/ap/" in key:
            cloud.on_segment(key, payload)
        else:
            cloud.on_done(key, payload)


def test_an_outage_delays_delivery_but_changes_nothing(road, tmp_path):
    site = load_site(road / "site.toml")
    # Reference: cloud present throughout, no outbox.
    ref = _cloud(road, [])
    direct = edge_messages(site, drive_logs(road), NET)
    _deliver(ref, None, direct)
    # Outage: no aggregator alive while the fleet drives; the edge only stores.
    wire: list = []
    edge = Edge(NET, lambda k, p: wire.append((k, p)), site, "nominal", outbox=Outbox(tmp_path / "spool"))
    edge.on_cloud_presence(False)
    drive(edge, drive_logs(road))
    assert wire == [] and len(edge.outbox.pending) == 3
    # The cloud comes back: everything is sent once, acknowledged, and the store empties.
    acks: list = []
    cloud = _cloud(road, acks)
    edge.on_cloud_presence(True)
    assert wire == direct
    _deliver(cloud, edge, wire)
    for key, payload in acks:
        if "/ack/" in key:
            edge.on_ack(payload, key.split("/")[3])
    assert edge.outbox.pending == {} and edge.outbox.acked == 3
    a, b = ref.profile.snapshot()["R1"], cloud.profile.snapshot()["R1"]
    assert np.array_equal(a.elevation_m, b.elevation_m, equal_nan=True)
    # A second appearance (say the cloud restarted) resends only what is still unacknowledged: nothing.
    wire.clear()
    edge.on_cloud_presence(True)
    assert wire == []


def test_a_resend_carries_each_messages_own_trace(road, tmp_path):
    """The trace (the zenoh attachment a benchmark times a segment by) is the edge's ``trace`` while
    it publishes: a message stored during an outage and resent when a cloud appears carries the
    trace of the chunk that released it, not the one the edge holds when it resends — in memory and
    from a restarted edge's spool."""
    site = load_site(road / "site.toml")

    def traced_drive(edge):  # each chunk tagged as the daemon tags it
        drive(edge, drive_logs(road), trace=lambda log, chunk: f"{log.meta.vehicle_id}/{chunk.seq}".encode())

    def wired(outbox):
        wire: list = []
        edge = Edge(NET, lambda k, p: wire.append((k, edge.trace)), site, "nominal", outbox=outbox)
        return edge, wire

    reference, direct = wired(None)  # cloud present throughout: each message tagged as released
    traced_drive(reference)
    assert direct and all(t is not None for _, t in direct)
    edge, wire = wired(Outbox(tmp_path / "spool"))
    edge.on_cloud_presence(False)
    traced_drive(edge)
    assert wire == []
    edge.trace = b"something else"  # the edge is busy with another chunk when the cloud appears
    edge.on_cloud_presence(True)
    assert wire == direct
    assert edge.trace == b"something else"
    edge.outbox.close()
    restarted, wire = wired(Outbox(tmp_path / "spool"))  # killed and restarted: the spool keeps them
    restarted.on_cloud_presence(True)
    assert wire == direct


def test_a_spool_written_without_traces_still_loads(tmp_path):
    """Spool files from before traces were kept: their messages load, untraced."""
    path = tmp_path / "veh-1" / "p1.arrows"
    path.parent.mkdir(parents=True)
    old = pa.schema([("calib_version", pa.int64()), ("key", pa.string()), ("payload", pa.binary())])
    with open(path, "wb") as f, pa.ipc.new_stream(f, old) as w:
        w.write_batch(pa.record_batch([pa.array([0, 0]), pa.array(["k0", "k1"]), pa.array([b"a", b"b"])], schema=old))
    box = Outbox(tmp_path)
    assert box.messages() == [("k0", b"a"), ("k1", b"b")]
    assert box.traced() == [("k0", b"a", None), ("k1", b"b", None)]
    box.add("veh-1", "p1", 0, "k2", b"c", b"t2")  # rewritten in the current schema, traces kept
    box.close()
    assert Outbox(tmp_path).traced() == [("k0", b"a", None), ("k1", b"b", None), ("k2", b"c", b"t2")]
