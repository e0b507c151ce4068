"""Hypothesis runs the same examples on every machine and every run.

The suite is the net under every change: a property test that drew a new counterexample on some run
would fail a fresh clone for a reason unrelated to what changed. So the ``deterministic`` profile is
the default, not only under CI: examples derived from each test's own source (``derandomize``), no
example database written into the tree, no per-example deadline (a loaded 2-core machine is slow,
not wrong), and the reproduction blob printed with any failure. ``--hypothesis-profile=explore``
draws fresh examples, to look for new counterexamples on purpose.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("deterministic", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", deadline=None, print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("deterministic")


@pytest.fixture(scope="session")
def network_one_trip(tmp_path_factory):
    """One trip of ``driveby sim network`` (seed 0), simulated once per worker through the CLI; the
    tests that use it only read it."""
    out = tmp_path_factory.mktemp("network_one_trip") / "net"
    r = subprocess.run([sys.executable, "-m", "simfleet", "sim", "network", "--out", str(out), "--passes", "1"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return out
