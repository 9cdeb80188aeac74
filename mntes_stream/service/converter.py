"""Converter service: zenoh counts + housekeeping in, power + status out (``[converter]`` config).

The loop is thin on purpose: a :class:`~mntes_stream.io.transport.QueueSubscriber`
hands ``(key, payload, t_recv_ns)`` to a :class:`~mntes_stream.service.pipeline.ConverterPipeline`
(the same object offline re-conversion uses), whose outputs go out through
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
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.messages import decode
from mntes_stream.io.transport import Publishers, QueueSubscriber, ZenohSettings, answer, open_session
from mntes_stream.service.base import Service, stop_on_signals
from mntes_stream.service.metrics import MetricsSettings
from mntes_stream.service.pipeline_config import AlignmentConfig, PipelineConfig

__all__ = ["ConverterConfig", "ConverterService", "StatusConfig", "build_converter", "run_converter", "subscriptions"]

log = logging.getLogger("mntes_stream.converter")


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
        "~/.cache/mntes-stream/tables", "banks built from params are kept here, keyed by parameters, kind and "
        "software version, so a restart loads instead of rebuilding ('' = no cache)", path=True)
    boards: tuple[int, ...] = setting((), "subscribe to these boards only ([] = every board)", ge=0)
    modules: tuple[int, ...] = setting((), "... and these modules ([] = every module)", ge=0)
    duration_s: float = setting(0.0, "stop by itself after this long (0 = run until stopped)", unit="s", ge=0)
    provenance_interval_s: float = setting(
        10.0, "re-publish parameters + table identity this often, for recorders started later (0 = at start only)",
        unit="s", ge=0)
    queue_size: int = setting(4096, "received messages waiting to be converted; beyond, back-pressure", ge=1)
    alignment: AlignmentConfig = setting(default_factory=AlignmentConfig, doc="housekeeping alignment ([alignment])")
    status: StatusConfig = setting(default_factory=StatusConfig, doc="status cadence ([status])")
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    def __post_init__(self):
        super().__post_init__()
        if not self.params and not self.tables:
            raise ConfigError("give params (a parameter file) or tables (a table bank file)")

    @classmethod
    def for_pipeline(cls, pipeline: PipelineConfig, **kw) -> ConverterConfig:
        """The config whose :attr:`pipeline` is ``pipeline`` (tests, ``up``, benchmarks)."""
        alignment = AlignmentConfig(**{f.name: getattr(pipeline, f.name) for f in fields(AlignmentConfig)})
        return cls(setup=pipeline.setup, name=pipeline.service, alignment=alignment,
                   status=StatusConfig(interval_s=pipeline.status_interval_s), **kw)

    @property
    def pipeline(self) -> PipelineConfig:
        """What the :class:`~mntes_stream.service.pipeline.ConverterPipeline` takes."""
        return PipelineConfig.from_parts(self.alignment, setup=self.setup, service=self.name,
                                         status_interval_s=self.status.interval_s)


def build_converter(cfg: ConverterConfig):
    """The ``core.convert`` converter the config asks for (tables loaded, taken from the cache, or built)."""
    from mntes_stream.core.convert import make_converter

    params = None
    if cfg.params:
        from mntes_stream.io.paramfile import load_params

        params = load_params(cfg.params)
    bank = None
    if cfg.tables:
        from mntes_stream.io.tablefile import load_bank

        bank = load_bank(cfg.tables)
    elif cfg.table_cache and cfg.kind in ("table", "grid") and params:
        bank = _cached_bank(cfg, params)
    return make_converter(cfg.kind, params, bank)


def _cached_bank(cfg: ConverterConfig, params):
    """The bank for ``params`` from the cache, or built and put there (a broken cache entry is rebuilt)."""
    import os
    from pathlib import Path

    from mntes_stream import __version__
    from mntes_stream.core.tables import TABLE_FORMAT, build_bank, params_identity
    from mntes_stream.errors import MntesError
    from mntes_stream.io.tablefile import load_bank, save_bank

    key = params_identity(list(params.values()), {"kind": cfg.kind, "format": TABLE_FORMAT, "software": __version__})
    directory = Path(os.path.expanduser(cfg.table_cache))
    path = directory / f"{cfg.kind}-{key[:32]}.npz"
    if path.exists():
        try:
            bank = load_bank(path)  # verifies the content hash: a damaged entry is not used
            log.info("table bank %s from the cache %s", bank.identity[:12], path)
            return bank
        except MntesError as exc:
            log.warning("table cache entry %s unusable (%s): rebuilding", path, exc)
    bank = build_bank(params, kind=cfg.kind)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        save_bank(bank, path)
    except OSError as exc:  # a read-only home must not stop the converter
        log.warning("cannot write the table cache %s: %s", path, exc)
    return bank


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


def subscriptions(cfg: ConverterConfig) -> list[str]:
    """Key expressions the converter subscribes to."""
    setup = cfg.setup
    boards = [str(b) for b in cfg.boards] or ["*"]
    modules = [str(m) for m in cfg.modules] or ["*"]
    exprs = [keys.counts_key(setup, b, m) for b in boards for m in modules]
    return [keys.hk_key(setup, "**")] + exprs


def run_converter(cfg: ConverterConfig, stop=None, ready=None, converter=None, heartbeat=None) -> dict:
    """Run until stopped; returns the final status as a dict.

    Parameters
    ----------
    cfg : ConverterConfig
    stop : Event-like, optional
        Set it to stop (SIGINT/SIGTERM also stop when run in the main thread).
    ready : Event-like, optional
        Set once subscribed and the provenance is out.
    converter : optional
        Use this converter instead of building one from ``cfg`` (tests, benchmarks).
    heartbeat : Heartbeat, optional
        Gets the pipeline's counters once per status.
    """
    from mntes_stream.service.pipeline import ConverterPipeline

    conv = converter if converter is not None else build_converter(cfg)
    _warm_up(conv)
    pipe = ConverterPipeline(conv, cfg.pipeline)
    beat = heartbeat.beat if heartbeat is not None else (lambda **_: None)
    t_start = time.monotonic()
    prov_key = keys.provenance_key(cfg.setup)
    status_key = keys.status_key(cfg.setup, cfg.name)
    with stop_on_signals(stop) as stopping, open_session(cfg.zenoh) as session:
        pubs = Publishers(session)
        # Channel mode: samples are read on this thread, no callback thread competing for the GIL.
        # Housekeeping first (subscriptions() lists it first): a batch's readings before its counts.
        sub = QueueSubscriber(session, subscriptions(cfg), maxsize=cfg.queue_size, stop=stopping, mode="channel")
        # Provenance on request too: a recorder started later asks instead of waiting for the next one.
        answer(session, prov_key, pipe.provenance_bytes())
        try:
            pubs.put(prov_key, pipe.provenance_bytes())
            next_prov = time.monotonic() + (cfg.provenance_interval_s or float("inf"))
            log.info("converter %s: %d detectors, kind %s, tables %s; subscribed to %s",
                     cfg.name, len(conv.detector_ids), conv.kind, str(conv.identity)[:12], subscriptions(cfg))
            if ready is not None:
                ready.set()
            while not stopping.is_set():
                if cfg.duration_s and time.monotonic() - t_start >= cfg.duration_s:
                    break
                item = sub.get(timeout_s=0.05)
                # Each output goes out as soon as it exists: a burst of chunks must not wait for its last one.
                outs = pipe.tick(time.time_ns()) if item is None else pipe.handle(*item)
                for key, payload in outs:
                    pubs.put(key, payload)
                    if key == status_key:  # what the status says, in the heartbeat too (ps)
                        st = decode(payload)
                        beat(**pipe.counters.as_dict(), chunks_lost=st.chunks_lost, latency_p99_ms=st.latency_p99_ms,
                             bad_messages=sum(st.bad_messages.values()), samples_per_s=st.rate_msamples_per_s * 1e6)
                if time.monotonic() >= next_prov:
                    pubs.put(prov_key, pipe.provenance_bytes())
                    next_prov = time.monotonic() + cfg.provenance_interval_s
            # Stop receiving, convert what is already here, say so, then close.
            sub.close()
            for item in sub.drain():
                for key, payload in pipe.handle(*item):
                    pubs.put(key, payload)
            for key, payload in pipe.flush():
                pubs.put(key, payload)
        finally:
            sub.close()
            pubs.close()
    final = pipe.status()
    log.info("converter stopped: %d chunks converted, %d lost, %d bad messages",
             final.chunks_converted, final.chunks_lost, sum(final.bad_messages.values()))
    return {f.name: getattr(final, f.name) for f in fields(final)} | {"dropped_on_close": sub.dropped_on_close}


class ConverterService(Service):
    """Counts + housekeeping in, optical power + status + provenance out."""

    name = "converter"
    Config = ConverterConfig
    summary = "counts + housekeeping in, power + status + provenance out"

    def owns(self) -> dict:
        return {"boards": list(self.config.boards) or "*", "modules": list(self.config.modules) or "*"}

    def run(self, stop=None, ready=None) -> dict:
        return run_converter(self.config, stop, ready, heartbeat=self.heartbeat)
