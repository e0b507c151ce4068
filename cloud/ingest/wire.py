"""A message's wire payload written into a template of its layout: what spilling and acks cost.

``encode()`` builds Arrow arrays and a record batch per call, many times the cost of the bytes it
writes, and a cloud at its resident bound spills (encodes) a segment for each one it takes in and
publishes an ack per pass. Arrow's IPC bytes of a one-row message whose columns are its fields
(texts, int64 and float64 scalars, ``list`` arrays: :class:`ApSegment`, :class:`Ack`) depend on
the values only through the buffers' contents: the metadata (buffer offsets and lengths, padding)
is fixed by the layout (text lengths in bytes, array sizes). So the first message of a layout is
encoded by Arrow and the positions of its value buffers in the payload are read back; every later
message of that layout is its bytes written at those positions into a copy of the template, byte
for byte what Arrow writes.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pyarrow as pa

_INT64, _FLOAT64 = struct.Struct("<q"), struct.Struct("<d")
_MAX_LAYOUTS = 512
_templates: dict[tuple, tuple[bytes, tuple]] = {}  # layout → template (a memo of this process, not configuration)
_fields: dict[type, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {}  # type → its fields by kind


def _kinds(msg) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """A message type's field names: every one, its texts, its arrays (the rest are numbers)."""
    names = tuple(f.name for f in dataclasses.fields(msg))
    return (names, tuple(n for n in names if isinstance(getattr(msg, n), str)),
            tuple(n for n in names if isinstance(getattr(msg, n), np.ndarray)))


def _template(payload: bytes, names: tuple[str, ...]) -> tuple:
    """Per field ``(name, position, struct)`` of its value bytes in ``payload`` (struct None: the
    raw bytes of a text or an array)."""
    buf = pa.py_buffer(payload)
    batch = pa.ipc.open_stream(buf).read_next_batch()
    base = buf.address
    places = []
    for name in names:
        col = batch.column(name)
        t = col.type
        if pa.types.is_list(t):
            data = col.values.buffers()[1]
            places.append((name, None if data is None else data.address - base, None))
        elif pa.types.is_string(t):
            places.append((name, col.buffers()[2].address - base, None))
        elif pa.types.is_int64(t) or pa.types.is_float64(t):
            places.append((name, col.buffers()[1].address - base, _INT64 if pa.types.is_int64(t) else _FLOAT64))
        else:
            raise TypeError(f"{name}: {t} is not a field this encoder writes")
    numbers = tuple((pos, fmt.pack_into, name) for name, pos, fmt in places if fmt is not None)
    texts = {name: pos for name, pos, fmt in places if fmt is None}
    return numbers, texts


def encode_flat(msg) -> bytes:
    """``msg.encode()``, byte for byte, from the template of its layout (a message whose wire
    columns are its fields, of the types above)."""
    kinds = _fields.get(type(msg))
    if kinds is None:
        kinds = _fields[type(msg)] = _kinds(msg)
    names, text_names, array_names = kinds
    values = msg.__dict__
    texts = [values[n].encode() for n in text_names]
    arrays = [values[n] for n in array_names]
    layout = (type(msg), *map(len, texts), *(a.size for a in arrays))
    hit = _templates.get(layout)
    if hit is None:
        if len(_templates) >= _MAX_LAYOUTS:
            _templates.clear()
        payload = msg.encode()
        _templates[layout] = (payload, _template(payload, names))
        return payload
    template, (numbers, places) = hit
    out = bytearray(template)
    for pos, pack_into, name in numbers:
        pack_into(out, pos, values[name])
    for name, raw in zip(text_names, texts):
        pos = places[name]
        out[pos : pos + len(raw)] = raw
    for name, a in zip(array_names, arrays):
        if a.size:
            pos = places[name]
            out[pos : pos + a.nbytes] = memoryview(np.ascontiguousarray(a)).cast("B")
    return bytes(out)


encode_segment = encode_flat  # an AP segment's payload (what the segment store spills)
