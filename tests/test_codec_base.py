"""The shared msgpack envelope and array codec."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mntes_stream.errors import SchemaError
from mntes_stream.io.codec import decode_array, encode_array, unpack


@given(
    hnp.arrays(
        dtype=st.sampled_from([np.int32, np.int64, np.float64, np.uint16, np.complex128, np.dtype(">f8"), np.dtype(">i4")]),
        shape=hnp.array_shapes(min_dims=0, max_dims=3, max_side=5),
    )
)
def test_array_round_trip(a):
    d = encode_array(a)
    assert d["dtype"].startswith(("<", "|"))
    b = decode_array(msgpack.unpackb(msgpack.packb(d, use_bin_type=True)))
    assert b.shape == a.shape and b.dtype == a.dtype.newbyteorder("<")
    np.testing.assert_array_equal(b, a)


@pytest.mark.parametrize(
    "bad",
    [
        {"dtype": ">f8", "shape": [1], "data": b"\0" * 8},
        {"dtype": "<f8", "shape": [2], "data": b"\0" * 8},
        {"dtype": "<f8", "shape": [-1], "data": b""},
        {"dtype": "object", "shape": [1], "data": b"\0"},
        {"dtype": "<f8", "shape": [1], "data": "text"},
        {"dtype": "<f8", "shape": [1]},
        {"dtype": "<f8", "shape": [2**32, 2**32], "data": b""},  # int64 product wraps to 0
        {"dtype": "<i4", "shape": [2**31, 2**31, 4], "data": b""},
        {"dtype": "<f8", "shape": [True], "data": b"\0" * 8},
        [1, 2, 3],
    ],
)
def test_bad_arrays_raise_schema_error(bad):
    with pytest.raises(SchemaError):
        decode_array(bad)


def test_envelope_errors():
    with pytest.raises(SchemaError, match="malformed"):
        unpack(b"\xc1\xff\x00")
    with pytest.raises(SchemaError, match="not a map"):
        unpack(msgpack.packb([1, 2]))
    with pytest.raises(SchemaError, match="schema"):
        unpack(msgpack.packb({"x": 1}))
    with pytest.raises(SchemaError, match="unknown"):
        unpack(msgpack.packb({"schema": "nope", "version": 1}))
