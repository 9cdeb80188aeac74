"""The converter's lean wire path (io/lean.py) against the full message classes it stands in for."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from mntes_stream.errors import SchemaError
from mntes_stream.io.lean import CountsDecoder, PowerEncoder
from mntes_stream.io.messages import CountsChunk, PowerChunk, detector_ids_for

KEY = "mntes/lab/counts/3/7"


def _chunk(seq=0, t0=1_700_000_000_000_000_000, n_ch=5, n=7, rate=152.587890625, channels=None, t_ns=None):
    rng = np.random.default_rng(seq)
    ch = np.arange(n_ch, dtype=np.int32) * 3 if channels is None else channels
    ci = rng.integers(-2**31, 2**31 - 1, size=(ch.size, n), dtype=np.int32)
    cq = rng.integers(-2**31, 2**31 - 1, size=(ch.size, n), dtype=np.int32)
    if t_ns is not None:
        return CountsChunk("lab", 3, 7, ch, seq, None, None, ci, cq, t0 + 5, t_ns=t_ns)
    return CountsChunk("lab", 3, 7, ch, seq, t0 + seq * 10**8, rate, ci, cq, t0 + seq * 10**8 + 5)


def _same(a: CountsChunk, b: CountsChunk) -> None:
    for f in ("setup", "board", "module", "seq", "t0_ns", "sample_rate_hz", "t_pub_ns"):
        assert getattr(a, f) == getattr(b, f) and type(getattr(a, f)) is type(getattr(b, f)), f
    for f in ("channels", "counts_i", "counts_q"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f
    assert (a.t_ns is None) == (b.t_ns is None)


def test_decoded_chunks_equal_the_full_decoder_on_a_changing_stream():
    dec = CountsDecoder()
    chunks = [_chunk(s) for s in range(4)] + [_chunk(4, channels=np.array([1, 2], np.int32))] + [_chunk(5, n=3)]
    chunks.append(_chunk(6, t_ns=np.arange(7, dtype=np.int64) * 1000))
    for c in chunks * 2:
        payload = c.to_bytes()
        _same(dec.decode(KEY, payload), CountsChunk.from_bytes(payload))


@pytest.mark.parametrize("change, reason", [
    (lambda m: m.update(seq=-1), "invalid"),
    (lambda m: m.update(seq=True), "invalid"),
    (lambda m: m.update(t0_ns=2**63 - 10), "invalid"),
    (lambda m: m.update(sample_rate_hz=0.0), "invalid"),
    (lambda m: m["counts_i"].update(shape=[5, 6]), "invalid"),
    (lambda m: m["counts_q"].update(dtype="<f8"), "invalid"),
    (lambda m: m.update(extra=1), "invalid"),
    (lambda m: m.update(version=99), "wrong_version"),
    (lambda m: m.update(schema="mntes.nope"), "unknown_schema"),
    (lambda m: m.update(channels={"dtype": "<i4", "shape": [5], "data": np.zeros(5, "<i4").tobytes()}), "invalid"),
])
def test_a_known_stream_s_bad_chunk_is_rejected_as_the_full_decoder_rejects_it(change, reason):
    dec = CountsDecoder()
    good = _chunk(0).to_bytes()
    dec.decode(KEY, good)  # the stream's header is now known: the next chunk takes the lean path if it can
    msg = msgpack.unpackb(_chunk(1).to_bytes())
    change(msg)
    bad = msgpack.packb(msg, use_bin_type=True)
    with pytest.raises(SchemaError) as full:
        CountsChunk.from_bytes(bad)
    with pytest.raises(SchemaError) as lean:
        dec.decode(KEY, bad)
    assert lean.value.reason == full.value.reason == reason
    _same(dec.decode(KEY, good), CountsChunk.from_bytes(good))  # and the stream goes on


def test_a_known_stream_s_chunks_are_read_from_their_bytes_as_the_full_decoder_reads_them():
    """Numbers of every msgpack width, and messages cut or grown, against ``from_bytes``."""
    dec = CountsDecoder()
    dec.decode(KEY, _chunk(0).to_bytes())  # the stream's header (and its bytes) are now known
    t0 = 1_700_000_000_000_000_000
    for seq in (1, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**40):
        c = _chunk(seq % 1000)
        c = CountsChunk("lab", 3, 7, c.channels, seq, t0 + seq, c.sample_rate_hz, c.counts_i, c.counts_q,
                        t0 + seq + 5)
        payload = c.to_bytes()
        got = dec.decode(KEY, payload)
        _same(got, CountsChunk.from_bytes(payload))
        for a in (got.counts_i, got.counts_q):  # read-only and aligned, as the kernels take them
            assert a.flags.aligned and not a.flags.writeable
    good = _chunk(3).to_bytes()
    for bad in (good[:-1], good + b"\x00", good[:-10] + b"\xa1x" + good[-8:]):  # cut, grown, a bad key
        with pytest.raises(SchemaError) as full:
            CountsChunk.from_bytes(bad)
        with pytest.raises(SchemaError) as lean:
            dec.decode(KEY, bad)
        assert lean.value.reason == full.value.reason
    # t_pub_ns packed as int64 (0xd3) of the same value: not the template's form, read in full and accepted.
    signed = good[:-9] + b"\xd3" + good[-8:]
    _same(dec.decode(KEY, signed), CountsChunk.from_bytes(signed))
    _same(dec.decode(KEY, good), CountsChunk.from_bytes(good))


@pytest.mark.parametrize("sigma", [False, True])
@pytest.mark.parametrize("late", [False, True])
@pytest.mark.parametrize("shape", [(5, 7), (1, 1), (128, 20), (20, 4000)])
def test_power_messages_are_byte_identical_to_the_message_class(late, shape, sigma):
    enc = PowerEncoder("lab", "f" * 64, "table")
    rng = np.random.default_rng(shape[0])
    for seq in range(3):
        c = _chunk(seq, n_ch=shape[0], n=shape[1])
        block = rng.normal(size=(shape[0] + 2, shape[1] * 2)) * 1e-12
        p = block[1:-1, shape[1]:]  # a strided view of a larger block, as the converter's runs give
        f = rng.integers(0, 2**16, size=shape).astype("<u2")
        s = (np.abs(block[:-2, :shape[1]]) * 1e-3).astype(np.float32) if sigma else None
        want = PowerChunk("lab", 3, 7, c.channels, detector_ids_for(3, 7, c.channels), c.seq, c.t0_ns,
                          c.sample_rate_hz, p, f, "f" * 64, "table", c.t_pub_ns, 42 + seq,
                          late=True if late else None, sigma_p_w=s).to_bytes()
        assert enc.encode(c, p, f, 42 + seq, late, s) == want
    t = _chunk(0, n=4, t_ns=np.arange(4, dtype=np.int64))
    p, f = np.zeros((5, 4)), np.zeros((5, 4), "<u2")
    got = PowerChunk.from_bytes(enc.encode(t, p, f, 9, late))
    assert np.array_equal(got.t_ns, t.t_ns) and got.t0_ns is None and got.late is (True if late else None)
