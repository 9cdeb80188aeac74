"""The converter's core, free of zenoh: messages in, power/status messages out.

The live service (``service/converter.py``) feeds it what its subscriber
receives; offline re-conversion of a recording feeds it the recorded messages
in log-time order. Both get the same outputs from the same inputs because
every decision here depends only on the messages and their receive times.

What happens to a message (``handle``):

- counts chunk: decoded and validated, checked against its key, its sequence
  number tracked per ``(board, module)`` stream (lost = numbers skipped, minus
  those that turn up late; out of order = a skipped number that turned up;
  duplicated = a number seen recently with the same first sample time:
  dropped; a jump of more than 4096 either way, or a recent number with other
  sample times = the stream restarted: resynchronised, counted as
  ``bad_messages["seq_reset"]``, not as lost). The chunk then waits until
  every *required* housekeeping sensor has a reading at or after its last
  sample (so housekeeping is interpolated, not extrapolated) or until it has
  waited ``hk_wait_s`` of receive time, whichever first;
- housekeeping: added to that sensor's history (``core.align.HkSeries``),
  except readings stamped more than ``hk_max_ahead_s`` ahead of the data clock
  or (bias excepted: a setting holds) more than ``hk_retention_s`` behind it,
  which are counted (``bad_messages["hk_time"]``) and dropped. The data clock
  is the receive clock minus the median delay (receive time minus ``t_pub_ns``)
  of the latest counts chunks, so a replayed old recording is judged by its own
  time. History is pruned relative to the data clock, never relative to the
  newest reading, which one bad time stamp could push anywhere;
- anything that fails to decode, or does not match its key, is counted by
  reason in the status and otherwise ignored: the service never stops on one.

A released chunk is converted with the housekeeping aligned to each sample
(``core.align``): flags HK_STALE / HK_MISSING / ENV_OUT_OF_RANGE come from
there; channels without detector parameters get UNKNOWN_CHANNEL and NaN; a
converter failure flags that chunk INVALID_INPUT and is counted, never raised.
Power is NaN wherever a flag in ``core.flags.UNUSABLE`` is set.
"""

from __future__ import annotations

import collections
import logging
import math
import statistics
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mntes_stream import __version__
from mntes_stream.core import flags as fl
from mntes_stream.core.align import HkSeries
from mntes_stream.core.checks import finite_float
from mntes_stream.core.convert import EnvironmentBlock
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.service.pipeline_config import SCALAR_SENSORS, PipelineConfig
from mntes_stream.io.messages import (
    CountsChunk,
    HousekeepingChunk,
    PowerChunk,
    Provenance,
    StatusMessage,
    detector_ids_for,
    reason_of,
)

__all__ = ["PipelineConfig", "ConverterPipeline", "SCALAR_SENSORS"]

log = logging.getLogger("mntes_stream.converter")

_SEQ_RECENT = 256      # sequence numbers remembered per stream to spot duplicates
_SEQ_MISSING = 4096    # skipped numbers remembered per stream to spot late arrivals; a longer jump is a restart
_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1
_OFFSETS = 32          # counts chunks whose receive delay sets the data clock (median: one bad t_pub_ns cannot move it)


def _ns(seconds: float) -> int | float:
    return math.inf if math.isinf(seconds) else int(round(seconds * 1e9))


class _Stream:
    """Sequence bookkeeping of one (board, module) counts stream."""

    __slots__ = ("next", "recent", "recent_t", "missing")

    def __init__(self):
        self.next: int | None = None
        self.recent: collections.deque = collections.deque()
        self.recent_t: dict[int, int] = {}  # seq -> first sample time: a duplicate has both equal
        self.missing: collections.OrderedDict = collections.OrderedDict()

    def remember(self, seq: int, t_first_ns: int) -> None:
        self.recent.append(seq)
        self.recent_t[seq] = t_first_ns
        if len(self.recent) > _SEQ_RECENT:
            self.recent_t.pop(self.recent.popleft(), None)

    def reset(self) -> None:
        self.next = None
        self.recent.clear()
        self.recent_t.clear()
        self.missing.clear()


@dataclass
class _Pending:
    chunk: CountsChunk
    t_recv_ns: int
    t_ns: np.ndarray
    t_last_ns: int | None


