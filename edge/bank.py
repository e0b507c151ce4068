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
    as soon as item ``i`` is through (so what it releases can leave before the rest is tiled), for
    every item that released segments, failed or ended its pass (the others need nothing done)."""
    out: list = [None] * len(items)
    z_of: list = [None] * len(items)
    groups: dict[tuple, list[int]] = {}
    for i, (proc, chunk) in enumerate(items):
        n = chunk.n
        if n:
            groups.setdefault((proc.bank_key, n), []).append(i)
            continue
        try:
            z_of[i] = proc.channels_of(chunk)
        except Exception as e:  # noqa: BLE001 -- one pass's failure is its own (the node counts it)
            out[i] = e
    ap_of: list = [None] * len(items)
    mean_of: list = [None] * len(items)
    for (_, n), idx in groups.items():
        names = items[idx[0]][0].channel_names
        good = []
        for i in idx:
            proc, chunk = items[i]
            try:
                if len(names) == 1 and names[0] in chunk.channels:
                    good.append(i)  # (one channel: stacked below in one conversion)
                    continue
                z_of[i] = proc.channels_of(chunk)  # (or the reason it has not the channels)
                good.append(i)
            except Exception as e:  # noqa: BLE001
                out[i] = e
        if not good:
            continue
        if len(names) == 1:
            z = np.array([items[i][1].channels[names[0]] for i in good], dtype=np.float64)[:, :, None]
        else:
            z = np.array([z_of[i] for i in good])  # (np.stack's result, in one array call)
        ap = update_streams([items[i][0].inverse for i in good], z.transpose(1, 2, 0))
        # each chunk's mean speed (np.add.reduce of a row is the row's own pairwise sum)
        means = (np.add.reduce(np.array([items[i][1].speed for i in good]), axis=1) / n).tolist()
        for j, i in enumerate(good):
            z_of[i], ap_of[i], mean_of[i] = z[j], ap[:, :, j], means[j]
    for i, (proc, chunk) in enumerate(items):
        result = out[i]
        if result is None:
            try:
                result = out[i] = proc.feed_ap(chunk, z_of[i], ap_of[i], mean_of[i])
            except Exception as e:  # noqa: BLE001
                result = out[i] = e
        if done is not None and (result or chunk.final):
            done(i, result)
    return out
