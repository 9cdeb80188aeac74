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
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.transport import Publishers, QueueSubscriber, ZenohSettings, open_session
from mntes_stream.service import split_config, stop_on_signals
from mntes_stream.service.pipeline import PipelineConfig

__all__ = ["ConverterConfig", "build_converter", "run_converter", "subscriptions"]

log = logging.getLogger("mntes_stream.converter")


@dataclass(frozen=True)
class ConverterConfig:
    """Everything ``services/converter.toml`` says.

    Attributes
    ----------
    params : str
        Detector parameter file (``io.paramfile``); optional when ``tables`` is
        given (the bank carries its parameters).
    kind : str
        ``core.convert`` kind: table, grid, exact, linear, electrical.
    tables : str
        Table bank file (``io.tablefile``); built from ``params`` when empty.
    boards, modules : tuple of int
        Subscribe to these only (empty: all).
    duration_s : float
        Stop by itself after this long (0: until stopped).
    provenance_interval_s : float
        Re-publish the provenance this often (0: only at start).
    pipeline : PipelineConfig
        ``[alignment]`` and ``[status]`` tables; ``setup`` and ``name`` come from ``[converter]``.
    """

    params: str = ""
    kind: str = "table"
    tables: str = ""
    boards: tuple[int, ...] = ()
    modules: tuple[int, ...] = ()
    duration_s: float = 0.0
    provenance_interval_s: float = 10.0
    queue_size: int = 4096
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    @property
    def setup(self) -> str:
        return self.pipeline.setup

    @classmethod
    def from_toml(cls, path: str | Path) -> "ConverterConfig":
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: {exc}") from None
        return cls.from_dict(doc, str(path), base_dir=path.parent)

    @classmethod
    def from_dict(cls, doc: dict, source: str = "<config>", base_dir: str | Path | None = None) -> "ConverterConfig":
        """From a parsed TOML document; relative file names resolve against ``base_dir``."""
        tables, z = split_config(doc, ("converter", "alignment", "status"), source, base_dir)
        conv, pipe, status = tables["converter"], tables["alignment"], tables["status"]
        bad_status = set(status) - {"interval_s"}
        if bad_status:
            raise ConfigError(f"{source} [status]: unknown key(s) {sorted(bad_status)} (known: ['interval_s'])")
        if "interval_s" in status:
            pipe["status_interval_s"] = status["interval_s"]
        for name, target in (("setup", "setup"), ("name", "service")):
            if name in conv:
                pipe[target] = conv.pop(name)
        for name in ("params", "tables"):
            if conv.get(name) and base_dir is not None and not Path(conv[name]).is_absolute():
                conv[name] = str(Path(base_dir) / conv[name])
        known = {f.name for f in fields(cls)} - {"pipeline", "zenoh"}
        unknown = set(conv) - known
        if unknown:
            raise ConfigError(f"{source} [converter]: unknown key(s) {sorted(unknown)} (known: {sorted(known | {'setup', 'name'})})")
        for name in ("boards", "modules"):
            if name in conv:
                v = conv[name]
                if isinstance(v, str) or not all(isinstance(x, int) and x >= 0 for x in v):
                    raise ConfigError(f"{source} [converter]: {name} must be a list of integers >= 0")
                conv[name] = tuple(v)
        pipeline = PipelineConfig.from_dict(pipe, f"{source} [alignment]")
        try:
            return cls(pipeline=pipeline, zenoh=z, **conv)
        except TypeError as exc:
            raise ConfigError(f"{source} [converter]: {exc}") from None

    def __post_init__(self):
        if not self.params and not self.tables:
            raise ConfigError("converter: give params (a parameter file) or tables (a table bank file)")
        if self.duration_s < 0 or self.provenance_interval_s < 0:
            raise ConfigError("converter: duration_s and provenance_interval_s must be >= 0")
        if self.queue_size < 1:
            raise ConfigError("converter: queue_size must be >= 1")


def build_converter(cfg: ConverterConfig):
    """The ``core.convert`` converter the config asks for (tables loaded or built)."""
    from mntes_stream.core.convert import make_converter

    params = None
    if cfg.params:
        from mntes_stream.io.paramfile import load_params

        params = load_params(cfg.params)
    bank = None
    if cfg.tables:
        from mntes_stream.io.tablefile import load_bank

        bank = load_bank(cfg.tables)
    return make_converter(cfg.kind, params, bank)


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


def run_converter(cfg: ConverterConfig, stop=None, ready=None, converter=None) -> dict:
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
    """
    from mntes_stream.service.pipeline import ConverterPipeline

    conv = converter if converter is not None else build_converter(cfg)
    _warm_up(conv)
    pipe = ConverterPipeline(conv, cfg.pipeline)
    t_start = time.monotonic()
    prov_key = keys.provenance_key(cfg.setup)
    with stop_on_signals(stop) as stopping, open_session(cfg.zenoh) as session:
        pubs = Publishers(session)
        # Channel mode: samples are read on this thread, no callback thread competing for the GIL.
        # Housekeeping first (subscriptions() lists it first): a batch's readings before its counts.
        sub = QueueSubscriber(session, subscriptions(cfg), maxsize=cfg.queue_size, stop=stopping, mode="channel")
        try:
            pubs.put(prov_key, pipe.provenance_bytes())
            next_prov = time.monotonic() + (cfg.provenance_interval_s or float("inf"))
            log.info("converter %s: %d detectors, kind %s, tables %s; subscribed to %s",
                     cfg.pipeline.service, len(conv.detector_ids), conv.kind, str(conv.identity)[:12], subscriptions(cfg))
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
