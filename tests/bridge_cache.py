"""Where bridge tests keep their simulated (and self-calibrated) passes between sessions.

Keyed by the source of everything that makes them — simulator, edge, cloud, shared; not the bridge
estimator under test (``cloud/bridge/``, ``cloud/bridge/monitor.py``), which runs every time — and by the
Python and NumPy versions: any change to that code simulates and calibrates afresh.
``DRIVEBY_BRIDGE_TEST_WORK`` (a directory) overrides the key: for checking the bridge estimator
alone against passes made earlier while other code changes under it (say so when quoting results).
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tests.support import made_once

ROOT = Path(__file__).resolve().parents[1]


def source_key() -> str:
    h = hashlib.sha256(f"{sys.version}|{np.__version__}".encode())
    for pkg in ("shared", "edge", "cloud", "simfleet"):
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).as_posix()
            if rel.startswith("cloud/bridge/"):
                continue
            h.update(rel.encode() + b"\0" + p.read_bytes())
    return h.hexdigest()[:16]


WORK = (Path(os.environ["DRIVEBY_BRIDGE_TEST_WORK"]) if os.environ.get("DRIVEBY_BRIDGE_TEST_WORK")
        else Path(tempfile.gettempdir()) / "driveby-test-bridge" / source_key())


def kept(name: str, make: Callable[[Path], None]) -> Path:
    """``WORK/name``, made by ``make(dir)`` once (sessions may run side by side: :func:`made_once`)."""
    return made_once(WORK / name, make)
