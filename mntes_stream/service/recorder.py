"""Recorder service: everything under ``mntes/<setup>/**`` into rotated MCAP files.

The zenoh callback only timestamps the sample and puts it on a bounded queue
(:class:`~mntes_stream.io.transport.QueueSubscriber`); the calling thread of
:class:`RecorderService` (its ``step``) drains it into a
:class:`~mntes_stream.service.recorder_sink.RecorderSink`, which reads each
payload's header (never decoding its arrays), books it and hands the bytes to
a writer thread (:class:`~mntes_stream.io.mcap.background.BackgroundMcapWriter`:
framing, compression, disk), which flushes every ``flush_interval_s`` so a
killed recorder loses at most that span (plus what was still queued). Nothing
is dropped: a full queue makes the callback (or the hand-over) wait, which
BLOCK publishers feel as back-pressure; high-water marks and waits are
reported so a recorder that cannot keep up shows it, and so is its CPU per
million samples.

Every counts chunk is in the recorder's ledger (``io.mcap.ledger.RecordingBook``:
recorded, duplicate, malformed, never received), beside the power it saw (live,
late) and each converter's newest status ledger; the ledger is written into
every file at its close (metadata ``mntes.ledger``) and stated in the final
statistics (``ledger``, ``ledger_line``). zenoh peers do not forward for each
other: a peer recorder that connects to one peer turns gossip scouting on
unless a layer names it, so it reaches the source too; a stream whose power
comes without its counts is warned about (log, heartbeat ``power_only``, stats).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.core.shards import Shard
from mntes_stream.errors import MntesError, TransportError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

# When a converter's provenance is asked again (its status came and it did not): after 2 s, then twice as long each
# time it is still missing, up to 30 s (one query each time, answered by every converter).
_ASK_AGAIN_S, _ASK_AGAIN_MAX_S = 2.0, 30.0

__all__ = ["RecorderConfig", "RecorderService", "RecorderStats", "cost_line", "final_line", "run_recorder"]

log = logging.getLogger("mntes_stream.recorder")


@dataclass(frozen=True)
class RecorderConfig(Settings):
    """What to record, where, and how safely: the ``[recorder]`` and ``[zenoh]`` tables.

    A killed recorder loses at most ``flush_interval_s`` of received data
    (plus its queues, reported as ``queue_high_water`` and ``writer_queue_high_water``).
    """

    setup: str = setting(keys.DEFAULT_SETUP, "records mntes/<setup>/** unless key_expr is given", pattern=NAME_PATTERN)
    key_expr: str = setting("", "record this key expression instead (e.g. mntes/lab/**)")
    directory: str = setting("recordings", "files: <directory>/<prefix>-<seq>.mcap; seq continues after existing files",
                             path=True)
    prefix: str = setting("mntes", "file name prefix", pattern=NAME_PATTERN)
    flush_interval_s: float = setting(1.0, "crash-loss bound: SIGKILL loses at most this much received data",
                                      unit="s", gt=0)
    rotate_mb: float = setting(1024.0, "new file after this size (0: never)", unit="MiB", ge=0)
    rotate_s: float = setting(3600.0, "... or after this long (0: never)", unit="s", ge=0)
    # lz4 in 256 KiB chunks: measured cheapest per sample with compression (bench recording --sweep, docs/recording.md)
    compression: str = setting("lz4", "chunk compression (zstd: 14 % smaller files for 1.7x the recorder's CPU)",
                               choices=("zstd", "lz4", "none"))
    chunk_size_kb: int = setting(256, "chunks close at this uncompressed size or at the flush cadence", unit="KiB",
                                 ge=1)
    fsync: bool = setting(False, "fsync each flush, so the loss bound also holds on power loss")
    duration_s: float = setting(0.0, "stop by itself after this long (0: run until stopped)", unit="s", ge=0)
    log_interval_s: float = setting(10.0, "progress log cadence", unit="s", gt=0)
    queue_messages: int = setting(4096, "buffer between zenoh and the writer; when full, publishers are slowed "
                                        "(BLOCK), never dropped", ge=1)
    queue_mb: float = setting(256.0, "... and at most this much payload: big messages cannot fill memory", unit="MB",
                              gt=0)
    writer_queue_mb: float = setting(64.0, "buffer between the receive thread and the writer thread (framing, "
                                     "compression, disk); when full, receiving waits (counted: writer_queue_full)",
                                     unit="MB", gt=0)
    shard: str = setting("", "i/N: record the counts, power and bias of the streams (board, module) in bucket i "
                         "of N (as converter shards split them); shard 0 also records everything else, every shard "
                         "the provenance. '' = everything. Files: <prefix>-shard<i>of<N>-<seq>.mcap")
    unconverted_after_s: float = setting(2.0, "a stream whose counts come with no power for this long is "
                                         "reported unconverted (heartbeat, log)", unit="s", gt=0)
    foxglove_channels: bool = setting(False, "also write json channels the Foxglove app reads (power of the first "
                                             "detectors per module, flag rates, housekeeping, status; foxglove/)")
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    def __post_init__(self):
        super().__post_init__()
        # Parsed once, here at the boundary (checks i/N); everything after takes the Shard.
        object.__setattr__(self, "_shard", Shard.parse(self.shard))

    @property
    def shard_parsed(self) -> Shard:
        """``shard`` as the :class:`~mntes_stream.core.shards.Shard` it names (``Shard()``: everything)."""
        return self._shard

    @property
    def subscription(self) -> str:
        return self.key_expr or keys.all_key(self.setup)

    @property
    def file_prefix(self) -> str:
        """``prefix``, or ``<prefix>-shard<i>of<N>`` for a recorder shard: one file set per shard."""
        shard = self.shard_parsed
        return self.prefix if shard.whole else f"{self.prefix}-shard{shard.index}of{shard.count}"

    def to_metadata(self) -> dict[str, str]:
        """Flat string form stored in every file's ``mntes.recording`` metadata."""
        d = asdict(self)
        z = d.pop("zenoh")
        d.pop("metrics")
        out = {f"recorder.{k}": str(v) for k, v in d.items()}
        out.update({f"recorder.zenoh.{k}": str(list(v) if isinstance(v, tuple) else v) for k, v in z.items()})
        out["recorder.subscription"] = self.subscription
        return out


