"""Sensor-chunk payloads decoded many at a time: one array operation per column over a tick's chunks.

A fleet's chunks repeat one Arrow layout byte for byte in everything but their values: the schema
message, the record batch's metadata, every offset and validity buffer (a one-row batch of lists of
50 samples), even the parameter names. So the first payload of a layout is decoded by the
contract's own :func:`shared.schema.decode_sensor_chunk` and, if valid, becomes its *plan*: where
each value lies in the payload and the bytes of everything structural. Later payloads of that
layout are read as rows of one ``(chunks, bytes)`` matrix: structure compared with the plan's,
values sliced out column by column and checked as :class:`~shared.schema.SensorChunk` checks them.

The fast path only ever accepts: a payload whose structure differs, whose strings the contract's
own checks refuse (a tuple of strings not seen before is checked once, by building a
:class:`~shared.schema.SensorChunk` of no samples with them), or whose values a check refuses is
decoded again by ``decode_sensor_chunk``, which accepts it or says why not. So what is accepted, rejected, and the
reason, are the contract's, and accepted values are its bits.
"""

from __future__ import annotations

import math
import struct
from typing import NamedTuple

import numpy as np
import pyarrow as pa

from shared.schema import (MAX_ABS_CHAINAGE_M, MAX_INT32, MAX_SPEED_MPS, DecodeError, InvalidMessage, SensorChunk,
                           decode_sensor_chunk)

_U32 = struct.Struct("<I")
_STRINGS = ("vehicle_id", "pass_id", "route_id", "vehicle_model")
#: Bounds of what the caches hold (layouts; validated string tuples).
_MAX_PLANS = 256
_MAX_NAMES = 1 << 16
_NO_SAMPLES = np.zeros(0)


class Chunk(NamedTuple):
    """A decoded, validated sensor chunk: the fields of :class:`~shared.schema.SensorChunk` (its
    arrays read-only, equal bit for bit), without validating them again."""

    vehicle_id: str
    pass_id: str
    route_id: str
    vehicle_model: str
    seq: int
    t0: float
    sample_rate_hz: float
    chainage: np.ndarray
    speed: np.ndarray
    channels: dict
    final: bool
    nominal_params: dict | None
    lane_offset_m: float | None

    @property
    def n(self) -> int:
        return int(self.chainage.size)

    @property
    def t(self) -> np.ndarray:
        return self.t0 + np.arange(self.n) / self.sample_rate_hz


class _Plan(NamedTuple):
    size: int  # payload bytes
    struct_idx: np.ndarray  # byte positions of everything structural in the body (the rest is the key) …
    struct_ref: np.ndarray  # … and their bytes
    strings: tuple  # (start, length) of each of _STRINGS' data …
    string_idx: np.ndarray  # … and the positions of all their bytes, in that order
    seq: int
    t0: int
    rate: int
    final: int  # the byte holding the flag's bit 0
    lane: int | None  # None: null in this layout
    params: tuple  # parameter names …
    params_at: int | None  # … and where their float64 values start (None: no parameters)
    n: int  # samples
    chainage: int
    speed: int
    channels: tuple  # (name, start)


def _body_start(payload) -> int | None:
    """Where the record batch's body starts (after the schema message and the batch's metadata)."""
    try:
        if _U32.unpack_from(payload, 0)[0] != 0xFFFFFFFF:
            return None
        schema_end = 8 + _U32.unpack_from(payload, 4)[0]
        if _U32.unpack_from(payload, schema_end)[0] != 0xFFFFFFFF:
            return None
        return schema_end + 8 + _U32.unpack_from(payload, schema_end + 4)[0]
    except struct.error:
        return None


