"""Converter service: zenoh counts + housekeeping in, power + status out (``[converter]`` config).

The loop is thin on purpose: a :class:`~mntes_stream.io.transport.QueueSubscriber`
hands ``(key, payload, t_recv_ns)`` to a :class:`~mntes_stream.pipeline.pipeline.ConverterPipeline`
through its :class:`~mntes_stream.pipeline.runner.Runner` (the same ones offline
re-conversion and the G3 module use), whose outputs go out through
BLOCK publishers. Provenance (parameters, table identity) is published at
start and every ``provenance_interval_s`` with identical bytes, so a recorder
started later still gets it. Stops on SIGINT/SIGTERM, a stop event or
``duration_s``; pending chunks are flushed and the session closed on the way out.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, fields

from mntes_stream.core.convert import CONVERTER_KINDS
from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.core.shards import Shard
from mntes_stream.core.uncertainty import UncertaintySettings
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.cache import DEFAULT_MAX_MB
from mntes_stream.io.messages import decode
from mntes_stream.io.transport import QueueSubscriber, ZenohSettings, answer
from mntes_stream.pipeline.build import ConverterSpec, default_table_cache
from mntes_stream.pipeline.config import SCALAR_SENSORS, AlignmentConfig, PipelineConfig
from mntes_stream.service.base import Service, announced
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["ConverterConfig", "ConverterService", "StatusConfig", "run_converter", "subscriptions"]

log = logging.getLogger("mntes_stream.converter")
_TRIM_EVERY_S = 2.0  # an idle converter gives freed heap back at most this often (service/heap.py trim_heap)


@dataclass(frozen=True)
class StatusConfig(Settings):
    """The ``[status]`` table."""

    interval_s: float = setting(1.0, "status message cadence", unit="s", gt=0)


@dataclass(frozen=True)
class ConverterConfig(Settings):
    """Everything ``services/converter.toml`` says: ``[converter]``, ``[alignment]``, ``[status]``, ``[zenoh]``."""

    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/counts|hk|power|status|provenance",
                         pattern=NAME_PATTERN)
    name: str = setting("converter", "service name: status on mntes/<setup>/status/<name>", pattern=NAME_PATTERN)
    params: str = setting("", "detector parameter file (TOML); optional when tables is given", path=True)
    kind: str = setting("table", "conversion kind (core/convert.py)", choices=CONVERTER_KINDS)
    tables: str = setting("", "table bank file (mntes-stream tables build); '' = build from params at start",
                          path=True)
    table_cache: str = setting(
        default_table_cache(), "banks built from params, and the converter as built "
        "(pipeline/snapshot.py), are kept here keyed by parameters, kind and software version, so a restart loads "
        "instead of rebuilding ('' = no cache; `mntes-stream cache` shows and clears it)", path=True)
    table_cache_max_mb: float = setting(DEFAULT_MAX_MB, "the table cache's size cap: after each write the least "
                                        "recently used entries beyond it are removed", unit="MB", gt=0)
    boards: tuple[int, ...] = setting((), "own these boards only ([] = every board)", ge=0)
    modules: tuple[int, ...] = setting((), "... and these modules ([] = every module)", ge=0)
    shard: str = setting("", "i/N: own the streams (board, module) whose CRC-32 falls in bucket i of N "
                         "('' = all); only their parameters are loaded, only their keys subscribed")
    standby: bool = setting(False, "hot standby: convert streams another converter claimed first without "
                            "publishing them, and take over when it goes (else: a conflict, reported)")
    holdback_s: float = setting(2.0, "power held back on a claimed stream is kept this long, published at a "
                                "takeover if its publisher never did", unit="s", ge=0)
    duration_s: float = setting(0.0, "stop by itself after this long (0 = run until stopped)", unit="s", ge=0)
    provenance_interval_s: float = setting(
        10.0, "re-publish parameters + table identity this often, for recorders started later (0 = at start only)",
        unit="s", ge=0)
    queue_size: int = setting(4096, "received messages waiting to be converted; beyond, back-pressure", ge=1)
    queue_mb: float = setting(64.0, "... and at most this much payload: a flood of big messages (valid or not) "
                              "cannot fill memory; beyond, back-pressure", unit="MB", gt=0)
    threads: int = setting(1, "threads converting a large batch side by side (the compiled kernel releases the "
                           "GIL): on a host with a core to spare, lower latency at high rates", ge=1, le=64)
    overload_after_s: float = setting(
        10.0, "a real overload: behind (every batch full) without a break for this long; only then are chunks "
        "further behind than [alignment] max_lag_s set aside (converted late when there is time, shed beyond "
        "set_aside_mb). A shorter stall or latency spike sheds nothing", unit="s", gt=0)
    set_aside_mb: float = setting(256.0, "counts held under overload for late conversion; beyond, the oldest are "
                                  "shed (in the ledger; their counts are recorded for offline convert)", unit="MB", gt=0)
    batch_max: int = setting(512, "received messages handled as one batch at most (chunks of one batch that share "
                             "sample times are converted in one call)", ge=1)
    checkpoint: str = setting("", "each stream's newest sequence number is kept in this file at every status, so "
                              "a restart reports the chunks it missed (service/checkpoint.py; '' = none)", path=True)
    low_responsivity: str = setting(
        "auto", "flag LOW_RESPONSIVITY (sigma_P above its tolerance, as [uncertainty] says) on every sample: 'auto' "
        "where it costs no second pass (the compiled table kernel flags it in its own pass, benchmarks/README.md; "
        "other kinds: not flagged, said at start), 'on' everywhere (other kinds: by the sigma_P pass, about a "
        "conversion's cost), 'off'", choices=("auto", "on", "off"))
    sigma_p: bool = setting(False, "publish each sample's power uncertainty sigma_P (readout noise through the "
                            "local responsivity) and flag LOW_RESPONSIVITY, as [uncertainty] says (costs about as "
                            "much as the conversion itself)")
    alignment: AlignmentConfig = setting(default_factory=AlignmentConfig, doc="housekeeping alignment ([alignment])")
    uncertainty: UncertaintySettings = setting(default_factory=UncertaintySettings,
                                               doc="readout noise and LOW_RESPONSIVITY ([uncertainty]: "
                                                   "low_responsivity, sigma_p)")
    status: StatusConfig = setting(default_factory=StatusConfig, doc="status cadence ([status])")
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    def __post_init__(self):
        super().__post_init__()
        if not self.params and not self.tables:
            raise ConfigError("give params (a parameter file) or tables (a table bank file)")
        # Parsed once, here at the boundary (checks 0 <= i < N); everything after takes the Shard.
        shard = Shard.parse(self.shard)
        object.__setattr__(self, "_shard", shard)
        if not shard.whole and self.name == "converter":  # shards of one setup need names of their own
            object.__setattr__(self, "name", f"converter-{shard.index}of{shard.count}")

    @property
    def uncertainty_used(self) -> UncertaintySettings | None:
        """``uncertainty`` where LOW_RESPONSIVITY is flagged or sigma_P published, else None."""
        return self.uncertainty if (self.low_responsivity != "off" or self.sigma_p) else None

    @property
    def shard_parsed(self) -> Shard:
        """``shard`` as the :class:`~mntes_stream.core.shards.Shard` it names (``Shard()``: the whole focal plane)."""
        return self._shard

    @property
    def partial(self) -> bool:
        """True when this converter owns part of the focal plane (boards, modules or a shard)."""
        return bool(self.boards or self.modules or not self.shard_parsed.whole)

    @classmethod
    def for_pipeline(cls, pipeline: PipelineConfig, **kw) -> ConverterConfig:
        """The config whose :attr:`pipeline` is ``pipeline`` (tests, ``up``, benchmarks)."""
        alignment = AlignmentConfig(**{f.name: getattr(pipeline, f.name) for f in fields(AlignmentConfig)})
        return cls(setup=pipeline.setup, name=pipeline.service, alignment=alignment,
                   status=StatusConfig(interval_s=pipeline.status_interval_s), **kw)

    @property
    def spec(self) -> ConverterSpec:
        """What :func:`~mntes_stream.pipeline.build.build_converter` builds this converter from."""
        flags_low = {"on": "yes", "auto": "if_fused", "off": "no"}[self.low_responsivity]
        return ConverterSpec(kind=self.kind, params_file=self.params, tables=self.tables, table_cache=self.table_cache,
                             table_cache_max_mb=self.table_cache_max_mb, boards=self.boards, modules=self.modules,
                             shard=self.shard, gradients="yes" if self.sigma_p else flags_low)

    @property
    def pipeline(self) -> PipelineConfig:
        """What the :class:`~mntes_stream.pipeline.pipeline.ConverterPipeline` takes."""
        return PipelineConfig.from_parts(self.alignment, setup=self.setup, service=self.name,
                                         status_interval_s=self.status.interval_s)


def _warm_up(conv) -> None:
    """One tiny conversion before going live: compiled kernels are built now, not on the first chunk."""
    import numpy as np

    from mntes_stream.core.convert import EnvironmentBlock

    if not conv.detector_ids:
        return
    p = getattr(conv, "params", None)
    t_bath = float(p[0].t_bath_k) if p else 0.1
    counts = np.ones((1, 2), dtype=np.int32)
    try:
        conv.convert(conv.detector_ids[:1], counts, counts, EnvironmentBlock(np.full(2, t_bath), np.zeros(2)))
    except Exception as exc:  # a converter that cannot convert shows it on real data, with a status
        log.warning("converter warm-up failed: %s", exc)


def subscriptions(cfg: ConverterConfig, streams=None) -> list[str]:
    """Key expressions the converter subscribes to: housekeeping first, then counts.

    ``streams``: the ``(board, module)`` streams it owns; a converter of part of the
    focal plane subscribes to exactly their counts and bias, and the scalar sensors.
    """
    setup = cfg.setup
    if streams is not None and cfg.partial:
        hk = [keys.hk_key(setup, s) for s in SCALAR_SENSORS]
        hk += [keys.hk_key(setup, keys.hk_sensor(s, b, m)) for b, m in streams for s in ("bias", "readout_flags")]
        return hk + [keys.counts_key(setup, b, m) for b, m in streams]
    boards = [str(b) for b in cfg.boards] or ["*"]
    modules = [str(m) for m in cfg.modules] or ["*"]
    exprs = [keys.counts_key(setup, b, m) for b in boards for m in modules]
    return [keys.hk_key(setup, "**")] + exprs


def run_converter(cfg: ConverterConfig, stop=None, ready=None, converter=None) -> dict:
    """Run until stopped; returns the final status as a dict.

    ``stop`` and ``ready`` are Event-like: set ``stop`` to stop (SIGINT/SIGTERM also stop when run in
    the main thread); ``ready`` is set once subscribed, the streams claimed and the provenance out.
    ``converter`` is used instead of building one from ``cfg`` (tests, benchmarks).
    """
    service = ConverterService(cfg)
    service.prebuilt = converter
    return dict(service.run(stop, ready))


def _owning(cfg: ConverterConfig, streams, owner) -> str:
    if streams is None:
        return "every stream"
    held = f", {len(owner.held)} held back (claimed first by another converter)" if owner and owner.held else ""
    what = f"shard {cfg.shard_parsed}" if cfg.shard else "boards/modules" if cfg.partial else "the focal plane"
    return f"{what}: {len(streams)} stream(s){held}"


class _PowerWatch:
    """The power other converters publish on this one's streams (remote origin only), for takeovers."""

    def __init__(self, session, owner, setup: str):
        import zenoh

        self._subs = []
        for key in owner.watch_keys(setup):
            self._subs.append(session.declare_subscriber(
                key, lambda s: owner.seen(str(s.key_expr), s.payload.to_bytes()),
                allowed_origin=zenoh.Locality.REMOTE))

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # the session is closing
                pass
        self._subs.clear()


