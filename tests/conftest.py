"""Hypothesis runs the same examples on every machine and every run.

The suite is the net under every change: a property test that drew a new counterexample on some run
would fail a fresh clone for a reason unrelated to what changed. So the ``deterministic`` profile is
the default, not only under CI: examples derived from each test's own source (``derandomize``), no
example database written into the tree, no per-example deadline (a loaded 2-core machine is slow,
not wrong), and the reproduction blob printed with any failure. ``--hypothesis-profile=explore``
draws fresh examples, to look for new counterexamples on purpose.

The two xdist workers take whole modules in collection order (``--dist loadfile
--no-loadscope-reorder``), and the collection puts the longest modules first (``LONG_FIRST``): they
run side by side from the start and the many short modules fill in at the end, so the two workers
finish together. (xdist's own order, most tests first, leaves the modules of one or two long tests
to the end, where one runs alone while the other worker idles.)
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from hypothesis import HealthCheck, settings

from tests.support import session_dir

settings.register_profile("deterministic", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", deadline=None, print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("deterministic")

#: Modules whose tests take longest (simulated fleets calibrated in process, whole runs of the
#: daemons), longest first; the rest follow in their usual order. The order only decides when a
#: module starts: a module missing here, or a stale entry, costs time at the end of the run, never a result.
LONG_FIRST = (
    "test_ratio_coverage.py", "test_demo.py", "test_bridge_second_world.py", "test_second_world_fleet.py",
    "test_gnss_carpet.py",
    "test_second_world.py", "test_rail_calibration.py", "test_rail_system.py", "test_durability.py",
    "test_reference.py", "test_network_accuracy.py", "test_router_restart.py", "test_profile_coverage.py",
    "test_calibration.py", "test_calibration_slices.py", "test_sim.py", "test_rail_bridge.py",
    "test_bridge_bearings.py", "test_transport.py", "test_scale_out.py", "test_bridge_scenarios.py", "test_cli.py",
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each module's own order kept


def _sim_network_one_trip(d):
    r = subprocess.run([sys.executable, "-m", "simfleet", "sim", "network", "--out", str(d / "net"), "--passes", "1"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="session")
def network_one_trip(tmp_path_factory):
    """One trip of ``driveby sim network`` (seed 0), simulated once per session through the CLI, for
    every worker; the tests that use it only read it."""
    return session_dir(tmp_path_factory, "network_one_trip", _sim_network_one_trip) / "net"
