"""What the recorder does with each received message, zenoh aside (:class:`RecorderSink`).

The receive thread reads each payload's header once (``peek_envelope``:
schema, version, seq, times, ``late``, the array's shape; the array bytes are
skipped, never decoded), books it (ledger, coverage, sequences) and hands the
bytes, as received, to a :class:`~mntes_stream.io.mcap.background.BackgroundMcapWriter`,
whose thread frames, compresses and writes them. ``mntes-stream bench
recording`` drives this same class, so its CPU figure is the recorder's.
"""

from __future__ import annotations

import os
import socket
import time

from mntes_stream.core.sequence import PublisherSequences
from mntes_stream.core.shards import Shard
from mntes_stream.errors import MntesError
from mntes_stream.io import keys
from mntes_stream.io.mcap.background import BackgroundMcapWriter
from mntes_stream.io.mcap.envelope import peek_envelope
from mntes_stream.io.mcap.ledger import LEDGER_METADATA, RecordingBook
from mntes_stream.io.messages import Provenance, StatusMessage
from mntes_stream.service.coverage import Coverage

__all__ = ["RecorderSink", "shard_filter"]

_MAX_TOPICS = 100_000  # topics whose kind is remembered (names come from any peer)
_MAX_CONVERTERS = 1024  # converters and provenances whose owns are kept (names come from any peer)


class RecorderSink:
    """Book and write every message of a recorder run (see the module docstring).

    Parameters
    ----------
    config : RecorderConfig
    """

    def __init__(self, config):
        self.writer = BackgroundMcapWriter(
            config.directory,
            config.file_prefix,
            flush_interval_s=config.flush_interval_s,
            rotate_bytes=int(config.rotate_mb * (1 << 20)),
            rotate_s=config.rotate_s,
            compression=config.compression,
            chunk_size_bytes=config.chunk_size_kb * 1024,
            fsync=config.fsync,
            metadata=config.to_metadata(),
            queue_messages=config.queue_messages,
            queue_bytes=int(config.writer_queue_mb * 1e6),
        )
        self.json_channels = None
        if config.foxglove_channels:
            from mntes_stream.foxglove.transcode import JsonChannels

            self.json_channels = JsonChannels(self.writer)
        self.book = RecordingBook(None if config.key_expr else config.setup)
        self.run = f"{socket.gethostname()}:{os.getpid()}:{time.time_ns()}"
        # Every file gets the ledger of the run so far as it is finished (rotation or close): the writer asks on
        # this thread, at the hand-over where the file ends, so it counts exactly what the file holds.
        self.writer.closing_metadata = lambda file_seq: {LEDGER_METADATA: self.book.metadata(self.run, file_seq)}
        self.coverage = Coverage(config.unconverted_after_s)
        self.sequences: dict[str, PublisherSequences] = {}  # topics other than counts (the book tracks those)
        self.by_kind: dict[str, int] = {}
        self.samples = 0  # counts samples (channels x samples of every valid counts chunk)
        self._kinds: dict[str, str] = {}
        self._mine = shard_filter(config.shard_parsed)
        # What each converter's newest status says it owns, and what the provenances recorded cover (their
        # ``owns``, that of the status less its state): a converter none of them covers has its provenance
        # asked again (the recorder) and named at the end.
        self._converter_owns: dict[str, dict] = {}
        self._provenance_owns: list[dict] = []
        self.cpu0_s = time.process_time()
        self.thread_cpu0_s = time.thread_time()  # the receive thread's: a sink is fed by the thread that made it

    def add(self, topic: str, payload: bytes, t_ns: int, source: str | None = None) -> None:
        """One received message (``source``: its publisher's zenoh id, if known): header, books, hand-over to the
        writer (waits while its queue is full)."""
        kind = self._kinds.get(topic)
        if kind is None:
            kind = keys.kind_of(topic) or "other"
            if len(self._kinds) < _MAX_TOPICS:
                self._kinds[topic] = kind
        if kind in ("status", "provenance"):  # a second or so apart: whose provenance is held (every shard)
            self._owner(kind, payload)
        if self._mine is not None and not self._mine(topic):
            return
        env = peek_envelope(payload)
        self.writer.write(topic, payload, t_ns, env)
        late = env.late and kind == "power" and not env.problem
        lag_s = None if kind != "power" or env.publish_time_ns is None else (t_ns - env.publish_time_ns) / 1e9
        self.coverage.add(topic, env.seq, time.monotonic(), late=late, lag_s=lag_s)
        self.book.add(topic, payload, env, t_ns, late=late, kind=kind, source=source)
        if kind == "counts":
            if not env.problem:
                self.samples += env.samples
        elif kind == "status" and topic in self.book.status_topics:
            service = self.book.status_topics[topic]
            entry = self.book.converters.get(service)
            if entry is not None:
                self.coverage.converter_status(service, entry["ledger"], entry["chunks_set_aside"])
        if self.json_channels is not None and not env.problem:
            self.json_channels.add(env.schema, payload)
        self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
        if env.seq is not None and kind != "counts":
            seq = self.sequences.get(topic)
            if seq is None:
                seq = self.sequences[topic] = PublisherSequences()
            seq.observe(env.seq, env.publish_time_ns if env.publish_time_ns is not None else t_ns, source)
        self.writer.rotate_if_full()  # after booking: the closing ledger of a full file counts its last message

    def _owner(self, kind: str, payload: bytes) -> None:
        try:
            msg = (StatusMessage if kind == "status" else Provenance).from_bytes(payload)
        except MntesError:  # booked as invalid where it is recorded
            return
        if kind == "status":
            if msg.service in self._converter_owns or len(self._converter_owns) < _MAX_CONVERTERS:
                self._converter_owns[msg.service] = dict(msg.owns)
        elif msg.owns not in self._provenance_owns and len(self._provenance_owns) < _MAX_CONVERTERS:
            self._provenance_owns.append(dict(msg.owns))

    def without_provenance(self) -> list[str]:
        """The converters (status service names) whose statuses came but none of whose provenance did: a
        provenance covers a converter whose status owns what it owns (an unsharded one's owns nothing: all)."""
        return sorted(name for name, owns in self._converter_owns.items()
                      if not any(p.items() <= owns.items() for p in self._provenance_owns))

    def cpu(self) -> dict:
        """CPU since the sink started, per million counts samples: the process's (every thread: receive, writer,
        zenoh) and the receive thread's alone (what caps how fast the recorder takes messages in).

        Call it from the receive thread."""
        cpu_s = time.process_time() - self.cpu0_s
        thread_s = time.thread_time() - self.thread_cpu0_s
        m = self.samples / 1e6
        return {"cpu_s": round(cpu_s, 3), "samples": self.samples,
                "cpu_s_per_msamples": round(cpu_s / m, 4) if m else None,
                "receive_cpu_s_per_msamples": round(thread_s / m, 4) if m else None}


def shard_filter(shard: Shard):
    """Whether a recorder shard keeps a topic (None: it keeps everything); cached per topic."""
    if shard.whole:
        return None
    cache: dict[str, bool] = {}

    def mine(topic: str) -> bool:
        keep = cache.get(topic)
        if keep is None:
            parts = topic.split("/")
            if len(parts) == 5 and parts[2] in ("counts", "power") or parts[2:4] == ["hk", "bias"] and len(parts) == 6:
                b, m = parts[-2:]
                keep = shard.owns(int(b), int(m)) if b.isdigit() and m.isdigit() else shard.index == 0
            else:
                keep = shard.index == 0 or keys.kind_of(topic) == "provenance"
            if len(cache) < _MAX_TOPICS:
                cache[topic] = keep
        return keep

    return mine