class ConverterService(Service):
    """Counts + housekeeping in, optical power + status + provenance out."""

    name = "converter"
    Config = ConverterConfig
    summary = "counts + housekeeping in, power + status + provenance out"

    _ownership = None
    #: a converter to use instead of building one from the config (tests, benchmarks: run_converter)
    prebuilt = None

    def owns(self) -> dict:
        if self._ownership is not None:
            return self._ownership.status()
        return {"boards": list(self.config.boards) or "*", "modules": list(self.config.modules) or "*",
                "shard": str(self.config.shard_parsed)}

    def history_chunks(self) -> int:
        from mntes_stream.io.history import POWER_CHUNK_S, cache_chunks

        return cache_chunks(self.config.zenoh.history_seconds, POWER_CHUNK_S)

    def setup(self, ctx) -> None:
        from mntes_stream.io.claims import StreamClaims
        from mntes_stream.pipeline import ConverterPipeline
        from mntes_stream.pipeline.build import build_converter, owned_part
        from mntes_stream.pipeline.housekeeping import known_modules
        from mntes_stream.pipeline.runner import Runner
        from mntes_stream.service.checkpoint import load_checkpoint
        from mntes_stream.service.ownership import Ownership, owns_summary

        cfg, converter = self.config, self.prebuilt
        if converter is None:
            # A restart takes the converter its last start built (same files, kind, part, software) from the cache.
            built = build_converter(cfg.spec, building=lambda text: announced(ctx.progress, text))
            conv, streams, params_toml = built.converter, built.streams, built.params_toml
        else:
            conv, streams = converter, owned_part(cfg.spec)[1] if cfg.params else None
            params_toml = None
            if streams is None:
                modules = known_modules(conv.detector_ids)
                streams = sorted(modules) if modules is not None else None
        with announced(ctx.progress, "compiling the conversion kernels (after an install or upgrade; cached "
                       "for the next start)"):
            _warm_up(conv)
        summary = owns_summary(cfg.shard_parsed, cfg.boards, cfg.modules, streams) if streams is not None else {}
        self._pipe = pipe = ConverterPipeline(conv, cfg.pipeline, params_toml=params_toml,
                                              owns=summary if cfg.partial else None,
                                              threads=cfg.threads, set_aside_bytes=int(cfg.set_aside_mb * 1e6),
                                              uncertainty=cfg.uncertainty_used, sigma_p=cfg.sigma_p,
                                              only_fused=cfg.low_responsivity == "auto")
        self._runner = Runner.around(pipe)  # batches are what piled up (step); ticks and late power when idle
        # The state of the last checkpoint written (the floor of the next one): at start, what the previous
        # converter surely sent (its checkpoint's floor).
        self._ckpt_sent: dict = {}
        if cfg.checkpoint and (ckpt := load_checkpoint(cfg.checkpoint, cfg.setup, cfg.name)) is not None:
            self._ckpt_sent = {k: v[2:] if len(v) > 2 else v for k, v in ckpt[0].items() if len(v) < 3 or v[2] >= 0}
            n = pipe.resume_sequences(ckpt[0])
            log.info("converter %s: %d streams continue from the checkpoint of %.1f s ago (%s); what was published "
                     "since counts as missed", cfg.name, n, (time.time_ns() - ckpt[1]) / 1e9, cfg.checkpoint)
        self._prov_key = keys.provenance_key(cfg.setup)
        self._status_key = keys.status_key(cfg.setup, cfg.name)
        topics = subscriptions(cfg, streams)
        self._claims = self._watch = None
        owner = None
        session = ctx.session
        # A blocking receive: zenoh's thread only queues each sample (bounded: a full queue makes it wait, which
        # pushes back on the publishers), and this thread sleeps until one is there instead of polling.
        # Each key expression's samples come in arrival order; housekeeping and counts are separate key
        # expressions with a callback thread each, so a step's counts may come before its housekeeping: the
        # housekeeping stage holds them until it comes ([alignment] hk_wait_s).
        # What the sources' caches hold (io/history.py) comes first, so a converter restarted after a crash
        # converts what was published while it was down (with a checkpoint, what it had converted is dropped as
        # a duplicate); samples missed on the way (a router restarting) are recovered from the caches too, and a
        # key whose history zenoh-ext dropped is asked again (io/history.HistoryTopUp; bench chaos: 3 streams of 4).
        self._sub = QueueSubscriber(session, topics, maxsize=cfg.queue_size, stop=ctx.stop, mode="callback",
                                    max_bytes=int(cfg.queue_mb * 1e6), recover="history",
                                    sources=True)  # each chunk's publisher: two on one key
        try:
            # Provenance on request too: a recorder started later asks instead of waiting for the next one.
            answer(session, self._prov_key, pipe.provenance_bytes())
            if streams:
                self._claims = StreamClaims(session, cfg.setup, cfg.name, streams, standby=cfg.standby)
                owner = Ownership(self._claims, summary, cfg.standby, cfg.holdback_s, warn=self.heartbeat.warn)
                pipe.owns_status = owner.status
                self._watch = _PowerWatch(session, owner, cfg.setup)
                self._ownership = owner
            ctx.publishers.put(self._prov_key, pipe.provenance_bytes())
        except BaseException:
            self._close()
            raise
        self._next_prov = time.monotonic() + (cfg.provenance_interval_s or float("inf"))
        self._behind_since = None  # monotonic time since when every batch was full (None: caught up)
        self._next_trim = time.monotonic() + _TRIM_EVERY_S
        log.info("converter %s: %d detectors, kind %s, tables %s; %s; subscribed to %s", cfg.name,
                 len(conv.detector_ids), conv.kind, str(conv.identity)[:12],
                 _owning(cfg, streams, owner), topics if len(topics) <= 8 else f"{len(topics)} key expressions")

    def step(self, ctx) -> bool:
        from mntes_stream.service.checkpoint import save_checkpoint
        from mntes_stream.service.heap import trim_heap

        cfg, pipe, sub, owner, pubs = self.config, self._pipe, self._sub, self._ownership, ctx.publishers
        item = sub.get(timeout_s=0.05 if not pipe.set_aside else 0.0)
        # What has arrived is handled as one batch (converted together: less work per chunk); nothing
        # waits for more to come, so a batch is what piled up while the previous one was converted.
        now = time.time_ns()
        if item is None:  # nothing waiting: time for what was set aside under overload
            self._behind_since, pipe.overloaded = None, False
            outs = self._runner.idle(now, cfg.batch_max // 8 or 1)
            if not pipe.set_aside and time.monotonic() >= self._next_trim:
                # Idle: what a burst (a flood of big messages in the queue) left freed in glibc's heaps goes back.
                trim_heap()
                self._next_trim = time.monotonic() + _TRIM_EVERY_S
        else:
            # A batch in bytes too: it leaves the queue (whose room fills again), so at most 2 x queue_mb is held.
            cap = int(cfg.queue_mb * 1e6)
            batch = [item, *sub.drain(cfg.batch_max - 1, max_bytes=max(1, cap - len(item[1])))]
            full = len(batch) >= cfg.batch_max or sum(len(b[1]) for b in batch) >= cap
            mono = time.monotonic()
            self._behind_since = (self._behind_since or mono) if full else None
            pipe.overloaded = self._behind_since is not None and mono - self._behind_since >= cfg.overload_after_s
            outs = self._runner.feed_batch(batch, now)
        outs = [(k, p) for k, p, _ in outs]
        if owner is not None:
            outs = owner.refresh() + [o for o in outs if owner.allow(o[0], o[1], now)]
        for key, payload in outs:
            # The checkpoint before the status: what a status says converted is on disk when it is seen.
            if key == self._status_key and cfg.checkpoint:
                # Floored at the previous status's numbers: what was converted since may still sit in zenoh's
                # queue, unsent, if this process is killed now (service/checkpoint.py).
                state = pipe.sequence_state()
                save_checkpoint(cfg.checkpoint, cfg.setup, cfg.name, state, floor=self._ckpt_sent)
                self._ckpt_sent = state
            pubs.put(key, payload)
            if key == self._status_key:  # what the status says, in the heartbeat too (ps)
                st = decode(payload)
                self.heartbeat.beat(**pipe.counters.as_dict(), chunks_lost=st.chunks_lost,
                                    latency_p99_ms=st.latency_p99_ms, arrival_p99_ms=st.arrival_p99_ms,
                                    bad_messages=sum(st.bad_messages.values()),
                                    samples_per_s=st.rate_msamples_per_s * 1e6, conflicts=st.conflicts)
        if time.monotonic() >= self._next_prov:
            pubs.put(self._prov_key, pipe.provenance_bytes())
            self._next_prov = time.monotonic() + cfg.provenance_interval_s
        return True

    def _close(self) -> None:
        self._sub.close()
        if self._watch is not None:
            self._watch.close()
        if self._claims is not None:
            self._claims.close()  # a standby takes over at once, not after the session's lease

    def finish(self, ctx) -> dict:
        from mntes_stream.service.checkpoint import save_checkpoint

        cfg, pipe, sub, owner = self.config, self._pipe, self._sub, self._ownership
        try:  # stop receiving, convert what is already here, say so, then close
            sub.close()
            outs = self._runner.feed_batch(list(sub.drain())) + self._runner.finish()
            for key, payload, _ in outs:
                if owner is None or owner.allow(key, payload, time.time_ns()):
                    ctx.publishers.put(key, payload)
            if cfg.checkpoint:
                save_checkpoint(cfg.checkpoint, cfg.setup, cfg.name, pipe.sequence_state())
        finally:
            self._close()
        final = pipe.status()
        line = pipe.ledger_now().line()
        log.info("converter %s stopped: %s", cfg.name, line)
        unconfirmed = {f"{b}/{m}": {"first_seq": lo, "last_seq": hi, "chunks": n}
                       for (b, m), (lo, hi, n) in sorted(pipe.unconfirmed_before_restart().items())}
        words = unconfirmed_line(unconfirmed) if unconfirmed else ""
        if words:
            log.warning("converter %s: %s", cfg.name, words)
        # The receive queue's peak in bytes: bounded by queue_mb whatever comes (a flood of big messages).
        return {f.name: getattr(final, f.name) for f in fields(final)} | {
            "dropped_on_close": sub.dropped_on_close, "ledger_line": line, "kernel_cpu_s": round(pipe.kernel_cpu_s, 4),
            "chunks_per_kernel_call": pipe.chunks_per_kernel_call,
            "queue_high_water_mb": round(sub.high_water_bytes / 1e6, 3), "unconfirmed_before_restart": unconfirmed,
            "ledger_note": f"; WARNING {words}" if words else ""}


def unconfirmed_line(unconfirmed: dict) -> str:
    """In words: ``{"b/m": {"first_seq", "last_seq", "chunks"}}`` of ``ConverterPipeline.unconfirmed_before_restart``."""
    n = sum(u["chunks"] for u in unconfirmed.values())
    where = ", ".join(f"{k} seq {u['first_seq']}..{u['last_seq']}" for k, u in list(unconfirmed.items())[:4])
    more = f" and {len(unconfirmed) - 4} streams more" if len(unconfirmed) > 4 else ""
    return (f"{n} chunks converted before the restart ({where}{more}) were not taken again (the sources no longer "
            "held them): whether their power went out is unknown here; a recording's coverage line names any "
            "without power")
