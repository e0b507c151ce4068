"""Versioned Arrow IPC messages of the driveby bus: one frozen dataclass and one decoder per kind.

Wire form
---------
Every payload is an Arrow IPC *stream* holding exactly one record batch of exactly
one row (an ``ap_batch``: one row per segment, see :class:`ApBatch`).  Scalars are typed
columns; arrays are ``list<...>`` columns (one list per row).  The schema metadata key ``driveby`` holds
``{"kind": <kind>, "version": SCHEMA_VERSION}``.  Decoders ignore columns they do not
know, so a message may grow optional columns without a version bump.

Every constructor validates its fields; ``decode_<kind>`` validates the payload
(``bytes``, or a ``zenoh.ZBytes`` such as ``sample.payload``: size, Arrow framing,
header, column presence and types, nulls) and then the fields,
raising :class:`DecodeError` whose ``reason`` is one short, countable word from
:data:`REASONS`.

AP values on the wire (:class:`ApSegment`)
------------------------------------------
* values: ``int16`` codes ``q`` with ``value = offset_m + scale_m * q``; :meth:`ApSegment.make`
  chooses ``offset_m`` = mid-range and ``scale_m`` = half-range / 32767, so the
  rounding error is at most ``scale_m / 2 = (max - min) / 131068`` (0.3 um for a
  tile whose AP spans 40 mm).
* sigma: ``int16`` codes ``q <= 0`` on a log2 scale, ``sigma = sigma_ref_m * 2**(q / 2048)``
  with ``sigma_ref_m`` = max(sigma); codes are rounded *up*, so a decoded sigma is
  never smaller than the encoded one and at most 0.034 % larger (sigmas below
  ``sigma_ref_m * 2**-16`` are raised to that floor).  A log scale keeps the
  relative precision of the smallest (most informative) sigmas, which a linear
  int16 code would not.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import math
import operator
import re
import struct
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, ClassVar, NoReturn

import numpy as np
import pyarrow as pa

from shared.keys import is_valid_id

SCHEMA_VERSION = 1
META_KEY = b"driveby"

MAX_PAYLOAD_BYTES = 4 * 1024 * 1024
MAX_DECODED_BYTES = 64 * 1024 * 1024  # cap on a decoded batch's buffers
MAX_SAMPLES = 1 << 20
MAX_CHANNELS = 32
MAX_PARAMS = 64
MAX_TEXT = 256
MAX_MESSAGE_TEXT = 4096
MAX_SPEED_MPS = 150.0
MAX_ABS_AP_M = 1.0e3
MAX_ABS_CHAINAGE_M = 1.0e7
MAX_INDEX = 1 << 40
MAX_INT32 = (1 << 31) - 1
MAX_BATCH_SEGMENTS = 256  # segments in one ap_batch (~1 MiB of 50 m tiles on a 0.05 m grid)

VEHICLE_MODELS = frozenset({"sprung_mass", "quarter_car", "half_car", "bogie_half_car", "carriage"})

FLAG_UNRELIABLE = 1 << 0
"""ApSegment.flags bit 0: the segment contains warm-up or otherwise unreliable points."""

Q_MAX = 32767
SIGMA_CODES_PER_OCTAVE = 2048
# 2**(q / 2048) of every sigma code q in [-32768, 0], at index -q: decoding a sigma is a table look-up
# (bit-identical to evaluating exp2), here and in the cloud's compiled kernels.
SIGMA_SCALE = np.exp2(-np.arange(Q_MAX + 2) / SIGMA_CODES_PER_OCTAVE)
SIGMA_SCALE.setflags(write=False)

REASONS = (
    "not_arrow",  # not bytes, empty, not an Arrow IPC stream, corrupt buffers
    "bad_header",  # no or unreadable `driveby` metadata
    "wrong_kind",
    "wrong_version",
    "missing_field",  # a required column is absent or null
    "bad_type",  # a column (or a constructor argument) has the wrong type
    "non_finite",  # NaN or inf where a finite number is required
    "bad_shape",  # not one batch of one row, duplicate columns, or array lengths disagree
    "oversize",  # payload or decoded data over the caps
    "bad_value",  # a value out of its range or set, a malformed id
)

_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")
_PARAM_RE = re.compile(r"[A-Za-z0-9_./-]{1,64}")


class InvalidMessage(ValueError):
    """A message field or payload is invalid; ``reason`` is one word of :data:`REASONS`."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


class DecodeError(InvalidMessage):
    """A payload could not be decoded; ``reason`` is one word of :data:`REASONS`."""


# -- field validation (raises InvalidMessage) -------------------------------------------


def _fail(reason: str, detail: str) -> NoReturn:
    raise InvalidMessage(reason, detail)


def _id(name: str, v: object) -> str:
    if not isinstance(v, str):
        _fail("bad_type", f"{name} must be str")
    if not is_valid_id(v):
        _fail("bad_value", f"{name} {v!r} is not [A-Za-z0-9_.-]{{1,128}}")
    return v  # type: ignore[return-value]


def _text(name: str, v: object, max_len: int = MAX_TEXT, *, printable: bool = True) -> str:
    if not isinstance(v, str):
        _fail("bad_type", f"{name} must be str")
    if len(v) > max_len:  # type: ignore[arg-type]
        _fail("oversize", f"{name} longer than {max_len}")
    if (printable and not v.isprintable()) or "\x00" in v:  # type: ignore[union-attr,operator]
        _fail("bad_value", f"{name} has control characters")
    return v  # type: ignore[return-value]


def _int(name: str, v: object, lo: int, hi: int) -> int:
    if type(v) is not int:  # the exact type first: the decoders' common case, and bool is not int here
        if isinstance(v, bool | np.bool_) or not isinstance(v, int | np.integer):
            _fail("bad_type", f"{name} must be int")
        v = int(v)  # type: ignore[arg-type]
    if not lo <= v <= hi:
        _fail("bad_value", f"{name}={v} outside [{lo}, {hi}]")
    return v


def _float(
    name: str, v: object, lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False
) -> float:
    if type(v) is not float:
        if isinstance(v, bool | np.bool_) or not isinstance(v, int | float | np.integer | np.floating):
            _fail("bad_type", f"{name} must be a real number")
        try:
            v = float(v)  # type: ignore[arg-type]
        except OverflowError:
            v = math.inf
    if not math.isfinite(v):
        _fail("non_finite", f"{name} is {v}")
    if v < lo or v > hi or (lo_open and v == lo):
        _fail("bad_value", f"{name}={v} outside {'(' if lo_open else '['}{lo}, {hi}]")
    return v


def _bool(name: str, v: object) -> bool:
    if not isinstance(v, bool | np.bool_):
        _fail("bad_type", f"{name} must be bool")
    return bool(v)


def _array(name: str, v: object, dtype: type, *, finite: bool = True) -> np.ndarray:
    """A read-only 1-D copy of ``v`` as ``dtype``; integer targets are range-checked."""
    target = np.dtype(dtype)
    if type(v) is np.ndarray and v.dtype == target and v.ndim == 1:
        # Already the target type (what the decoders hand over): no conversion, no range to check.
        if v.size > MAX_SAMPLES:
            _fail("oversize", f"{name} has {v.size} > {MAX_SAMPLES} points")
        if finite and target.kind == "f" and not np.isfinite(v).all():
            _fail("non_finite", f"{name} has NaN or inf")
        out = v.copy()
        out.setflags(write=False)
        return out
    try:
        a = np.asarray(v)
    except (TypeError, ValueError):
        _fail("bad_type", f"{name} is not an array")
    if a.dtype.kind not in "iuf":
        _fail("bad_type", f"{name} has dtype {a.dtype}, expected numbers")
    if a.ndim != 1:
        _fail("bad_shape", f"{name} must be 1-D, got shape {a.shape}")
    if a.size > MAX_SAMPLES:
        _fail("oversize", f"{name} has {a.size} > {MAX_SAMPLES} points")
    if target.kind in "iu":
        if a.dtype.kind == "f":
            if not np.all(np.isfinite(a)):
                _fail("non_finite", f"{name} has NaN or inf")
            if np.any(a != np.round(a)):
                _fail("bad_type", f"{name} must hold integers")
        info = np.iinfo(target)
        if a.size and (a.min() < info.min or a.max() > info.max):
            _fail("bad_value", f"{name} outside the {target} range")
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(a, dtype=target, copy=True)
    if finite and target.kind == "f" and not np.all(np.isfinite(out)):
        _fail("non_finite", f"{name} has NaN or inf")
    out.setflags(write=False)
    return out


def _params(name: str, v: object) -> dict[str, float]:
    if not isinstance(v, Mapping):
        _fail("bad_type", f"{name} must be a mapping name -> float")
    if len(v) > MAX_PARAMS:  # type: ignore[arg-type]
        _fail("oversize", f"{name} has more than {MAX_PARAMS} entries")
    out: dict[str, float] = {}
    for k, x in v.items():  # type: ignore[union-attr]
        if not isinstance(k, str):
            _fail("bad_type", f"{name} keys must be str")
        if _PARAM_RE.fullmatch(k) is None:
            _fail("bad_value", f"{name} key {k!r} is not [A-Za-z0-9_./-]{{1,64}}")
        out[k] = _float(f"{name}[{k}]", x)
    return out


def _utc(name: str, v: object) -> str:
    s = _text(name, v, 64)
    try:
        t = datetime.fromisoformat(s)
    except ValueError:
        _fail("bad_value", f"{name} {s!r} is not ISO 8601")
    if t.tzinfo is None:
        _fail("bad_value", f"{name} {s!r} has no time zone")
    return s


# -- Arrow framing --------------------------------------------------------------------


def _list_column(a: np.ndarray, value_type: pa.DataType) -> pa.Array:
    offsets = pa.array(np.array([0, a.size], dtype=np.int32))
    return pa.ListArray.from_arrays(offsets, pa.array(a, type=value_type))


_PARAMS_TYPE = pa.map_(pa.string(), pa.float64())


def _params_column(p: Mapping[str, float] | None) -> pa.Array:
    return pa.array([None if p is None else list(p.items())], type=_PARAMS_TYPE)


_NUMPY_OF = {pa.int64(): np.int64, pa.float64(): np.float64, pa.int32(): np.int32, pa.int16(): np.int16}


def _numeric(values: np.ndarray, t: pa.DataType) -> pa.Array:
    """A numeric Arrow array over ``values`` (1-D, contiguous, of ``t``'s numpy type, no nulls) without
    converting element by element (``pa.array`` of a one-element list: ~10 µs; this: ~3 µs)."""
    return pa.Array.from_buffers(t, len(values), [None, pa.py_buffer(values)])


def _scalar(v: object, t: pa.DataType) -> pa.Array:
    dtype = _NUMPY_OF.get(t)
    if dtype is not None and (type(v) is int or (type(v) is float and dtype is np.float64)):  # (validated: in range)
        return _numeric(np.array([v], dtype=dtype), t)
    return pa.array([v], type=t)


