"""The bank inverse keeps its stacked matrices from call to call: members that stay, leave, join
and change places (a fleet whose passes start and end at every tick) must give each stream's AP
bit for bit as the stream alone, for several vehicle models called in turn."""

from __future__ import annotations

import numpy as np

from shared.dynamics.inverse import InverseStream, build_inverse, edge_gamma, update_streams
from shared.vehicles import vehicle_from_params

QC = {"M": 400.0, "m": 40.0, "K": 2.0e4, "c": 1.5e3, "k": 2.0e5}


def _models(n: int):
    return [build_inverse(vehicle_from_params("quarter_car", {k: v * (1 + 0.03 * i) for k, v in QC.items()}).system(),
                          1.0 / 500.0, gamma=edge_gamma("quarter_car")) for i in range(n)]


def test_members_joining_and_leaving_give_each_streams_own_ap():
    models = _models(9)
    rng = np.random.default_rng(4)
    alone = [InverseStream(m) for m in models]
    together = [InverseStream(m) for m in models]
    for s in alone + together:  # started: every later call goes through the bank
        s.update(np.zeros((3, 1)))
    previous = list(range(9))
    for k in range(14):
        match k % 4:
            case 0:
                members = previous  # the same bank again
            case 1:
                members = [int(q) for q in rng.permutation(previous)]  # the same members, other places
            case 2:
                members = sorted(rng.choice(9, size=int(rng.integers(1, 9)), replace=False).tolist())  # some leave
            case _:
                members = [int(q) for q in rng.permutation(9)]  # they join again
        z = rng.standard_normal((int(rng.integers(1, 60)), 1, len(members)))
        y = update_streams([together[q] for q in members], z)
        for j, q in enumerate(members):
            assert y[:, :, j].tobytes() == alone[q].update(z[:, :, j]).tobytes(), (k, q)
        previous = members
    for a, b in zip(alone, together):
        assert a.n_seen == b.n_seen


def test_a_new_stream_of_a_model_joins_with_its_own_matrices():
    """Streams replaced by new ones (a vehicle's next pass, a recalibrated model) between calls."""
    models = _models(4)
    rng = np.random.default_rng(8)
    alone = [InverseStream(m) for m in models]
    together = [InverseStream(m) for m in models]
    for k in range(6):
        if k in (2, 4):
            fresh = _models(6)[k]  # a model the bank has not seen
            alone[k % 4], together[k % 4] = InverseStream(fresh), InverseStream(fresh)
        z = rng.standard_normal((40, 1, 4))
        y = update_streams(together, z)
        for q in range(4):
            assert y[:, :, q].tobytes() == alone[q].update(z[:, :, q]).tobytes(), (k, q)
