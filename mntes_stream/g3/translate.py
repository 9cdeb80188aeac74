"""G3 frames -> the project's counts and housekeeping messages (one translator for file and live).

:class:`FrameTranslator` takes frames one at a time, in the order a G3Reader
gives them, and returns ``(key, payload)`` messages:

- Wiring: the bolometer <-> detector-id map (``mapping.Wiring``);
- Housekeeping: one ``bias`` reading per module (spt3g's RMS bias voltage of
  each wired channel, ``mntes/<setup>/hk/bias/<board>/<module>``);
- GcpSlow: ``t_bath`` (and the configured constant ``b_field``: spt3g has no
  field source);
- Timepoint: collected, one counts chunk per module every ``chunk_samples``;
- Scan with ``RawTimestreams_I``/``_Q``: one counts chunk per module.

Frames come from outside and are checked here, at the boundary: an entry of
the wrong class, an empty map, a blob spt3g cannot decode is a
:class:`~mntes_stream.g3.wire.BadFrame`; :meth:`FrameTranslator.accept`
counts it by reason (``counters.rejected``) and skips it. Scan and Timepoint
frames before the first Wiring frame are held (at most ``max_held`` frames,
the oldest counted ``before_wiring`` beyond that) and translated when it
arrives.

Counts chunks carry the G3 sample times (ticks x 10 ns) explicitly. A counts
value that is not a reading (NaN, or at/beyond the 24-bit range FLAC keeps)
travels as the int32 rail ``2**31 - 1`` (sign kept), which every converter
flags ``INVALID_INPUT``: never a silent number. Gaps in the Timepoint clock
(more than 1.5 sample periods) are counted in missing samples.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core.timing import DFMUX_TICKS_PER_SAMPLE, G3_TICK_NS
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.g3.counts import TimepointBuffer, scan_block
from mntes_stream.g3.mapping import (
    SQRT2,
    BathHistory,
    G3InputConfig,
    HkHistory,
    Wiring,
    bath_reading,
    g3_time_ns,
    hk_snapshot,
    invalid_counts,
)
from mntes_stream.g3.runtime import spt3g
from mntes_stream.g3.wire import BadFrame
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk

__all__ = ["FrameTranslator", "TranslatorCounters", "RAIL", "to_int32_counts", "check_frame"]

log = logging.getLogger("mntes_stream.g3")

RAIL = int(np.iinfo(np.int32).max)
_SAMPLE_NS = DFMUX_TICKS_PER_SAMPLE * G3_TICK_NS


def to_int32_counts(x: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
    """int32 counts (times ``scale`` if given); NaN or beyond 24 bits (before scaling) -> the rail
    (+-(2**31 - 1)), which converters flag."""
    bad = invalid_counts(x)
    y = x if scale is None else x * scale
    if not bad.any():
        return np.rint(y).astype(np.int32)
    out = np.where(bad, np.where(np.signbit(np.nan_to_num(x, nan=1.0)), -RAIL, RAIL), np.nan_to_num(y))
    return np.rint(out).astype(np.int32)


@dataclass
class TranslatorCounters:
    """What a translator has seen (cumulative)."""

    frames: int = 0
    timepoints: int = 0
    scans: int = 0
    samples: int = 0            # detector samples put into counts chunks
    invalid_samples: int = 0    # of which NaN or beyond 24 bits
    gap_samples: int = 0        # missing from the Timepoint clock
    housekeeping: int = 0
    gain_changes: int = 0       # housekeeping that changed amps per count
    bias_changes: int = 0       # housekeeping that changed a bias
    bath_readings: int = 0
    by_type: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)       # frames skipped, by reason (wire.FRAME_REASONS)
    stream_gaps: dict = field(default_factory=dict)    # "board/module" -> samples missing from its clock

    def reject(self, reason: str, n: int = 1) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + n


class FrameTranslator:
    """Frames in, messages out.

    Parameters
    ----------
    setup : str
    config : G3InputConfig, optional
    chunk_samples : int
        Timepoints per counts chunk (raw layout).
    boards : sequence of int
        Only these board serials (several bridges share an array); empty: all.
    gain_reference : mapping, optional
        ``|gain_a_per_count|`` (peak A per count) of the converter's parameters, by detector id or bolometer
        name. Given, the counts are published in units of that gain: ``round(counts * sqrt(2) a(t) / |g|)``
        with ``a(t)`` the housekeeping's amps per count in force, so a converter with fixed parameters follows
        a gain change from its sample on (rounding to whole reference counts aside). Without it the counts
        are the DfMux's own and a gain change is only reported.
    max_held : int
        Scan/Timepoint frames kept while no Wiring frame has come (then translated); beyond, the oldest are
        counted ``before_wiring`` and dropped.
    typed : bool
        Counts messages carry the ``CountsChunk`` itself, not its bytes (an in-process consumer: the G3
        module's ``ConverterPipeline(typed=True)``); housekeeping stays bytes.
    """

    LOG_EVERY_S = 10.0

    def __init__(self, setup: str = keys.DEFAULT_SETUP, config: G3InputConfig | None = None, chunk_samples: int = 16,
                 boards=(), gain_reference=None, max_held: int = 256, typed: bool = False):
        keys.counts_key(setup)
        if chunk_samples < 1:
            raise ConfigError("chunk_samples must be >= 1")
        self.setup = setup
        self.config = config or G3InputConfig()
        self.chunk_samples = int(chunk_samples)
        self.boards = tuple(int(b) for b in boards)
        self.gain_reference = dict(gain_reference) if gain_reference else None
        self._gref: np.ndarray | None = None
        self.wiring: Wiring | None = None
        self.hk = HkHistory(int(self.config.hk_retention_s * 1e9))
        self.bath = BathHistory(self.config)
        self.counters = TranslatorCounters()
        self._buffer: TimepointBuffer | None = None
        self._pending: list = []
        self._seq: dict[str, int] = {}
        self._t_last_ns = 0
        self._groups: list = []
        self.gain_changed_at: list[int] = []
        self._times: list[int] = []  # data time of each message made, in order (see timed)
        self.max_held = int(max_held)
        self.typed = bool(typed)
        self._held: deque = deque()
        self._logged: dict[str, float] = {}
        self.last_error: dict[str, str] = {}

    def set_gain_reference(self, gain_reference) -> None:
        """Publish counts in units of this reference gain from now on (see the class parameters)."""
        self.gain_reference = dict(gain_reference) if gain_reference else None
        self._gref = None
        if self.gain_reference is not None and self.wiring is not None:
            g, w = self.gain_reference, self.wiring
            self._gref = np.array([float(g.get(n, g.get(d, np.nan))) for n, d in zip(w.names, w.detector_ids)])

    # -- helpers ------------------------------------------------------------------------------
    def _next_seq(self, name: str) -> int:
        seq = self._seq.get(name, 0)
        self._seq[name] = seq + 1
        return seq

    def _hk_msg(self, sensor: str, t_ns: int, value, **where) -> tuple[str, bytes]:
        sk = keys.hk_sensor(sensor, where.get("board"), where.get("module"))
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        msg = HousekeepingChunk(setup=self.setup, sensor=sensor, seq=self._next_seq(sk), t_ns=t,
                                value=np.asarray(value, dtype=float),
                                unit={"t_bath": "K", "b_field": "T", "bias": "V"}[sensor], **where)
        self._times.append(int(t[-1]))
        return keys.hk_key(self.setup, sk), msg.to_bytes()

    def _set_wiring(self, wiring: Wiring) -> list:
        out = self.flush()
        self.wiring = wiring
        self.hk = HkHistory(int(self.config.hk_retention_s * 1e9))
        self._buffer = TimepointBuffer(wiring)
        self._groups = [(b, m, rows) for (b, m), rows in wiring.modules().items()]
        self.set_gain_reference(self.gain_reference)
        for hkmap in self._pending:
            out += self._housekeeping(hkmap)
        self._pending = []
        held, self._held = list(self._held), deque()
        for frame in held:
            out += self.accept(frame)
        return out

    def _housekeeping(self, hkmap) -> list:
        snap = hk_snapshot(hkmap, self.wiring, self._t_last_ns, self.hk.latest())
        self.counters.housekeeping += 1
        before = self.hk.before(snap.t_ns)
        gain, bias = self.hk.add(snap)
        self.counters.bias_changes += bias
        if gain and self._gref is not None:
            self.counters.gain_changes += 1  # applied: the counts follow the reference gain
            log.info("DfMux housekeeping at %d ns changes amps per count: counts rescaled from here on", snap.t_ns)
        elif gain:
            # The messages carry counts and bias, not the gain: a converter keeps the gain of its parameters.
            self.counters.gain_changes += 1
            self.gain_changed_at.append(snap.t_ns)
            log.warning("DfMux housekeeping at %d ns changes amps per count: live conversion keeps the gain of "
                        "the converter's parameters (convert the G3 run offline, or restart the converter with "
                        "parameters of the new gain)", snap.t_ns)
        out = []
        for b, m, rows in self._groups:
            t, v = [snap.t_ns], [snap.v_bias_rms_v[rows]]
            if bias and before is not None and not np.array_equal(before.v_bias_rms_v[rows], v[0], equal_nan=True):
                # A step: the old value 1 ns before it too, so interpolating readings reproduces the step.
                t, v = [snap.t_ns - 1, snap.t_ns], [before.v_bias_rms_v[rows], v[0]]
            out.append(self._hk_msg("bias", t, np.stack(v), board=int(b), module=int(m),
                                    channels=self.wiring.channel[rows].astype(np.int32)))
        return out

    def _bath(self, t_ns: int, t_bath_k: float) -> list:
        self.bath.add(t_ns, t_bath_k)
        self.counters.bath_readings += 1
        out = [self._hk_msg("t_bath", t_ns, [t_bath_k])]
        out.append(self._hk_msg("b_field", t_ns, [self.config.b_field_t]))
        return out

    def _counts(self, blk, t_pub_ns: int) -> list:
        out = []
        if blk is None or not blk.n_samples:
            return out
        t = blk.t_ns if not self._t_last_ns else np.concatenate([[self._t_last_ns], blk.t_ns])
        step = np.diff(t)
        late = step > 1.5 * _SAMPLE_NS
        n_gap = 0
        if late.any():  # samples the DfMux clock says were taken but never reached us
            n_gap = int(np.sum(np.rint(step[late] / _SAMPLE_NS) - 1))
            self.counters.gap_samples += n_gap
        have = np.full(len(self.wiring), -1, dtype=np.int64)
        have[blk.rows] = np.arange(blk.rows.size)
        # The whole block at once: validity and int32 (the rail where not a reading).
        n_bad = int(np.count_nonzero(invalid_counts(blk.counts_i) | invalid_counts(blk.counts_q)))
        self.counters.invalid_samples += n_bad
        self.counters.samples += blk.counts_i.size
        scale = None
        if self._gref is not None and len(self.hk):
            amps, _ = self.hk.at(blk.t_ns, blk.rows)
            with np.errstate(invalid="ignore"):
                scale = SQRT2 * amps / self._gref[blk.rows][:, None]
            scale = np.where(np.isfinite(scale), scale, 1.0)  # no reference or housekeeping: the DfMux's counts
        ci_all, cq_all = to_int32_counts(blk.counts_i, scale), to_int32_counts(blk.counts_q, scale)
        for b, m, rows in self._groups:
            rows = rows[have[rows] >= 0]
            if not rows.size:
                continue
            src = have[rows]
            if src[-1] - src[0] == src.size - 1:  # contiguous (the usual case): a view, no copy
                ci, cq = ci_all[src[0]:src[-1] + 1], cq_all[src[0]:src[-1] + 1]
            else:
                ci, cq = ci_all[src], cq_all[src]
            stream = f"{b}/{m}"
            if n_gap:
                self.counters.stream_gaps[stream] = self.counters.stream_gaps.get(stream, 0) + n_gap
            chunk = CountsChunk(setup=self.setup, board=int(b), module=int(m),
                                channels=self.wiring.channel[rows].astype(np.int32), seq=self._next_seq(stream),
                                t0_ns=None, sample_rate_hz=None, counts_i=ci, counts_q=cq,
                                t_pub_ns=int(t_pub_ns), t_ns=blk.t_ns)
            out.append((keys.counts_key(self.setup, int(b), int(m)), chunk if self.typed else chunk.to_bytes()))
            self._times.append(int(blk.t_ns[-1]))
        self._t_last_ns = int(blk.t_ns[-1])
        self.hk.prune(self._t_last_ns)  # bounded in a long run: what is in force now and the retention before it
        return out

    # -- the interface ------------------------------------------------------------------------
    def flush(self, t_pub_ns: int | None = None) -> list:
        """Counts chunks of the Timepoints collected so far."""
        if self._buffer is None or not len(self._buffer):
            return []
        blk = self._buffer.take()
        return self._counts(blk, int(blk.t_ns[-1]) if t_pub_ns is None else t_pub_ns)

    def handle(self, frame, t_pub_ns: int | None = None) -> list:
        """Messages for one frame (``t_pub_ns``: publication time of counts; default their last sample time).

        Raises :class:`~mntes_stream.g3.wire.BadFrame` for a frame it cannot use (see :meth:`accept`).
        """
        core, _ = spt3g()
        ft = frame.type
        c = self.counters
        c.frames += 1
        c.by_type[str(ft)] = c.by_type.get(str(ft), 0) + 1
        check_frame(frame)
        if ft == core.G3FrameType.Wiring:
            try:
                wiring = Wiring.from_frame(frame, self.config, self.boards)
            except SchemaError as exc:
                raise BadFrame(str(exc), "empty_map" if "empty" in str(exc) else "bad_content") from None
            if self.wiring is not None and wiring.names == self.wiring.names and \
                    wiring.detector_ids == self.wiring.detector_ids:
                return []
            return self._set_wiring(wiring)
        if ft == core.G3FrameType.Housekeeping and "DfMuxHousekeeping" in frame:
            hkmap = frame["DfMuxHousekeeping"]
            if self.wiring is None:
                self._pending = self._pending[-(self.max_held - 1):] + [hkmap] if self.max_held > 1 else [hkmap]
                return []
            return self._housekeeping(hkmap)
        if ft == core.G3FrameType.GcpSlow:
            r = bath_reading(frame, self.config, self._t_last_ns)
            return self._bath(*r) if r is not None else []
        if ft == core.G3FrameType.Timepoint and "DfMux" in frame:
            if self.wiring is None:
                return self._hold(frame)
            self._check_after(np.array([g3_time_ns(frame["EventHeader"])]), "Timepoint")
            c.timepoints += 1
            self._buffer.add(frame)
            if len(self._buffer) >= self.chunk_samples:
                return self.flush(t_pub_ns)
            return []
        if ft == core.G3FrameType.Scan:
            if self.wiring is None:
                return self._hold(frame)
            blk = scan_block(frame, self.wiring)
            if blk is None:  # an empty Scan frame: a scan boundary in a raw stream
                return self.flush(t_pub_ns)
            self._check_after(blk.t_ns, "Scan")
            c.scans += 1
            return self.flush(t_pub_ns) + self._counts(blk, int(blk.t_ns[-1]) if t_pub_ns is None else t_pub_ns)
        if ft == core.G3FrameType.EndProcessing:
            return self.flush(t_pub_ns)
        return []

    def _check_after(self, t_ns: np.ndarray, kind: str) -> None:
        # Samples go out in time order, each once: a frame going back in time (a DAQ resending, a clock
        # jump) is refused whole, before it is collected, rather than break a chunk later.
        last = self._buffer.last_t_ns if self._buffer is not None and len(self._buffer) else None
        last = self._t_last_ns if last is None else last
        if t_ns.size and (int(t_ns[0]) <= last or int(t_ns.min()) < 0 or np.any(np.diff(t_ns) <= 0)):
            raise BadFrame(f"G3 {kind} frame at {int(t_ns[0])} ns: samples not after the last one ({last} ns) or "
                           "not in time order", "out_of_order")

    def _hold(self, frame) -> list:
        # A Scan/Timepoint before the first Wiring frame: kept (bounded) until the wiring arrives.
        self._held.append(frame)
        self.counters.frames -= 1  # counted again when translated
        self.counters.by_type[str(frame.type)] -= 1
        if len(self._held) > self.max_held:
            self._held.popleft()
            self.counters.reject("before_wiring")
        return []

    @property
    def held(self) -> int:
        """Frames waiting for a Wiring frame."""
        return len(self._held)

    def drop_held(self) -> int:
        """Count what still waits for a Wiring frame as ``before_wiring`` (end of a run); how many."""
        n = len(self._held)
        if n:
            self.counters.reject("before_wiring", n)
            self._held.clear()
        return n

    def accept(self, frame, t_pub_ns: int | None = None) -> list:
        """:meth:`handle`, with a frame it cannot use counted by reason (``counters.rejected``) and skipped.

        spt3g decodes entries lazily, so a damaged blob or a wrong class
        shows here; what it raises is the frame's fault, never the bridge's.
        """
        n_times = len(self._times)
        try:
            return self.handle(frame, t_pub_ns)
        except BadFrame as exc:
            reason, text = exc.reason, str(exc)
        except (RuntimeError, MemoryError) as exc:  # spt3g could not decode an entry
            reason, text = "undecodable", str(exc).split(" (in ", 1)[0]
        except (SchemaError, TypeError, ValueError, KeyError, AttributeError, IndexError, OverflowError) as exc:
            reason, text = "bad_content", f"{type(exc).__name__}: {exc}"
        del self._times[n_times:]  # nothing of the frame goes out: nor its times (timed)
        self.counters.reject(reason)
        self.last_error[reason] = text
        now = time.monotonic()
        if now - self._logged.get(reason, -1e9) >= self.LOG_EVERY_S:  # one line per reason per interval
            self._logged[reason] = now
            log.warning("G3 frame skipped (%s, %d so far): %s", reason, self.counters.rejected[reason], text)
        return []

    def published(self) -> dict:
        """Counts chunks made per stream (``"board/module"`` -> n)."""
        return {k: v for k, v in self._seq.items() if k.partition("/")[0].isdigit()}  # hk keys are named

    def timed(self, method, *args) -> list:
        """``(t_ns, key, payload)`` of what ``method(*args)`` (handle, flush, default_bath) gives: ``t_ns`` is
        the data time a message stands for (last sample of a chunk, time of a reading)."""
        self._times = []
        out = method(*args)
        return [(t, k, p) for t, (k, p) in zip(self._times, out, strict=True)]

    def default_bath(self, t_ns: int) -> list:
        """A reading of the configured default bath temperature (a run without a thermometer)."""
        if self.config.t_bath_default_k is None:
            self.bath.require()
        return self._bath(int(t_ns), float(self.config.t_bath_default_k))


def check_frame(frame) -> None:
    """BadFrame (``wrong_type``, ``empty_map``) unless the entries the DfMux frames are read by have spt3g's
    classes and hold something; other frames pass. Reading an entry decodes it: RuntimeError if spt3g cannot."""
    core, dfmux = spt3g()
    T = core.G3FrameType
    ft = frame.type
    if ft == T.Wiring:
        wm = _entry(frame, "WiringMap", dfmux.DfMuxWiringMap, "Wiring", required=True)
        if not len(wm):
            raise BadFrame("G3 Wiring frame with an empty WiringMap", "empty_map")
    elif ft == T.Housekeeping:
        hk = _entry(frame, "DfMuxHousekeeping", dfmux.DfMuxHousekeepingMap, "Housekeeping")
        if hk is not None and not len(hk):
            raise BadFrame("G3 Housekeeping frame with an empty DfMuxHousekeeping map", "empty_map")
    elif ft == T.Timepoint:
        meta = _entry(frame, "DfMux", dfmux.DfMuxMetaSample, "Timepoint")
        if meta is not None:
            _entry(frame, "EventHeader", core.G3Time, "Timepoint", required=True)
            if not len(meta):
                raise BadFrame("G3 Timepoint frame with an empty DfMux map", "empty_map")
    elif ft == T.Scan:
        for name in ("RawTimestreams_I", "RawTimestreams_Q"):
            _entry(frame, name, core.G3TimestreamMap, "Scan")
        _entry(frame, "DetectorSampleTimes", core.G3VectorTime, "Scan")


def _entry(frame, name: str, cls, kind: str, required: bool = False):
    """``frame[name]`` if it is a ``cls`` (None if absent and not required); BadFrame otherwise."""
    if name not in frame:
        if required:
            raise BadFrame(f"G3 {kind} frame without {name}", "wrong_type")
        return None
    value = frame[name]  # decodes the blob: RuntimeError if spt3g cannot
    if not isinstance(value, cls):
        raise BadFrame(f"G3 {kind} frame: {name} is a {type(value).__name__}, not a {cls.__name__}", "wrong_type")
    return value
