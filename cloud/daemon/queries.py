"""The answers to state queries: a tile of a route's profile (Arrow IPC) and a bridge's state (JSON)."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa

#: Tile length (m) of ``state/profile/<route>/<tile>`` answers and of the view's passes-per-tile bars.
TILE_M = 50.0


def tile_points(spacing_m: float, tile_m: float = TILE_M) -> int:
    """Grid points per tile."""
    return int(round(tile_m / spacing_m))


def tile_state(profile, route_id: str, tile: int) -> bytes | None:
    """The answer to ``state/profile/<route>/<tile>``: an Arrow IPC stream of the tile's chainage_m,
    elevation_m, lo95_m, hi95_m and n_passes from the profile posterior; None for an unknown route."""
    snaps = profile.snapshot(route_id)
    if route_id not in snaps:
        return None
    s = snaps[route_id]
    P = tile_points(profile.spacing_m)
    sl = slice(tile * P, (tile + 1) * P)
    table = pa.table({"chainage_m": s.chainage_m[sl], "elevation_m": s.elevation_m[sl],
                      "lo95_m": s.lo95_m[sl], "hi95_m": s.hi95_m[sl], "n_passes": s.n_passes[sl]})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table)
    return sink.getvalue().to_pybytes()


def bridge_state(monitor, bridge_id: str) -> bytes:
    """The answer to ``state/bridge/<bridge>``: JSON of the bridge's export rows (``summary``,
    ``elements``, ``bearings``: interfaces.md §3) and its ``assessment`` (the hypotheses'
    probabilities, the decision, location and severity; null when off). Not-a-number is null. As of
    the monitor's last estimate."""
    summary = next(r for r in monitor.summary_rows() if r["bridge_id"] == bridge_id)
    st = monitor.bridges[bridge_id]
    est = st.latest
    a = est.assessment if est is not None else None
    body = {
        "summary": summary,
        "elements": est.element_rows() if est is not None else [],
        "bearings": est.bearing_rows() if est is not None else [],
        "assessment": None if a is None else {
            "probabilities": a.probabilities, "best": a.best, "alarm": a.alarm,
            "loss_probability": a.loss_probability, "kind": a.kind, "element": a.element,
            "location_m": a.location_m, "severity": a.severity},
    }
    return json.dumps(finite_or_null(body), allow_nan=False).encode()


def finite_or_null(v):
    """JSON-safe: non-finite floats (and numpy scalars of them) become None."""
    if isinstance(v, dict):
        return {str(k): finite_or_null(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [finite_or_null(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v
