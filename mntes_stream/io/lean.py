"""The converter's hot path on the wire: counts decoded against a cached header, power encoded from a template.

A stream repeats everything but its numbers: the same setup, board, module,
channel list, array dtypes and shapes, chunk after chunk. :class:`CountsDecoder`
checks a counts message in full (``CountsChunk.from_bytes``) the first time a
stream's header is seen, and afterwards only that the message still has that
header, plus the checks on the numbers that change (sequence number and times);
anything else (a new channel list, a different shape, a bad value) takes the
full path, which accepts or rejects it exactly as before. The arrays are views
of the payload (no copy) either way.

:class:`PowerEncoder` writes a power message as bytes identical to
``PowerChunk(...).to_bytes()``: the parts fixed for a stream (setup, board,
module, channel list, detector ids, table identity, array headers) are packed
once per stream; a message is those parts joined with the packed numbers and
the array bytes.
"""

from __future__ import annotations

import struct

import msgpack
import numpy as np

from mntes_stream.io.codec import current_versions as _versions
from mntes_stream.io.message_base import unpack_payload as _unpack
from mntes_stream.io.messages import CountsChunk, PowerChunk, detector_ids_for

__all__ = ["CountsDecoder", "PowerEncoder"]

_I64 = (1 << 63) - 1
# Headers kept: one per stream and channel list; a peer cycling channel lists only evicts, never grows it.
_MAX_HEADERS = 4096


def _pack(value) -> bytes:
    return msgpack.packb(value, use_bin_type=True)


_U8, _U16, _U32, _U64, _F64 = (struct.Struct(f).pack for f in (">B", ">H", ">I", ">Q", ">d"))


def _pack_number(value) -> bytes:
    """``_pack(value)`` for an int or float, written directly (msgpack's smallest form; a test compares bytes)."""
    if type(value) is int and value >= 0:
        if value < 0x80:
            return _U8(value)
        if value < 0x100:
            return b"\xcc" + _U8(value)
        if value < 0x10000:
            return b"\xcd" + _U16(value)
        if value < 0x100000000:
            return b"\xce" + _U32(value)
        if value < 0x10000000000000000:
            return b"\xcf" + _U64(value)
    elif type(value) is float:
        return b"\xcb" + _F64(value)
    return _pack(value)


def _raw(a: np.ndarray, dtype: str):
    """The bytes of ``a`` as ``dtype``, C order: the array's own buffer when it is laid out so (no copy)."""
    if a.dtype == dtype and a.flags.c_contiguous and a.size:
        return memoryview(a).cast("B")
    return a.astype(dtype, copy=False).tobytes()


class CountsDecoder:
    """Counts payloads to :class:`CountsChunk`, fully checked once per stream header (see the module docstring)."""

    def __init__(self):
        # key expression -> (keys, setup, board, module, channels map, channels array, rate, i/q shape, n bytes)
        self._headers: dict[str, tuple] = {}

    def decode(self, key: str, payload) -> CountsChunk:
        """The chunk of ``payload`` received on ``key``; raises :class:`SchemaError` as ``from_bytes`` does."""
        msg = _unpack(payload, CountsChunk.SCHEMA)
        h = self._headers.get(key)
        if h is not None:
            chunk = self._lean(msg, h)
            if chunk is not None:
                return chunk
        chunk = CountsChunk._from_map(msg)
        self._remember(key, msg, chunk)
        return chunk

    def _remember(self, key: str, msg: dict, chunk: CountsChunk) -> None:
        if chunk.t_ns is not None or chunk.detector_ids is not None:
            return  # explicit sample times or named rows: checked in full every time (no regular header to keep)
        if len(self._headers) >= _MAX_HEADERS:
            self._headers.clear()
        ci = msg["counts_i"]
        self._headers[key] = (frozenset(msg), chunk.setup, chunk.board, chunk.module, msg["channels"],
                              chunk.channels, chunk.sample_rate_hz, ci["shape"], len(ci["data"]))

    @staticmethod
    def _lean(msg: dict, h: tuple) -> CountsChunk | None:
        """The chunk when ``msg`` has header ``h`` and valid numbers; None: take the full path."""
        names, setup, board, module, ch_map, channels, rate, shape, nbytes = h
        if msg.keys() != names or msg["setup"] != setup or msg["board"] != board or msg["module"] != module:
            return None
        if msg["channels"] != ch_map or msg["sample_rate_hz"] != rate or type(msg["sample_rate_hz"]) is not float:
            return None
        ci, cq = msg["counts_i"], msg["counts_q"]
        for a in (ci, cq):
            if (type(a) is not dict or len(a) != 3 or a.get("dtype") != "<i4" or a.get("shape") != shape
                    or type(a.get("data")) is not bytes or len(a["data"]) != nbytes):
                return None
        seq, t0, t_pub = msg["seq"], msg["t0_ns"], msg["t_pub_ns"]
        if type(seq) is not int or type(t0) is not int or type(t_pub) is not int:
            return None
        if not (0 <= seq <= _I64 and 0 <= t_pub <= _I64 and 0 <= t0 and t0 + _span_ns(rate, shape[1]) <= _I64):
            return None
        dims = (shape[0], shape[1])
        return CountsChunk.unchecked(
            setup=setup, board=board, module=module, channels=channels, seq=seq, t0_ns=t0, sample_rate_hz=rate,
            counts_i=np.frombuffer(ci["data"], dtype="<i4").reshape(dims),
            counts_q=np.frombuffer(cq["data"], dtype="<i4").reshape(dims),
            t_pub_ns=t_pub, t_ns=None,
        )


