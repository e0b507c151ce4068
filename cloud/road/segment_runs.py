"""Runs of segment updates packed for one compiled call: the estimators' batched entry.

An estimator adds (or, sign −1, retracts) a segment's information by one kernel call on its wire
codes. A batch of segments (an ``ap_batch``, or what the aggregator applies between two
retractions) is packed here into flat arrays, one call per route then walks them in order, calling
the same per-segment kernel on each: the same operations in the same order as segment by segment,
so the sums hold the same bits, without a Python call and a kernel dispatch per segment.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from shared.schema import ApSegment


class Run(NamedTuple):
    """Segments of one route, in order: segment ``k`` adds ``signs[k]`` times its information from
    grid index ``los[k]``; its first ``m_k`` codes are ``values_q[starts[k]:starts[k + 1]]`` (likewise
    ``sigma_q``) and its error model ``error_models[em_starts[k]:em_starts[k + 1]]`` (empty: none)."""

    los: np.ndarray  # int64 (n,)
    starts: np.ndarray  # int64 (n + 1,)
    values_q: np.ndarray  # int16
    sigma_q: np.ndarray  # int16
    scales: np.ndarray  # float64 (n,): scale_m
    offsets: np.ndarray  # float64 (n,): offset_m
    sigma_refs: np.ndarray  # float64 (n,): sigma_ref_m
    error_models: np.ndarray  # float64
    em_starts: np.ndarray  # int64 (n + 1,)
    signs: np.ndarray  # float64 (n,)
    is_pass: np.ndarray  # bool (n,): axle 1 (a segment of the pass itself)


def pack(ops: list[tuple[ApSegment, float, int]]) -> Run:
    """``(segment, sign, m)`` in order (``m``: how many of its points lie on the route) as a :class:`Run`."""
    n = len(ops)
    ms = [m for _, _, m in ops]
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(ms, out=starts[1:])
    ems = [seg.error_model for seg, _, _ in ops]
    em_starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum([em.size for em in ems], out=em_starts[1:])
    return Run(
        los=np.array([seg.start_index for seg, _, _ in ops], dtype=np.int64),
        starts=starts,
        values_q=np.concatenate([seg.values_q[:m] for seg, _, m in ops]),
        sigma_q=np.concatenate([seg.sigma_q[:m] for seg, _, m in ops]),
        scales=np.array([seg.scale_m for seg, _, _ in ops]),
        offsets=np.array([seg.offset_m for seg, _, _ in ops]),
        sigma_refs=np.array([seg.sigma_ref_m for seg, _, _ in ops]),
        error_models=np.concatenate(ems) if em_starts[-1] else np.zeros(0),
        em_starts=em_starts,
        signs=np.array([sign for _, sign, _ in ops]),
        is_pass=np.array([seg.axle == 1 for seg, _, _ in ops]),
    )


def by_route(ops: list[tuple[ApSegment, float, int]]) -> dict[str, list[tuple[ApSegment, float, int]]]:
    """The ops of each route, each route's in their order (routes share no sums: their relative
    order changes nothing)."""
    out: dict[str, list] = {}
    for op in ops:
        out.setdefault(op[0].route_id, []).append(op)
    return out
