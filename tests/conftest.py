"""Hypothesis runs the same examples on every machine and every run.

The suite is the net under every change: a property test that drew a new counterexample on some run
would fail a fresh clone for a reason unrelated to what changed. So the ``deterministic`` profile is
the default, not only under CI: examples derived from each test's own source (``derandomize``), no
example database written into the tree, no per-example deadline (a loaded 2-core machine is slow,
not wrong), and the reproduction blob printed with any failure. ``--hypothesis-profile=explore``
draws fresh examples, to look for new counterexamples on purpose.
"""

from __future__ import annotations

from hypothesis import HealthCheck, settings

settings.register_profile("deterministic", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", deadline=None, print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("deterministic")