@dataclass(frozen=True)
class RecorderStats:
    """What a recorder run wrote.

    ``by_kind`` counts messages per key kind (counts, hk, power, status,
    provenance, other); ``seq_gaps`` sums the sequence numbers skipped per
    topic (messages the recorder never received and that never came late),
    ``seq_repeats`` the messages whose ``seq`` did not increase (duplicates,
    reordering, a restarted publisher; ``core.sequence``); ``invalid`` the payloads that were not a valid
    envelope (recorded anyway); ``dropped_on_close`` the samples a full
    queue could not take while the subscriber was being closed;
    ``unconverted`` the streams with counts but no power at the end,
    ``power_gaps`` the power chunks each stream missed while its counts came
    and that never came late, ``power_late`` those that came late
    (``service/coverage.py``); ``ledger`` the counts chunks of every stream
    (``core.ledger``, verb ``recorded``) and ``ledger_line`` its one-line
    summary; ``converters`` each converter's ledger line from its last
    recorded status; ``power_only`` the streams whose power came while their
    counts never did (this recorder does not receive their source);
    ``writer_queue_full`` the hand-overs to the writer thread that waited for
    room (``writer_wait_s`` in all; nothing is dropped); ``cpu_s`` the
    process's CPU (every thread), ``samples`` the counts samples recorded and
    ``cpu_s_per_msamples`` the one per million of the other;
    ``receive_cpu_s_per_msamples`` the same for the receive thread alone;
    ``unpowered`` per stream the counts chunks recorded without their power
    (``count``, ``ranges`` of numbers ``[lo, hi)``: ``io.mcap.ledger.unpowered``)
    ``conflicts`` the streams two or more publishers sent side by side (each
    one's chunks numbered apart: ``core.sequence.PublisherSequences``);
    ``no_provenance`` the converters whose statuses were recorded and none of
    whose provenance was; and ``ledger_note`` these in words, for the closing line.
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
    queue_high_water_mb: float
    dropped_on_close: int
    duration_s: float
    unconverted: tuple[str, ...] = ()
    power_gaps: dict | None = None
    power_late: dict | None = None
    unconverted_why: dict | None = None
    power_only: tuple[str, ...] = ()
    ledger: dict | None = None
    ledger_line: str = ""
    converters: dict | None = None
    writer_queue_full: int = 0
    writer_wait_s: float = 0.0
    writer_queue_high_water: int = 0
    cpu_s: float = 0.0
    samples: int = 0
    cpu_s_per_msamples: float | None = None
    receive_cpu_s_per_msamples: float | None = None
    unpowered: dict | None = None
    conflicts: dict | None = None
    no_provenance: tuple[str, ...] = ()
    ledger_note: str = ""

    def final_line(self) -> str:
        """The ledger in one line: what ``record`` prints last."""
        return final_line(asdict(self))


def _names(names, most: int = 8) -> str:
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _no_provenance_line(names) -> str:
    if not names:
        return ""
    return (f"no provenance recorded from {_names(names)}: this recording does not hold the parameters "
            "their power was converted with")


def final_line(stats: dict) -> str:
    """The recorder's ledger in one line, from its statistics as a dict (``RecorderStats`` or a child's summary)."""
    line = f"ledger: counts {stats.get('ledger_line') or 'received 0 chunks'}{stats.get('ledger_note') or ''}"
    only = list(stats.get("power_only") or ())
    if only:
        line += (f"; WARNING power without its counts for {len(only)} stream(s) ({', '.join(only[:8])}"
                 f"{', ...' if len(only) > 8 else ''}): this recorder does not receive their source")
    return line


def cost_line(stats: dict) -> str:
    """The recorder's cost in one line: CPU per million counts samples, and any waits for the writer thread."""
    per = stats.get("cpu_s_per_msamples")
    line = (f"CPU {stats.get('cpu_s', 0.0):.2f} s for {stats.get('samples', 0) / 1e6:.2f} M counts samples"
            + (f" ({per:.4f} s per M samples)" if per is not None else ""))
    if stats.get("writer_queue_full"):
        line += (f"; the writer's queue was full {stats['writer_queue_full']} time(s): receiving waited "
                 f"{stats.get('writer_wait_s', 0.0):.1f} s (back-pressure, nothing dropped)")
    return line