@functools.lru_cache(maxsize=64)
def _framing(kind: str, fields: tuple[tuple[str, pa.DataType], ...]) -> tuple[pa.Schema, bytes]:
    """The schema of a message's columns and its IPC stream header (the schema message): the same
    for every message of a kind, so built once."""
    header = json.dumps({"kind": kind, "version": SCHEMA_VERSION}).encode()
    schema = pa.schema([pa.field(k, t) for k, t in fields], metadata={META_KEY: header})
    return schema, schema.serialize().to_pybytes()


_END_OF_STREAM = b"\xff\xff\xff\xff\x00\x00\x00\x00"


def _encode(kind: str, columns: dict[str, pa.Array]) -> bytes:
    """An Arrow IPC stream of one batch: the schema message, the batch, the end marker (byte for
    byte what ``pa.ipc.new_stream`` writes, without building a writer and a schema per message)."""
    schema, head = _framing(kind, tuple((k, c.type) for k, c in columns.items()))
    batch = pa.RecordBatch.from_arrays(list(columns.values()), schema=schema)
    payload = b"".join((head, batch.serialize().to_pybytes(), _END_OF_STREAM))
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise InvalidMessage("oversize", f"{kind} payload of {len(payload)} B > {MAX_PAYLOAD_BYTES} B")
    return payload


def _payload_bytes(payload: object) -> bytes | bytearray | memoryview:
    """The payload's bytes, of an acceptable size, or DecodeError."""
    zenoh = sys.modules.get("zenoh")  # accept sample.payload as is, without importing zenoh here
    if zenoh is not None and isinstance(payload, zenoh.ZBytes):
        payload = payload.to_bytes()
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise DecodeError("not_arrow", f"payload is {type(payload).__name__}, expected bytes")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise DecodeError("oversize", f"payload of {len(payload)} B > {MAX_PAYLOAD_BYTES} B")
    if len(payload) == 0:
        raise DecodeError("not_arrow", "empty payload")
    return payload


def _read_batch(payload: object) -> tuple[str, int, pa.RecordBatch]:
    """Parse the framing and header; returns ``(kind, version, batch)`` or raises DecodeError."""
    payload = _payload_bytes(payload)
    fast = _read_our_batch(payload)
    if fast is not None:
        return fast
    try:
        _refuse_compressed(payload)
        reader = pa.ipc.open_stream(pa.py_buffer(payload))
        batches = []
        for batch in reader:
            batches.append(batch)
            if len(batches) > 1:
                break
        for batch in batches:
            # Validate before touching anything else: `nbytes` follows the offsets, and
            # corrupt offsets crash the process (found by fuzzing). The cap is checked on the
            # sum of the buffers' sizes, which bounds what the batch holds (it may count a
            # sliced buffer whole, never less) and, unlike `nbytes`, costs nothing.
            batch.validate(full=True)
            size = batch.get_total_buffer_size()
            if size > MAX_DECODED_BYTES:
                raise DecodeError("oversize", f"decoded batch of {size} B")
        schema = reader.schema
        names = schema.names  # raises UnicodeDecodeError (a ValueError) on corrupt names
    except (pa.ArrowException, OSError, ValueError) as e:
        if isinstance(e, DecodeError):
            raise
        raise DecodeError("not_arrow", str(e)[:200]) from None
    kind, version = _header((schema.metadata or {}).get(META_KEY))
    if len(set(names)) != len(names):
        raise DecodeError("bad_shape", "duplicate column names")
    max_rows = _MAX_ROWS.get(kind, 1)
    if len(batches) != 1 or not 1 <= batches[0].num_rows <= max_rows:
        n_rows = [b.num_rows for b in batches]
        want = "one row" if max_rows == 1 else f"1 to {max_rows} rows"
        raise DecodeError("bad_shape", f"expected one batch of {want}, got rows {n_rows}")
    return kind, version, batches[0]


_U8, _U16, _U32, _I32, _I64 = (struct.Struct(f) for f in ("<B", "<H", "<I", "<i", "<q"))
_SCHEMA, _DICTIONARY_BATCH, _RECORD_BATCH = 1, 2, 3  # Arrow's MessageHeader union
_CONTINUATION = 0xFFFFFFFF
_METADATA_V5 = 4  # Arrow's MetadataVersion of what pyarrow writes
_MAX_CACHED_SCHEMA_BYTES = 64 * 1024  # bounds what the schema cache holds (64 entries)


def _schema_end(payload) -> int | None:
    """Where the schema message of a payload framed as :func:`_encode` writes it ends (a continuation
    marker and length, a cacheable schema, a continuation marker after it), else None."""
    n = len(payload)
    if n < 24 or _fb(_U32, payload, 0) != _CONTINUATION:
        return None
    schema_end = 8 + _fb(_U32, payload, 4)
    if schema_end > _MAX_CACHED_SCHEMA_BYTES or schema_end + 16 > n or _fb(_U32, payload, schema_end) != _CONTINUATION:
        return None
    return schema_end


def _read_our_batch(payload) -> tuple[str, int, pa.RecordBatch] | None:
    """The fast path of :func:`_read_batch`, for payloads laid out exactly as :func:`_encode` writes them.

    That is: a schema message, one uncompressed record-batch message, the end-of-stream marker,
    and nothing else. The schema message repeats byte for byte across a stream's chunks, so its
    parse and checks (header, duplicate names) are cached on its bytes; only the batch message is
    read per call, with the same full validation and size cap as the general path. Anything else
    -- other framing, a schema or batch Arrow refuses, any check failing -- returns None and the
    general path decides, so errors (reason and text) come from one place and stay the same.
    """
    view = memoryview(payload)
    try:
        n = len(view)
        schema_end = _schema_end(view)
        if schema_end is None:
            return None
        plan = _schema_plan(view[:schema_end].tobytes())
        if plan is None:
            return None
        schema, kind, version, max_rows = plan
        start = schema_end + 8
        meta = view[start : start + _fb(_U32, view, schema_end + 4)]
        body_length = _batch_body_length(meta.tobytes()) if len(meta) <= _MAX_CACHED_BATCH_META_BYTES else None
        if body_length is None:
            return None
        end = start + len(meta) + body_length
        if end + len(_END_OF_STREAM) != n or view[end:] != _END_OF_STREAM:
            return None
        batch = pa.ipc.read_record_batch(pa.ipc.read_message(pa.py_buffer(view[schema_end:end])), schema)
        batch.validate(full=True)  # before anything else touches it, as in the general path
        if batch.get_total_buffer_size() > MAX_DECODED_BYTES or not 1 <= batch.num_rows <= max_rows:
            return None
        return kind, version, batch
    except Exception:  # noqa: BLE001 -- any failure: the general path reads it again and says why
        return None


@functools.lru_cache(maxsize=64)
def _schema_plan(message: bytes) -> tuple[pa.Schema, str, int, int] | None:
    """``(schema, kind, version, max_rows)`` of a well-formed schema message of ours, else None (cached)."""
    try:
        meta = memoryview(message)[8:]
        root = _fb(_U32, meta, 0)
        header_type, body = _fb_field(meta, root, 1), _fb_field(meta, root, 3)
        if header_type is None or _fb(_U8, meta, header_type) != _SCHEMA:
            return None
        if body is not None and _fb(_I64, meta, body) != 0:
            return None  # a schema with a body: the general path follows its framing
        schema = pa.ipc.read_schema(pa.py_buffer(message))
        names = schema.names
        kind, version = _header((schema.metadata or {}).get(META_KEY))
    except Exception:  # noqa: BLE001 -- not ours: the general path reports it
        return None
    if len(set(names)) != len(names):
        return None
    return schema, kind, version, _MAX_ROWS.get(kind, 1)


_MAX_CACHED_BATCH_META_BYTES = 4096  # a sensor chunk's is ~600 B; bounds the cache below (256 entries)


@functools.lru_cache(maxsize=256)
def _batch_body_length(meta: bytes) -> int | None:
    """The body length of an uncompressed record-batch message with this metadata, else None (cached).

    The metadata repeats byte for byte across chunks of the same length (and the same text lengths),
    so its flatbuffer walk is done once per layout, not once per chunk.
    """
    try:
        root = _fb(_U32, meta, 0)
        header_type = _fb_field(meta, root, 1)
        header = _fb_field(meta, root, 2)
        body = _fb_field(meta, root, 3)
        if header_type is None or _fb(_U8, meta, header_type) != _RECORD_BATCH or header is None or body is None:
            return None
        if _fb_field(meta, header + _fb(_U32, meta, header), 3) is not None:
            return None  # compressed: refused by the general path before anything inflates
        body_length = _fb(_I64, meta, body)
    except ValueError:  # an offset out of range: the general path reports it
        return None
    return body_length if body_length >= 0 else None


def _fb(fmt: struct.Struct, buf, pos: int) -> int:
    if not 0 <= pos <= len(buf) - fmt.size:
        raise ValueError("flatbuffer offset out of range")
    return fmt.unpack_from(buf, pos)[0]


def _fb_field(buf, table: int, field: int) -> int | None:
    """Position of a flatbuffer table's field, or None if absent (bounds-checked: ValueError)."""
    vtable = table - _fb(_I32, buf, table)
    if 4 + 2 * field >= _fb(_U16, buf, vtable):
        return None
    offset = _fb(_U16, buf, vtable + 4 + 2 * field)
    return table + offset if offset else None


def _refuse_compressed(payload) -> None:
    """Refuse compressed record batches and dictionaries *before* Arrow inflates them.

    A few kB of zstd expand to gigabytes (9 kB can become 200 MB before a size cap sees it),
    and a bound checked after decompression comes too late. Our
    encoder never compresses, nor uses dictionaries, so both are refused from the message
    headers alone, walking the stream's framing (Arrow's Message.fbs: ``Message`` fields
    1 ``header_type``, 2 ``header``, 3 ``bodyLength``; ``RecordBatch`` field 3 ``compression``).
    Framing it cannot follow is left to Arrow's reader, which refuses it.
    """
    view = memoryview(payload)
    pos = 0
    for _ in range(3):  # the schema and the (at most) two batches _read_batch reads
        if pos + 8 > len(view):
            return
        size = _fb(_U32, view, pos)
        if size == 0xFFFFFFFF:  # continuation marker, then the metadata's length
            size = _fb(_U32, view, pos + 4)
            pos += 8
        else:  # the pre-1.0 framing: the length alone
            pos += 4
        if size == 0 or pos + size > len(view):
            return
        meta = view[pos : pos + size]
        root = _fb(_U32, meta, 0)
        kind = _fb_field(meta, root, 1)
        kind = _fb(_U8, meta, kind) if kind is not None else 0
        if kind == _DICTIONARY_BATCH:
            raise DecodeError("bad_type", "dictionary-encoded columns")
        if kind == _RECORD_BATCH:
            header = _fb_field(meta, root, 2)
            if header is None:
                return
            batch = header + _fb(_U32, meta, header)
            if _fb_field(meta, batch, 3) is not None:
                raise DecodeError("oversize", "compressed IPC body (its decoded size is unknown until inflated)")
        body = _fb_field(meta, root, 3)
        pos += size + (_fb(_I64, meta, body) if body is not None else 0)


