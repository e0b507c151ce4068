"""The cloud core without a transport: its settings, its injected clock, what a road-only daemon loads."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from cloud.daemon.core import Cloud
from cloud.daemon.settings import CloudSettings
from cloud.road.mean_profile import MeanProfile
from shared import keys
from shared.registry import Route, Site, VehicleClass
from shared.schema import ApSegment, PassDone

NET = "t"
SITE = Site(routes=(Route(id="R1", length_m=200.0),),
            vehicle_classes=(VehicleClass(model="quarter_car", mean={"M": 1.0}, std={"M": 0.1}),))


def _segment(pass_id: str, n: int = 40) -> ApSegment:
    rng = np.random.default_rng(len(pass_id))
    return ApSegment.make(rng.normal(0.0, 2e-3, n), np.full(n, 1e-3), vehicle_id="veh-1", pass_id=pass_id,
                          route_id="R1", tile=0, axle=1, start_index=10, spacing_m=0.05, calib_version=0,
                          speed_mps=15.0, t_first=0.0, t_last=1.0, seq=0, n_segments_in_pass=1, flags=0)


@pytest.mark.parametrize("change", [
    dict(spacing_m=0.0), dict(calibration="both"), dict(drift_knot_m=-1.0), dict(bridge_duty=0.0),
    dict(quiet_s=-0.1), dict(epoch_first=0), dict(max_resident=0), dict(max_resident_passes=1),
    dict(shard=frozenset()), dict(align_max_stretch=1.0), dict(refresh_wait_s=float("nan")),
    dict(status_heartbeat_s=-1.0)])
def test_settings_are_validated_once(change):
    with pytest.raises(ValueError, match=next(iter(change))):
        CloudSettings(**change)


def test_settings_are_a_frozen_value():
    s = CloudSettings(shard={"R1"})
    assert s.shard == frozenset({"R1"}) and hash(s) == hash(CloudSettings(shard=frozenset({"R1"})))
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.quiet_s = 1.0


def test_the_status_follows_the_clock_it_is_given():
    """Acks publish the status at most every ``status_interval_s`` of the core's clock."""
    now = [0.0]
    published = []
    cloud = Cloud(NET, SITE, lambda k, p: published.append((k, p)), CloudSettings(status_interval_s=10.0),
                  clock=lambda: now[0])
    status_key = keys.status_key(NET, cloud.node_id)

    def complete(pass_id):
        cloud.on_segment(keys.ap_key(NET, "R1", 0, "veh-1"), _segment(pass_id).encode())
        cloud.on_done(keys.done_key(NET, "veh-1"), PassDone("veh-1", pass_id, "R1", 0, 1).encode())

    complete("p1")
    complete("p2")
    statuses = [json.loads(p) for k, p in published if k == status_key]
    assert len(statuses) == 1 and statuses[0]["passes"] == 1 and cloud.status_due  # p2's is held back
    now[0] = 9.9
    cloud.flush_status()
    assert sum(k == status_key for k, _ in published) == 1
    now[0] = 10.0
    cloud.flush_status()
    statuses = [json.loads(p) for k, p in published if k == status_key]
    assert len(statuses) == 2 and statuses[-1]["passes"] == 2 and not cloud.status_due


def test_a_quiet_cloud_repeats_its_status_so_a_lost_one_is_not_waited_on_for_good():
    """A status is published when acks change it; one lost on the way (a router restarting after the
    last acknowledgement) would leave the run waiting on "settled". While the bus is quiet the core
    repeats it every ``status_heartbeat_s`` of its clock, and no more often."""
    now = [0.0]
    published = []
    cloud = Cloud(NET, SITE, lambda k, p: published.append(k), CloudSettings(status_heartbeat_s=2.0),
                  clock=lambda: now[0])
    status_key = keys.status_key(NET, cloud.node_id)
    cloud.on_segment(keys.ap_key(NET, "R1", 0, "veh-1"), _segment("p1").encode())
    cloud.on_done(keys.done_key(NET, "veh-1"), PassDone("veh-1", "p1", "R1", 0, 1).encode())
    assert published.count(status_key) == 1 and not cloud.status_due
    for t in (0.5, 1.0, 1.99):  # quiet ticks within the heartbeat: nothing new to say, nothing said
        now[0] = t
        cloud.flush_status(force=True)
    assert published.count(status_key) == 1
    now[0] = 2.0
    cloud.flush_status(force=True)
    assert published.count(status_key) == 2
    now[0] = 10.0
    cloud.flush_status()  # not quiet (input streaming): only changes are published
    assert published.count(status_key) == 2


def test_leaving_a_pass_out_of_an_estimator_gives_it_back():
    """``Aggregator.left_out``: the leave-one-out view alignment reads is the estimator without the
    pass, and afterwards it holds the pass again."""
    cloud = Cloud(NET, SITE, lambda k, p: None, CloudSettings(continuous_aps=False))
    agg = cloud.aggregator
    for pass_id in ("p1", "p2"):
        cloud.on_segment(keys.ap_key(NET, "R1", 0, "veh-1"), _segment(pass_id).encode())
    alone = MeanProfile({"R1": 200.0}, 0.05)
    alone.update(agg.held[("veh-1", "p2", "R1", 0, 1)])
    before = cloud.consensus.snapshot("R1")["R1"].n_passes.copy()
    with agg.left_out(cloud.consensus, [("veh-1", "p1", "R1", 0, 1)]):
        inside = cloud.consensus.snapshot("R1")["R1"]
        assert np.array_equal(inside.n_passes, alone.snapshot("R1")["R1"].n_passes)
        assert np.allclose(inside.elevation_m, alone.snapshot("R1")["R1"].elevation_m, equal_nan=True)
    assert np.array_equal(cloud.consensus.snapshot("R1")["R1"].n_passes, before)


def test_a_road_only_daemon_does_not_load_rail():
    """Rail (numba-heavy) is loaded only for a registry with a rail vehicle class."""
    code = (
        "import sys\n"
        "from cloud.daemon.core import Cloud\n"
        "from shared.registry import Route, Site, VehicleClass\n"
        "def site(model): return Site(routes=(Route(id='R1', length_m=100.0),),"
        " vehicle_classes=(VehicleClass(model=model, mean={}, std={}),))\n"
        "Cloud('t', site('quarter_car'), lambda k, p: None)\n"
        "road = any(m.startswith('cloud.rail') for m in sys.modules)\n"
        "rail = Cloud('t', site('carriage'), lambda k, p: None).rail is not None\n"
        "print(road, rail, any(m.startswith('cloud.rail') for m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True", "True"]
