"""An AP segment's wire payload written into a template of its layout: what spilling costs.

``ApSegment.encode`` builds Arrow arrays and a record batch per call (~100 µs), and a cloud at its
resident bound spills (encodes) a segment for each one it takes in. Arrow's IPC bytes of a
one-segment batch depend on the segment's values only through the buffers' contents: the
metadata (buffer offsets and lengths, padding) is fixed by the layout (points, text lengths,
error-model size). So the first segment of a layout is encoded by Arrow and the positions of its
value buffers in the payload are read back; every later segment of that layout is its bytes
written at those positions into a copy of the template, byte for byte what Arrow writes.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pyarrow as pa

from shared.schema import ApSegment

_ARRAYS = ("values_q", "sigma_q", "error_model")
_TEXTS = ("vehicle_id", "pass_id", "route_id")
_FIELDS = tuple(f.name for f in dataclasses.fields(ApSegment))


def _layout(seg: ApSegment) -> tuple:
    return (seg.values_q.size, seg.error_model.size,
            *(len(getattr(seg, name).encode()) for name in _TEXTS))


def _template(layout: tuple, payload: bytes) -> tuple[bytes, tuple]:
    """The payload of a segment of ``layout`` and, per field, ``(position, struct or None)`` of its
    value bytes in it (``None``: raw bytes of a text or an array)."""
    buf = pa.py_buffer(payload)
    reader = pa.ipc.open_stream(buf)
    batch = reader.read_next_batch()
    base = buf.address
    places = []
    for name in _FIELDS:
        col = batch.column(name)
        t = col.type
        if pa.types.is_list(t):
            data = col.values.buffers()[1]
            places.append((name, None if data is None else data.address - base, None))
        elif pa.types.is_string(t):
            places.append((name, col.buffers()[2].address - base, None))
        else:
            fmt = struct.Struct("<q" if pa.types.is_int64(t) else "<d")
            places.append((name, col.buffers()[1].address - base, fmt))
    return payload, tuple(places)


_cache: dict[tuple, tuple[bytes, tuple]] = {}  # layout → template (a memo of this process, not configuration)
_MAX_LAYOUTS = 256


def encode_segment(seg: ApSegment) -> bytes:
    """``seg.encode()``, byte for byte, from the template of its layout."""
    wire = seg.__dict__.get("_wire")  # (it came alone in a payload: that one)
    if wire is not None:
        return wire
    layout = _layout(seg)
    hit = _cache.get(layout)
    if hit is None:
        if len(_cache) >= _MAX_LAYOUTS:
            _cache.clear()
        payload = seg.encode()
        hit = _cache[layout] = _template(layout, payload)
        return payload
    template, places = hit
    out = bytearray(template)
    for name, pos, fmt in places:
        value = getattr(seg, name)
        if fmt is not None:
            fmt.pack_into(out, pos, value)
        elif name in _ARRAYS:
            if value.size:
                raw = np.ascontiguousarray(value).tobytes()
                out[pos : pos + len(raw)] = raw
        else:
            raw = value.encode()
            out[pos : pos + len(raw)] = raw
    return bytes(out)