@functools.lru_cache(maxsize=64)
def _header(raw: bytes | None) -> tuple[str, int]:
    """``(kind, version)`` from the ``driveby`` schema metadata (a handful of distinct values: cached)."""
    if raw is None:
        raise DecodeError("bad_header", "no 'driveby' schema metadata")
    try:
        header = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise DecodeError("bad_header", "'driveby' metadata is not JSON") from None
    kind = header.get("kind") if isinstance(header, dict) else None
    version = header.get("version") if isinstance(header, dict) else None
    if not isinstance(kind, str) or isinstance(version, bool) or not isinstance(version, int):
        raise DecodeError("bad_header", "'driveby' metadata needs a str kind and an int version")
    return kind, version


def _type_ids(*types: pa.DataType) -> frozenset[int]:
    return frozenset(t.id for t in types)


# Accepted Arrow types per field kind, as type ids: a set lookup per column instead of predicate calls.
_TEXT_IDS = _type_ids(pa.string(), pa.large_string())
_INTEGER_IDS = _type_ids(pa.int8(), pa.int16(), pa.int32(), pa.int64(),
                         pa.uint8(), pa.uint16(), pa.uint32(), pa.uint64())
_FLOAT_IDS = _type_ids(pa.float16(), pa.float32(), pa.float64())
_BOOL_IDS = _type_ids(pa.bool_())
_LIST_IDS = _type_ids(pa.list_(pa.int8()), pa.large_list(pa.int8()))
_MAP_IDS = _type_ids(_PARAMS_TYPE)


class _Row:
    """Typed access to the row of a decoded batch (or, column-wise, to its rows; raises InvalidMessage).

    The batch has been fully validated (:func:`_read_batch`), so scalars are read with one
    ``to_pylist()`` per column and lists as zero-copy numpy views of their values (read-only;
    the message constructors copy them).
    """

    def __init__(self, batch: pa.RecordBatch) -> None:
        self.batch = batch
        self.n_rows = batch.num_rows
        # One pass over the columns: a name lookup per field would be most of the decoding time.
        self.columns = dict(zip(batch.schema.names, batch.columns))
        self.names = self.columns.keys()

    def _col(self, name: str) -> pa.Array | None:
        return self.columns.get(name)

    def _required(self, name: str, type_ids: frozenset[int], what: str) -> pa.Array:
        col = self.columns.get(name)
        if col is None:
            _fail("missing_field", f"no column {name!r}")
        if col.type.id not in type_ids:
            _fail("bad_type", f"column {name!r} is {col.type}, expected {what}")
        if col.null_count:
            _fail("missing_field", f"column {name!r} is null")
        return col

    def texts(self, name: str) -> list[str]:
        return self._required(name, _TEXT_IDS, "string").to_pylist()

    def integers(self, name: str) -> list[int]:
        return self._required(name, _INTEGER_IDS, "integer").to_pylist()

    def reals(self, name: str) -> list[float]:
        return self._required(name, _FLOAT_IDS, "float").to_pylist()

    def arrays(self, name: str, value_type: pa.DataType) -> list[np.ndarray]:
        col = self._required(name, _LIST_IDS, f"list<{value_type}>")
        if not col.type.value_type.equals(value_type):
            _fail("bad_type", f"column {name!r} is {col.type}, expected list<{value_type}>")
        if self.n_rows == 1:
            values = col[0].values
            bounds = [0, len(values)]
        else:  # offsets index the child array `values`; read only the stretch the rows use
            bounds = col.offsets.to_numpy().tolist()
            values = col.values.slice(bounds[0], bounds[-1] - bounds[0])
            bounds = [b - bounds[0] for b in bounds]
        if values.null_count:
            _fail("missing_field", f"column {name!r} has null items")
        flat = values.to_numpy(zero_copy_only=False)
        return [flat[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:])]

    def text(self, name: str) -> str:
        return self.texts(name)[0]

    def integer(self, name: str) -> int:
        return self.integers(name)[0]

    def real(self, name: str) -> float:
        return self.reals(name)[0]

    def flag(self, name: str) -> bool:
        return self._required(name, _BOOL_IDS, "bool").to_pylist()[0]

    def opt_real(self, name: str) -> float | None:
        col = self._col(name)
        if col is None or col.null_count:
            return None
        return self.real(name)

    def array(self, name: str, value_type: pa.DataType) -> np.ndarray:
        return self.arrays(name, value_type)[0]

    def params(self, name: str, *, optional: bool) -> dict[str, float] | None:
        col = self._col(name)
        if optional and (col is None or col.null_count):
            return None
        col = self._required(name, _MAP_IDS, str(_PARAMS_TYPE))
        if not (pa.types.is_string(col.type.key_type) and pa.types.is_float64(col.type.item_type)):
            _fail("bad_type", f"column {name!r} is {col.type}, expected {_PARAMS_TYPE}")
        items = col.to_pylist()[0]
        keys = [k for k, _ in items]
        if len(set(keys)) != len(keys):
            _fail("bad_value", f"column {name!r} has duplicate keys")
        if any(v is None for _, v in items):
            _fail("missing_field", f"column {name!r} has null values")
        return dict(items)


# -- messages ---------------------------------------------------------------------------


class _Message:
    """Shared behaviour: field-wise equality that understands numpy arrays."""

    KIND: ClassVar[str]
    __hash__ = None  # type: ignore[assignment]  # arrays make messages unhashable

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(
            _same(getattr(self, f.name), getattr(other, f.name)) for f in dataclasses.fields(self)  # type: ignore[arg-type]
        )


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and np.array_equal(a, b)
        )
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def _decoding(kind: str, payload: object, build) -> Any:
    got, version, batch = _read_batch(payload)
    if got != kind:
        raise DecodeError("wrong_kind", f"expected {kind}, got {got}")
    return _build(kind, version, batch, build)


def _build(kind: str, version: int, batch: pa.RecordBatch, build) -> Any:
    if version != SCHEMA_VERSION:
        raise DecodeError("wrong_version", f"{kind} version {version}, expected {SCHEMA_VERSION}")
    try:
        return build(_Row(batch))
    except DecodeError:
        raise
    except InvalidMessage as e:
        raise DecodeError(e.reason, e.detail) from None


@dataclass(frozen=True, eq=False)
class SensorChunk(_Message):
    """A chunk of one vehicle's raw sensor stream (simfleet -> edge).

    ``chainage`` (m) and ``speed`` (m/s) are float64, every channel float32, all of the
    chunk's length ``n``; sample ``i`` is at ``t0 + i / sample_rate_hz`` seconds since
    the start of the log.  ``seq`` numbers the chunks of a pass from 0; ``final``
    marks the pass's last chunk (which may be empty).
    """

    KIND: ClassVar[str] = "sensor_chunk"

    vehicle_id: str
    pass_id: str
    route_id: str
    vehicle_model: str
    seq: int
    t0: float
    sample_rate_hz: float
    chainage: np.ndarray
    speed: np.ndarray
    channels: Mapping[str, np.ndarray]
    final: bool = False
    nominal_params: Mapping[str, float] | None = None
    lane_offset_m: float | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        _id("vehicle_id", self.vehicle_id)
        _text("pass_id", self.pass_id, MAX_TEXT)
        if not self.pass_id:
            _fail("bad_value", "pass_id is empty")
        _id("route_id", self.route_id)
        if _text("vehicle_model", self.vehicle_model) not in VEHICLE_MODELS:
            _fail("bad_value", f"vehicle_model {self.vehicle_model!r} not in {sorted(VEHICLE_MODELS)}")
        set_(self, "seq", _int("seq", self.seq, 0, MAX_INT32))
        set_(self, "t0", _float("t0", self.t0, 0.0))
        set_(self, "sample_rate_hz", _float("sample_rate_hz", self.sample_rate_hz, 0.0, 1.0e5, lo_open=True))
        chainage = _array("chainage", self.chainage, np.float64)
        speed = _array("speed", self.speed, np.float64)
        n = chainage.size
        if speed.size != n:
            _fail("bad_shape", f"speed has {speed.size} samples, chainage {n}")
        if n and np.abs(chainage).max() > MAX_ABS_CHAINAGE_M:
            _fail("bad_value", f"|chainage| > {MAX_ABS_CHAINAGE_M} m")
        if n and np.abs(speed).max() > MAX_SPEED_MPS:
            _fail("bad_value", f"|speed| > {MAX_SPEED_MPS} m/s")
        if not isinstance(self.channels, Mapping):
            _fail("bad_type", "channels must be a mapping name -> array")
        if len(self.channels) > MAX_CHANNELS:
            _fail("oversize", f"more than {MAX_CHANNELS} channels")
        channels = {}
        for name, values in self.channels.items():
            if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None:
                _fail("bad_value", f"channel name {name!r} is not an identifier")
            a = _array(f"channels[{name}]", values, np.float32)
            if a.size != n:
                _fail("bad_shape", f"channel {name} has {a.size} samples, chainage {n}")
            channels[name] = a
        set_(self, "chainage", chainage)
        set_(self, "speed", speed)
        set_(self, "channels", channels)
        set_(self, "final", _bool("final", self.final))
        if self.nominal_params is not None:
            set_(self, "nominal_params", _params("nominal_params", self.nominal_params))
        if self.lane_offset_m is not None:
            set_(self, "lane_offset_m", _float("lane_offset_m", self.lane_offset_m, -10.0, 10.0))

    @property
    def n(self) -> int:
        """Number of samples in the chunk."""
        return int(self.chainage.size)

    @property
    def t(self) -> np.ndarray:
        """Sample times (s since the start of the log), float64."""
        return self.t0 + np.arange(self.n) / self.sample_rate_hz

    def encode(self) -> bytes:
        """Arrow IPC payload of this chunk."""
        cols = {
            "vehicle_id": _scalar(self.vehicle_id, pa.string()),
            "pass_id": _scalar(self.pass_id, pa.string()),
            "route_id": _scalar(self.route_id, pa.string()),
            "vehicle_model": _scalar(self.vehicle_model, pa.string()),
            "seq": _scalar(self.seq, pa.int64()),
            "t0": _scalar(self.t0, pa.float64()),
            "sample_rate_hz": _scalar(self.sample_rate_hz, pa.float64()),
            "final": _scalar(self.final, pa.bool_()),
            "nominal_params": _params_column(self.nominal_params),
            "lane_offset_m": _scalar(self.lane_offset_m, pa.float64()),
            "chainage": _list_column(self.chainage, pa.float64()),
            "speed": _list_column(self.speed, pa.float64()),
        }
        for name, values in self.channels.items():
            cols["ch." + name] = _list_column(values, pa.float32())
        return _encode(self.KIND, cols)