_SPANS: dict[tuple[float, int], int] = {}


def _span_ns(rate: float, n: int) -> int:
    """Offset of a chunk's last sample (cached: a stream keeps its rate and length)."""
    span = _SPANS.get((rate, n))
    if span is None:
        from mntes_stream.core.align import last_sample_offset_ns

        if len(_SPANS) > 256:
            _SPANS.clear()
        span = _SPANS[(rate, n)] = last_sample_offset_ns(rate, n)
    return span


def _array_head(dtype: str, shape) -> bytes:
    """Packed ``{"dtype", "shape", "data": <n bytes>}`` up to the data bytes (as ``codec.encode_array`` orders it)."""
    n = int(np.prod(shape)) * np.dtype(dtype).itemsize
    full = _pack({"dtype": dtype, "shape": list(shape), "data": b"\0" * n})
    return full[:len(full) - n]


class PowerEncoder:
    """Power messages as bytes, equal to ``PowerChunk(...).to_bytes()`` (see the module docstring).

    Parameters
    ----------
    setup, table_identity, converter_kind : str
        Fixed for a converter.
    """

    def __init__(self, setup: str, table_identity: str, converter_kind: str):
        self._setup, self._identity, self._kind = setup, table_identity, converter_kind
        self._templates: dict[tuple, tuple] = {}

    def _template(self, board: int, module: int, channels: np.ndarray, shape: tuple, late: bool,
                  sigma: bool, names: tuple | None = None) -> tuple:
        key = (board, module, channels.tobytes(), shape, late, sigma, names)
        t = self._templates.get(key)
        if t is None:
            # Field order and encodings as PowerChunk._body() and codec.pack() make them (a test compares bytes).
            ids = names if names is not None else detector_ids_for(board, module, channels)
            n_fields = 16 + (1 if late else 0) + (1 if sigma else 0)  # the envelope (2) and every field but t_ns
            head = b"".join([
                _map_head(n_fields), _pack("schema"), _pack(PowerChunk.SCHEMA), _pack("version"),
                _pack(_versions()[PowerChunk.SCHEMA]), _pack("setup"), _pack(self._setup), _pack("board"),
                _pack(int(board)), _pack("module"), _pack(int(module)), _pack("channels"),
                _pack({"dtype": "<i4", "shape": [int(channels.size)], "data": channels.astype("<i4").tobytes()}),
                _pack("detector_ids"), _pack(list(ids)), _pack("seq"),
            ])
            t = (head, _pack("t0_ns"), _pack("sample_rate_hz"), _pack("p_opt_w") + _array_head("<f8", shape),
                 _pack("flags") + _array_head("<u2", shape),
                 _pack("table_identity") + _pack(self._identity) + _pack("converter_kind") + _pack(self._kind)
                 + _pack("source_t_pub_ns"), _pack("t_pub_ns"),
                 (_pack("late") + _pack(True) if late else b"")
                 + (_pack("sigma_p_w") + _array_head("<f4", shape) if sigma else b""))
            if len(self._templates) >= _MAX_HEADERS:
                self._templates.clear()
            self._templates[key] = t
        return t

    def encode(self, chunk: CountsChunk, p_opt_w: np.ndarray, flags: np.ndarray, t_pub_ns: int,
               late: bool = False, sigma_p_w: np.ndarray | None = None) -> bytes:
        """The power message of ``chunk`` with ``p_opt_w`` (float64), ``flags`` (uint16), ``sigma_p_w`` (float32).

        p_opt_w, flags, sigma_p_w : ndarray, shape (n_ch, n_samp), any layout (a view of a larger block is copied
        once); ``sigma_p_w`` None: not in the message.
        """
        if chunk.t_ns is not None:  # explicit times: the general encoder
            return PowerChunk.unchecked(
                setup=self._setup, board=chunk.board, module=chunk.module, channels=chunk.channels,
                detector_ids=chunk.row_ids(), seq=chunk.seq,
                t0_ns=chunk.t0_ns, sample_rate_hz=chunk.sample_rate_hz, p_opt_w=p_opt_w, flags=flags,
                table_identity=self._identity, converter_kind=self._kind, source_t_pub_ns=chunk.t_pub_ns,
                t_pub_ns=t_pub_ns, t_ns=chunk.t_ns, late=True if late else None,
                sigma_p_w=sigma_p_w).to_bytes()
        head, k_t0, k_rate, k_p, k_f, mid, k_pub, tail = self._template(
            chunk.board, chunk.module, chunk.channels, p_opt_w.shape, bool(late), sigma_p_w is not None,
            chunk.detector_ids)
        # One copy of the arrays: joined from their own buffers where they are laid out as the message wants.
        return b"".join((head, _pack_number(chunk.seq), k_t0, _pack_number(chunk.t0_ns), k_rate,
                         _pack_number(chunk.sample_rate_hz), k_p, _raw(p_opt_w, "<f8"), k_f, _raw(flags, "<u2"), mid,
                         _pack_number(chunk.t_pub_ns), k_pub, _pack_number(int(t_pub_ns)), tail,
                         b"" if sigma_p_w is None else _raw(sigma_p_w, "<f4")))


def _map_head(n: int) -> bytes:
    """msgpack map header of ``n`` entries (as msgpack writes it for a dict of that size)."""
    full = _pack({str(i): None for i in range(n)})
    return full[:1] if n < 16 else full[:3]