class ConverterPipeline:
    """Counts + housekeeping in, power chunks + status out (no I/O).

    Parameters
    ----------
    converter
        Has ``kind``, ``identity``, ``detector_ids`` and
        ``convert(detector_ids, counts_i, counts_q, env) -> PowerBlock``
        (``core.convert.make_converter``).
    config : PipelineConfig
    params : dict or list of DetectorParams, optional
        The detector parameters (provenance and nominal bias); default
        ``converter.params`` when it has them.
    clock : callable or None
        Publication time stamp of outputs (ns); default ``time.time_ns``.
        None stamps outputs with the receive time of the message being handled,
        which makes offline re-conversion reproducible.
    """

    def __init__(self, converter, config: PipelineConfig | None = None, params=None, clock: Callable[[], int] | None = time.time_ns):
        self.converter = converter
        self.config = config or PipelineConfig()
        self._clock = clock
        if params is None:
            params = getattr(converter, "params", None)
        if isinstance(params, dict):
            params = list(params.values())
        self._params = list(params) if params is not None else []
        self._nominal_bias = {p.detector_id: float(p.v_thev_v) for p in self._params}
        self._known = frozenset(converter.detector_ids)
        self._staleness_ns = _ns(self.config.hk_staleness_s)
        self._bias_staleness_ns = _ns(self.config.bias_staleness_s)
        self._wait_ns = _ns(self.config.hk_wait_s)
        self._status_ns = _ns(self.config.status_interval_s)
        self._retention_ns = _ns(self.config.hk_retention_s)
        self._ahead_ns = _ns(self.config.hk_max_ahead_s)
        self._hk: dict[str, HkSeries] = {s: HkSeries(None, self._retention_ns) for s in SCALAR_SENSORS}
        self._bias: dict[tuple[int, int], tuple[np.ndarray, HkSeries]] = {}
        self._streams: dict[tuple[int, int], _Stream] = {}
        self._pending: collections.deque[_Pending] = collections.deque()
        self._delays: collections.deque[int] = collections.deque(maxlen=_OFFSETS)  # receive minus t_pub_ns
        self._rows: dict[tuple, tuple] = {}
        self._env_cache: dict[tuple, tuple] = {}
        self._provenance: bytes | None = None
        self._t_created_ns = time.time_ns()
        self._t_first_ns: int | None = None
        self._now_ns: int | None = None
        self._next_status_ns: int | None = None
        self._last_status_ns: int | None = None
        self._interval_latency_ms: list[float] = []
        self._interval_chunks = 0
        self._interval_samples = 0
        self.counters = collections.Counter()
        self.bad_messages = collections.Counter()
        self.flag_counts = collections.Counter()
        self.last_error = ""

    # ------------------------------------------------------------------ public API

    @property
    def pending(self) -> int:
        """Chunks held back waiting for housekeeping."""
        return len(self._pending)

    def handle(self, key: str, payload: bytes, t_recv_ns: int) -> list[tuple[str, bytes]]:
        """Process one received message; returns ``(key, payload)`` messages to publish."""
        out: list[tuple[str, bytes]] = []
        self._advance(t_recv_ns)
        self._guarded(self._dispatch, key, str(key), payload, int(t_recv_ns))
        self._guarded(self._release, key, out)
        self._guarded(self._maybe_status, key, out)
        return out

    def tick(self, t_now_ns: int) -> list[tuple[str, bytes]]:
        """Let time pass without a message: release chunks that waited long enough, status when due."""
        out: list[tuple[str, bytes]] = []
        self._advance(t_now_ns)
        self._guarded(self._release, "tick", out)
        self._guarded(self._maybe_status, "tick", out)
        return out

    def _guarded(self, step, key, *args) -> None:
        try:
            step(*args)
        except Exception as exc:  # the service must survive its own bugs too: counted and shown
            self._bad("internal_error", f"{type(exc).__name__}: {exc}", str(key))
            log.exception("internal error (%s) handling %s", getattr(step, "__name__", step), key)

    def flush(self) -> list[tuple[str, bytes]]:
        """Convert everything still held (with what housekeeping there is) and emit a final status."""
        out: list[tuple[str, bytes]] = []
        self._guarded(self._release, "flush", out, True)
        if self._now_ns is not None:
            self._guarded(lambda: out.append(self._emit_status()), "flush")
        return out

    def status(self) -> StatusMessage:
        """The status as of the latest message (interval figures since the last emitted status)."""
        now = self._now_ns if self._now_ns is not None else time.time_ns()
        start = self._t_first_ns if self._t_first_ns is not None else now
        since = self._last_status_ns if self._last_status_ns is not None else start
        interval_s = max(now - since, 0) / 1e9
        lat = np.asarray(self._interval_latency_ms)
        c = self.counters
        hk_age = {}
        for sensor, series in self._hk.items():
            if len(series):
                hk_age[sensor] = (now - series.newest_t_ns) / 1e9
        return StatusMessage(
            setup=self.config.setup,
            service=self.config.service,
            t_ns=max(now, 0),
            uptime_s=max(now - start, 0) / 1e9,
            interval_s=interval_s,
            chunks_received=c["chunks_received"],
            chunks_converted=c["chunks_converted"],
            chunks_pending=len(self._pending),
            samples_converted=c["samples_converted"],
            chunks_lost=max(c["chunks_lost"], 0),
            chunks_duplicated=c["chunks_duplicated"],
            chunks_out_of_order=c["chunks_out_of_order"],
            hk_received=c["hk_received"],
            hk_stale_samples=c["hk_stale_samples"],
            hk_missing_samples=c["hk_missing_samples"],
            unknown_channel_samples=c["unknown_channel_samples"],
            bad_messages=dict(self.bad_messages),
            flag_counts={name: self.flag_counts.get(name, 0) for name in fl.NAMES.values()},
            hk_age_s=hk_age,
            rate_chunks_per_s=self._interval_chunks / interval_s if interval_s > 0 else 0.0,
            rate_msamples_per_s=self._interval_samples / interval_s / 1e6 if interval_s > 0 else 0.0,
            latency_p50_ms=float(np.percentile(lat, 50)) if lat.size else None,
            latency_p99_ms=float(np.percentile(lat, 99)) if lat.size else None,
            latency_max_ms=float(lat.max()) if lat.size else None,
            last_error=self.last_error,
        )

    def provenance(self) -> Provenance:
        """Parameters (TOML text), table identity, converter kind and software version."""
        from mntes_stream.io.paramfile import params_to_toml

        return Provenance(
            setup=self.config.setup,
            params_toml=params_to_toml(self._params) if self._params else "",
            table_identity=str(self.converter.identity),
            converter_kind=str(self.converter.kind),
            software_version=__version__,
            t_ns=self._t_created_ns,
        )

    def provenance_bytes(self) -> bytes:
        """:meth:`provenance` encoded once: identical bytes on every publication."""
        if self._provenance is None:
            self._provenance = self.provenance().to_bytes()
        return self._provenance

    # ------------------------------------------------------------------ internals

    def _advance(self, t_ns: int) -> None:
        t_ns = int(t_ns)
        if self._t_first_ns is None:
            self._t_first_ns = t_ns
            self._last_status_ns = t_ns
            self._next_status_ns = t_ns + self._status_ns
        self._now_ns = t_ns if self._now_ns is None else max(self._now_ns, t_ns)

    def _stamp(self) -> int:
        return int(self._clock()) if self._clock is not None else int(self._now_ns)

    def _bad(self, reason: str, detail: str, key: str) -> None:
        self.bad_messages[reason] += 1
        self.last_error = f"{reason} on {key}: {detail}"[:500]
        n = self.bad_messages[reason]
        if n <= 10 or n % 1000 == 0:  # log, but never flood the log
            log.warning("bad message #%d (%s) on %s: %s", n, reason, key, detail)

    def _dispatch(self, key: str, payload: bytes, t_recv_ns: int) -> None:
        try:
            info = keys.parse_key(key)
        except ConfigError as exc:
            self._bad("wrong_key", str(exc), key)
            return
        if info["setup"] != self.config.setup:
            self._bad("wrong_key", f"setup {info['setup']!r} is not {self.config.setup!r}", key)
            return
        kind = info["kind"]
        try:
            if kind == "counts":
                self._on_counts(info, CountsChunk.from_bytes(payload), key, t_recv_ns)
            elif kind == "hk":
                self._on_hk(info, HousekeepingChunk.from_bytes(payload), key, t_recv_ns)
            else:
                self._bad("wrong_key", f"the converter does not consume {kind!r} messages", key)
        except SchemaError as exc:
            self._bad(reason_of(exc), str(exc), key)

    def _on_counts(self, info: dict, chunk: CountsChunk, key: str, t_recv_ns: int) -> None:
        if chunk.setup != self.config.setup or info["board"] != str(chunk.board) or info["module"] != str(chunk.module):
            self._bad("wrong_key", f"payload is setup {chunk.setup} board {chunk.board} module {chunk.module}", key)
            return
        self.counters["chunks_received"] += 1
        t = chunk.times_ns()
        if not self._sequence((chunk.board, chunk.module), chunk.seq, int(t[0]) if t.size else chunk.t_pub_ns, key):
            return
        self._delays.append(t_recv_ns - chunk.t_pub_ns)
        self._pending.append(_Pending(chunk, t_recv_ns, t, int(t.max()) if t.size else None))

    def _sequence(self, stream_id: tuple[int, int], seq: int, t_first_ns: int, key: str) -> bool:
        """Book-keep a sequence number; False for a duplicate (to drop)."""
        s = self._streams.get(stream_id)
        if s is None:
            s = self._streams[stream_id] = _Stream()
        c = self.counters
        seen = s.recent_t.get(seq)
        if seen == t_first_ns:
            c["chunks_duplicated"] += 1
            return False
        if seen is not None or (s.next is not None and abs(seq - s.next) > _SEQ_MISSING):
            # A restarted source (a recent number with other samples, or a long jump back) or a
            # corrupt number: start over from it. Counting the jump as lost, everything after
            # it as out of order, or a new run's chunks as duplicates would bury the status.
            why = "a recent number with other sample times" if seen is not None else f"expected {s.next}"
            self._bad("seq_reset", f"sequence number {seq}, {why}: stream restarted", key)
            s.reset()
        if s.next is None or seq >= s.next:
            if s.next is not None and seq > s.next:
                c["chunks_lost"] += seq - s.next
                for missing in range(max(s.next, seq - _SEQ_MISSING), seq):
                    s.missing[missing] = None
                while len(s.missing) > _SEQ_MISSING:
                    s.missing.popitem(last=False)
            s.next = seq + 1
        elif seq in s.missing:
            del s.missing[seq]
            c["chunks_lost"] -= 1
            c["chunks_out_of_order"] += 1
        else:
            # Older than anything remembered (e.g. a restarted source): convert it, count it.
            c["chunks_out_of_order"] += 1
        s.remember(seq, t_first_ns)
        return True

    def _on_hk(self, info: dict, hk: HousekeepingChunk, key: str, t_recv_ns: int) -> None:
        sensor = info["sensor"]
        expected = keys.hk_sensor(hk.sensor, hk.board, hk.module)
        if hk.setup != self.config.setup or sensor != expected:
            self._bad("wrong_key", f"payload is setup {hk.setup} sensor {expected}", key)
            return
        self.counters["hk_received"] += 1
        # The data clock: receive clock minus the counts' median delay (none yet: the receive clock).
        now = t_recv_ns - (int(statistics.median_low(self._delays)) if self._delays else 0)
        t_ns, value = hk.t_ns, hk.value
        # Too old only once the data clock is known (a replayed recording's first readings
        # come before its first counts chunk), and never for the bias: a setting holds.
        lo = now - self._retention_ns if self._delays and hk.sensor != "bias" else _INT64_MIN
        ok = (t_ns >= max(lo, _INT64_MIN)) & (t_ns <= min(now + self._ahead_ns, _INT64_MAX))
        if not ok.all():
            bad = t_ns[~ok]
            self._bad("hk_time", f"{bad.size} reading(s) stamped {(int(bad[0]) - now) / 1e9:+.4g} s from the data clock "
                                 f"(accepted: -{self.config.hk_retention_s:g} s to +{self.config.hk_max_ahead_s:g} s)", key)
            t_ns, value = t_ns[ok], value[ok]
        if hk.sensor == "bias":
            module = (hk.board, hk.module)
            entry = self._bias.get(module)
            if entry is None or not np.array_equal(entry[0], hk.channels):
                # A new channel list starts a new history: columns must line up.
                entry = (hk.channels.copy(), HkSeries(hk.channels.size, self._retention_ns))
                self._bias[module] = entry
            entry[1].add(t_ns, value, now_ns=now)
        else:
            self._hk[hk.sensor].add(t_ns, value, now_ns=now)

    def _bracketed(self, p: _Pending) -> bool:
        if p.t_last_ns is None:
            return True
        for sensor in self.config.required_hk:
            newest = self._hk[sensor].newest_t_ns
            if newest is None or newest < p.t_last_ns:
                return False
        return True

    def _release(self, out: list, force: bool = False) -> None:
        if not self._pending:
            return
        now = self._now_ns
        keep: collections.deque[_Pending] = collections.deque()
        overflow = len(self._pending) - self.config.max_pending
        try:
            # Each chunk leaves the queue before it is converted: one that cannot be
            # converted is counted and dropped, never re-published nor left blocking the rest.
            for i in range(len(self._pending)):
                p = self._pending.popleft()
                try:
                    if force or i < overflow or self._bracketed(p) or now - p.t_recv_ns >= self._wait_ns:
                        out.append(self._convert(p))
                    else:
                        keep.append(p)
                except Exception as exc:
                    key = keys.counts_key(self.config.setup, p.chunk.board, p.chunk.module)
                    self.counters["chunks_failed"] += 1
                    self._bad("internal_error", f"chunk seq {p.chunk.seq} dropped: {type(exc).__name__}: {exc}", key)
                    log.exception("internal error converting %s seq %d; chunk dropped", key, p.chunk.seq)
        finally:
            keep.extend(self._pending)
            self._pending = keep

    def _scalar_env(self, sensor: str, chunk: CountsChunk, t: np.ndarray, default: float, valid_range):
        """Aligned value and flags, shape (n_samp,); cached, since every module of a step shares its times."""
        series = self._hk[sensor]
        times = (chunk.t0_ns, chunk.sample_rate_hz, t.size) if chunk.t_ns is None else t.tobytes()
        key = (sensor, times)
        hit = self._env_cache.get(key)
        if hit is not None and hit[0] == series.version:
            return hit[1], hit[2]
        value, flags = self._scalar_env_uncached(sensor, t, default, valid_range)
        value.setflags(write=False)
        flags.setflags(write=False)
        if len(self._env_cache) > 1024:
            self._env_cache.clear()
        self._env_cache[key] = (series.version, value, flags)
        return value, flags

    def _scalar_env_uncached(self, sensor: str, t: np.ndarray, default: float, valid_range):
        series = self._hk[sensor]
        required = sensor in self.config.required_hk
        if not len(series):
            flags = np.full(t.size, fl.HK_MISSING if required else 0, dtype=fl.FLAG_DTYPE)
            return np.full(t.size, default), flags
        a = series.align(t, self._staleness_ns, valid_range)
        missing = (a.flags & fl.HK_MISSING) != 0
        flags = a.flags if required else a.flags & ~np.uint16(fl.HK_MISSING)
        return np.where(missing, default, a.value), flags

    def _rows_for(self, chunk: CountsChunk) -> tuple:
        """Detector ids of the rows and which the converter knows (cached per channel list)."""
        cache_key = (chunk.board, chunk.module, chunk.channels.tobytes())
        rows = self._rows.get(cache_key)
        if rows is None:
            ids = detector_ids_for(chunk.board, chunk.module, chunk.channels)
            known = np.array([d in self._known for d in ids], dtype=bool)
            if len(self._rows) > 4096:
                self._rows.clear()
            rows = self._rows[cache_key] = (ids, known, int((~known).sum()))
        return rows

    def _bias_env(self, chunk: CountsChunk, t: np.ndarray, ids) -> tuple[np.ndarray | None, np.ndarray | None]:
        entry = self._bias.get((chunk.board, chunk.module))
        if entry is None or not len(entry[1]):
            return None, None
        channels, series = entry
        a = series.align(t, self._bias_staleness_ns, self.config.bias_range_v)
        n_ch, n = chunk.channels.size, t.size
        v = np.empty((n_ch, n))
        col = {int(c): j for j, c in enumerate(channels.tolist())}
        for r, c in enumerate(chunk.channels.tolist()):
            j = col.get(int(c))
            v[r] = self._nominal_bias.get(ids[r], np.nan) if j is None else a.value[:, j]
        missing = (a.flags & fl.HK_MISSING) != 0
        flags = a.flags & ~np.uint16(fl.HK_MISSING)
        if missing.any():  # before any bias reading: the nominal bias
            nominal = np.array([self._nominal_bias.get(d, np.nan) for d in ids])[:, None]
            v = np.where(missing[None, :], nominal, v)
        return v, np.broadcast_to(flags, (n_ch, n))

    def _convert(self, p: _Pending) -> tuple[str, bytes]:
        chunk, t = p.chunk, p.t_ns
        cfg = self.config
        n_ch, n = chunk.channels.size, t.size
        t_bath, f_tb = self._scalar_env("t_bath", chunk, t, cfg.t_bath_default_k, cfg.t_bath_range_k)
        b_field, f_b = self._scalar_env("b_field", chunk, t, cfg.b_field_default_t, cfg.b_field_range_t)
        env_flags_t = f_tb | f_b
        ids, known, n_unknown = self._rows_for(chunk)
        v_bias, f_bias = self._bias_env(chunk, t, ids)
        env_flags = env_flags_t if f_bias is None else env_flags_t[None, :] | f_bias
        try:
            # The converter flags rows it has no parameters for (UNKNOWN_CHANNEL) itself.
            env = EnvironmentBlock(t_bath_k=t_bath, b_field_t=b_field, v_thev_v=v_bias, flags=env_flags)
            block = self.converter.convert(ids, chunk.counts_i, chunk.counts_q, env)
            p_opt, flags = np.asarray(block.p_opt_w, dtype=float), np.asarray(block.flags, dtype=fl.FLAG_DTYPE)
            if p_opt.shape != (n_ch, n) or flags.shape != (n_ch, n):
                raise ValueError(f"converter returned shapes {p_opt.shape}, {flags.shape} for {(n_ch, n)}")
        except Exception as exc:  # one bad block must not stop the stream
            p_opt = np.full((n_ch, n), np.nan)
            flags = np.full((n_ch, n), fl.INVALID_INPUT, dtype=fl.FLAG_DTYPE)
            self._bad("convert_failed", f"{type(exc).__name__}: {exc}", keys.counts_key(cfg.setup, chunk.board, chunk.module))
        # Whatever the converter did: housekeeping and unknown-channel flags hold, and flagged power is NaN.
        flags = flags | env_flags
        if n_unknown:
            flags[~known] |= fl.UNKNOWN_CHANNEL
            self.counters["unknown_channel_samples"] += n_unknown * n
        p_opt = np.where((flags & fl.UNUSABLE) != 0, np.nan, p_opt)
        t_pub = self._stamp()
        power = PowerChunk(
            setup=cfg.setup,
            board=chunk.board,
            module=chunk.module,
            channels=chunk.channels,
            detector_ids=ids,
            seq=chunk.seq,
            t0_ns=chunk.t0_ns,
            sample_rate_hz=chunk.sample_rate_hz,
            p_opt_w=p_opt,
            flags=flags,
            table_identity=str(self.converter.identity),
            converter_kind=str(self.converter.kind),
            source_t_pub_ns=chunk.t_pub_ns,
            t_pub_ns=t_pub,
            t_ns=chunk.t_ns,
        )
        c = self.counters
        c["chunks_converted"] += 1
        c["samples_converted"] += n_ch * n
        c["hk_stale_samples"] += int(np.count_nonzero(env_flags_t & fl.HK_STALE))
        c["hk_missing_samples"] += int(np.count_nonzero(env_flags_t & fl.HK_MISSING))
        if flags.any():
            self.flag_counts.update(fl.counts_by_flag(flags))
        self._interval_chunks += 1
        self._interval_samples += n_ch * n
        self._interval_latency_ms.append((t_pub - chunk.t_pub_ns) / 1e6)
        return keys.power_key(cfg.setup, chunk.board, chunk.module), power.to_bytes()

    def _maybe_status(self, out: list) -> None:
        if self._now_ns is not None and self._now_ns >= self._next_status_ns:
            out.append(self._emit_status())
            # Skip missed slots rather than bursting after a pause.
            while self._next_status_ns <= self._now_ns:
                self._next_status_ns += self._status_ns

    def _emit_status(self) -> tuple[str, bytes]:
        msg = self.status()
        self._last_status_ns = self._now_ns
        self._interval_latency_ms = []
        self._interval_chunks = 0
        self._interval_samples = 0
        return keys.status_key(self.config.setup, self.config.service), msg.to_bytes()