def _open_holes(book) -> dict:
    """The heartbeat's (``ps``) view of counts recorded without power, below each stream's newest power: ``unpowered``
    (stream -> chunks) and ``unpowered_seqs`` (stream -> its first ranges, as text); empty when none."""
    from mntes_stream.core.sequence import format_ranges

    holes = book.unpowered(open_only=True)  # always both keys: the heartbeat keeps what a beat does not name
    return {"unpowered": {s: h["count"] for s, h in holes.items()},
            "unpowered_seqs": {s: format_ranges(h["ranges"], 4) for s, h in list(holes.items())[:64]}}


def run_recorder(config: RecorderConfig, stop=None, ready=None) -> RecorderStats:
    """Record until ``stop`` is set, SIGINT/SIGTERM arrives, or ``duration_s`` passes.

    ``stop`` and ``ready`` are Event-like (safe in a spawned process); ``ready`` is set once
    subscribed. Returns after the last file is finished (summary and footer written).
    """
    service = RecorderService(config)
    service.run(stop, ready)
    return service.stats


def _failed(exc: BaseException) -> BaseException:
    """Our errors as they are; anything else (a dead network, a full disk) as one TransportError."""
    if isinstance(exc, (MntesError, KeyboardInterrupt)):
        return exc
    return TransportError(f"recorder failed: {type(exc).__name__}: {exc}")


