"""Recorder service: everything under ``mntes/<setup>/**`` into rotated MCAP files.

The zenoh callback only timestamps the sample and puts it on a bounded queue
(:class:`~mntes_stream.io.transport.QueueSubscriber`); the calling thread of
:func:`run_recorder` drains it into a
:class:`~mntes_stream.io.mcap_io.RotatingMcapWriter`, flushing every
``flush_interval_s`` so a killed recorder loses at most that span (plus what
was still queued). Nothing is dropped: a full queue makes the callback wait,
which BLOCK publishers feel as back-pressure; the high-water mark is reported
so a recorder that cannot keep up shows it.
"""

from __future__ import annotations

import logging
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError, MntesError, TransportError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service import dataclass_from_table, split_config, stop_on_signals

__all__ = ["RecorderConfig", "RecorderStats", "run_recorder"]

log = logging.getLogger("mntes_stream.recorder")


@dataclass(frozen=True)
class RecorderConfig:
    """What to record, where, and how safely.

    Attributes
    ----------
    setup : str
        Records ``mntes/<setup>/**`` unless ``key_expr`` is given.
    directory, prefix : str
        Files are ``<directory>/<prefix>-<seq>.mcap``.
    flush_interval_s : float
        The crash-loss bound: a killed recorder loses at most this much received data
        (plus its queue, reported as ``queue_high_water``).
    rotate_mb, rotate_s : float
        New file after this size / duration (0 disables either).
    compression : {"zstd", "lz4", "none"}
    chunk_size_kb : int
        Chunks close at this uncompressed size or at the flush cadence, whichever first.
    fsync : bool
        fsync at every flush (bounds loss on power failure too).
    duration_s : float
        Stop by itself after this long (0: run until stopped).
    log_interval_s : float
        Progress log line cadence.
    queue_messages : int
        Messages buffered between the zenoh callback and the writer; when full,
        the callback waits (back-pressure on BLOCK publishers, no loss).
    """

    setup: str = keys.DEFAULT_SETUP
    key_expr: str = ""
    directory: str = "recordings"
    prefix: str = "mntes"
    flush_interval_s: float = 1.0
    rotate_mb: float = 1024.0
    rotate_s: float = 3600.0
    compression: str = "zstd"
    chunk_size_kb: int = 4096
    fsync: bool = False
    duration_s: float = 0.0
    log_interval_s: float = 10.0
    queue_messages: int = 4096
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    def __post_init__(self):
        keys.all_key(self.setup)  # validates the setup name
        for name in ("key_expr", "directory", "prefix"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"recorder: {name} must be a string, got {getattr(self, name)!r}")
        if not keys.NAME_PATTERN.fullmatch(self.prefix):
            raise ConfigError(f"recorder: prefix {self.prefix!r} must match [A-Za-z0-9_.-]+")
        # Finite numbers only: a NaN flush interval never flushes (no crash-loss bound),
        # a NaN duration never stops.
        for name, positive in (("flush_interval_s", True), ("log_interval_s", True), ("rotate_mb", False),
                               ("rotate_s", False), ("duration_s", False)):
            v = finite_float("recorder", name, getattr(self, name))
            if v < 0 or (positive and v == 0):
                raise ConfigError(f"recorder: {name} must be {'> 0' if positive else '>= 0 (0 disables)'}, got {v}")
            object.__setattr__(self, name, v)
        for name in ("queue_messages", "chunk_size_kb"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"recorder: {name} must be an integer >= 1, got {v!r}")
        if not isinstance(self.fsync, bool):
            raise ConfigError(f"recorder: fsync must be true or false, got {self.fsync!r}")
        if self.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(f"recorder: compression must be zstd, lz4 or none, got {self.compression!r}")
        if not isinstance(self.zenoh, ZenohSettings):
            raise ConfigError("recorder: zenoh must be a ZenohSettings (the [zenoh] table)")

    @property
    def subscription(self) -> str:
        return self.key_expr or keys.all_key(self.setup)

    @classmethod
    def from_toml(cls, path: str | Path) -> RecorderConfig:
        """Read ``[recorder]`` and ``[zenoh]`` tables (see ``services/recorder.toml``)."""
        try:
            doc = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: {exc}") from None
        return cls.from_dict(doc, str(path), base_dir=str(Path(path).parent))

    @classmethod
    def from_dict(cls, doc: dict, source: str = "<config>", base_dir: str | None = None) -> RecorderConfig:
        tables, z = split_config(doc, ("recorder",), source, base_dir)
        rec = tables["recorder"]
        if "zenoh" in rec:
            raise ConfigError(f"{source}: put zenoh settings in the [zenoh] table")
        return dataclass_from_table(cls, {**rec, "zenoh": z}, f"{source} [recorder]")

    def to_metadata(self) -> dict[str, str]:
        """Flat string form stored in every file's ``mntes.recording`` metadata."""
        d = asdict(self)
        z = d.pop("zenoh")
        out = {f"recorder.{k}": str(v) for k, v in d.items()}
        out.update({f"recorder.zenoh.{k}": str(list(v) if isinstance(v, tuple) else v) for k, v in z.items()})
        out["recorder.subscription"] = self.subscription
        return out