def _make_plan(payload: bytes, chunk: SensorChunk) -> _Plan | None:
    """The plan of a payload the contract's decoder accepted, or None when its buffers are not
    plain slices of the payload (then every payload of the layout takes the general path)."""
    buf = pa.py_buffer(payload)
    schema_end = 8 + _U32.unpack_from(payload, 4)[0]
    try:
        schema = pa.ipc.read_schema(buf.slice(0, schema_end))
        batch = pa.ipc.read_record_batch(pa.ipc.read_message(buf.slice(schema_end)), schema)
    except (pa.ArrowException, ValueError):
        return None
    base, size = buf.address, len(payload)
    structural = np.zeros(size, dtype=bool)
    structural[: _body_start(payload)] = True  # framing, schema, the batch's metadata
    values: dict[str, list[tuple[int, int] | None]] = {}
    for name, col in zip(batch.schema.names, batch.columns):
        spans = []
        for b in col.buffers():
            if b is None or b.size == 0:
                spans.append(None)
                continue
            at = b.address - base
            if not 0 <= at <= size - b.size:
                return None  # a copy (e.g. realigned): not a slice of the payload
            spans.append((at, b.size))
            structural[at : at + b.size] = True
        values[name] = spans

    def value(name: str, k: int, nbytes: int | None = None) -> int:
        at, n = values[name][k]
        span = n if nbytes is None else nbytes
        structural[at : at + span] = False
        return at

    try:
        strings = tuple((value(s, 2), values[s][2][1]) if values[s][2] else (0, 0) for s in _STRINGS)
        lane = None if chunk.lane_offset_m is None else value("lane_offset_m", 1, 8)
        params = tuple(chunk.nominal_params or ())
        params_at = value("nominal_params", 7, 8 * len(params)) if params else None
        n = chunk.n
        scalars = value("seq", 1, 8), value("t0", 1, 8), value("sample_rate_hz", 1, 8), value("final", 1, 1)
        arrays = (value("chainage", 3, 8 * n) if n else 0, value("speed", 3, 8 * n) if n else 0,
                  tuple((name, value("ch." + name, 3, 4 * n) if n else 0) for name in chunk.channels))
    except (KeyError, IndexError, TypeError):
        return None
    # (every value's bytes are unmarked by now: what is left is structure.) The bytes before the
    # body are the plan's key, which a payload matches byte for byte to be read by this plan: only
    # the body's structure is left to compare.
    structural[: _body_start(payload)] = False
    string_idx = np.array([at + k for at, n in strings for k in range(n)], dtype=np.intp)
    plan = _Plan(size, np.flatnonzero(structural), np.frombuffer(payload, np.uint8)[structural].copy(), strings,
                 string_idx,
                 *scalars, lane, params, params_at, n, *arrays)
    # The plan reads back what the decoder read, or it is not used.
    read = _read_rows(plan, np.frombuffer(payload, np.uint8)[None, :])
    names = (chunk.vehicle_id, chunk.pass_id, chunk.route_id, chunk.vehicle_model)
    if not (read[0][0] and same_chunk(_row_chunk(plan, read, 0, names), chunk)):
        return None
    return plan


def _column(rows: np.ndarray, at: int, count: int, dtype: str) -> np.ndarray:
    """(chunks, count) values of ``dtype`` starting at byte ``at`` of every row."""
    width = np.dtype(dtype).itemsize * count
    return np.ascontiguousarray(rows[:, at : at + width]).view(dtype)