def _reach_the_source(z: ZenohSettings) -> ZenohSettings:
    """A peer recorder that connects to others: gossip scouting on unless a layer names it, so it connects to the
    source too (zenoh peers do not forward another peer's publications: connected to the converter alone, it would
    record power and status but no counts nor housekeeping). Named off: a warning, and it records what it reaches."""
    from mntes_stream.io.transport import describe_config, zenoh_config

    named = describe_config(zenoh_config(z))
    if named.get("mode") != "peer" or not named.get("connect/endpoints") or named.get("scouting/gossip/enabled"):
        return z
    said = z.gossip is not None or any(c.partition(":")[0].strip("/").startswith("scouting") for c in z.cfg)
    if not said and z.file:
        from mntes_stream.io.transport import _named_paths

        said = "scouting/gossip/enabled" in _named_paths(z.file) or "scouting/gossip" in _named_paths(z.file)
    if said:
        log.warning("gossip scouting is off and this peer recorder connects to %s: it records only what those "
                    "peers publish themselves (zenoh peers do not forward); a source it does not connect to is not "
                    "recorded", ", ".join(named["connect/endpoints"]))
        return z
    log.info("gossip scouting on: a peer connected to %s learns of the others (the source) and records them too",
             ", ".join(named["connect/endpoints"]))
    return ZenohSettings(gossip=True).over(z)


