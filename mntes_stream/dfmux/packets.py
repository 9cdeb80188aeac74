"""IceBoard data packets, byte for byte as spt3g's ``DfMuxCollector`` reads them (synthetic senders, tests).

Layout (spt3g 1.0.2 ``dfmux/src/DfMuxCollector.cxx``, ``struct DfmuxPacket``,
packed, little-endian): magic ``0x666d7578``, version u16 (2, 3, 4), serial
u16 (0 in V2: the collector names a V2 board by its IP address),
num_modules u8, channels_per_module u8 (the block 0-7 in V4), fir_stage u8,
module u8 (0-indexed), seq u32; then ``nchan`` pairs of int32 I, Q times 256
(the collector divides by 256; V4 always 128 channels a block); then the
IRIG-B time stamp, eight int32: year % 100, day of year (1-based), hour,
minute, second, sub-second in 100 MHz ticks, and two unused words. The
collector adds one second to every time stamp (the IceBoards report one
second late), so a packet for time ``t`` carries ``t - 1 s``.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from mntes_stream.core.timing import DFMUX_TICKS_PER_SAMPLE, G3_TICK_NS

__all__ = ["MARKER_NS", "marker_packets", "MAGIC", "PORT", "GROUP", "SAMPLE_NS", "VERSIONS", "header_dtype", "irig_words", "packet_nchan",
           "synthetic_counts", "PacketBuilder"]

MAGIC = 0x666D7578
PORT = 9876
GROUP = "239.192.0.2"
SAMPLE_NS = DFMUX_TICKS_PER_SAMPLE * G3_TICK_NS  # 6,553,600 ns: 20 MHz / 2**17
VERSIONS = (2, 3, 4)
V4_CHANNELS = 128
V4_BLOCKS = 8
_COUNTS_SPAN = 2**20
# 2099-01-01: far beyond any real sample. The bridge sends packets stamped from here on at its stop: they
# push the samples spt3g's builder still holds (incomplete ones wait for 1000 later samples) out before them.
MARKER_NS = 4_070_908_800 * 1_000_000_000  # synthetic counts stay well inside the 24 bits FLAC keeps


def header_dtype(nchan: int) -> np.dtype:
    """One packet as a numpy record (packed), ``nchan`` channels."""
    return np.dtype([("magic", "<u4"), ("version", "<u2"), ("serial", "<u2"), ("num_modules", "u1"),
                     ("channels_per_module", "u1"), ("fir_stage", "u1"), ("module", "u1"), ("seq", "<u4"),
                     ("s", "<i4", (2 * nchan,)), ("ts", "<i4", (8,))])


def packet_nchan(version: int, channels: int) -> int:
    """Channels in one packet: 128 in V4 (a block), ``channels`` otherwise."""
    return V4_CHANNELS if version == 4 else channels


def irig_words(t_ns: np.ndarray) -> np.ndarray:
    """The IRIG-B words (int32, shape (n, 8)) a board sends for samples at ``t_ns`` (collector's +1 s undone)."""
    t = np.asarray(t_ns, dtype=np.int64) - 1_000_000_000
    sec = t // 1_000_000_000
    out = np.zeros((t.size, 8), dtype=np.int32)
    for k, s in enumerate(sec):  # one calendar lookup per sample: cheap at 152.6 Hz
        d = _dt.datetime.fromtimestamp(int(s), _dt.UTC)
        out[k, :5] = (d.year % 100, d.timetuple().tm_yday, d.hour, d.minute, d.second)
    out[:, 5] = (t - sec * 1_000_000_000) // G3_TICK_NS
    return out


def synthetic_counts(board: int, module: int, channels: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Counts I, Q (int64, shape (n_ch, n)) of the synthetic sender for sample numbers ``k``: a function of
    (board, module, channel, k) only, so a receiver can check every value it got."""
    return _values(board, module, np.asarray(channels, dtype=np.int64)[:, None],
                   np.asarray(k, dtype=np.int64)[None, :])


def _values(board, module, ch, k):
    base = np.asarray(board * 7919 + module * 131 + ch * 17 + k * 3, dtype=np.int64)
    return (base % _COUNTS_SPAN) - _COUNTS_SPAN // 2, ((base * 5 + 1) % _COUNTS_SPAN) - _COUNTS_SPAN // 2


class PacketBuilder:
    """All the packets of one board for one sample, as bytes.

    Parameters
    ----------
    version : {2, 3, 4}
    serial : int
        Board serial (not sent in V2).
    modules : int
        Modules on the board (V2/V3: packets for modules 0..modules-1; V4: ``num_modules``, 8 blocks each).
    channels : int
        Channels per module (V2/V3, at most 255); V4 modules have 8 x 128.
    """

    def __init__(self, version: int, serial: int, modules: int, channels: int = 64):
        if version not in VERSIONS:
            raise ValueError(f"packet version {version} not one of {VERSIONS}")
        self.version, self.serial, self.modules = int(version), int(serial), int(modules)
        self.nchan = packet_nchan(version, channels)
        self.channels = V4_CHANNELS * V4_BLOCKS if version == 4 else int(channels)
        n_pk = self.modules * (V4_BLOCKS if version == 4 else 1)
        rec = np.zeros(n_pk, dtype=header_dtype(self.nchan))
        rec["magic"] = MAGIC
        rec["version"] = version
        rec["serial"] = 0 if version == 2 else serial
        if version == 4:
            rec["num_modules"] = modules
            rec["module"] = np.repeat(np.arange(modules), V4_BLOCKS)
            rec["channels_per_module"] = np.tile(np.arange(V4_BLOCKS), modules)  # the block
        else:
            rec["num_modules"] = modules
            rec["channels_per_module"] = self.nchan
            rec["module"] = np.arange(modules)
        self._rec = rec
        # (module, channel) of every I/Q pair of every packet: counts for all packets in one call
        blk = np.arange(n_pk) % V4_BLOCKS if version == 4 else np.zeros(n_pk, dtype=np.int64)
        self._mod = rec["module"].astype(np.int64)
        self._ch = (blk[:, None] * self.nchan + np.arange(self.nchan)[None, :]) if version == 4 else \
            np.broadcast_to(np.arange(self.nchan), (n_pk, self.nchan))

    @property
    def n_packets(self) -> int:
        return int(self._rec.size)

    def packets(self, k: int, t_ns: int, seq: int | None = None, counts=None) -> list[bytes]:
        """The board's packets for sample number ``k`` at ``t_ns`` (``seq``: the packets' sequence number,
        ``k`` by default). ``counts``: ``(I, Q)`` of shape (modules, channels), within the 24-bit word;
        None: :func:`synthetic_counts`."""
        rec = self._rec
        rec["seq"] = k if seq is None else seq
        rec["ts"] = irig_words(np.array([t_ns]))[0]
        if counts is None:
            i, q = _values(self.serial, self._mod[:, None], self._ch, k)
        else:  # a V4 module's channels are its blocks' in order: one packet a block
            i, q = (np.asarray(c).reshape(self.n_packets, self.nchan) for c in counts)
        rec["s"][:, 0::2] = i * 256  # the collector divides by 256
        rec["s"][:, 1::2] = q * 256
        raw = rec.tobytes()
        size = rec.dtype.itemsize
        return [raw[j * size:(j + 1) * size] for j in range(rec.size)]


def marker_packets(serial: int, n: int) -> list[bytes]:
    """``n`` one-channel V3 packets of board ``serial`` at ``MARKER_NS`` + k samples (the bridge's stop)."""
    rec = np.zeros(n, dtype=header_dtype(1))
    rec["magic"] = MAGIC
    rec["version"] = 3
    rec["serial"] = serial
    rec["num_modules"] = 1
    rec["channels_per_module"] = 1
    rec["seq"] = np.arange(n)
    rec["ts"] = irig_words(MARKER_NS + np.arange(n, dtype=np.int64) * SAMPLE_NS)
    raw = rec.tobytes()
    size = rec.dtype.itemsize
    return [raw[j * size:(j + 1) * size] for j in range(n)]
