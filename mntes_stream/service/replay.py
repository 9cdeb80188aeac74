"""Replay: re-publish a recorded session onto zenoh, paced by the recorded receive times.

Messages go out in log-time order with their payload bytes unchanged, on their
recorded keys, through publishers with BLOCK congestion control (a slow
subscriber slows the replay instead of losing data). ``speed`` 1 is real time,
10 ten times faster, 0 as fast as possible.
"""

from __future__ import annotations

import logging
import time
import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service import dataclass_from_table, split_config, stop_on_signals

__all__ = ["INPUT_KINDS", "ReplayConfig", "ReplayStats", "input_topics", "parse_time", "run_replay"]

log = logging.getLogger("mntes_stream.replay")

#: Key kinds a converter consumes: the default selection of a replay (any setup).
INPUT_KINDS = ("counts", "hk")


def input_topics(setup: str) -> tuple[str, ...]:
    """Key expressions of a converter's inputs for one setup: counts and housekeeping."""
    return (keys.counts_key(setup), keys.hk_key(setup))


@dataclass(frozen=True)
class ReplayConfig:
    """What to replay and how fast.

    Attributes
    ----------
    source : tuple of str
        Files or directories (one session; rotated files are read in order).
    speed : float
        Multiple of real time; 0 means as fast as possible.
    start_ns, end_ns : int, optional
        Replay messages with ``start_ns <= log_time < end_ns``.
    topics : tuple of str
        Topics or zenoh-style patterns (``("**",)``: everything); empty (the
        default): the converter's inputs, i.e. every recorded topic whose kind
        is in :data:`INPUT_KINDS`, whatever its setup.
    wait_subscribers_s : float
        Wait up to this long for every publisher to have a matching subscriber.
    linger_s : float
        Keep the session open this long after the last message so it is delivered.
    """

    source: tuple[str, ...] = ()
    speed: float = 1.0
    start_ns: int | None = None
    end_ns: int | None = None
    topics: tuple[str, ...] = ()
    wait_subscribers_s: float = 5.0
    linger_s: float = 0.5
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    def __post_init__(self):
        for name in ("source", "topics"):
            v = getattr(self, name)
            if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v):
                raise ConfigError(f"replay: {name} must be a list of strings, got {v!r}")
            object.__setattr__(self, name, tuple(v))
        for name in ("speed", "wait_subscribers_s", "linger_s"):
            v = finite_float("replay", name, getattr(self, name))
            if v < 0:
                raise ConfigError(f"replay: {name} must be >= 0{' (0: as fast as possible)' if name == 'speed' else ''}, got {v}")
            object.__setattr__(self, name, v)
        for name in ("start_ns", "end_ns"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool)):
                raise ConfigError(f"replay: {name} must be an integer (ns since the epoch), got {v!r}")
        if self.start_ns is not None and self.end_ns is not None and self.end_ns <= self.start_ns:
            raise ConfigError("replay: end must be after start")
        if not isinstance(self.zenoh, ZenohSettings):
            raise ConfigError("replay: zenoh must be a ZenohSettings (the [zenoh] table)")

    @classmethod
    def from_toml(cls, path: str | Path, **overrides) -> ReplayConfig:
        """Read ``[replay]`` and ``[zenoh]`` tables (see ``services/replay.toml``)."""
        try:
            doc = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: {exc}") from None
        tables, z = split_config(doc, ("replay",), str(path), str(Path(path).parent))
        d = {**tables["replay"], "zenoh": z, **overrides}
        return dataclass_from_table(cls, d, f"{path} [replay]", tuples=True)


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
            dt = dt.replace(tzinfo=timezone.utc)
        return int(round(dt.timestamp() * 1e9))
    if session_start_ns is None:
        raise ConfigError("the session has no messages to count time from")
    return session_start_ns + int(round(rel * 1e9))


def run_replay(config: ReplayConfig, stop_event=None, progress: bool = False) -> ReplayStats:
    """Publish the selected messages of ``config.source``; returns when done or stopped."""
    from mntes_stream.io.mcap_io import Session, topic_matcher
    from mntes_stream.io.transport import Publishers

    if not config.source:
        raise ConfigError("nothing to replay: no source files")
    session_in = Session(list(config.source))
    match = topic_matcher(config.topics) if config.topics else (lambda t: keys.kind_of(t) in INPUT_KINDS)
    topics = sorted(t for t in session_in.message_counts() if match(t))
    total = session_in.count(topics)
    by_kind: dict[str, int] = {}
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
            n += 1
            nbytes += len(msg.payload)
            kind = keys.kind_of(msg.topic) or "other"
            by_kind[kind] = by_kind.get(kind, 0) + 1
            if bar is not None:
                bar.update(1)
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
    )
    log.info("replay done: %s", stats)
    return stats