def _read_rows(plan: _Plan, rows: np.ndarray):
    """Vectorised checks and values of a layout's rows: ``(ok, seq, t0, rate, final, lane, params,
    chainage, speed, channels)``, ``ok`` false where the fast path cannot vouch for a row."""
    ok = (rows[:, plan.struct_idx] == plan.struct_ref).all(axis=1)
    seq = _column(rows, plan.seq, 1, "<i8")[:, 0]
    t0 = _column(rows, plan.t0, 1, "<f8")[:, 0]
    rate = _column(rows, plan.rate, 1, "<f8")[:, 0]
    final = (rows[:, plan.final] & 1).astype(bool)
    ok &= (seq >= 0) & (seq <= MAX_INT32) & np.isfinite(t0) & (t0 >= 0.0) & np.isfinite(rate) & (rate > 0.0)
    ok &= rate <= 1.0e5
    lane = None
    if plan.lane is not None:
        lane = _column(rows, plan.lane, 1, "<f8")[:, 0]
        ok &= np.isfinite(lane) & (lane >= -10.0) & (lane <= 10.0)
    params = None
    if plan.params_at is not None:
        params = _column(rows, plan.params_at, len(plan.params), "<f8")
        ok &= np.isfinite(params).all(axis=1)
    n = plan.n
    chainage = _column(rows, plan.chainage, n, "<f8")
    speed = _column(rows, plan.speed, n, "<f8")
    channels = [(name, _column(rows, at, n, "<f4")) for name, at in plan.channels]
    if n:
        ok &= np.isfinite(chainage).all(axis=1) & np.isfinite(speed).all(axis=1)
        ok &= (np.abs(chainage).max(axis=1) <= MAX_ABS_CHAINAGE_M) & (np.abs(speed).max(axis=1) <= MAX_SPEED_MPS)
        for _, a in channels:
            ok &= np.isfinite(a).all(axis=1)
    for a in (chainage, speed, *(a for _, a in channels)):
        a.setflags(write=False)
    return ok, seq, t0, rate, final, lane, params, chainage, speed, channels


class ChunkDecoder:
    """Decodes a tick's sensor-chunk payloads together (see the module docstring).

    ``decode(payloads)`` returns, in order, a :class:`Chunk` (or the contract's
    :class:`~shared.schema.SensorChunk` where the general path decoded it) or the
    :class:`~shared.schema.DecodeError` the contract raises for that payload.
    """

    def __init__(self) -> None:
        self._plans: dict[bytes, _Plan | None] = {}
        self._names: set[tuple[str, str, str, str]] = set()  # string tuples a full decode validated
        self._known: dict[tuple, dict] = {}  # … by their UTF-8 bytes, per layout of the strings
        self.fast = 0  # payloads decoded by the fast path
        self.general = 0  # … and by the contract's decoder

    def decode(self, payloads: list[bytes]) -> list:
        out: list = [None] * len(payloads)
        groups: dict[bytes, list[int]] = {}
        last, last_size, last_group = None, -1, None  # the previous payload's key (a fleet's chunks share a few)
        for i, p in enumerate(payloads):
            # A payload that starts with a key is that key's (the key holds every byte _body_start reads)
            if len(p) == last_size and p.startswith(last):
                last_group.append(i)
                continue
            start = _body_start(p) if len(p) >= 24 else None
            key = None if start is None or start > len(p) else bytes(p[:start])
            plan = self._plans.get(key) if key is not None else None
            if plan is None or len(p) != plan.size:
                out[i] = self._general(p, key)
            else:
                last, last_size = key, plan.size
                last_group = groups.setdefault(key, [])
                last_group.append(i)
        for key, idx in groups.items():
            self._fast(self._plans[key], [payloads[i] for i in idx], idx, out)
        return out

    def _general(self, payload: bytes, key: bytes | None):
        self.general += 1
        try:
            chunk = decode_sensor_chunk(payload)
        except DecodeError as e:
            return e
        self._add_names((chunk.vehicle_id, chunk.pass_id, chunk.route_id, chunk.vehicle_model))
        if key is not None and key not in self._plans:
            if len(self._plans) >= _MAX_PLANS:
                self._plans.clear()
            self._plans[key] = _make_plan(bytes(payload), chunk)
        return chunk

    def _add_names(self, names: tuple) -> None:
        if len(self._names) >= _MAX_NAMES:
            self._names.clear()
            self._known.clear()
        self._names.add(names)

    def _validate(self, names: tuple) -> bool:
        """Whether the contract accepts these strings in a sensor chunk (its own checks, which look
        at each string alone: a chunk of no samples with them is built); if so they join the
        validated ones. A new pass's first chunk, of a known layout, then needs no full decode."""
        try:
            SensorChunk(*names, 0, 0.0, 1.0, _NO_SAMPLES, _NO_SAMPLES, {})
        except InvalidMessage:
            return False
        self._add_names(names)
        return True

    def _fast(self, plan: _Plan, group: list[bytes], idx: list[int], out: list) -> None:
        blob = b"".join(group)
        rows = np.frombuffer(blob, np.uint8).reshape(len(group), plan.size)
        read = _read_rows(plan, rows)
        ok = read[0].tolist()
        # every row's strings' bytes, one after the other, as one key per row: a tuple validated once
        # is looked up, not decoded again
        width = plan.string_idx.size
        keys = rows[:, plan.string_idx].tobytes()
        cuts = np.cumsum([0] + [n for _, n in plan.strings]).tolist()
        known = self._known.setdefault(plan.strings, {})
        rows_of = _Rows(plan, read)
        for r, i in enumerate(idx):
            if ok[r]:
                raw = keys[r * width : (r + 1) * width]
                names = known.get(raw)  # (only tuples in self._names: the two are cleared together)
                if names is None:
                    try:
                        names = tuple(raw[a:b].decode() for a, b in zip(cuts[:-1], cuts[1:]))
                    except UnicodeDecodeError:
                        names = None
                    if names is None or not (names in self._names or self._validate(names)):
                        out[i] = self._general(group[r], None)
                        known = self._known.setdefault(plan.strings, {})  # (which may have cleared both)
                        continue
                    known = self._known.setdefault(plan.strings, {})
                    if len(known) >= _MAX_NAMES:
                        known.clear()
                    known[raw] = names
                self.fast += 1
                out[i] = rows_of.chunk(r, names)
            else:
                out[i] = self._general(group[r], None)
                known = self._known.setdefault(plan.strings, {})


