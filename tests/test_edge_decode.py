"""The edge's tick decoder (:class:`edge.bank_decode.ChunkDecoder`) on strings it has not seen: a new
pass's first chunk of a known layout is read on the fast path once the contract's own checks accept
its strings, and strings the contract refuses are refused for the contract's reason."""

from __future__ import annotations

import numpy as np

from edge.bank_decode import ChunkDecoder, same_chunk
from shared.schema import DecodeError, SensorChunk, decode_sensor_chunk


def _chunk(vehicle: str, pass_id: str, seq: int = 0) -> bytes:
    rng = np.random.default_rng(seq)
    n = 50
    return SensorChunk(vehicle, pass_id, "route-1", "quarter_car", seq, 0.1 * seq, 500.0,
                       10.0 + np.arange(n) * 0.04, np.full(n, 20.0), {"body_acc": rng.normal(size=n).astype(np.float32)},
                       nominal_params={"ms": 300.0, "ks": 2.0e4}).encode()


def test_new_strings_of_a_known_layout_are_checked_by_the_contract():
    decoder = ChunkDecoder()
    first = [_chunk("veh-0001", "veh-0001-p0"), _chunk("veh-0002", "veh-0002-p0")]
    decoder.decode(first)  # the layout's plan, from the contract's decoder
    general = decoder.general
    fresh = [_chunk("veh-0003", "veh-0003-p0", 1), _chunk("veh-0004", "veh-0004-p0", 2)]
    out = decoder.decode(fresh)
    assert decoder.general == general  # strings never seen, of a known layout: no full decode …
    for payload, chunk in zip(fresh, out):
        assert same_chunk(chunk, decode_sensor_chunk(payload))  # … and the contract's values
    # the same layout (same lengths) with strings the contract refuses: its decoder's reason
    bad = [first[0].replace(b"veh-0001", b"veh 0001"), first[0].replace(b"quarter_car", b"quarter_cab")]
    for payload, got in zip(bad, decoder.decode(bad)):
        assert isinstance(got, DecodeError)
        try:
            decode_sensor_chunk(payload)
        except DecodeError as e:
            assert got.reason == e.reason == "bad_value"
        else:
            raise AssertionError("the contract accepted a payload the test means to be refused")
