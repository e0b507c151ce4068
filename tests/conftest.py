"""Hypothesis runs the same examples on every machine and every run.

The suite is the net under every change: a property test that drew a new counterexample on some run
would fail a fresh clone for a reason unrelated to what changed. So the ``deterministic`` profile is
the default, not only under CI: examples derived from each test's own source (``derandomize``), no
example database written into the tree, no per-example deadline (a loaded 2-core machine is slow,
not wrong), and the reproduction blob printed with any failure. ``--hypothesis-profile=explore``
draws fresh examples, to look for new counterexamples on purpose.

Under xdist the controller first compiles the project's kernels into the numba cache, in as many
processes as there are workers (:mod:`tests.warm_kernels`): with a cold cache every worker would
otherwise compile the same kernels itself.
"""

from __future__ import annotations

from hypothesis import HealthCheck, settings

from tests.warm_kernels import warm_in

settings.register_profile("deterministic", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("explore", deadline=None, print_blob=True, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("deterministic")


def pytest_configure(config):
    workers = getattr(config.option, "numprocesses", None)
    if (not hasattr(config, "workerinput") and isinstance(workers, int) and workers > 1
            and not config.option.collectonly):
        warm_in(workers)