@dataclass(frozen=True)
class RecorderStats:
    """What a recorder run wrote.

    ``by_kind`` counts messages per key kind (counts, hk, power, status,
    provenance, other); ``seq_gaps`` sums the sequence numbers skipped per
    topic (messages the recorder never received), ``seq_repeats`` the
    messages whose ``seq`` did not increase (duplicates, reordering, a
    restarted publisher); ``invalid`` the payloads that were not a valid
    envelope (recorded anyway); ``dropped_on_close`` the samples a full
    queue could not take while the subscriber was being closed.
    """

    messages: int
    payload_bytes: int
    by_kind: dict
    invalid: int
    seq_gaps: int
    seq_repeats: int
    files: tuple[str, ...]
    flushes: int
    queue_high_water: int
    dropped_on_close: int
    duration_s: float


def run_recorder(config: RecorderConfig, stop_event=None, ready=None) -> RecorderStats:
    """Record until ``stop_event`` is set, SIGINT/SIGTERM arrives, or ``duration_s`` passes.

    Parameters
    ----------
    config : RecorderConfig
    stop_event : threading.Event or multiprocessing.Event, optional
        Anything with ``is_set()``; safe to launch in a spawned process.
        SIGINT/SIGTERM also stop it when it runs in the main thread.
    ready : Event-like, optional
        Set once subscribed.

    Returns
    -------
    RecorderStats
        After the last file is finished (summary and footer written).
    """
    from mntes_stream.io.mcap_io import RotatingMcapWriter
    from mntes_stream.io.transport import QueueSubscriber

    writer = RotatingMcapWriter(
        config.directory,
        config.prefix,
        flush_interval_s=config.flush_interval_s,
        rotate_bytes=int(config.rotate_mb * (1 << 20)),
        rotate_s=config.rotate_s,
        compression=config.compression,
        chunk_size_bytes=config.chunk_size_kb * 1024,
        fsync=config.fsync,
        metadata=config.to_metadata(),
    )
    last_seq: dict[str, int] = {}
    by_kind: dict[str, int] = {}
    gaps = repeats = 0
    t_start = time.monotonic()
    next_log = t_start + config.log_interval_s

    def write(item) -> None:
        nonlocal gaps, repeats
        topic, payload, t_ns = item
        env = writer.write(topic, payload, t_ns)
        kind = keys.kind_of(topic) or "other"
        by_kind[kind] = by_kind.get(kind, 0) + 1
        if env.seq is not None:
            prev = last_seq.get(topic)
            if prev is not None:
                if env.seq > prev + 1:
                    gaps += env.seq - prev - 1
                elif env.seq <= prev:
                    repeats += 1
            last_seq[topic] = env.seq

    session = sub = None
    error: BaseException | None = None
    with stop_on_signals(stop_event) as stopping:
        try:
            session = open_session(config.zenoh)
            # The callback only timestamps and queues; a full queue makes it wait,
            # which BLOCK publishers feel as back-pressure (nothing is dropped).
            sub = QueueSubscriber(session, [config.subscription], maxsize=config.queue_messages)
            log.info("recording %s into %s", config.subscription, writer.current_path)
            if ready is not None:
                ready.set()
            while not stopping.is_set():
                if config.duration_s and time.monotonic() - t_start >= config.duration_s:
                    break
                item = sub.get(timeout_s=min(0.1, max(writer.next_tick_s(), 0.005)))
                if item is not None:
                    write(item)
                    for item in sub.drain(10_000):  # then check the stop flags once per batch
                        write(item)
                writer.tick()
                if time.monotonic() >= next_log:
                    next_log += config.log_interval_s
                    log.info("recorded %d messages (%d invalid) into %s", writer.messages, writer.invalid, writer.current_path.name)
        except BaseException as exc:  # finish the file whatever happened, then re-raise
            error = exc
        finally:
            try:
                if sub is not None:
                    for item in sub.drain():
                        write(item)
                    sub.close()
                if session is not None:
                    session.close()
                if sub is not None:
                    for item in sub.drain():
                        write(item)
            except BaseException as exc:  # a dead network or a full disk must not lose the file
                error = error or exc
            writer.close()
    if error is not None:
        if isinstance(error, (MntesError, KeyboardInterrupt)):
            raise error
        raise TransportError(f"recorder failed: {type(error).__name__}: {error}") from error
    stats = RecorderStats(
        messages=writer.messages,
        payload_bytes=writer.payload_bytes,
        by_kind=by_kind,
        invalid=writer.invalid,
        seq_gaps=gaps,
        seq_repeats=repeats,
        files=tuple(str(p) for p in writer.files),
        flushes=writer.flushes,
        queue_high_water=sub.high_water,
        dropped_on_close=sub.dropped_on_close,
        duration_s=time.monotonic() - t_start,
    )
    log.info("recorder stopped: %s", stats)
    return stats
