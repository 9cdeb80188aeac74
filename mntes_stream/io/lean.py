"""The converter's hot path on the wire: counts decoded against a cached header, power encoded from a template.

A stream repeats everything but its numbers: the same setup, board, module,
channel list, array dtypes and shapes, chunk after chunk. :class:`CountsDecoder`
checks a counts message in full (``CountsChunk.from_bytes``) the first time a
stream's header is seen, and afterwards only that the message still has that
header, plus the checks on the numbers that change (sequence number and times);
anything else (a new channel list, a different shape, a bad value) takes the
full path, which accepts or rejects it exactly as before. The header is kept
as the message's bytes around its numbers and arrays (:func:`_template`): a
later message of the stream is read by comparing those bytes and reading the
numbers and the arrays' offsets between them, without unpacking it
(:func:`_from_template`); one that differs anywhere else is unpacked and
checked as before. The arrays are views of the payload (an aligned copy where
the view would not be aligned).

:class:`PowerEncoder` writes a power message as bytes identical to
``PowerChunk(...).to_bytes()``: the parts fixed for a stream (setup, board,
module, channel list, detector ids, table identity, array headers) are packed
once per stream; a message is those parts joined with the packed numbers and
the arrays' own buffers (one copy).
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
        h = self._headers.get(key)
        if h is not None and h[9] is not None and type(payload) is bytes:
            chunk = _from_template(payload, h)
            if chunk is not None:
                return chunk
        msg = _unpack(payload, CountsChunk.SCHEMA)
        if h is not None:
            chunk = self._lean(msg, h)
            if chunk is not None:
                return chunk
        chunk = CountsChunk._from_map(msg)
        self._remember(key, msg, chunk, payload)
        return chunk

    def _remember(self, key: str, msg: dict, chunk: CountsChunk, payload) -> None:
        if chunk.t_ns is not None or chunk.detector_ids is not None:
            return  # explicit sample times or named rows: checked in full every time (no regular header to keep)
        if len(self._headers) >= _MAX_HEADERS:
            self._headers.clear()
        ci = msg["counts_i"]
        self._headers[key] = (frozenset(msg), chunk.setup, chunk.board, chunk.module, msg["channels"],
                              chunk.channels, chunk.sample_rate_hz, ci["shape"], len(ci["data"]),
                              _template(msg, bytes(payload)))

    @staticmethod
    def _lean(msg: dict, h: tuple) -> CountsChunk | None:
        """The chunk when ``msg`` has header ``h`` and valid numbers; None: take the full path."""
        names, setup, board, module, ch_map, channels, rate, shape, nbytes, _ = h
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


_NUMBERS = ("seq", "t0_ns", "t_pub_ns")
_ARRAYS = ("counts_i", "counts_q")
_SLOTS = {"seq": 0, "t0_ns": 1, "t_pub_ns": 2, "counts_i": 3, "counts_q": 4}
_UINT = {0xcc: 2, 0xcd: 3, 0xce: 5, 0xcf: 9}  # msgpack uint type byte: its length with the value


def _template(msg: dict, payload: bytes) -> tuple | None:
    """Where a stream's counts message varies: the bytes between its numbers and its arrays' data.

    ``msg``: ``payload`` unpacked and accepted in full. Returns ``(steps, last)``: in message order, per number
    and array, ``(fixed bytes before it, their length, its slot in _SLOTS, the data's length or 0 for a
    number)``; ``last`` the fixed bytes after them. None: no template (a rate not a float, or a layout this
    does not read).
    """
    if type(msg.get("sample_rate_hz")) is not float:
        return None
    up = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(payload), 1 << 20))
    up.feed(payload)
    cuts = []  # (start, end, what)
    try:
        for _ in range(up.read_map_header()):
            name = up.unpack()
            if name in _NUMBERS:
                start = up.tell()
                up.skip()
                cuts.append((start, up.tell(), name))
            elif name in _ARRAYS:
                for _ in range(up.read_map_header()):
                    inner = up.unpack()
                    up.skip()
                    if inner == "data":
                        n = len(msg[name]["data"])
                        cuts.append((up.tell() - n, up.tell(), (name, n)))
            else:
                up.skip()
        if up.tell() != len(payload) or len(cuts) != len(_NUMBERS) + len(_ARRAYS):
            return None
    except Exception:  # noqa: BLE001 - accepted in full already; no template then, never an error
        return None
    cuts.sort()
    steps, at = [], 0
    for start, end, what in cuts:  # (fixed bytes before it, their length, its slot, an array's data length)
        slot = _SLOTS[what] if type(what) is str else _SLOTS[what[0]]
        steps.append((payload[at:start], start - at, slot, 0 if type(what) is str else what[1]))
        at = end
    return tuple(steps), payload[at:]


def _from_template(payload: bytes, h: tuple) -> CountsChunk | None:
    """The chunk when ``payload`` is the template's fixed bytes with valid numbers and arrays of their length
    between them (the arrays: views of ``payload``); None: take the general path, which decides."""
    steps, last = h[9]
    at, got, size = 0, [0, 0, 0, 0, 0], len(payload)
    for piece, n, slot, nbytes in steps:
        if not payload.startswith(piece, at):
            return None
        at += n
        if nbytes:
            got[slot], at = at, at + nbytes
            continue
        if at >= size:
            return None
        b = payload[at]
        if b < 0x80:
            got[slot], at = b, at + 1
        else:
            w = _UINT.get(b)
            if w is None or at + w > size:
                return None
            got[slot], at = int.from_bytes(payload[at + 1:at + w], "big"), at + w
    if at + len(last) != size or not payload.startswith(last, at):
        return None
    seq, t0, t_pub, at_i, at_q = got
    shape, rate = h[7], h[6]
    if not (seq <= _I64 and t_pub <= _I64 and t0 + _span_ns(rate, shape[1]) <= _I64):
        return None
    dims, count = (shape[0], shape[1]), shape[0] * shape[1]
    return CountsChunk.unchecked(
        setup=h[1], board=h[2], module=h[3], channels=h[5], seq=seq, t0_ns=t0, sample_rate_hz=rate,
        counts_i=_view(payload, at_i, count, dims), counts_q=_view(payload, at_q, count, dims),
        t_pub_ns=t_pub, t_ns=None,
    )


def _view(payload: bytes, offset: int, count: int, dims: tuple) -> np.ndarray:
    """int32 counts at ``offset`` of ``payload``: a read-only view, or an aligned copy where the view would not
    be aligned (compiled kernels are built for aligned arrays)."""
    a = np.frombuffer(payload, dtype="<i4", count=count, offset=offset).reshape(dims)
    if a.flags.aligned:
        return a
    a = a.copy()
    a.setflags(write=False)
    return a


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
        self._last: dict[tuple, tuple] = {}  # (board, module) -> (channels, detector_ids, layout, template) last used

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

    def chunk(self, chunk: CountsChunk, p_opt_w: np.ndarray, flags: np.ndarray, t_pub_ns: int,
              late: bool = False, sigma_p_w: np.ndarray | None = None) -> PowerChunk:
        """The power chunk :meth:`encode` writes, as an object (from checked inputs: not checked again)."""
        return PowerChunk.unchecked(
            setup=self._setup, board=chunk.board, module=chunk.module, channels=chunk.channels,
            detector_ids=chunk.row_ids(), seq=chunk.seq,
            t0_ns=chunk.t0_ns, sample_rate_hz=chunk.sample_rate_hz, p_opt_w=p_opt_w, flags=flags,
            table_identity=self._identity, converter_kind=self._kind, source_t_pub_ns=chunk.t_pub_ns,
            t_pub_ns=t_pub_ns, t_ns=chunk.t_ns, late=True if late else None, sigma_p_w=sigma_p_w)

    def encode(self, chunk: CountsChunk, p_opt_w: np.ndarray, flags: np.ndarray, t_pub_ns: int,
               late: bool = False, sigma_p_w: np.ndarray | None = None) -> bytes:
        """The power message of ``chunk`` with ``p_opt_w`` (float64), ``flags`` (uint16), ``sigma_p_w`` (float32).

        p_opt_w, flags, sigma_p_w : ndarray, shape (n_ch, n_samp), any layout (a view of a larger block is copied
        once); ``sigma_p_w`` None: not in the message.
        """
        if chunk.t_ns is not None:  # explicit times: the general encoder
            return self.chunk(chunk, p_opt_w, flags, t_pub_ns, late, sigma_p_w).to_bytes()
        stream, shape, late, sigma = (chunk.board, chunk.module), p_opt_w.shape, bool(late), sigma_p_w is not None
        last = self._last.get(stream)
        # A stream's chunks share one channels array while its header holds (CountsDecoder): no bytes to compare.
        if (last is not None and last[0] is chunk.channels and last[1] is chunk.detector_ids
                and last[2] == (shape, late, sigma)):
            t = last[3]
        else:
            t = self._template(chunk.board, chunk.module, chunk.channels, shape, late, sigma, chunk.detector_ids)
            if len(self._last) >= _MAX_HEADERS:
                self._last.clear()
            self._last[stream] = (chunk.channels, chunk.detector_ids, (shape, late, sigma), t)
        head, k_t0, k_rate, k_p, k_f, mid, k_pub, tail = t
        # One copy of the arrays: joined from their own buffers where they are laid out as the message wants.
        return b"".join((head, _pack_number(chunk.seq), k_t0, _pack_number(chunk.t0_ns), k_rate,
                         _pack_number(chunk.sample_rate_hz), k_p, _raw(p_opt_w, "<f8"), k_f, _raw(flags, "<u2"), mid,
                         _pack_number(chunk.t_pub_ns), k_pub, _pack_number(int(t_pub_ns)), tail,
                         b"" if sigma_p_w is None else _raw(sigma_p_w, "<f4")))


def _map_head(n: int) -> bytes:
    """msgpack map header of ``n`` entries (as msgpack writes it for a dict of that size)."""
    full = _pack({str(i): None for i in range(n)})
    return full[:1] if n < 16 else full[:3]

