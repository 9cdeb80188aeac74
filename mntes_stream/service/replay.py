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
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.pipeline.config import INPUT_KINDS
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["ReplayConfig", "ReplayService", "ReplayStats", "parse_time", "run_replay"]

log = logging.getLogger("mntes_stream.replay")

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


def run_replay(config: ReplayConfig, stop=None, ready=None, progress: bool = False) -> ReplayStats:
    """Publish the selected messages of ``config.source``; returns when done or stopped.

    ``ready`` is set when the first message goes out (a replay that publishes nothing never is).
    """
    svc = ReplayService(config)
    svc.progress = progress
    svc.run(stop, ready)
    return svc.stats


def _published(led):
    led.verb = "published"
    return led


class ReplayService(Service):
    """A recorded session back onto zenoh, paced or as fast as possible; ready when it first publishes."""

    name = "replay"
    Config = ReplayConfig
    summary = "a recording back onto zenoh"
    ready_after_setup = False
    #: messages per step when not paced (a stop is seen within this many)
    BURST = 64

    progress = False
    stats: ReplayStats | None = None

    def setup(self, ctx) -> None:
        from mntes_stream.io.mcap import Session, topic_matcher

        config = self.config
        if not config.source:
            raise ConfigError("nothing to replay: no source files")
        self._t_begin = time.monotonic()
        self._in = Session(list(config.source))
        match = topic_matcher(config.topics) if config.topics else (lambda t: keys.kind_of(t) in INPUT_KINDS)
        self._topics = sorted(t for t in self._in.message_counts() if match(t))
        total = self._in.count(self._topics)
        self._by_kind: dict[str, int] = {}
        self._book = RecordingBook()
        self._n = self._nbytes = 0
        self._behind_max = 0.0
        self._first_log = self._last_log = None
        pubs = ctx.publishers  # BLOCK congestion control
        self._unmatched: tuple[str, ...] = ()
        if not pubs.wait_matching(self._topics, config.wait_subscribers_s, ctx.stop):
            self._unmatched = tuple(t for t in self._topics if not pubs.publisher(t).matching_status.matching)
        if self._unmatched:
            log.warning("no subscriber for %d of %d topics (e.g. %s); publishing anyway", len(self._unmatched),
                        len(self._topics), self._unmatched[0])
        self._bar = None
        if self.progress:
            from tqdm import tqdm

            self._bar = tqdm(total=total, unit="msg", desc="replay")
        self._messages = self._in.iter_messages(self._topics, config.start_ns, config.end_ns)
        self._wall0 = time.monotonic()

    def step(self, ctx) -> bool:
        speed = self.config.speed
        for _ in range(1 if speed > 0 else self.BURST):
            msg = next(self._messages, None)
            if msg is None:
                return False
            if self._first_log is None:
                self._first_log = msg.log_time_ns
            if speed > 0:
                due = self._wall0 + (msg.log_time_ns - self._first_log) / 1e9 / speed
                while (wait := due - time.monotonic()) > 0 and not ctx.stop.is_set():
                    time.sleep(min(wait, 0.05))
                self._behind_max = max(self._behind_max, time.monotonic() - due)
                if ctx.stop.is_set():
                    return False
            self._last_log = msg.log_time_ns
            ctx.publishers.put(msg.topic, msg.payload)
            ctx.mark_ready()
            kind = keys.kind_of(msg.topic)
            if kind == "counts":  # what the recording holds of each stream, and its gaps
                self._book.add(msg.topic, msg.payload, peek_envelope(msg.payload), msg.log_time_ns)
            self._n += 1
            self._nbytes += len(msg.payload)
            kind = kind or "other"
            self._by_kind[kind] = self._by_kind.get(kind, 0) + 1
            if self._bar is not None:
                self._bar.update(1)
        return True

    def counters(self) -> dict:
        return {"messages": getattr(self, "_n", 0), "payload_bytes": getattr(self, "_nbytes", 0)}

    def finish(self, ctx) -> dict:
        if self._bar is not None:
            self._bar.close()
        led = self._book.ledger_now()
        self.stats = stats = ReplayStats(
            messages=self._n,
            payload_bytes=self._nbytes,
            by_kind=self._by_kind,
            topics=len(self._topics),
            unmatched_topics=self._unmatched,
            duration_s=time.monotonic() - self._t_begin,
            recorded_span_s=0.0 if self._first_log is None else (self._last_log - self._first_log) / 1e9,
            behind_max_ms=self._behind_max * 1e3,
            complete=self._in.complete,
            ledger=led.as_dict(),
            ledger_line=_published(led).line(),
        )
        log.info("replay done: %s", stats)
        return asdict(stats)
