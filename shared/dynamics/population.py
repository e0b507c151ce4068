"""The apparent profiles (APs) one vehicle's record gives under many trial parameter sets, in one compiled call.

Calibration scores trial parameter sets by the APs they give: the Cross-Entropy reference
(:mod:`cloud.reference.cross_entropy`) a population on each vehicle's record, the rail batches
(:mod:`cloud.rail.batches`) one run under its calibrated properties. The inverse is
:func:`shared.dynamics.batched_inverse.inverse_runs`, the readable inverse step of
:mod:`shared.dynamics.inverse` for every trial at once, without compiling a state-space model per trial.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from shared.dynamics.batched_inverse import inverse_runs
from shared.dynamics.newmark import newmark_constants
from shared.vehicles import vehicle_from_params


def population_aps(model: str, trials: Sequence[dict[str, float]], channels: np.ndarray, dt: float,
                   gamma: float = 0.8, beta: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """APs (T, n_samples, n_contacts) of one vehicle's ``channels`` under each trial parameter set.

    Also returns the contact offsets (T, n_contacts) ahead of the centre of gravity, m.
    """
    c = newmark_constants(dt, gamma, beta)
    systems = [vehicle_from_params(model, p).system() for p in trials]
    s0 = systems[0]
    measured = [ch.dof for ch in s0.channels]
    free = np.array([i for i in range(s0.n_dof) if i not in measured], dtype=np.int64)
    M = np.stack([s.M for s in systems])
    C = np.stack([s.C for s in systems])
    K = np.stack([s.K for s in systems])
    G = np.stack([s.G for s in systems])
    S = np.concatenate([M[:, :, free] + c.gamma * dt * C[:, :, free] + c.beta * dt * dt * K[:, :, free], -G], axis=2)
    Sinv = np.ascontiguousarray(np.linalg.inv(S))
    kc = np.stack([s.kc for s in systems])
    cc = np.stack([s.cc for s in systems])
    dof = np.array(measured, dtype=np.int64)
    is_acc = np.array([ch.kind == "acc" for ch in s0.channels])
    z = np.ascontiguousarray(channels, dtype=np.float64).reshape(1, len(channels), -1)  # one run
    out = np.empty((len(systems), s0.n_contacts, z.shape[1]))
    inverse_runs(Sinv, M, C, K, kc, cc, dof, is_acc, free, np.zeros(len(systems), dtype=np.int64), z,
                 np.array([z.shape[1]], dtype=np.int64), np.array([float(dt)]), c.gamma, c.beta, out)
    return out.transpose(0, 2, 1), np.stack([s.offsets_m for s in systems])
