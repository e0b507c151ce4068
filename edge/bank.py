"""Many passes fed one chunk each, as a bank: the inverse of every pass of one vehicle model in one
compiled call (:func:`shared.dynamics.inverse.update_streams`), then each pass's tiling.

The result is each :class:`~edge.pipeline.PassProcessor`'s own: the bank kernel does each stream's
operations in the same order as the single-stream one, so segments are bit for bit those of
feeding the passes one at a time.
"""

from __future__ import annotations

import numpy as np

from shared.dynamics.inverse import update_streams
from shared.schema import ApSegment

from .pipeline import PassProcessor


def feed_bank(items: list[tuple[PassProcessor, object]], done=None) -> list[list[ApSegment] | Exception]:
    """``[p.feed(chunk) for p, chunk in items]`` with one inverse call per vehicle model and chunk
    length. A pass whose chunk fails (e.g. lacks a channel) gets the exception in its place and the
    others carry on. Each processor appears at most once. ``done(i, result)``, if given, is called
    as soon as item ``i`` is through (so what it releases can leave before the rest is tiled)."""
    out: list = [None] * len(items)
    z_of: list = [None] * len(items)
    groups: dict[tuple, list[int]] = {}
    for i, (proc, chunk) in enumerate(items):
        try:
            z_of[i] = proc.channels_of(chunk)
        except Exception as e:  # noqa: BLE001 -- one pass's failure is its own (the node counts it)
            out[i] = e
            continue
        if chunk.n:
            system = proc.model.system
            groups.setdefault((proc.model_name, len(system.channels), system.n_contacts, chunk.n), []).append(i)
    ap_of: list = [None] * len(items)
    for idx in groups.values():
        z = np.array([z_of[i] for i in idx]).transpose(1, 2, 0)  # (np.stack's result, in one array call)
        ap = update_streams([items[i][0].inverse for i in idx], z)
        for j, i in enumerate(idx):
            ap_of[i] = ap[:, :, j]
    for i, (proc, chunk) in enumerate(items):
        if out[i] is None:
            try:
                out[i] = proc.feed_ap(chunk, z_of[i], ap_of[i])
            except Exception as e:  # noqa: BLE001
                out[i] = e
        if done is not None:
            done(i, out[i])
    return out
