"""A minimal data source: counts and housekeeping from the physics model, published over zenoh.

The *generator* contract (shared with the richer ``service/simulator.py``):
an iterable of batches ``(t_pub_ns, [(key, payload), ...])`` in publication
order, ``t_pub_ns`` being when the batch is due on the data clock.
:func:`publish` sends them, paced to real time (or a multiple), through BLOCK
publishers.

:class:`MinimalSource` is deliberately simple: Table-1-like detectors with a
small seeded scatter, bias tuned to R = 0.7 R_n, a constant optical loading
plus a 2f HWP sinusoid, bath temperature and field as triangle waves
(when the housekeeping interval divides a quarter cycle, readings fall on
the corners and linear interpolation is exact). The forward model is solved once for
one cycle per module and the cycle repeats (the 2f frequency is rounded to a
whole number of periods per cycle).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ids import NAME_PATTERN, detector_id
from mntes_stream.core.params import DetectorParams, ParamArray, table1_params
from mntes_stream.core.settings import Settings, setting
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.messages import SENSOR_UNITS, CountsChunk, HousekeepingChunk
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["SourceConfig", "SourceServiceConfig", "SourceService", "MinimalSource", "default_params", "publish", "run_source", "Batch"]


log = logging.getLogger("mntes_stream.source")

Batch = tuple[int, list[tuple[str, bytes]]]


@dataclass(frozen=True)
class SourceConfig(Settings):
    """The minimal source's array and signals (the ``[source]`` table).

    Bath temperature: a triangle wave around ``t_bath_k``; field: a triangle
    around 0; optical power: ``p_opt_w`` plus a 2f_HWP sinusoid whose phase
    differs per detector.
    """

    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    boards: int = setting(1, "boards", ge=1)
    modules: int = setting(2, "modules per board", ge=1)
    channels: int = setting(16, "channels per module", ge=1)
    sample_rate_hz: float = setting(DFMUX_SAMPLE_RATE_HZ, "sample rate (DfMux: 20 MHz / 2**17)", unit="Hz", gt=0)
    chunk_s: float = setting(0.1, "one counts chunk per module this often (whole samples)", unit="s", gt=0)
    hk_interval_s: float = setting(0.1, "housekeeping cadence (t_bath, b_field)", unit="s", gt=0)
    p_opt_w: float = setting(0.5e-12, "optical loading", unit="W")
    hwp_2f_amplitude_w: float = setting(0.02e-12, "2f_HWP modulation amplitude", unit="W")
    f_hwp_hz: float = setting(0.77, "half-wave plate frequency (2f rounded to whole periods per cycle)", unit="Hz")
    t_bath_k: float = setting(0.100, "mean bath temperature", unit="K", gt=0)
    t_bath_swing_k: float = setting(0.5e-3, "bath temperature triangle amplitude", unit="K")
    b_field_swing_t: float = setting(20e-6, "field triangle amplitude", unit="T")
    cycle_s: float = setting(2.0, "length of the precomputed cycle that repeats", unit="s", gt=0)
    scatter: float = setting(0.01, "fractional 1-sigma spread of T_c, K and R_n (generated detectors only)")
    seed: int = setting(0, "random seed", ge=0)

    def __post_init__(self):
        super().__post_init__()
        if self.chunk_samples < 1:
            raise ConfigError("source: chunk_s * sample_rate_hz must give at least one sample")

    @property
    def chunk_samples(self) -> int:
        return int(round(self.chunk_s * self.sample_rate_hz))

    @property
    def cycle_chunks(self) -> int:
        return max(1, int(math.ceil(self.cycle_s * self.sample_rate_hz / self.chunk_samples)))

    @property
    def cycle_samples(self) -> int:
        return self.cycle_chunks * self.chunk_samples

    @property
    def n_detectors(self) -> int:
        return self.boards * self.modules * self.channels


def _triangle(phase: np.ndarray) -> np.ndarray:
    """Triangle wave of period 1: 0 at phase 0, +1 at 1/4, -1 at 3/4."""
    x = np.mod(phase, 1.0)
    return np.where(x < 0.25, 4 * x, np.where(x < 0.75, 2 - 4 * x, 4 * x - 4))


class MinimalSource:
    """Counts + housekeeping batches from the forward model (see module docstring).

    Parameters
    ----------
    config : SourceConfig
    params : list of DetectorParams, optional
        The truth; default: Table-1-like detectors with seeded scatter.
    """

    def __init__(self, config: SourceConfig | None = None, params: list[DetectorParams] | None = None):
        self.config = cfg = config or SourceConfig()
        self.params = list(params) if params is not None else default_params(cfg)
        by_id = {p.detector_id: p for p in self.params}
        self._modules = []
        for b in range(cfg.boards):
            for m in range(cfg.modules):
                ids = [detector_id(b, m, c) for c in range(cfg.channels)]
                missing = [d for d in ids if d not in by_id]
                if missing:
                    raise ConfigError(f"source: no parameters for {missing[:3]}{'...' if len(missing) > 3 else ''}")
                self._modules.append((b, m, [by_id[d] for d in ids]))
        self._cycles: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._period_s = cfg.cycle_samples / cfg.sample_rate_hz
        n2f = max(1, round(2 * cfg.f_hwp_hz * self._period_s))
        self.f_2f_hz = n2f / self._period_s

    # Environment as functions of time since the start (s): triangle waves whose
    # corners fall on housekeeping reading times when hk_interval_s divides cycle/4.
    def t_bath_k(self, t_s) -> np.ndarray:
        return self.config.t_bath_k + self.config.t_bath_swing_k * _triangle(np.asarray(t_s) / self._period_s)

    def b_field_t(self, t_s) -> np.ndarray:
        return self.config.b_field_swing_t * _triangle(np.asarray(t_s) / self._period_s + 0.25)

    def p_opt_w(self, params: list[DetectorParams], t_s) -> np.ndarray:
        """Optical power truth, shape (n_det, n_samp)."""
        cfg = self.config
        phase = np.array([_stable_phase(p.detector_id) for p in params])[:, None]
        return cfg.p_opt_w + cfg.hwp_2f_amplitude_w * np.cos(2 * np.pi * self.f_2f_hz * np.asarray(t_s)[None, :] + phase)

    def _cycle(self, board: int, module: int, params: list[DetectorParams]):
        key = (board, module)
        if key not in self._cycles:
            from mntes_stream.core import model

            cfg = self.config
            t_s = np.arange(cfg.cycle_samples) / cfg.sample_rate_hz
            pa = ParamArray.from_params(params)
            t_bath, b = self.t_bath_k(t_s), self.b_field_t(t_s)
            op = model.solve_operating_point(pa, self.p_opt_w(params, t_s), t_bath, b)
            i_meas = model.readout_current_a(pa, op.i_a, b)
            counts = i_meas / pa.gain_a_per_count
            self._cycles[key] = (np.rint(counts.real).astype(np.int32), np.rint(counts.imag).astype(np.int32))
        return self._cycles[key]

    def prepare(self) -> None:
        """Solve the forward model for every module now (else lazily on first use)."""
        for board, module, params in self._modules:
            self._cycle(board, module, params)

    def batches(self, t_start_ns: int, duration_s: float = 0.0) -> Iterator[Batch]:
        """Batches from ``t_start_ns`` on (for ``duration_s`` of data; 0: forever).

        Each step publishes, at the end of a chunk, the housekeeping read since
        the previous step and then one counts chunk per module (housekeeping
        first so it is there when the chunk arrives). Reading ``i`` is at
        ``t_start_ns + round(i * hk_interval_s)``, never accumulated step by
        step, and one due within 1 us of a step's end goes with that step: with
        ``hk_interval_s`` the chunk length, every chunk's last sample has a
        reading at or after it in its own step, whatever the rounding to ns
        (else a chunk would wait a step for its housekeeping).
        """
        cfg = self.config
        rate, n = cfg.sample_rate_hz, cfg.chunk_samples
        hk_dt_s = float(cfg.hk_interval_s)
        channels = np.arange(cfg.channels, dtype=np.int32)
        hk_i = 0
        next_hk_ns = int(t_start_ns)
        hk_seq = 0
        step = 0
        while True:
            t0_ns = int(t_start_ns) + int(round(step * n * 1e9 / rate))
            t_pub_ns = int(t_start_ns) + int(round((step + 1) * n * 1e9 / rate))
            if duration_s and t0_ns - t_start_ns >= duration_s * 1e9:
                return
            batch: list[tuple[str, bytes]] = []
            hk_t = []
            while next_hk_ns <= t_pub_ns + 1000:
                hk_t.append(next_hk_ns)
                hk_i += 1
                next_hk_ns = int(t_start_ns) + int(round(hk_i * hk_dt_s * 1e9))
            if hk_t:
                t_arr = np.array(hk_t, dtype=np.int64)
                t_rel = (t_arr - int(t_start_ns)) / 1e9
                for sensor, value in (("t_bath", self.t_bath_k(t_rel)), ("b_field", self.b_field_t(t_rel))):
                    hk = HousekeepingChunk(cfg.setup, sensor, hk_seq, t_arr, value, SENSOR_UNITS[sensor])
                    batch.append((keys.hk_key(cfg.setup, sensor), hk.to_bytes()))
                hk_seq += 1
            k = step % cfg.cycle_chunks
            for board, module, params in self._modules:
                ci, cq = self._cycle(board, module, params)
                chunk = CountsChunk(
                    setup=cfg.setup, board=board, module=module, channels=channels, seq=step,
                    t0_ns=t0_ns, sample_rate_hz=rate,
                    counts_i=ci[:, k * n:(k + 1) * n], counts_q=cq[:, k * n:(k + 1) * n], t_pub_ns=t_pub_ns,
                )
                batch.append((keys.counts_key(cfg.setup, board, module), chunk.to_bytes()))
            yield t_pub_ns, batch
            step += 1

    def truth_p_opt_w(self, board: int, module: int, t_ns: np.ndarray, t_start_ns: int) -> np.ndarray:
        """Optical power truth of one module at sample times (n_ch, n_samp)."""
        params = next(p for b, m, p in self._modules if (b, m) == (board, module))
        t_s = (np.asarray(t_ns, dtype=np.int64) - int(t_start_ns)) / 1e9
        return self.p_opt_w(params, np.mod(t_s, self._period_s))


def _stable_phase(det_id: str) -> float:
    # Python's hash() is salted per process; the phase must be reproducible.
    return (sum((i + 1) * ord(ch) for i, ch in enumerate(det_id)) % 997) / 997 * 2 * np.pi


def default_params(cfg: SourceConfig) -> list[DetectorParams]:
    """Table-1-like detectors with seeded scatter, bias tuned to R = 0.7 R_n at the loading."""
    from mntes_stream.core import model

    rng = np.random.default_rng(cfg.seed)
    base = table1_params()
    out = []
    for b in range(cfg.boards):
        for m in range(cfg.modules):
            for c in range(cfg.channels):
                s = 1 + cfg.scatter * rng.standard_normal(3)
                p = base.replace(
                    detector_id=detector_id(b, m, c),
                    t_c_k=base.transition.t_c_k * s[0],
                    k_w_per_k_n=base.k_w_per_k_n * s[1],
                    r_n_ohm=base.transition.r_n_ohm * s[2],
                    t_bath_k=cfg.t_bath_k,
                    p_opt_w=cfg.p_opt_w,
                )
                out.append(p)
    pa = ParamArray.from_params(out)
    v = np.asarray(model.tune_bias_v(pa, 0.7)).reshape(-1)
    return [p.replace(v_thev_v=float(vi)) for p, vi in zip(out, v)]


class Pacer:
    """When each batch is due: ``speed`` x real time from the first batch (or from ``t_ref_ns`` = now).

    ``wait(t_pub_ns, stop)`` sleeps until the batch is due (waking for ``stop``); ``behind_max_ms``
    is the worst lateness against the schedule.
    """

    def __init__(self, speed: float, t_ref_ns: int | None = None):
        self.speed, self.t_ref_ns = speed, t_ref_ns
        self._wall0 = self._t_first = None
        self.behind_max_s = 0.0

    @property
    def behind_max_ms(self) -> float:
        return self.behind_max_s * 1e3

    def wait(self, t_pub_ns: int, stop=None) -> None:
        if self._wall0 is None:
            self._wall0, self._t_first = time.monotonic(), (t_pub_ns if self.t_ref_ns is None else self.t_ref_ns)
        if self.speed <= 0:
            return
        if self.t_ref_ns is not None:
            # Data clock started at t_ref_ns = wall clock then: pace on the wall clock itself.
            due = (self.t_ref_ns + (t_pub_ns - self.t_ref_ns) / self.speed) / 1e9
            clock = time.time
        else:
            due = self._wall0 + (t_pub_ns - self._t_first) / 1e9 / self.speed
            clock = time.monotonic
        while (wait := due - clock()) > 0:
            time.sleep(min(wait, 0.05))
            if stop is not None and stop.is_set():
                break
        self.behind_max_s = max(self.behind_max_s, clock() - due)


def publish(session, batches: Iterable[Batch], *, speed: float = 1.0, stop=None, wait_keys: Iterable[str] = (),
            wait_s: float = 10.0, progress=None, t_ref_ns: int | None = None, history_chunks: int = 0,
            history_bytes: int = 0) -> dict:
    """Publish batches on ``session`` paced by their ``t_pub_ns`` (``speed`` x real time; 0: flat out).

    Parameters
    ----------
    session : zenoh.Session
    batches : iterable of (t_pub_ns, [(key, payload), ...])
    speed : float
    stop : Event-like, optional
        Checked between batches.
    wait_keys : keys that must have a subscriber before the first batch (up to ``wait_s``).
    progress : callable(dict), optional
        Called about once a second with the running counters.
    t_ref_ns : int, optional
        Data time that corresponds to "now" when publishing starts (default:
        the first batch's time). With the data clock started now, a batch then
        goes out when its ``t_pub_ns`` comes, so latencies measured from
        ``t_pub_ns`` are honest.
    history_chunks : int
        Samples each counts and housekeeping key keeps for late or recovering
        subscribers (``io/history.py``; 0: none).
    history_bytes : int
        ... and at most this many bytes per key (``[zenoh] history_mb``; 0: no cap in bytes).

    Returns
    -------
    dict
        ``batches``, ``messages``, ``bytes``, ``behind_max_ms`` (worst lateness
        against the schedule), ``matched`` (whether the wait succeeded).
    """
    from mntes_stream.io.transport import Publishers

    pubs = Publishers(session, history_chunks=history_chunks, history_bytes=history_bytes)
    matched = True
    if wait_keys:
        matched = pubs.wait_matching(wait_keys, wait_s, stop)
        if not matched:
            log.warning("no subscriber yet for some of %s; publishing anyway", list(wait_keys))
    n_batches = 0
    pacer = Pacer(speed, t_ref_ns)
    next_progress = time.monotonic() + 1.0
    try:
        for t_pub_ns, batch in batches:
            if stop is not None and stop.is_set():
                break
            pacer.wait(t_pub_ns, stop)
            for key, payload in batch:
                pubs.put(key, payload)
            n_batches += 1
            if progress is not None and time.monotonic() >= next_progress:
                next_progress += 1.0
                progress({"batches": n_batches, "messages": pubs.messages, "bytes": pubs.bytes})
    finally:
        pubs.close()
    return {"batches": n_batches, "messages": pubs.messages, "bytes": pubs.bytes,
            "behind_max_ms": pacer.behind_max_ms, "matched": matched}


@dataclass(frozen=True)
class SourceServiceConfig(Settings):
    """The ``[source]`` and ``[zenoh]`` tables: the array (:class:`SourceConfig`, same table) plus how to run it."""

    source: SourceConfig = setting(default_factory=SourceConfig, doc="the array and signals", flatten=True)
    params: str = setting("", "detector parameter file used as the truth ('' = generated Table-1-like detectors)",
                          path=True)
    speed: float = setting(1.0, "multiple of real time (0 = as fast as possible)", ge=0)
    duration_s: float = setting(0.0, "seconds of data (0 = until stopped)", unit="s", ge=0)
    linger_s: float = setting(1.0, "keep the session open this long after the last batch (queued is not delivered)",
                              unit="s", ge=0)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")


def run_source(svc: SourceServiceConfig, stop=None, ready=None, t_start_ns: int | None = None) -> dict:
    """Publish :class:`MinimalSource` batches until done or stopped; returns :func:`publish`'s counters."""
    service = SourceService(svc)
    service.t_start_ns = t_start_ns
    return dict(service.run(stop, ready))


class PacedBatches:
    """The hooks a paced publisher of batches shares (source, simulator): its ``setup`` sets ``_batches`` (an
    iterator of ``(t_pub_ns, [(key, payload), ...])``), ``_pacer``, ``_n_batches`` and ``_matched``; the summary
    counts the counts chunks published per stream (``counts_published``, ``"<board>/<module>"``)."""

    def step(self, ctx) -> bool:
        item = next(self._batches, None)
        if item is None:
            return False
        t_pub_ns, batch = item
        self._pacer.wait(t_pub_ns, ctx.stop)
        for key, payload in batch:
            ctx.publishers.put(key, payload)
            if keys.kind_of(key) == "counts":
                # Per stream: what every downstream ledger (received + never received) must add up to.
                stream = key.split("/", 3)[3]
                counted = self.__dict__.setdefault("_counts_published", {})
                counted[stream] = counted.get(stream, 0) + 1
        self._n_batches += 1
        return True

    def counters(self) -> dict:
        return {"batches": getattr(self, "_n_batches", 0)}

    def finish(self, ctx) -> dict:
        pubs = ctx.publishers
        result = {"batches": self._n_batches, "messages": pubs.messages, "bytes": pubs.bytes,
                  "behind_max_ms": self._pacer.behind_max_ms, "matched": self._matched,
                  "counts_published": dict(sorted(getattr(self, "_counts_published", {}).items()))}
        log.info("%s stopped: %s", self.name, result)
        return result


class SourceService(PacedBatches, Service):
    """The minimal physics source: counts and housekeeping in real time.

    Ready once its session is open, before it waits (up to 30 s) for a subscriber to the counts:
    the converter started after it is what it waits for, and waiting is not latency.
    """

    name = "source"
    Config = SourceServiceConfig
    summary = "the minimal physics source (counts + housekeeping)"
    #: data time of the first sample (None: now)
    t_start_ns: int | None = None

    def duration_s(self) -> float:
        return 0.0  # duration_s is seconds of data: the batches end there

    def history_chunks(self) -> int:
        from mntes_stream.io.history import cache_chunks

        return cache_chunks(self.config.zenoh.history_seconds, self.config.source.chunk_s)

    def setup(self, ctx) -> None:
        svc, cfg = self.config, self.config.source
        params = None
        if svc.params:
            from mntes_stream.io.paramfile import load_params

            params = list(load_params(svc.params).values())
        src = MinimalSource(cfg, params)
        ctx.mark_ready()
        counts_keys = [keys.counts_key(cfg.setup, b, m) for b in range(cfg.boards) for m in range(cfg.modules)]
        self._matched = ctx.publishers.wait_matching(counts_keys, 30.0, ctx.stop)
        if not self._matched:
            log.warning("source: no subscriber for the counts yet; publishing anyway")
        src.prepare()
        start = self.t_start_ns if self.t_start_ns is not None else time.time_ns()
        log.info("source: %d detectors, %d modules, %.2f Hz, publishing", cfg.n_detectors, cfg.boards * cfg.modules,
                 cfg.sample_rate_hz)
        self._batches = src.batches(start, svc.duration_s)
        self._pacer = Pacer(svc.speed, start)
        self._n_batches = 0