def _build_sensor_chunk(r: _Row) -> SensorChunk:
    channels = {
        name[3:]: r.array(name, pa.float32()) for name in r.names if name.startswith("ch.")
    }
    return SensorChunk(
        vehicle_id=r.text("vehicle_id"),
        pass_id=r.text("pass_id"),
        route_id=r.text("route_id"),
        vehicle_model=r.text("vehicle_model"),
        seq=r.integer("seq"),
        t0=r.real("t0"),
        sample_rate_hz=r.real("sample_rate_hz"),
        chainage=r.array("chainage", pa.float64()),
        speed=r.array("speed", pa.float64()),
        channels=channels,
        final=r.flag("final"),
        nominal_params=r.params("nominal_params", optional=True),
        lane_offset_m=r.opt_real("lane_offset_m"),
    )



def decode_sensor_chunk(payload: bytes) -> SensorChunk:
    """Decode and validate a :class:`SensorChunk` payload; raises :class:`DecodeError`."""
    return _decoding(SensorChunk.KIND, payload, _build_sensor_chunk)


def quantize_values(values_m: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Linear int16 code of finite values: returns ``(q, scale_m, offset_m)``.

    ``values ~= offset_m + scale_m * q`` with an error of at most ``scale_m / 2``.
    """
    v = np.asarray(values_m, dtype=np.float64)
    return _quantize_values(v, float(v.min()), float(v.max()))


def _quantize_values(v: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, float, float]:
    """:func:`quantize_values` of float64 ``v`` whose extremes ``lo`` and ``hi`` are known."""
    offset = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    scale = half / Q_MAX
    if not scale > 0.0:  # constant segment (or a half-range below the smallest float)
        scale = 1.0
    x = np.subtract(v, offset)  # (in place from here: one temporary instead of four)
    x /= scale
    np.rint(x, out=x)
    np.maximum(x, -Q_MAX, out=x)  # (np.clip's bounds as two ufuncs: no wrapper; x has no NaN)
    np.minimum(x, Q_MAX, out=x)
    return x.astype(np.int16), scale, offset


def quantize_sigma(sigma_m: np.ndarray) -> tuple[np.ndarray, float]:
    """Log2 int16 code of positive sigmas, rounded up: returns ``(q, sigma_ref_m)``.

    ``sigma ~= sigma_ref_m * 2**(q / 2048)``, never below the true sigma.
    """
    s = np.asarray(sigma_m, dtype=np.float64)
    return _quantize_sigma(s, float(s.max()))


def _quantize_sigma(s: np.ndarray, ref: float) -> tuple[np.ndarray, float]:
    """:func:`quantize_sigma` of positive float64 ``s`` whose largest value ``ref`` is known."""
    code = np.divide(s, ref)  # (in place from here: one temporary instead of four)
    np.log2(code, out=code)
    code *= SIGMA_CODES_PER_OCTAVE
    np.ceil(code, out=code)
    np.maximum(code, -Q_MAX - 1, out=code)  # (np.clip's bounds as two ufuncs; code has no NaN)
    np.minimum(code, 0, out=code)
    return code.astype(np.int16), ref


ERROR_MODEL_NONE = np.zeros(0)
ERROR_MODEL_NONE.setflags(write=False)
#: Largest order p of an AP error model's precision band.
MAX_ERROR_BAND = 8
_ERROR_OMEGA = np.linspace(0.0, np.pi, 513)
_ERROR_COS = np.cos(np.outer(_ERROR_OMEGA, np.arange(1, MAX_ERROR_BAND + 1)))  # cos kω, k = 1..p: once


def _error_model(value: object) -> np.ndarray:
    """An ApSegment.error_model: empty, or ``[r > 0, c₀, …, c_p]`` (p ≤ 8) whose symbol
    ``c₀ + 2 Σ c_k cos kω`` is positive on [0, π] (so the precision is positive definite)."""
    if type(value) is np.ndarray and value.size == 0 and value.ndim == 1:
        return ERROR_MODEL_NONE  # none (every segment of an edge without one: no copy, no checks)
    em = _array("error_model", value, np.float64)
    if em.size == 0:
        return ERROR_MODEL_NONE
    if em.ndim != 1 or not 2 <= em.size <= MAX_ERROR_BAND + 2:
        _fail("bad_shape", f"error_model has {em.size} values, expected 0 or 2..{MAX_ERROR_BAND + 2}")
    if not (em[0] > 0 and em[0] <= 1e6):
        _fail("bad_value", "error_model scale must lie in (0, 1e6]")
    p = em.size - 2
    symbol = em[1] + 2.0 * (_ERROR_COS[:, :p] @ em[2:]) if p else np.full(1, em[1])
    if not np.min(symbol) > 0:
        _fail("bad_value", "error_model band is not positive definite")
    return em


def _extremes(name: str, v: object) -> tuple[np.ndarray, float, float]:
    """``v`` as a finite 1-D float64 array (not copied when it is one) and its least and largest
    values, with the reasons :func:`_array` gives."""
    if type(v) is not np.ndarray or v.dtype != np.float64 or v.ndim != 1 or v.size > MAX_SAMPLES:
        v = _array(name, v, np.float64)
    if v.size == 0:
        return v, 0.0, 0.0
    lo, hi = float(v.min()), float(v.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):  # (a NaN anywhere makes both NaN)
        _fail("non_finite", f"{name} has NaN or inf")
    return v, lo, hi


@dataclass(frozen=True, eq=False)
class ApSegment(_Message):
    """A segment of one pass's apparent profile on the route's global grid (edge -> cloud).

    Point ``i`` lies at chainage ``(start_index + i) * spacing_m`` of route ``route_id``,
    under axle ``axle`` (1-based, 1 = leading); ``tile`` is the tile the segment
    belongs to.  Build with :meth:`make`; read with :attr:`values` and :attr:`sigma`
    (float64, m).  Identity for idempotent fusion: :attr:`identity`.
    """

    KIND: ClassVar[str] = "ap_segment"

    vehicle_id: str
    pass_id: str
    route_id: str
    tile: int
    axle: int
    start_index: int
    spacing_m: float
    values_q: np.ndarray
    scale_m: float
    offset_m: float
    sigma_q: np.ndarray
    sigma_ref_m: float
    calib_version: int
    speed_mps: float
    t_first: float
    t_last: float
    seq: int
    n_segments_in_pass: int = -1
    flags: int = 0
    # Optional (additive) AP error model from the edge (edge.error_model): empty, or
    # ``[r, c₀, c₁, …, c_p]`` — the error at point i is ``r · sigma[i]`` times a stationary
    # unit-variance process whose precision is the banded Toeplitz matrix ``c_{|i−j|}``. Empty: the
    # cloud's own white/AR(1) model of ``sigma``.
    error_model: np.ndarray = field(default_factory=lambda: ERROR_MODEL_NONE)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        self._check_place()
        values_q = _array("values_q", self.values_q, np.int16)
        sigma_q = _array("sigma_q", self.sigma_q, np.int16)
        if values_q.size == 0:
            _fail("bad_shape", "a segment needs at least one point")
        if sigma_q.size != values_q.size:
            _fail("bad_shape", f"sigma has {sigma_q.size} points, values {values_q.size}")
        if sigma_q.max() > 0:  # not empty, checked above
            _fail("bad_value", "sigma codes must be <= 0")
        set_(self, "values_q", values_q)
        set_(self, "sigma_q", sigma_q)
        self._check_rest()

    def _check_place(self) -> None:
        """Validate the fields before the codes (identity and grid position)."""
        set_ = object.__setattr__
        _id("vehicle_id", self.vehicle_id)
        _text("pass_id", self.pass_id, MAX_TEXT)
        if not self.pass_id:
            _fail("bad_value", "pass_id is empty")
        _id("route_id", self.route_id)
        set_(self, "tile", _int("tile", self.tile, 0, MAX_INT32))
        set_(self, "axle", _int("axle", self.axle, 1, 16))
        # Negative: points before the route's start (a rail vehicle's trailing wheels when its log
        # starts; the cloud keeps them for re-running the pass, and fuses only chainage >= 0).
        set_(self, "start_index", _int("start_index", self.start_index, -MAX_INDEX, MAX_INDEX))
        set_(self, "spacing_m", _float("spacing_m", self.spacing_m, 0.0, 100.0, lo_open=True))

    def _check_rest(self) -> None:
        """Validate the fields after the codes (their decoding, calibration, times, sequence, error model)."""
        set_ = object.__setattr__
        set_(self, "scale_m", _float("scale_m", self.scale_m, 0.0, 1.0, lo_open=True))
        set_(self, "offset_m", _float("offset_m", self.offset_m, -MAX_ABS_AP_M, MAX_ABS_AP_M))
        set_(self, "sigma_ref_m", _float("sigma_ref_m", self.sigma_ref_m, 0.0, MAX_ABS_AP_M, lo_open=True))
        set_(self, "calib_version", _int("calib_version", self.calib_version, 0, MAX_INT32))
        set_(self, "speed_mps", _float("speed_mps", self.speed_mps, 0.0, MAX_SPEED_MPS))
        set_(self, "t_first", _float("t_first", self.t_first))
        set_(self, "t_last", _float("t_last", self.t_last))
        if self.t_last < self.t_first:
            _fail("bad_value", f"t_last {self.t_last} < t_first {self.t_first}")
        set_(self, "seq", _int("seq", self.seq, 0, MAX_INT32))
        set_(self, "n_segments_in_pass", _int("n_segments_in_pass", self.n_segments_in_pass, -1, MAX_INT32))
        if self.n_segments_in_pass >= 0 and self.seq >= self.n_segments_in_pass:
            _fail("bad_value", f"seq {self.seq} >= n_segments_in_pass {self.n_segments_in_pass}")
        set_(self, "flags", _int("flags", self.flags, 0, MAX_INT32))
        set_(self, "error_model", _error_model(self.error_model))

    @classmethod
    def make(
        cls,
        values_m: np.ndarray,
        sigma_m: np.ndarray,
        *,
        vehicle_id: str,
        pass_id: str,
        route_id: str,
        tile: int,
        axle: int,
        start_index: int,
        spacing_m: float,
        calib_version: int,
        speed_mps: float,
        t_first: float,
        t_last: float,
        seq: int,
        n_segments_in_pass: int = -1,
        flags: int = 0,
        error_model: np.ndarray | None = None,
    ) -> ApSegment:
        """Quantise float AP values and sigmas (m) into a segment.

        Parameters
        ----------
        values_m : array (n,)
            Apparent profile (m, up positive), finite, ``|v| <= 1000``.
        sigma_m : array (n,)
            Per-point error scale (m), finite and positive.
        error_model : array, optional
            ``[r, c₀, …, c_p]`` (see the class), or None for none.
        """
        values, lo, hi = _extremes("values_m", values_m)
        sigma, s_lo, s_hi = _extremes("sigma_m", sigma_m)
        if values.size == 0:
            _fail("bad_shape", "a segment needs at least one point")
        if sigma.size != values.size:
            _fail("bad_shape", f"sigma has {sigma.size} points, values {values.size}")
        if lo < -MAX_ABS_AP_M or hi > MAX_ABS_AP_M:
            _fail("bad_value", f"|AP| > {MAX_ABS_AP_M} m")
        if s_lo <= 0.0 or s_hi > MAX_ABS_AP_M:
            _fail("bad_value", f"sigma must lie in (0, {MAX_ABS_AP_M}] m")
        q, scale, offset = _quantize_values(values, lo, hi)
        sq, ref = _quantize_sigma(sigma, s_hi)
        # The codes are valid by construction (int16, as many as the values, sigma codes <= 0):
        # every other field is validated as the constructor does, the codes not a second time.
        q.setflags(write=False)
        sq.setflags(write=False)
        seg = cls.__new__(cls)
        seg.__dict__.update(
            vehicle_id=vehicle_id,
            pass_id=pass_id,
            route_id=route_id,
            tile=tile,
            axle=axle,
            start_index=start_index,
            spacing_m=spacing_m,
            values_q=q,
            scale_m=scale,
            offset_m=offset,
            sigma_q=sq,
            sigma_ref_m=ref,
            calib_version=calib_version,
            speed_mps=speed_mps,
            t_first=t_first,
            t_last=t_last,
            seq=seq,
            n_segments_in_pass=n_segments_in_pass,
            flags=flags,
            error_model=ERROR_MODEL_NONE if error_model is None else error_model,
        )
        seg._check_place()
        seg._check_rest()
        return seg

    @property
    def n(self) -> int:
        """Number of grid points."""
        return int(self.values_q.size)

    @property
    def end_index(self) -> int:
        """Grid index one past the segment's last point."""
        return self.start_index + self.n

    # The decoded arrays are computed once per segment and read-only, like the segment itself: the
    # cloud reads them in its checks and in every estimator's update and retract.
    @functools.cached_property
    def values(self) -> np.ndarray:
        """AP values (m), float64, read-only."""
        v = self.offset_m + self.scale_m * self.values_q.astype(np.float64)
        v.setflags(write=False)
        return v

    @functools.cached_property
    def sigma(self) -> np.ndarray:
        """Per-point error scale (m), float64, read-only, never below what was encoded."""
        s = self.sigma_ref_m * SIGMA_SCALE[np.negative(self.sigma_q, dtype=np.intp)]
        s.setflags(write=False)
        return s

    @property
    def value_range(self) -> tuple[float, float]:
        """``(min, max)`` of :attr:`values` (m), from the extreme codes (the decoding is monotone)."""
        return (self.offset_m + self.scale_m * float(self.values_q.min()),
                self.offset_m + self.scale_m * float(self.values_q.max()))

    @property
    def chainage_m(self) -> np.ndarray:
        """Route chainage (m) of each point."""
        return (self.start_index + np.arange(self.n)) * self.spacing_m

    @property
    def identity(self) -> tuple[str, str, str, int, int, int]:
        """``(vehicle_id, pass_id, route_id, tile, axle, calib_version)``: same identity,
        same segment, so a redelivery replaces rather than adds."""
        return (self.vehicle_id, self.pass_id, self.route_id, self.tile, self.axle, self.calib_version)

    def encode(self) -> bytes:
        """Arrow IPC payload of this segment."""
        return _encode_ap(self.KIND, (self,))


# The wire columns of an AP segment, in order (an ap_batch has the same columns, one row per segment).
_AP_COLUMNS = (
    ("vehicle_id", pa.string()),
    ("pass_id", pa.string()),
    ("route_id", pa.string()),
    ("tile", pa.int64()),
    ("axle", pa.int64()),
    ("start_index", pa.int64()),
    ("spacing_m", pa.float64()),
    ("values_q", pa.list_(pa.int16())),
    ("scale_m", pa.float64()),
    ("offset_m", pa.float64()),
    ("sigma_q", pa.list_(pa.int16())),
    ("sigma_ref_m", pa.float64()),
    ("calib_version", pa.int64()),
    ("speed_mps", pa.float64()),
    ("t_first", pa.float64()),
    ("t_last", pa.float64()),
    ("seq", pa.int64()),
    ("n_segments_in_pass", pa.int64()),
    ("flags", pa.int64()),
    ("error_model", pa.list_(pa.float64())),
)
#: Columns a payload may lack (written by an older edge): their default is used.
_AP_OPTIONAL = {"error_model": ERROR_MODEL_NONE}
_AP_NAMES = tuple(name for name, _ in _AP_COLUMNS)
# The decoder builds segments from the columns positionally.
assert _AP_NAMES == tuple(f.name for f in dataclasses.fields(ApSegment)), "AP columns out of the fields' order"
_AP_READERS = tuple(  # the _Row method reading each column, and its list value type
    ("arrays", t.value_type) if pa.types.is_list(t) else
    ("texts", None) if pa.types.is_string(t) else
    ("integers", None) if pa.types.is_integer(t) else ("reals", None)
    for _, t in _AP_COLUMNS
)


_AP_INT64 = tuple(name for name, t in _AP_COLUMNS if t == pa.int64())
_AP_FLOAT64 = tuple(name for name, t in _AP_COLUMNS if t == pa.float64())


def _ap_columns(segments: list[ApSegment] | tuple[ApSegment, ...]) -> dict[str, pa.Array]:
    # The numeric fields of every segment in one array per type (row j: the j-th such field), each
    # column a view of its row: two conversions per payload instead of one per field (a conversion
    # per field would be most of the cost of spilling a segment).
    n = len(segments)
    numeric = {name: row for names, dtype in ((_AP_INT64, np.int64), (_AP_FLOAT64, np.float64))
               for name, row in zip(names, np.array([[getattr(s, f) for s in segments] for f in names],
                                                     dtype=dtype).reshape(len(names), n))}
    cols = {}
    for name, t in _AP_COLUMNS:
        row = numeric.get(name)
        if row is not None:
            cols[name] = _numeric(row, t)
        elif pa.types.is_list(t):
            items = [getattr(s, name) for s in segments]
            offsets = np.array([0, *itertools.accumulate(a.size for a in items)], dtype=np.int32)
            values = np.ascontiguousarray(items[0] if n == 1 else np.concatenate(items), _NUMPY_OF[t.value_type])
            cols[name] = pa.Array.from_buffers(t, n, [None, pa.py_buffer(offsets)],
                                               children=[_numeric(values, t.value_type)])
        else:
            cols[name] = pa.array([getattr(s, name) for s in segments], type=t)
    return cols


# Payloads written into a template of their layout (AP segments and batches, acknowledgements: the
# messages the cloud writes per segment or per pass). Arrow's IPC bytes of a batch whose columns
# are texts, int64 and float64 scalars and lists of numbers, each a field of the row objects, depend
# on the values only through the contents of the value buffers: the metadata (buffer offsets and
# lengths, list and text offsets, padding) is fixed by the layout (the rows, each row's text lengths
# in bytes and array sizes). So the first payload of a layout is encoded by Arrow and the positions
# of its value buffers read back; every later payload of that layout is its values written at those
# positions into a copy of it, byte for byte what Arrow writes, without building arrays and a record
# batch each time.


@dataclass(frozen=True)
class _Flat:
    """How the template encoder reads a kind whose wire columns are its row objects' fields."""

    names: tuple[str, ...]  # every column, in the wire's order
    texts: tuple[str, ...]
    lists: tuple[tuple[str, Any, type], ...]  # (name, getter, numpy type of the values)
    numbers: tuple[tuple[tuple[str, ...], Any, type], ...]  # the scalar columns per numpy type, their getter
    packs: dict  # a scalar column's name → how one value is packed (one-row payloads)


def _flat(columns) -> _Flat:
    scalars = {np.int64: [], np.float64: []}
    for name, t in columns:
        if pa.types.is_int64(t) or pa.types.is_float64(t):
            scalars[_NUMPY_OF[t]].append(name)
        elif not (pa.types.is_string(t) or (pa.types.is_list(t) and t.value_type in _NUMPY_OF)):
            raise TypeError(f"{name}: {t} is not a column the template encoder writes")
    return _Flat(names=tuple(name for name, _ in columns),
                 texts=tuple(name for name, t in columns if pa.types.is_string(t)),
                 lists=tuple((name, operator.attrgetter(name), _NUMPY_OF[t.value_type])
                             for name, t in columns if pa.types.is_list(t)),
                 numbers=tuple((tuple(names), operator.attrgetter(*names), dtype)
                               for dtype, names in scalars.items() if names),
                 packs={name: (struct.Struct("<q") if pa.types.is_int64(t) else struct.Struct("<d")).pack_into
                        for name, t in columns if pa.types.is_int64(t) or pa.types.is_float64(t)})


_AP_FLAT = _flat(_AP_COLUMNS)
_MAX_LAYOUTS = 1024
_templates: dict[tuple, tuple[bytes, dict] | None] = {}  # layout → template (a memo of this process)


def _encode_ap(kind: str, segments: tuple[ApSegment, ...]) -> bytes:
    """The Arrow IPC payload of AP ``segments`` (an ``ap_segment`` or ``ap_batch``)."""
    return _encode_templated(kind, _AP_FLAT, segments, _ap_columns)


def _encode_templated(kind: str, flat: _Flat, rows: tuple, columns_of) -> bytes:
    """The Arrow IPC payload of ``rows`` (objects whose fields are the columns ``flat`` reads),
    from the template of its layout; ``columns_of(rows)``: its Arrow columns (a new layout's)."""
    texts = [[getattr(r, name).encode() for r in rows] for name in flat.texts]
    layout = (kind, *(len(b) for col in texts for b in col),
              *(get(r).size for _, get, _ in flat.lists for r in rows))
    hit = _templates.get(layout, False)
    if hit is False:
        if len(_templates) >= _MAX_LAYOUTS:
            _templates.clear()
        payload = _encode(kind, columns_of(rows))
        _templates[layout] = _template(payload, flat, rows)
        return payload
    if hit is None:  # (a layout whose buffers could not be placed: Arrow writes each payload)
        return _encode(kind, columns_of(rows))
    template, places = hit
    out = bytearray(template)
    if len(rows) == 1:  # (its scalars packed in place: no array per type)
        values = rows[0].__dict__
        for name, pack_into in flat.packs.items():
            pack_into(out, places[name], values[name])
        buffers = _buffers(flat, rows, texts, scalars=False)
    else:
        buffers = _buffers(flat, rows, texts)
    for name, raw in buffers.items():
        if raw:
            pos = places[name]
            out[pos : pos + len(raw)] = raw
    return bytes(out)


def _buffers(flat: _Flat, rows: tuple, texts: list[list[bytes]] | None = None, scalars: bool = True) -> dict:
    """The contents of each column's value buffer (the scalar ones only if ``scalars``), by name."""
    if texts is None:
        texts = [[getattr(r, name).encode() for r in rows] for name in flat.texts]
    out = dict(zip(flat.texts, map(b"".join, texts)))
    if scalars:
        for names, get, dtype in flat.numbers:
            table = np.array(list(map(get, rows)), dtype=dtype).reshape(len(rows), len(names))
            out.update(zip(names, map(np.ndarray.tobytes, table.T)))
    for name, get, dtype in flat.lists:
        out[name] = np.concatenate(list(map(get, rows))).astype(dtype, copy=False).tobytes()
    return out


def _template(payload: bytes, flat: _Flat, rows: tuple) -> tuple[bytes, dict] | None:
    """``(payload, positions)``: where each column's value buffer lies in ``payload``, by name, or
    None when a buffer is not found there holding what the rows hold (Arrow chose another placement)."""
    buf = pa.py_buffer(payload)
    batch = pa.ipc.open_stream(buf).read_next_batch()
    base = buf.address
    buffers = _buffers(flat, rows)
    places = {}
    for name in flat.names:
        col, raw = batch.column(name), buffers[name]
        t = col.type
        data = (col.values.buffers()[1] if pa.types.is_list(t) else
                col.buffers()[2] if pa.types.is_string(t) else col.buffers()[1])
        if not raw:
            places[name] = 0  # (nothing to write)
            continue
        pos = -1 if data is None else data.address - base
        if not 0 <= pos <= len(payload) - len(raw) or payload[pos : pos + len(raw)] != raw:
            return None
        places[name] = pos
    return payload, places


def _ap_segments(r: _Row) -> list[ApSegment]:
    """Every row of an ``ap_segment`` or ``ap_batch`` batch as a validated :class:`ApSegment`."""
    columns = [[_AP_OPTIONAL[name]] * r.n_rows if name in _AP_OPTIONAL and name not in r.names else
               getattr(r, method)(name, value_type) if value_type is not None else getattr(r, method)(name)
               for name, (method, value_type) in zip(_AP_NAMES, _AP_READERS)]
    return [ApSegment(*row) for row in zip(*columns)]  # (the columns are in the fields' order)


def _build_ap_segment(r: _Row) -> ApSegment:
    return _ap_segments(r)[0]


def decode_ap_segment(payload: bytes) -> ApSegment:
    """Decode and validate an :class:`ApSegment` payload; raises :class:`DecodeError`."""
    return _decoding(ApSegment.KIND, payload, _build_ap_segment)


@dataclass(frozen=True, eq=False)
class ApBatch(_Message):
    """Several AP segments of one vehicle on one route in one payload (edge -> cloud).

    The edge publishes what one raw chunk releases (every tile and axle the pass has completed)
    as one message: framing, decoding and the transport are paid once per batch instead of once
    per segment. On the wire it is an ``ap_segment`` batch with one row per segment, under the key
    of its first segment (``ap/<route>/<tile>/<vehicle>``), so shards by route or vehicle see
    every batch they own. Receivers read AP keys with :func:`decode_ap`, which takes both kinds;
    each segment keeps its own identity, so fusion is the same as for single segments.
    """

    KIND: ClassVar[str] = "ap_batch"

    segments: tuple[ApSegment, ...]

    def __post_init__(self) -> None:
        segments = self.segments
        if not isinstance(segments, tuple | list) or not all(isinstance(s, ApSegment) for s in segments):
            _fail("bad_type", "segments must be a sequence of ApSegment")
        if not 1 <= len(segments) <= MAX_BATCH_SEGMENTS:
            _fail("bad_shape", f"a batch holds 1 to {MAX_BATCH_SEGMENTS} segments, got {len(segments)}")
        first = segments[0]
        if any(s.vehicle_id != first.vehicle_id or s.route_id != first.route_id for s in segments):
            _fail("bad_value", "a batch holds the segments of one vehicle on one route")
        object.__setattr__(self, "segments", tuple(segments))

    @property
    def vehicle_id(self) -> str:
        return self.segments[0].vehicle_id

    @property
    def route_id(self) -> str:
        return self.segments[0].route_id

    @property
    def tile(self) -> int:
        """The first segment's tile: the batch's key is that segment's key."""
        return self.segments[0].tile

    def encode(self) -> bytes:
        """Arrow IPC payload of this batch."""
        return _encode_ap(self.KIND, self.segments)


def _build_ap_batch(r: _Row) -> ApBatch:
    return ApBatch(tuple(_ap_segments(r)))


def decode_ap_batch(payload: bytes) -> ApBatch:
    """Decode and validate an :class:`ApBatch` payload; raises :class:`DecodeError`."""
    return _decoding(ApBatch.KIND, payload, _build_ap_batch)


# -- payloads read as columns: the fast path of decode_ap and decode_pass_done ----------------
#
# The general path builds a pyarrow array per column and a Python object per value, and runs every
# field's validator per segment: most of the cloud's cost per segment. A payload laid out as ours
# (the schema message, one uncompressed record batch of exactly a kind's columns and types, the
# end marker) is read here straight from its buffers: every number and offset in one struct read at
# positions taken from the batch's metadata (the same bytes for every payload of a layout: parsed,
# and checked by Arrow, once), list values as numpy views, and each rule of ApSegment checked once
# per column for the whole batch. Arrow's full validation of what the metadata cannot vouch for
# (offsets, UTF-8, validity bits) is done on the values. Anything else, and any payload failing
# any check, goes to the general path, which decides: accepted payloads give the same messages
# either way, and refused ones the same reason.


def _reads(columns, optional) -> tuple[dict, frozenset]:
    """How a kind's columns are read: name → (Arrow type, layout, struct code of scalars or numpy
    type of list values), and the names a payload must have."""
    table = {name: (t, "list", np.dtype(_NUMPY_OF[t.value_type]).newbyteorder("<")) if pa.types.is_list(t) else
             (t, "text", None) if pa.types.is_string(t) else
             (t, "nullmap", None) if t.equals(_PARAMS_TYPE) else  # (read when null: else the general path)
             (t, "scalar", "q" if t == pa.int64() else "d")
             for name, t in columns}
    return table, frozenset(table) - frozenset(optional)


# Kinds read by the column reader: their columns' types and layouts, and required names.
_AP_KINDS = (ApSegment.KIND, ApBatch.KIND)
_COLUMN_READS = {kind: _reads(_AP_COLUMNS, _AP_OPTIONAL) for kind in _AP_KINDS}


@functools.lru_cache(maxsize=64)
def _columns_schema(message: bytes) -> tuple[str, int, tuple[str, ...], dict] | None:
    """``(kind, max_rows, column names in order, how each is read)`` of a schema message whose
    columns are exactly those of a kind the column reader reads (the optional ones may be absent),
    of exactly their types, else None."""
    plan = _schema_plan(message)
    if plan is None:
        return None
    schema, kind, version, max_rows = plan
    if kind not in _COLUMN_READS or version != SCHEMA_VERSION:
        return None
    table, required = _COLUMN_READS[kind]
    names = tuple(schema.names)
    if not required <= set(names) <= table.keys():
        return None
    if any(not f.type.equals(table[f.name][0]) for f in schema):
        return None
    return kind, max_rows, names, table


def _fb_structs(buf, table: int, field: int) -> list[tuple[int, int]]:
    """A flatbuffer table's vector of two-int64 structs (Arrow's FieldNode and Buffer)."""
    pos = _fb_field(buf, table, field)
    if pos is None:
        return []
    vec = pos + _fb(_U32, buf, pos)
    count = _fb(_U32, buf, vec)
    if count > 4096:
        raise ValueError("implausible vector length")
    return [(_fb(_I64, buf, vec + 4 + 16 * i), _fb(_I64, buf, vec + 12 + 16 * i)) for i in range(count)]


@dataclass(frozen=True)
class _ColumnPlan:
    """Where a batch's values lie in its message body (see :func:`_column_plan`)."""

    kind: str
    rows: int
    body_length: int
    start: int  # body offset of the first number ``numbers`` reads
    numbers: struct.Struct  # every scalar and every offset of the body, in one read
    # name → (layout, first index in what ``numbers`` reads, data buffer offset, data length)
    columns: dict
    types: dict  # name → numpy type of a list column's values
    # (getter of the scalars the kind's rules bound from what ``numbers`` reads, lowest, highest)
    ranges: tuple[Any, tuple, tuple] | None


@functools.lru_cache(maxsize=256)
def _column_plan(schema_message: bytes, meta: bytes) -> _ColumnPlan | None:
    """Where a batch's columns lie in its message body, with every check the metadata alone
    decides done (uncompressed, no nulls but all-null maps, every buffer inside the body, aligned,
    large enough for its length, none overlapping); None if any fails (cached: the metadata repeats
    across payloads of a layout)."""
    schema = _columns_schema(schema_message)
    if schema is None:
        return None
    kind, max_rows, names, table = schema
    try:
        root = _fb(_U32, meta, 0)
        version, header_type = _fb_field(meta, root, 0), _fb_field(meta, root, 1)
        header, body = _fb_field(meta, root, 2), _fb_field(meta, root, 3)
        if version is None or _fb(_U16, meta, version) != _METADATA_V5:
            return None
        if header_type is None or _fb(_U8, meta, header_type) != _RECORD_BATCH or header is None or body is None:
            return None
        batch = header + _fb(_U32, meta, header)
        if _fb_field(meta, batch, 3) is not None or _fb_field(meta, batch, 4) is not None:
            return None  # compressed, or variadic buffers: not ours
        length = _fb_field(meta, batch, 0)
        rows = _fb(_I64, meta, length) if length is not None else 0
        nodes, buffers = _fb_structs(meta, batch, 1), _fb_structs(meta, batch, 2)
        body_length = _fb(_I64, meta, body)
    except ValueError:
        return None
    if not 1 <= rows <= max_rows or not 0 <= body_length <= MAX_PAYLOAD_BYTES:
        return None
    try:  # Arrow's own checks of the metadata (its flatbuffer verifier, buffers against lengths): once per layout
        framing = _U32.pack(_CONTINUATION) + _U32.pack(len(meta))
        message = pa.ipc.read_message(pa.py_buffer(framing + meta + bytes(body_length)))
        pa.ipc.read_record_batch(message, _schema_plan(schema_message)[0]).validate()
    except Exception:  # noqa: BLE001 -- not ours: the general path reports it
        return None
    if any(off < 0 or size < 0 or off % 8 or off + size > body_length for off, size in buffers):
        return None
    if sum(size for _, size in buffers) > MAX_DECODED_BYTES:
        return None
    reads = []  # (body offset, struct code, count, column)
    columns = {}
    node, buf = iter(nodes), iter(buffers)
    try:
        for name in names:
            _, layout, code = table[name]
            if next(node) != (rows, rows if layout == "nullmap" else 0):
                return None
            validity = next(buf)  # no data to read when there are no nulls
            off, size = next(buf)
            if layout == "scalar":
                if size < rows * 8:
                    return None
                reads.append((off, code, rows, name))
                columns[name] = (layout, None, 0, 0)
                continue
            if size < (rows + 1) * 4:  # int32 offsets
                return None
            reads.append((off, "i", rows + 1, name))
            if layout == "text":
                data, data_size = next(buf)
                columns[name] = (layout, None, data, data_size)
                continue
            if layout == "nullmap":  # entries (struct: validity), keys (text), values (scalars): none
                entries = [next(node) for _ in range(3)]
                _, _, (key_offsets, size), _, _, _ = [next(buf) for _ in range(6)]
                if any(length for length, _ in entries):
                    return None
                columns[name] = (layout, None, 0, 0)
                n_bytes = (rows + 7) // 8
                if validity[1] < n_bytes:
                    return None
                reads.append((validity[0], "B", n_bytes, name + "/valid"))  # every bit 0: null
                columns[name + "/valid"] = ("nulls", None, 0, rows)
                if size:  # the keys' one offset: 0, as Arrow writes it (so its validation passes)
                    reads.append((key_offsets, "i", 1, name + "/keys"))
                    columns[name + "/keys"] = ("zero", None, 0, 0)
                continue
            n_values, nulls = next(node)
            next(buf)
            data, data_size = next(buf)
            if nulls or data_size < n_values * code.itemsize:
                return None
            columns[name] = (layout, None, data, n_values)
    except StopIteration:
        return None
    if next(node, None) is not None or next(buf, None) is not None:
        return None
    reads.sort()
    fmt, at, index = ["<"], reads[0][0], 0
    for off, code, count, name in reads:
        if off < at:
            return None  # overlapping buffers: read by the general path
        fmt.append(f"{off - at}x{count}{code}")
        at = off + count * struct.calcsize(code)
        layout, _, data, limit = columns[name]
        columns[name] = (layout, index, data, limit)
        index += count
    types = {name: table[name][2] for name, c in columns.items() if c[0] == "list"}
    ranges = _RANGES_OF.get(kind)
    if ranges is not None:  # each bounded scalar's place and bounds (closed: an open end is the next float)
        ranges = [(columns[name][1] + r, lo if not lo_open else math.nextafter(lo, math.inf), hi)
                  for name, (lo, hi, lo_open) in ranges.items() for r in range(rows)]
        at, lo, hi = zip(*ranges)
        get = operator.itemgetter(*at)
        ranges = (get if len(at) > 1 else lambda numbers: (get(numbers),), lo, hi)
    return _ColumnPlan(kind, rows, body_length, reads[0][0], struct.Struct("".join(fmt)), columns, types, ranges)


def _columns_of(payload) -> tuple[str, int, dict] | None:
    """``(kind, rows, {name: per-row values})`` of a payload laid out as ours, of a kind the column
    reader reads, from its buffers (texts as str, scalars as Python numbers, lists as ``(flat
    values, offsets)``, null maps as None), if Arrow's full validation would accept them; else None."""
    n = len(payload)
    schema_end = _schema_end(payload)
    if schema_end is None:
        return None
    meta_length = _fb(_U32, payload, schema_end + 4)
    start = schema_end + 8
    if meta_length > _MAX_CACHED_BATCH_META_BYTES or start + meta_length > n:
        return None
    view = memoryview(payload)
    plan = _column_plan(view[:schema_end].tobytes(), view[start : start + meta_length].tobytes())
    if plan is None:
        return None
    rows = plan.rows
    body = start + meta_length
    end = body + plan.body_length
    if end + len(_END_OF_STREAM) != n or view[end:] != _END_OF_STREAM:
        return None
    numbers = plan.numbers.unpack_from(payload, body + plan.start)
    if plan.ranges is not None:
        at, lo, hi = plan.ranges
        # (Python's comparisons: exact between ints and floats, as the constructor's; NaN fails both)
        a = at(numbers)
        if not (all(map(operator.le, lo, a)) and all(map(operator.le, a, hi))):
            return None
    out = {}
    for name, (layout, i, data, limit) in plan.columns.items():
        if layout == "scalar":
            out[name] = numbers[i : i + rows]
            continue
        if layout == "zero":
            if numbers[i]:
                return None
            continue
        if layout == "nulls":  # a validity bitmap saying every row is null
            bits = numbers[i : i + (rows + 7) // 8]
            if any(bits[:-1]) or bits[-1] & ((1 << (rows % 8 or 8)) - 1):
                return None
            continue
        bounds = numbers[i : i + rows + 1]
        if layout == "nullmap":
            if any(bounds):  # (no entries: every offset 0)
                return None
            out[name] = [None] * rows
            continue
        # Arrow's full validation: offsets non-decreasing and within the data
        if bounds[0] < 0 or bounds[-1] > limit or any(a > b for a, b in zip(bounds, bounds[1:])):
            return None
        if layout == "text":
            raw = view[body + data : body + data + limit]
            try:
                out[name] = [str(raw[a:b], "utf-8") for a, b in zip(bounds, bounds[1:])]
            except UnicodeDecodeError:
                return None
        else:
            out[name] = (np.frombuffer(payload, plan.types[name], limit, body + data), bounds)
    return plan.kind, rows, out


# ApSegment's rules on its numeric fields, per column: (low, high, low open).
_AP_RANGES = {"tile": (0, MAX_INT32, False), "axle": (1, 16, False), "start_index": (-MAX_INDEX, MAX_INDEX, False),
              "spacing_m": (0.0, 100.0, True), "scale_m": (0.0, 1.0, True),
              "offset_m": (-MAX_ABS_AP_M, MAX_ABS_AP_M, False), "sigma_ref_m": (0.0, MAX_ABS_AP_M, True),
              "calib_version": (0, MAX_INT32, False), "speed_mps": (0.0, MAX_SPEED_MPS, False),
              "t_first": (-sys.float_info.max, sys.float_info.max, False),  # (finite)
              "t_last": (-sys.float_info.max, sys.float_info.max, False),
              "seq": (0, MAX_INT32, False), "n_segments_in_pass": (-1, MAX_INT32, False),
              "flags": (0, MAX_INT32, False)}
_RANGES_OF = {kind: _AP_RANGES for kind in _AP_KINDS}  # the scalar ranges _columns_of checks, per kind


def _ap_segments_of(rows: int, c: dict) -> list[ApSegment] | None:
    """The segments of the columns, if every one passes :class:`ApSegment`'s rules (checked per
    column; the ranges of its numbers by :func:`_columns_of`), built without running them again;
    else None (the general path says which failed)."""
    if any(b < a for a, b in zip(c["t_first"], c["t_last"])):
        return None
    if any(0 <= n <= s for s, n in zip(c["seq"], c["n_segments_in_pass"])):
        return None
    vehicles, routes = set(c["vehicle_id"]), set(c["route_id"])
    if len(vehicles) != 1 or len(routes) != 1 or not (is_valid_id(*vehicles) and is_valid_id(*routes)):
        return None  # (a batch holds the segments of one vehicle on one route)
    for p in set(c["pass_id"]):
        if not p or len(p) > MAX_TEXT or not p.isprintable():
            return None
    (values, vb), (sigmas, sb) = c["values_q"], c["sigma_q"]
    sizes = [b - a for a, b in zip(vb, vb[1:])]
    if min(sizes) < 1 or max(sizes) > MAX_SAMPLES or sizes != [b - a for a, b in zip(sb, sb[1:])]:
        return None
    if sigmas[sb[0] : sb[-1]].max() > 0:
        return None
    models = c.get("error_model")
    try:
        if models is None:
            models = [ERROR_MODEL_NONE] * rows
        else:
            flat, mb = models
            models = [ERROR_MODEL_NONE if a == b else _error_model(flat[a:b]) for a, b in zip(mb, mb[1:])]
    except InvalidMessage:
        return None
    columns = dict(c, values_q=_frozen_copies(values, vb), sigma_q=_frozen_copies(sigmas, sb), error_model=models)
    out = []
    new, cls, names = object.__new__, ApSegment, _AP_NAMES
    for row in zip(*(columns[name] for name in names)):
        seg = new(cls)
        object.__setattr__(seg, "__dict__", dict(zip(names, row)))
        out.append(seg)
    return out


def _frozen_copies(flat: np.ndarray, bounds) -> list[np.ndarray]:
    """Each row's values, read-only: views of one copy of the rows' values (a segment holds its
    own arrays, not the payload; one copy per column of a batch, not one per row)."""
    first, last = bounds[0], bounds[-1]
    copy = flat[first:last].copy()
    copy.flags.writeable = False
    if len(bounds) == 2:
        return [copy]
    return [copy[a - first : b - first] for a, b in zip(bounds, bounds[1:])]


def decode_ap(payload: bytes) -> list[ApSegment]:
    """The segments of an AP payload of either kind (``ap_segment`` or ``ap_batch``); what a
    subscriber to AP keys calls. Raises :class:`DecodeError` (``wrong_kind`` for other kinds)."""
    payload = _payload_bytes(payload)
    try:
        columns = _columns_of(payload)
        segments = _ap_segments_of(*columns[1:]) if columns is not None and columns[0] in _AP_KINDS else None
    except ValueError:  # an offset out of range (_fb): the general path reports it
        segments = None
    if segments is not None:
        return segments
    kind, version, batch = _read_batch(payload)
    if kind == ApSegment.KIND:
        return [_build(kind, version, batch, _build_ap_segment)]
    if kind == ApBatch.KIND:
        return list(_build(kind, version, batch, _build_ap_batch).segments)
    raise DecodeError("wrong_kind", f"expected {ApSegment.KIND} or {ApBatch.KIND}, got {kind}")


#: s: the sample interval of a pass-done that does not say (the logger's original 500 Hz).
LEGACY_SAMPLE_INTERVAL_S = 0.002


@dataclass(frozen=True, eq=False)
class PassDone(_Message):
    """The edge's end-of-pass marker: segments ``0 .. n_segments-1`` of the pass were
    published under ``calib_version``, so the cloud can acknowledge completion."""

    KIND: ClassVar[str] = "pass_done"

    vehicle_id: str
    pass_id: str
    route_id: str
    calib_version: int
    n_segments: int
    vehicle_model: str = ""  # optional (added in v1.1 of the message): lets the cloud calibrate
    # Optional (v1.2): the vehicle parameters the edge computed the pass with (e.g. a log's nominal
    # ones under ``--calibration nominal``), so the cloud's models of the pass use the same vehicle.
    params: Mapping[str, float] | None = None
    # Optional (v1.3): the sample interval (s) the edge inverted the pass at (1 / the log's
    # sample_rate_hz); the cloud's models of the pass undo or re-run that inverse at this step.
    # A message without it was made at the logger's original 500 Hz.
    sample_interval_s: float = LEGACY_SAMPLE_INTERVAL_S

    def __post_init__(self) -> None:
        _id("vehicle_id", self.vehicle_id)
        _text("pass_id", self.pass_id, MAX_TEXT)
        if not self.pass_id:
            _fail("bad_value", "pass_id is empty")
        _id("route_id", self.route_id)
        object.__setattr__(self, "calib_version", _int("calib_version", self.calib_version, 0, MAX_INT32))
        object.__setattr__(self, "n_segments", _int("n_segments", self.n_segments, 0, MAX_INT32))
        object.__setattr__(self, "sample_interval_s",
                           _float("sample_interval_s", self.sample_interval_s, 0.0, 1.0, lo_open=True))
        if self.vehicle_model and _text("vehicle_model", self.vehicle_model) not in VEHICLE_MODELS:
            _fail("bad_value", f"vehicle_model {self.vehicle_model!r} not in {sorted(VEHICLE_MODELS)}")
        if self.params is not None:
            object.__setattr__(self, "params", _params("params", self.params))

    def encode(self) -> bytes:
        """Arrow IPC payload of this marker."""
        return _encode(
            self.KIND,
            {
                "vehicle_id": _scalar(self.vehicle_id, pa.string()),
                "pass_id": _scalar(self.pass_id, pa.string()),
                "route_id": _scalar(self.route_id, pa.string()),
                "calib_version": _scalar(self.calib_version, pa.int64()),
                "n_segments": _scalar(self.n_segments, pa.int64()),
                "vehicle_model": _scalar(self.vehicle_model, pa.string()),
                "params": _params_column(self.params),
                "sample_interval_s": _scalar(self.sample_interval_s, pa.float64()),
            },
        )


def _build_pass_done(r: _Row) -> PassDone:
    return PassDone(
        vehicle_id=r.text("vehicle_id"),
        pass_id=r.text("pass_id"),
        route_id=r.text("route_id"),
        calib_version=r.integer("calib_version"),
        n_segments=r.integer("n_segments"),
        vehicle_model=r.text("vehicle_model") if "vehicle_model" in r.names else "",
        params=r.params("params", optional=True) if "params" in r.names else None,
        sample_interval_s=r.real("sample_interval_s") if "sample_interval_s" in r.names else LEGACY_SAMPLE_INTERVAL_S,
    )



_PASS_DONE_COLUMNS = (("vehicle_id", pa.string()), ("pass_id", pa.string()), ("route_id", pa.string()),
                      ("calib_version", pa.int64()), ("n_segments", pa.int64()), ("vehicle_model", pa.string()),
                      ("params", _PARAMS_TYPE), ("sample_interval_s", pa.float64()))
_COLUMN_READS[PassDone.KIND] = _reads(_PASS_DONE_COLUMNS, ("vehicle_model", "params", "sample_interval_s"))


def decode_pass_done(payload: bytes) -> PassDone:
    """Decode and validate a :class:`PassDone` payload; raises :class:`DecodeError`."""
    payload = _payload_bytes(payload)
    try:  # the column reader (as decode_ap's), for one laid out as ours without parameters
        columns = _columns_of(payload)
        if columns is not None and columns[0] == PassDone.KIND:
            return PassDone(**{name: values[0] for name, values in columns[2].items()})
    except (ValueError, InvalidMessage):  # (a ValueError: an offset out of range) the general path says why
        pass
    return _decoding(PassDone.KIND, payload, _build_pass_done)


@dataclass(frozen=True, eq=False)
class Calibration(_Message):
    """Vehicle parameters published by the cloud (``version`` grows with each update).

    ``params`` maps a name (a model parameter such as ``K`` or a ratio such as
    ``K/M``) to its value in SI units; ``source`` says how it was obtained
    (e.g. ``fleet``, ``nominal``).
    """

    KIND: ClassVar[str] = "calibration"

    vehicle_id: str
    version: int
    vehicle_model: str
    params: Mapping[str, float]
    source: str

    def __post_init__(self) -> None:
        _id("vehicle_id", self.vehicle_id)
        object.__setattr__(self, "version", _int("version", self.version, 0, MAX_INT32))
        if _text("vehicle_model", self.vehicle_model) not in VEHICLE_MODELS:
            _fail("bad_value", f"vehicle_model {self.vehicle_model!r} not in {sorted(VEHICLE_MODELS)}")
        object.__setattr__(self, "params", _params("params", self.params))
        _text("source", self.source)

    def encode(self) -> bytes:
        """Arrow IPC payload of this calibration."""
        return _encode(
            self.KIND,
            {
                "vehicle_id": _scalar(self.vehicle_id, pa.string()),
                "version": _scalar(self.version, pa.int64()),
                "vehicle_model": _scalar(self.vehicle_model, pa.string()),
                "params": _params_column(self.params),
                "source": _scalar(self.source, pa.string()),
            },
        )


def _build_calibration(r: _Row) -> Calibration:
    return Calibration(
        vehicle_id=r.text("vehicle_id"),
        version=r.integer("version"),
        vehicle_model=r.text("vehicle_model"),
        params=r.params("params", optional=False),
        source=r.text("source"),
    )



def decode_calibration(payload: bytes) -> Calibration:
    """Decode and validate a :class:`Calibration` payload; raises :class:`DecodeError`."""
    return _decoding(Calibration.KIND, payload, _build_calibration)


@dataclass(frozen=True, eq=False)
class Alarm(_Message):
    """A bridge alarm: ``kind`` (e.g. ``crack``), finite element ``element`` (-1: the
    whole bridge) at ``x_m`` from the first support, ``severity`` (>= 0, e.g. relative
    stiffness loss) with ``probability`` in [0, 1]; ``time_utc`` is ISO 8601 with zone."""

    KIND: ClassVar[str] = "alarm"

    bridge_id: str
    time_utc: str
    kind: str
    element: int
    x_m: float
    severity: float
    probability: float
    message: str = ""

    def __post_init__(self) -> None:
        _id("bridge_id", self.bridge_id)
        _utc("time_utc", self.time_utc)
        _id("kind", self.kind)
        object.__setattr__(self, "element", _int("element", self.element, -1, MAX_INT32))
        object.__setattr__(self, "x_m", _float("x_m", self.x_m))
        object.__setattr__(self, "severity", _float("severity", self.severity, 0.0))
        object.__setattr__(self, "probability", _float("probability", self.probability, 0.0, 1.0))
        _text("message", self.message, MAX_MESSAGE_TEXT, printable=False)

    def encode(self) -> bytes:
        """Arrow IPC payload of this alarm."""
        return _encode(
            self.KIND,
            {
                "bridge_id": _scalar(self.bridge_id, pa.string()),
                "time_utc": _scalar(self.time_utc, pa.string()),
                "kind": _scalar(self.kind, pa.string()),
                "element": _scalar(self.element, pa.int64()),
                "x_m": _scalar(self.x_m, pa.float64()),
                "severity": _scalar(self.severity, pa.float64()),
                "probability": _scalar(self.probability, pa.float64()),
                "message": _scalar(self.message, pa.string()),
            },
        )


def _build_alarm(r: _Row) -> Alarm:
    return Alarm(
        bridge_id=r.text("bridge_id"),
        time_utc=r.text("time_utc"),
        kind=r.text("kind"),
        element=r.integer("element"),
        x_m=r.real("x_m"),
        severity=r.real("severity"),
        probability=r.real("probability"),
        message=r.text("message"),
    )



def decode_alarm(payload: bytes) -> Alarm:
    """Decode and validate an :class:`Alarm` payload; raises :class:`DecodeError`."""
    return _decoding(Alarm.KIND, payload, _build_alarm)


@dataclass(frozen=True, eq=False)
class Ack(_Message):
    """The cloud's acknowledgement of a pass (cloud -> run orchestrator): it accepted
    ``n_segments_accepted`` segments of ``pass_id`` under ``calib_version``."""

    KIND: ClassVar[str] = "ack"

    pass_id: str
    vehicle_id: str
    n_segments_accepted: int
    calib_version: int = 0

    def __post_init__(self) -> None:
        _text("pass_id", self.pass_id, MAX_TEXT)
        if not self.pass_id:
            _fail("bad_value", "pass_id is empty")
        _id("vehicle_id", self.vehicle_id)
        object.__setattr__(
            self, "n_segments_accepted", _int("n_segments_accepted", self.n_segments_accepted, 0, MAX_INT32)
        )
        object.__setattr__(self, "calib_version", _int("calib_version", self.calib_version, 0, MAX_INT32))

    def encode(self) -> bytes:
        """Arrow IPC payload of this acknowledgement (the cloud writes one per pass: from the
        template of its layout)."""
        return _encode_templated(self.KIND, _ACK_FLAT, (self,), _ack_columns)


_ACK_COLUMNS = (("pass_id", pa.string()), ("vehicle_id", pa.string()), ("n_segments_accepted", pa.int64()),
                ("calib_version", pa.int64()))
_ACK_FLAT = _flat(_ACK_COLUMNS)


def _ack_columns(acks: tuple[Ack]) -> dict[str, pa.Array]:
    (ack,) = acks
    return {name: _scalar(getattr(ack, name), t) for name, t in _ACK_COLUMNS}


def _build_ack(r: _Row) -> Ack:
    return Ack(
        pass_id=r.text("pass_id"),
        vehicle_id=r.text("vehicle_id"),
        n_segments_accepted=r.integer("n_segments_accepted"),
        calib_version=r.integer("calib_version"),
    )



def decode_ack(payload: bytes) -> Ack:
    """Decode and validate an :class:`Ack` payload; raises :class:`DecodeError`."""
    return _decoding(Ack.KIND, payload, _build_ack)


Message = SensorChunk | ApSegment | ApBatch | PassDone | Calibration | Alarm | Ack

_BUILDERS = {
    SensorChunk.KIND: _build_sensor_chunk,
    ApSegment.KIND: _build_ap_segment,
    ApBatch.KIND: _build_ap_batch,
    PassDone.KIND: _build_pass_done,
    Calibration.KIND: _build_calibration,
    Alarm.KIND: _build_alarm,
    Ack.KIND: _build_ack,
}
KINDS = tuple(_BUILDERS)
_MAX_ROWS = {ApBatch.KIND: MAX_BATCH_SEGMENTS}  # rows a payload may hold, per kind (others: one)


def decode(payload: bytes) -> Message:
    """Decode a payload of any kind (e.g. a journal replay); raises :class:`DecodeError`."""
    kind, version, batch = _read_batch(payload)
    build = _BUILDERS.get(kind)
    if build is None:
        raise DecodeError("wrong_kind", f"unknown kind {kind!r}")
    return _build(kind, version, batch, build)