class RecorderService(Service):
    """Everything under ``mntes/<setup>/**`` into rotated MCAP files."""

    name = "recorder"
    Config = RecorderConfig
    summary = "every message of a setup into rotated MCAP files"
    beat_every_s = 0.25  # counts without power are said in the heartbeat (ps) this soon
    stats: RecorderStats | None = None

    def zenoh_settings(self) -> ZenohSettings:
        return _reach_the_source(self.config.zenoh)

    def setup(self, ctx) -> None:
        from mntes_stream.io.transport import QueueSubscriber
        from mntes_stream.service.recorder_sink import RecorderSink

        config = self.config
        self._t_start = time.monotonic()
        self._next_log = self._t_start + config.log_interval_s
        # A converter whose status came but whose provenance did not is asked again, at growing intervals.
        self._ask_every_s, self._next_ask = _ASK_AGAIN_S, self._t_start + _ASK_AGAIN_S
        self._sink = sink = RecorderSink(config)
        self._sub = None
        try:
            # The callback only timestamps and queues; a full queue makes it wait,
            # which BLOCK publishers feel as back-pressure (nothing is dropped).
            # History: what the sources' caches hold (io/history.py) is recorded too, so a recorder restarted
            # after a crash, or started late, fills what it missed; a gap seen later is recovered from them
            # (and a key whose history zenoh dropped is asked again: io/history.HistoryTopUp).
            self._sub = QueueSubscriber(ctx.session, [config.subscription], maxsize=config.queue_messages,
                                        max_bytes=int(config.queue_mb * 1e6), recover="history",
                                        sources=True)  # each message's publisher: two on one stream told apart
            # A converter's provenance, answered on request, is recorded from the start too (only that:
            # the heartbeat queryables under alive/ answer a wider query, and are not data). Replies are taken
            # for 30 s, so a converter slow to answer is still recorded; the query ends as soon as every converter
            # has answered anyway.
            self._sub.query(ctx.session, keys.provenance_key(config.setup), timeout_s=30.0)
        except BaseException as exc:  # the file is finished whatever happened
            sink.writer.close()
            raise _failed(exc) from exc
        log.info("recording %s into %s", config.subscription, sink.writer.current_path)

    def step(self, ctx) -> bool:
        sink, sub, writer = self._sink, self._sub, self._sink.writer
        try:
            item = sub.get(timeout_s=min(0.1, max(writer.next_tick_s(), 0.005)))
            if item is not None:
                for got in (item, *sub.drain(10_000)):  # then check the stop flags once per batch
                    sink.add(*got)
            writer.tick()
        except BaseException as exc:
            raise _failed(exc) from exc
        now = time.monotonic()
        if now >= self._next_ask:
            self._ask_again(ctx, now)
        if now >= self._next_log:
            self._next_log += self.config.log_interval_s
            log.info("recorded %d messages (%d invalid) into %s", writer.messages, writer.invalid,
                     writer.current_path.name)
        return True

    def _ask_again(self, ctx, now: float) -> None:
        """Ask for the provenance again if a converter's statuses came and it did not. Twice in CI one of three
        shards' answer to the first query never came (cause unknown: docs/streaming.md); without this its
        provenance waited for its next periodic publication (``provenance_interval_s``), or never came in a
        recording shorter than that."""
        missing = self._sink.without_provenance()
        if missing:
            log.info("no provenance recorded yet from %s: asking again", _names(missing))
            try:
                self._sub.query(ctx.session, keys.provenance_key(self.config.setup), timeout_s=10.0)
            except MntesError as exc:  # the next attempt may do; the closing line names what is still missing
                log.warning("%s", exc)
            self._ask_every_s = min(2 * self._ask_every_s, _ASK_AGAIN_MAX_S)
        self._next_ask = now + self._ask_every_s

    def counters(self) -> dict:
        sink, sub = getattr(self, "_sink", None), getattr(self, "_sub", None)
        if sink is None or sub is None:
            return {}
        writer, book = sink.writer, sink.book
        led = book.ledger_now()
        t = led.totals()
        # numbers are Prometheus counters too (service/metrics.py)
        return {"messages": writer.messages, "payload_bytes": writer.payload_bytes, "invalid": writer.invalid,
                "files": len(writer.files), "queue_depth": sub.qsize(), "writer_queue_depth": writer.qsize(),
                "writer_queue_full": writer.queue_full, **sink.coverage.summary(time.monotonic()),
                "ledger_line": led.line(), "chunks_recorded": t.done, "chunks_missing": t.missing,
                "chunks_duplicate": t.duplicate, "chunks_lost": t.lost,
                "cpu_s_per_msamples": sink.cpu()["cpu_s_per_msamples"], **_open_holes(book),
                "conflicts": book.conflicts()}

    def finish(self, ctx) -> dict:
        sink, sub = self._sink, self._sub
        writer, book, coverage = sink.writer, sink.book, sink.coverage
        error = None
        try:  # what arrived before the session closed is recorded too
            for item in sub.drain():
                sink.add(*item)
            sub.close()
            ctx.session.close()
            for item in sub.drain():
                sink.add(*item)
        except BaseException as exc:  # a dead network or a full disk must not lose the file
            error = exc
        try:
            writer.close()
        except BaseException as exc:
            error = error or exc
        if error is not None:
            raise _failed(error) from error
        from mntes_stream.io.mcap.ledger import conflict_line, unpowered_line

        led = book.ledger_now()
        holes = book.unpowered()
        no_provenance = sink.without_provenance()
        if holes:
            log.warning("recording lacks %s", unpowered_line(holes))
        trackers = [*sink.sequences.values(), *book.sequences.values()]
        now = time.monotonic()
        self.stats = stats = RecorderStats(
            messages=writer.messages,
            payload_bytes=writer.payload_bytes,
            by_kind=sink.by_kind,
            invalid=writer.invalid,
            seq_gaps=max(sum(q.lost for q in trackers), 0),
            seq_repeats=sum(q.duplicated + q.out_of_order + q.resets for q in trackers),
            files=tuple(str(p) for p in writer.files),
            flushes=writer.flushes,
            queue_high_water=sub.high_water,
            queue_high_water_mb=sub.high_water_bytes / 1e6,
            dropped_on_close=sub.dropped_on_close,
            duration_s=time.monotonic() - self._t_start,
            unconverted=tuple(coverage.unconverted(now)),
            power_gaps=dict(coverage.gaps),
            power_late=dict(coverage.late),
            unconverted_why={s: coverage.reason(s) for s in coverage.unconverted(now)},
            power_only=tuple(coverage.power_only(now)),
            ledger=led.as_dict(),
            ledger_line=led.line(),
            converters={name: book.converter_line(name) for name in sorted(book.converters)},
            writer_queue_full=writer.queue_full,
            writer_wait_s=round(writer.wait_s, 3),
            writer_queue_high_water=writer.queue_high_water,
            unpowered=holes,
            conflicts=book.conflicts(),
            no_provenance=tuple(no_provenance),
            ledger_note="".join(f"; WARNING {x}" for x in (unpowered_line(holes), conflict_line(book.conflicts()),
                                                           _no_provenance_line(no_provenance)) if x),
            **sink.cpu(),
        )
        log.info("recorder stopped: %s", stats)
        log.info("recorder %s", cost_line(asdict(stats)))
        log.info("recorder %s", stats.final_line())
        return asdict(stats)
