"""A turn is not road: the splitter cuts where the vehicle turns (edge.trip), so no kept sample of a
simulated drive lies on a route's corner."""

import numpy as np

from edge.trip import split_drives
from shared.drivelog import list_drive_logs, read_drive_log
from shared.registry import load_site
from simfleet.network import CORNER_M, ROUTES_EN


def _corners() -> dict[str, list[float]]:
    """Route → chainage (m, along the local frame's straight segments) of each interior vertex."""
    out = {}
    for rid, pts in ROUTES_EN.items():
        p = np.asarray(pts, float)
        out[rid] = list(np.cumsum(np.hypot(*np.diff(p, axis=0).T))[:-1])
    return out


def test_no_kept_sample_on_a_corner(network_one_trip):
    out = network_one_trip
    paths = list_drive_logs(out / "logs")
    _, passes, cut = split_drives(paths, [read_drive_log(p) for p in paths], load_site(out / "site.toml"))
    assert cut["turn"] > 0.0 and passes
    corners = _corners()
    for p in passes:
        for c in corners[p.meta.route_id]:
            # The simulated driver rounds a corner over CORNER_M; the matched chainage is metres off.
            near = np.abs(p.chainage - c) < 0.5 * CORNER_M
            assert not near.any(), f"{p.meta.pass_id} keeps {near.sum()} samples on the corner at {c:.0f} m"
