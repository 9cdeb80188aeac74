"""Replay: re-publish a recorded session onto zenoh, paced by the recorded receive times.

Messages go out in log-time order with their payload bytes unchanged, on their
recorded keys, through publishers with BLOCK congestion control (a slow
subscriber slows the replay instead of losing data). ``speed`` 1 is real time,
10 ten times faster, 0 as fast as possible.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime

from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.mcap.envelope import peek_envelope
from mntes_stream.io.mcap.ledger import RecordingBook
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service.base import Service, stop_on_signals
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["INPUT_KINDS", "ReplayConfig", "ReplayService", "ReplayStats", "input_topics", "parse_time", "run_replay"]

log = logging.getLogger("mntes_stream.replay")

#: Key kinds a converter consumes: the default selection of a replay (any setup).
INPUT_KINDS = ("counts", "hk")


def input_topics(setup: str) -> tuple[str, ...]:
    """Key expressions of a converter's inputs for one setup: counts and housekeeping."""
    return (keys.counts_key(setup), keys.hk_key(setup))


@dataclass(frozen=True)
class ReplayConfig(Settings):
    """What to replay and how fast: the ``[replay]`` and ``[zenoh]`` tables.

    ``topics`` empty (the default) replays the converter's inputs: every
    recorded topic whose kind is in :data:`INPUT_KINDS`, whatever its setup;
    ``("**",)`` replays everything.
    """

    source: tuple[str, ...] = setting((), "recorded files or directories (one session; rotated files in order)",
                                      path=True)
    speed: float = setting(1.0, "multiple of real time; 0 = as fast as possible", ge=0)
    start_ns: int | None = setting(None, "replay messages with log time >= this (ns since the epoch)")
    end_ns: int | None = setting(None, "... and < this")
    topics: tuple[str, ...] = setting((), "topics or zenoh-style patterns; [] = the converter's inputs")
    wait_subscribers_s: float = setting(5.0, "wait this long for subscribers before the first message", unit="s",
                                        ge=0)
    linger_s: float = setting(0.5, "keep the session open this long after the last message", unit="s", ge=0)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    def __post_init__(self):
        super().__post_init__()
        if self.start_ns is not None and self.end_ns is not None and self.end_ns <= self.start_ns:
            raise ConfigError("replay: end must be after start")


@dataclass(frozen=True)
class ReplayStats:
    """``behind_max_ms``: the most a message went out after its scheduled time."""

    messages: int
    payload_bytes: int
    by_kind: dict
    topics: int
    unmatched_topics: tuple[str, ...]
    duration_s: float
    recorded_span_s: float
    behind_max_ms: float
    complete: bool
    ledger: dict | None = None  # counts chunks of every stream published (core.ledger), gaps of the recording
    ledger_line: str = ""


def parse_time(text: str, session_start_ns: int | None) -> int:
    """``12.5`` (seconds after the session's first message) or an ISO-8601 time -> ns."""
    try:
        rel = float(text)
    except ValueError:
        try:
            dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(f"time {text!r}: give seconds from the start or an ISO-8601 time") from None
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=UTC)
        return int(round(dt.timestamp() * 1e9))
    if session_start_ns is None:
        raise ConfigError("the session has no messages to count time from")
    return session_start_ns + int(round(rel * 1e9))


def run_replay(config: ReplayConfig, stop_event=None, progress: bool = False, heartbeat=None) -> ReplayStats:
    """Publish the selected messages of ``config.source``; returns when done or stopped."""
    from mntes_stream.io.mcap import Session, topic_matcher
    from mntes_stream.io.transport import Publishers

    if not config.source:
        raise ConfigError("nothing to replay: no source files")
    session_in = Session(list(config.source))
    match = topic_matcher(config.topics) if config.topics else (lambda t: keys.kind_of(t) in INPUT_KINDS)
    topics = sorted(t for t in session_in.message_counts() if match(t))
    total = session_in.count(topics)
    by_kind: dict[str, int] = {}
    book = RecordingBook()
    n = nbytes = 0
    behind_max = 0.0
    first_log = last_log = None
    unmatched: tuple[str, ...] = ()
    t_begin = time.monotonic()
    with stop_on_signals(stop_event) as stopping, open_session(config.zenoh) as z:
        pubs = Publishers(z)  # BLOCK congestion control
        if not pubs.wait_matching(topics, config.wait_subscribers_s, stopping):
            unmatched = tuple(t for t in topics if not pubs.publisher(t).matching_status.matching)
        if unmatched:
            log.warning("no subscriber for %d of %d topics (e.g. %s); publishing anyway", len(unmatched), len(topics), unmatched[0])
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, unit="msg", desc="replay")
        wall0 = time.monotonic()
        for msg in session_in.iter_messages(topics, config.start_ns, config.end_ns):
            if first_log is None:
                first_log = msg.log_time_ns
            if config.speed > 0:
                due = wall0 + (msg.log_time_ns - first_log) / 1e9 / config.speed
                while (wait := due - time.monotonic()) > 0 and not stopping.is_set():
                    time.sleep(min(wait, 0.05))
                behind_max = max(behind_max, time.monotonic() - due)
            if (config.speed > 0 or n % 64 == 0) and stopping.is_set():
                break
            last_log = msg.log_time_ns
            pubs.put(msg.topic, msg.payload)
            if keys.kind_of(msg.topic) == "counts":  # what the recording holds of each stream, and its gaps
                book.add(msg.topic, msg.payload, peek_envelope(msg.payload), msg.log_time_ns)
            n += 1
            nbytes += len(msg.payload)
            kind = keys.kind_of(msg.topic) or "other"
            by_kind[kind] = by_kind.get(kind, 0) + 1
            if bar is not None:
                bar.update(1)
            if heartbeat is not None and n % 256 == 0:
                heartbeat.beat(messages=n, payload_bytes=nbytes)
        if bar is not None:
            bar.close()
        time.sleep(config.linger_s)
        pubs.close()
    stats = ReplayStats(
        messages=n,
        payload_bytes=nbytes,
        by_kind=by_kind,
        topics=len(topics),
        unmatched_topics=unmatched,
        duration_s=time.monotonic() - t_begin,
        recorded_span_s=0.0 if first_log is None else (last_log - first_log) / 1e9,
        behind_max_ms=behind_max * 1e3,
        complete=session_in.complete,
        ledger=(led := book.ledger_now()).as_dict(),
        ledger_line=_published(led).line(),
    )
    log.info("replay done: %s", stats)
    return stats


def _published(led):
    led.verb = "published"
    return led


class ReplayService(Service):
    """A recorded session back onto zenoh, paced or as fast as possible."""

    name = "replay"
    Config = ReplayConfig
    summary = "a recording back onto zenoh"

    def run(self, stop=None, ready=None) -> dict:
        if ready is not None:
            ready.set()
        return asdict(run_replay(self.config, stop, heartbeat=self.heartbeat))
