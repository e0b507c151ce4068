"""The consensus's leave-one-out view is exact where it matters: a point only the retracted passes held
has no value, whatever rounding the sums' history left.

The aligner places each pass against the consensus with that pass retracted, and the vehicle step
fits each vehicle against it; where only the retracted pass was (a pass's first metres at a route's
end), a ratio of two rounding residues would be read as the road, present or absent by the
residue's sign — so the whole run turned on the rounding of its inputs.
"""

from __future__ import annotations

import numpy as np

from cloud.road.mean_profile import MeanProfile
from shared.schema import ApSegment


def _segment(pass_id: str, start: int, n: int, rng) -> ApSegment:
    # Sigmas over decades: the sums' rounding then differs from point to point.
    sigma = 1e-4 * np.exp(rng.normal(0.0, 2.0, n))
    return ApSegment.make(rng.normal(0.0, 3e-3, n), sigma, vehicle_id=f"veh-{pass_id}", pass_id=pass_id,
                          route_id="R1", tile=0, axle=1, start_index=start, spacing_m=0.05, calib_version=0,
                          speed_mps=15.0, t_first=0.0, t_last=1.0, seq=0)


def test_a_point_only_retracted_passes_held_is_empty():
    rng = np.random.default_rng(7)
    m = MeanProfile({"R1": 100.0})
    early = _segment("a", 0, 600, rng)  # a pass placed first where it reports…
    late = _segment("b", 0, 600, rng)  # …then the pass the aligner leaves out
    other = _segment("c", 400, 1000, rng)  # the rest of the fleet, from 20 m on
    for seg in (early, late, other):
        m.update(seg)
    m.retract(early)  # re-gridded elsewhere (the aggregator replaces what the estimators hold)
    m.retract(late)  # the leave-one-out view of ``late``
    snap = m.snapshot("R1")["R1"]
    assert np.isnan(snap.elevation_m[:400]).all() and not snap.n_passes[:400].any()
    # Where another pass is, it alone: its values up to the rounding of the sums it went through, whose
    # retracted terms weighed up to ~1e4 times its own (sigmas over decades): 1e-16 x 1e4, with margin.
    np.testing.assert_allclose(snap.elevation_m[400:600], other.values[:200], rtol=1e-7, atol=0)
    m.update(late)
    again = m.snapshot("R1")["R1"]
    np.testing.assert_allclose(again.elevation_m[:400], late.values[:400], rtol=1e-12, atol=0)