class _Rows:
    """The chunks of a layout's rows read by :func:`_read_rows`, the scalars as Python values once
    for all rows (what :func:`_row_chunk` makes of one row)."""

    def __init__(self, plan: _Plan, read) -> None:
        _, seq, t0, rate, final, lane, params, chainage, speed, channels = read
        self.seq, self.t0, self.rate, self.final = seq.tolist(), t0.tolist(), rate.tolist(), final.tolist()
        self.lane = None if lane is None else lane.tolist()
        self.params = None if params is None else params.tolist()
        self.names = plan.params
        self.chainage, self.speed = chainage, speed
        self.channels = channels

    def chunk(self, r: int, names: tuple) -> Chunk:
        return Chunk(names[0], names[1], names[2], names[3], self.seq[r], self.t0[r], self.rate[r],
                     self.chainage[r], self.speed[r], {name: a[r] for name, a in self.channels}, self.final[r],
                     None if self.params is None else dict(zip(self.names, self.params[r])),
                     None if self.lane is None else self.lane[r])


def _row_chunk(plan: _Plan, read, r: int, names: tuple) -> Chunk:
    _, seq, t0, rate, final, lane, params, chainage, speed, channels = read
    return Chunk(names[0], names[1], names[2], names[3], int(seq[r]), float(t0[r]), float(rate[r]),
                 chainage[r], speed[r], {name: a[r] for name, a in channels}, bool(final[r]),
                 None if params is None else dict(zip(plan.params, params[r].tolist())),
                 None if lane is None else float(lane[r]))


def same_chunk(a, b) -> bool:
    """Whether two decoded chunks hold the same fields, arrays bit for bit (a test's check)."""
    for name in Chunk._fields:
        x, y = getattr(a, name), getattr(b, name)
        if name == "channels":
            if list(x) != list(y) or any(not _same_array(x[k], y[k]) for k in x):
                return False
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not _same_array(x, y):
                return False
        elif isinstance(x, float) and isinstance(y, float):
            if not (x == y or (math.isnan(x) and math.isnan(y))):
                return False
        elif x != y:
            return False
    return True


def _same_array(x, y) -> bool:
    return (isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape
            and x.tobytes() == y.tobytes())
